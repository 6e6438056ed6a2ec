"""Re-simulate each result file's final policy on the true system, for any task.

    python experiments/resimulate_final.py results/thesis/unicycle_*.h5 --fresh 300

A success must survive an independent re-simulation of the stored policy. For every file this
runs the final trial's policy twice, outside the learning loop
(:class:`pipps.experiments.resimulate.Resimulator`):

1. with the trial's own evaluation keys: the true system is deterministic given them, so the
   returns must equal the stored ones to rounding and the task's per-rollout criterion must give
   the stored flags (a check that the file's verdict is what its policy does);
2. with ``--fresh`` rollouts whose keys the experiment never used (``--seed``): the fraction of
   them meeting the task's criterion (the per-trial reading for that seed), the per-seed verdict
   again, and, where the task has a return threshold (the cart-pole's), the fraction below it.

Per cell (task, cost, k, method, estimator choices) it prints the per-trial rate, the mean over
seeds of those fractions, from the stored and from the fresh rollouts.
"""

from __future__ import annotations

import argparse
from collections import defaultdict

import numpy as np

from pipps.experiments.methods import METHODS
from pipps.experiments.resimulate import Resimulator
from pipps.experiments.results import read_result
from pipps.precision import enable_float64
from pipps.reporting.verdicts import criterion, final_flags, verdict


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("results", nargs="+", metavar="H5")
    ap.add_argument("--fresh", type=int, default=300, help="independent rollouts per final policy (default 300)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the fresh rollouts' keys")
    args = ap.parse_args(argv)
    if args.fresh < 2:
        ap.error("--fresh must be >= 2")
    enable_float64()
    sim = Resimulator()
    print("| file | seed | own keys: max abs. return difference, flags equal | stored: fraction meeting the "
          "criterion, verdict | fresh: fraction ± SE, mean return ± SE, verdict | verdict holds |")
    print("|---|---|---|---|---|---|")
    cells = defaultdict(list)
    worst, mismatched = 0.0, []
    for path in args.results:
        res = read_result(path)
        cfg, index = res.config, len(res.trials) - 1
        final = res.trials[index]
        if final.kind != "learned":
            ap.error(f"{path}: its last trial is random; is the experiment complete?")
        success = criterion(cfg)
        stored_flags = final_flags(cfg, final)
        own_ret, own_up, own_flags = sim.trial(res, index)
        diff = float(np.max(np.abs(own_ret - np.asarray(final.eval_returns))))
        same = stored_flags is None or bool(np.array_equal(np.asarray(own_flags, bool), np.asarray(stored_flags, bool)))
        worst = max(worst, diff)
        if not same:
            mismatched.append(path)
        stored = verdict(cfg, final.eval_returns, own_flags if stored_flags is None else stored_flags)
        ret, _, flags = sim.trial(res, index, fresh=args.fresh, seed=args.seed)
        fresh = verdict(cfg, ret, flags)
        se_f = float(np.sqrt(fresh.fraction * (1 - fresh.fraction) / ret.size))
        se_r = float(np.std(ret, ddof=1) / np.sqrt(ret.size))
        holds = fresh.success == stored.success
        print(f"| {path.split('/')[-1]} | {cfg.seed} | {diff:.1e}, {'yes' if same else 'NO'} | "
              f"{stored.fraction:.2f}, {'pass' if stored.success else 'fail'} | {fresh.fraction:.2f} ± {se_f:.2f}, "
              f"{np.mean(ret):.2f} ± {se_r:.2f}, {'pass' if fresh.success else 'fail'} | {'yes' if holds else 'NO'} |")
        below = (None if success.threshold is None else
                 (float(np.mean(np.asarray(final.eval_returns) < success.threshold)),
                  float(np.mean(ret < success.threshold))))
        key = (cfg.task, cfg.cost or "-", cfg.k, METHODS[cfg.method].label, cfg.estimator_choices)
        cells[key].append((stored.fraction, fresh.fraction, below, holds))
    print(f"\nOwn keys: the largest return difference from the stored returns is {worst:.1e}; "
          + ("every file's criterion flags equal the stored ones." if not mismatched else
             f"the flags differ from the stored ones in {', '.join(mismatched)}."))
    print(f"\nPer cell, the per-trial rate (mean over seeds of the final policy's fractions), stored (30 rollouts "
          f"per seed) and fresh ({args.fresh} per seed):")
    print("| task | cost | k | method | choices | seeds | physical: stored | fresh | return: stored | fresh "
          "| per-seed verdicts that hold |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for (task, cost, k, label, choices), v in sorted(cells.items()):
        phys = np.mean([(a, b) for a, b, _, _ in v], axis=0)
        belows = [c for _, _, c, _ in v if c is not None]
        ret = ("–", "–") if not belows else tuple(f"{x:.2f}" for x in np.mean(belows, axis=0))
        print(f"| {task} | {cost} | {k:g} | {label} | {choices} | {len(v)} | {phys[0]:.2f} | {phys[1]:.2f} | "
              f"{ret[0]} | {ret[1]} | {sum(h for *_, h in v)}/{len(v)} |")


if __name__ == "__main__":
    main()
