"""Per-trial seconds of result files, with the GP size and whether FITC ran (docs/results.md, wall times).

    python experiments/trial_timings.py results/thesis/unicycle_*.h5

Unfinished files are read too (no checksum verification), so a running sweep can be watched.
"""

import sys

from pipps.experiments.results import read_result


def main(paths) -> None:
    for path in paths:
        result = read_result(path, verify=False)
        print(f"{path}: wall {result.wall_seconds / 60:.1f} min")
        for t in result.trials:
            gp = t.gp
            print(f"  trial {t.index:03d} {t.kind:>7}: {t.timings.total:7.0f} s  "
                  f"N = {gp.num_points if gp else '-'}  FITC = {gp.sparse if gp else '-'}")


if __name__ == "__main__":
    main(sys.argv[1:])
