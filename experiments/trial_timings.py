"""Per-trial seconds of result files, with the GP size and whether FITC ran (docs/results.md, wall times).

    python experiments/trial_timings.py results/thesis/unicycle_*.h5
"""

import sys

import h5py


def main(paths) -> None:
    for path in paths:
        with h5py.File(path, "r") as f:
            print(f"{path}: wall {f.attrs['wall_seconds'] / 60:.1f} min")
            for name in sorted(f["trials"]):
                g = f["trials"][name]
                gp = g["gp"].attrs if "gp" in g else {}
                print(f"  trial {name} {g.attrs['kind']:>7}: {g['timings'].attrs['total']:7.0f} s  "
                      f"N = {gp.get('num_points', '-')}  FITC = {gp.get('sparse', '-')}")


if __name__ == "__main__":
    main(sys.argv[1:])
