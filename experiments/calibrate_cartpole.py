"""Calibrate the cart-pole's return threshold against the physical criterion (docs/results.md).

Success on the cart-pole is physical (pipps.tasks.cartpole.balanced): in at least ``balanced_fraction``
of the final trial's evaluation rollouts the pole ends within ``balance_angle`` of upright and the
cart within ``balance_position`` of the centre over the last ``balance_steps`` states. The thesis'
own rule is "final evaluated return below 15". This script puts the two side by side on every
learned policy of the given result files:

1. each learned trial is one policy; its 30 evaluation rollouts are re-simulated on the true system
   with the stored policy and the trial's own keys (the returns must equal the stored ones; the
   largest difference is printed), or read from the file where it stores the per-rollout flags;
2. :func:`pipps.reporting.calibration.fit_return_threshold` finds the thresholds τ for which
   "return < τ" agrees best with the physical verdict, and the agreement of the thesis' τ = 15;
3. every policy on which the thesis' threshold and the physical criterion disagree is listed, per k;
4. the final trials' rates at other required fractions and other bounds of the criterion.

The independent check that a verdict is not an accident of its 30 rollouts (each final policy rerun
with new keys) is ``pipps resimulate FILES --fresh N``, for any task.

    python experiments/calibrate_cartpole.py results/thesis/cartpole_*.h5
"""

from __future__ import annotations

import argparse
from collections import defaultdict

import numpy as np

import pipps
from pipps.reporting.calibration import fit_return_threshold
from pipps.experiments.methods import METHODS
from pipps.experiments.resimulate import Resimulator
from pipps.experiments.results import read_result
from pipps.tasks.registry import get_task

pipps.enable_float64()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", nargs="+", metavar="H5", help="cart-pole result files")
    ap.add_argument("--fractions", default="0.5,0.8", help="required balanced fractions to report rates at")
    ap.add_argument("--bounds", default="0.2:0.3,0.3:0.5,0.5:1.0",
                    help="ANGLE:POSITION pairs (rad, m) to report the final trials' rates at (sensitivity)")
    args = ap.parse_args(argv)
    sim = Resimulator()
    rows = []  # (k, method, seed, trial, mean return, balanced fraction, required fraction, threshold)
    worst = 0.0
    finals = []
    cartpole = (get_task("cartpole_swingup"), get_task("cartpole_balance"))  # the records this script knows
    tasks = {}  # (task, cost) -> a file of it: the tables below group by k and method only
    for path in args.results:
        res = read_result(path)
        cfg = res.config
        if cfg.task_spec not in cartpole:
            raise SystemExit(f"{path}: task {cfg.task!r} is not a cart-pole task; the balance criterion's bounds "
                             "calibrated here are the cart-pole's")
        # a file that does not name its cost ran the preset's (older files store None)
        tasks.setdefault((cfg.task, cfg.cost_name), path)
        if len(tasks) > 1:
            (t0, c0), (t1, c1) = tasks
            raise SystemExit(f"{path}: task {t1!r} with the {c1} cost, and {tasks[(t0, c0)]}: {t0!r} with the {c0} "
                             "cost; give one task and cost at a time (a threshold and a cell are one cost's)")
        for t in res.trials:
            if t.kind != "learned":
                continue
            if t.eval_balanced is not None:
                frac = float(np.mean(t.eval_balanced))
            else:
                ret, _, flags = sim.trial(res, t.index)
                worst = max(worst, float(np.max(np.abs(ret - t.eval_returns))))
                frac = float(np.mean(flags))
            rows.append((cfg.k, cfg.method, cfg.seed, t.index, t.eval_return, frac, cfg.balanced_fraction,
                         cfg.success_threshold))
        finals.append((res, rows[-1]))
    if not rows:
        raise SystemExit("no learned trials in these files")
    returns = np.array([r[4] for r in rows])
    frac = np.array([r[5] for r in rows])
    need = np.array([r[6] for r in rows])
    success = frac >= need
    fit = fit_return_threshold(returns, success)
    thesis = returns < np.array([r[7] for r in rows])
    print(f"{len(rows)} learned policies from {len(args.results)} files (re-simulated returns differ from the "
          f"stored ones by at most {worst:.1e}); {int(success.sum())} meet the physical criterion")
    print(f"best return threshold: any tau in ({fit.low:.3f}, {fit.high:.3f}]; 'return < tau' agrees with the "
          f"physical criterion on {fit.n - fit.errors} of {fit.n} policies ({fit.agreement:.1%}): "
          f"{fit.false_pass} failing policies pass, {fit.false_fail} successful ones fail")
    agree = int(np.sum(thesis == success))
    print(f"the thesis' threshold (return < 15) agrees on {agree} of {len(rows)} ({agree / len(rows):.1%})")
    by_k = defaultdict(list)
    for r, ok, th in zip(rows, success, thesis):
        by_k[r[0]].append((r, ok, th))
    for k, items in sorted(by_k.items()):
        n_agree = sum(ok == th for _, ok, th in items)
        print(f"\nk = {k:g}: {len(items)} policies, the thesis' threshold agrees on {n_agree}")
        bad = [(r, ok) for r, ok, th in items if ok != th]
        if bad:
            print("| method | seed | trial | mean return | balanced fraction | physical | return < 15 |")
            print("|---|---|---|---|---|---|---|")
            for r, ok in sorted(bad, key=lambda x: (x[0][1], x[0][2], x[0][3])):
                print(f"| {METHODS[r[1]].label} | {r[2]} | {r[3]} | {r[4]:.2f} | {r[5]:.2f} | {'yes' if ok else 'no'} | "
                      f"{'no' if ok else 'yes'} |")
    fractions = [float(x) for x in args.fractions.split(",")]
    print("\nFinal trials: success rate by required balanced fraction (sensitivity of the criterion)")
    print("| k | method | n | " + " | ".join(f">= {f:.0%}" for f in fractions) + " | return < 15 |")
    print("|---|---|---|" + "---|" * (len(fractions) + 1))
    cells = defaultdict(list)
    for _, r in finals:
        cells[(r[0], r[1])].append(r)
    for (k, m), items in sorted(cells.items()):
        rates = [f"{sum(r[5] >= f for r in items)}/{len(items)}" for f in fractions]
        print(f"| {k:g} | {METHODS[m].label} | {len(items)} | " + " | ".join(rates)
              + f" | {sum(r[4] < r[7] for r in items)}/{len(items)} |")
    bounds = [tuple(float(v) for v in b.split(":")) for b in args.bounds.split(",")]
    print("\nFinal trials: success rate (>= the configured fraction balanced) by the criterion's bounds "
          "(angle rad : cart m, last 10 states)")
    print("| k | method | n | " + " | ".join(f"{a:g} : {p:g}" for a, p in bounds) + " |")
    print("|---|---|---|" + "---|" * len(bounds))
    by_cell = defaultdict(list)
    for res, r in finals:
        by_cell[(r[0], r[1])].append((res, r))
    differ = []  # (cell, bounds, seeds whose verdict at these bounds differs from the criterion's)
    for (k, m), items in sorted(by_cell.items()):
        rates = []
        for a, p in bounds:
            passed = []
            for res, r in sorted(items, key=lambda x: x[1][2]):
                _, _, flags = sim.trial(res, len(res.trials) - 1, balance=(res.config.balance_steps, a, p))
                if float(np.mean(flags)) >= r[6]:
                    passed.append(r[2])
            rates.append(f"{len(passed)}/{len(items)}")
            moved = sorted(set(passed) ^ {r[2] for _, r in items if r[5] >= r[6]})
            if moved and (a, p) != (items[0][0].config.balance_angle, items[0][0].config.balance_position):
                differ.append(((k, m), (a, p), moved, passed))
        print(f"| {k:g} | {METHODS[m].label} | {len(items)} | " + " | ".join(rates) + " |")
    for (k, m), (a, p), moved, passed in differ:
        print(f"  k = {k:g}, {METHODS[m].label}, at {a:g} : {p:g}: the verdict differs from the criterion's on seed(s) "
              + ", ".join(f"{s} ({'passes' if s in passed else 'fails'})" for s in moved))


if __name__ == "__main__":
    main()
