"""Stored policies observed at other noise levels: is a cell's failure the policy's reaction to
observation noise, or a policy that does not swing up at all?

For each result file, the final learned trial's policy (or ``--trial``'s) runs ``--rollouts`` fresh
true-system rollouts at each observation-noise multiplier of ``--k`` (default: the experiment's own
k and 0, where the policy sees the state). The keys are common to every k and every file of a
seed, so the start states and the noise directions are paired; only the noise's scale changes. Per
rollout the return and the task's success criterion are judged as the table judges them
(:class:`pipps.experiments.resimulate.Resimulator`). Printed per file: the fraction of rollouts with
return below the threshold, the fraction meeting the criterion (cart-pole: swung up and balanced)
and the mean return, at each k; then per cell (task, cost, method, experiment k) the means over
seeds with their standard errors over seeds.

    taskset -c 1 python experiments/observation_noise_eval.py --rollouts 100 --out tip_noise.json \\
        results/thesis/cartpole_swingup_tip_k1_{pilco,tp}_thesis_s{0,1,2,3,4}.h5

``--out`` (JSON; an existing file is refused without ``--overwrite``) is rewritten after every file, so a stopped run keeps
what it finished. Result files are only read (unfinished ones are refused).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

import pipps


def measure(path: str, resim, ks: list[float | None], rollouts: int, key_seed: int, trial: int | None) -> dict:
    from pipps.experiments.config import canonical
    from pipps.experiments.results import read_result

    result = read_result(path)
    cfg = result.config
    learned = [t.index for t in result.trials if t.kind == "learned"]
    trial = learned[-1] if trial is None else trial
    row = dict(file=str(path), task=cfg.task, cost=str(canonical(cfg)["cost"]), method=cfg.method, seed=int(cfg.seed), k=float(cfg.k),
               trial=int(trial), threshold=float(cfg.success_threshold), rollouts=rollouts, at={})
    for k in ks:
        k = float(cfg.k) if k is None else k
        returns, _, ok = resim.trial(result, trial, fresh=rollouts, seed=key_seed, k=k)
        row["at"][f"{k:g}"] = dict(below_threshold=float(np.mean(returns < cfg.success_threshold)),
                                   criterion=float(np.mean(ok)), mean_return=float(np.mean(returns)))
    return row


def row_text(r: dict) -> str:
    parts = [f"{Path(r['file']).name} (trial {r['trial']}):"]
    for k, v in r["at"].items():
        parts.append(f"k={k}: <{r['threshold']:g} {v['below_threshold']:.2f}, criterion {v['criterion']:.2f}, "
                     f"mean return {v['mean_return']:.2f}")
    return "  ".join(parts)


def summary(rows: list[dict]) -> list[dict]:
    """Per cell (task, cost, method, experiment k) and observed k: means over seeds and their SE."""
    out = []
    cells = sorted({(r["task"], r["cost"], r["method"], r["k"]) for r in rows})
    for cell in cells:
        group = [r for r in rows if (r["task"], r["cost"], r["method"], r["k"]) == cell]
        for k in group[0]["at"]:
            entry = dict(task=cell[0], cost=cell[1], method=cell[2], k=cell[3], observed_k=k, seeds=len(group))
            for metric in ("below_threshold", "criterion", "mean_return"):
                v = np.array([r["at"][k][metric] for r in group])
                entry[metric] = float(v.mean())
                entry[f"{metric}_se"] = float(v.std(ddof=1) / math.sqrt(v.size)) if v.size > 1 else math.nan
            out.append(entry)
    return out


def summary_text(e: dict) -> str:
    return (f"{e['task']} {e['cost']} {e['method']} k={e['k']:g}, observed at k={e['observed_k']} over {e['seeds']} "
            f"seeds: <threshold {e['below_threshold']:.2f} ± {e['below_threshold_se']:.2f}, criterion "
            f"{e['criterion']:.2f} ± {e['criterion_se']:.2f}, mean return {e['mean_return']:.2f} ± "
            f"{e['mean_return_se']:.2f} (SE over seeds)")


def write(out: Path, payload: dict) -> None:
    """Rewrite ``out`` in one step (the library's :func:`pipps.experiments.storage.publish`)."""
    from pipps.experiments.storage import publish

    with publish(out, overwrite=True, command="observation_noise_eval.py") as tmp:
        tmp.write_text(json.dumps(payload, indent=1) + "\n")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", nargs="+", help="result files (read only)")
    parser.add_argument("--out", required=True, type=Path, help="JSON to write (an existing file is refused)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    parser.add_argument("--k", default="own,0",
                        help="comma-separated observation-noise multipliers; 'own' is the experiment's (default own,0)")
    parser.add_argument("--rollouts", type=int, default=100, help="fresh true-system rollouts per policy and k")
    parser.add_argument("--key-seed", type=int, default=0, help="seed of the fresh rollouts' keys")
    parser.add_argument("--trial", type=int, default=None, help="the learned trial (default: the last)")
    args = parser.parse_args(argv)
    try:
        ks = [None if s.strip() == "own" else float(s) for s in args.k.split(",")]
    except ValueError:
        parser.error(f"--k: expected numbers or 'own' separated by commas, got {args.k!r}")
    if any(k is not None and not (math.isfinite(k) and k >= 0) for k in ks):
        parser.error(f"--k: each multiplier must be a finite number >= 0, got {args.k!r}")
    if args.rollouts < 2:
        parser.error(f"--rollouts must be at least 2, got {args.rollouts}")
    from pipps.experiments.storage import OutputError, check_new_file

    try:
        check_new_file(args.out, overwrite=args.overwrite, option="--out", suffix=".json", inputs=tuple(args.files),
                       command="observation_noise_eval.py")
    except OutputError as e:
        parser.error(str(e))
    pipps.enable_float64()
    from pipps.experiments.resimulate import Resimulator
    from pipps.experiments.results import code_version

    resim, rows = Resimulator(), []
    command = "python experiments/observation_noise_eval.py " + " ".join(argv if argv is not None else sys.argv[1:])
    for path in args.files:
        rows.append(measure(path, resim, ks, args.rollouts, args.key_seed, args.trial))
        print(row_text(rows[-1]), flush=True)
        write(args.out, dict(command=command, code=code_version(), rows=rows, summary=summary(rows)))
    for entry in summary(rows):
        print(summary_text(entry))


if __name__ == "__main__":
    main()
