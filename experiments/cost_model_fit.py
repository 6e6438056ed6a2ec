"""Fit the cost model of :mod:`pipps.experiments.budget` to committed result files, and measure its error.

    JAX_PLATFORMS=cpu taskset -c 0 python experiments/cost_model_fit.py results/thesis results/library-tp \
        results/in-progress results/spec-init

Every learned trial of a CPU result file (not a batched or GPU one) stores ``timings`` (GP
training, policy search, whole trial) and its GP's size. The script fits the model's coefficients
to the files of even seeds (least squares on log seconds, so a trial that shared its core with other
work weighs by its ratio, not its seconds), prints them as ``budget.Coefficients(...)``, and then
predicts every odd-seed file's experiment from its configuration alone — as ``pipps run
--dry-run`` does — against the file's measured wall time, per method and task.

The coefficients are seconds at :data:`pipps.experiments.budget.REFERENCE_GFLOPS`. A trial that
stores its core's GEMM rate (``timings.extra["gemm_gflops"]``, measured after each learned trial
since 2026-11-28) has its seconds scaled to that reference, and a held-out file is predicted at its
trials' median rate, as ``--dry-run`` predicts at the rate it measures; older files hold no rate and
count as if measured at the reference.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from pipps.experiments import budget
from pipps.experiments.results import read_result, verify_result
from pipps.gp import capacity_for


def learned_rows(result):
    """Per learned trial: (the stored shape, phase seconds) with the N and M the trial really had."""
    cfg = result.config
    shape = budget.experiment_shape(cfg)
    rows, fitc_seen = [], False
    for t in result.trials:
        if t.kind != "learned" or t.gp is None or t.timings.optimize is None:
            continue
        n = int(t.gp.num_points)
        sparse = bool(t.gp.sparse)
        size = cfg.num_inducing if sparse else int(t.gp.capacity or capacity_for(n, cfg.gp_chunk))
        iters = (cfg.fitc_iters if fitc_seen else cfg.fitc_first_iters) if sparse else 0
        fitc_seen |= sparse
        if cfg.is_pilco:
            evals = float(np.asarray(t.opt_trace.evaluations)[-1])
        else:
            evals = float(cfg.policy_evals)
        rows.append((shape, budget.TrialShape(t.index, True, n, size, iters, evals), t.timings))
    return rows


def at_reference(tm) -> float:
    """The factor that takes a trial's measured seconds to the reference rate: its stored GEMM rate
    over the reference (1 where the file holds none)."""
    rate = tm.extra.get("gemm_gflops")
    return float(rate) / budget.REFERENCE_GFLOPS if rate else 1.0


def file_rate(result) -> float:
    """The median GEMM rate a file's learned trials stored (the reference where none did)."""
    rates = [float(t.timings.extra["gemm_gflops"]) for t in result.trials if t.timings.extra.get("gemm_gflops")]
    return float(np.median(rates)) if rates else budget.REFERENCE_GFLOPS


def usable(path) -> bool:
    r = read_result(path, verify=False)
    with_batch = any(t.timings.batched_seeds for t in r.trials)
    import h5py

    with h5py.File(path, "r") as f:
        device = str(f["versions"].attrs.get("device", "cpu")) if "versions" in f else "cpu"
    return not with_batch and device == "cpu" and r.trials


def fit(files) -> budget.Coefficients:
    results = [read_result(p, verify=False) for p in files]
    rows = [row for r in results for row in learned_rows(r)]
    particle = [(s, t, tm) for s, t, tm in rows if not s.pilco]
    pilco = [(s, t, tm) for s, t, tm in rows if s.pilco]

    def log_fit(model, data, target, start):
        y = np.log(np.array([target(tm) * at_reference(tm) for *_, tm in data]))

        def residual(theta):
            p = np.exp(theta)
            return np.log(np.array([model(p, s, t) for s, t, _ in data])) - y

        out = least_squares(residual, np.log(start))
        return np.exp(out.x)

    def search_particle(p, s, t):
        ratio = budget.METHOD_RATIO.get(s.method, 1.0)
        E, M, T = s.outputs, t.size, s.horizon
        return t.evaluations * ratio * T * s.particles * (p[0] * E * M * M + p[1] * E * M + p[2]) + p[3]

    def search_pilco(p, s, t):
        E, M, T = s.outputs, t.size, s.horizon
        return t.evaluations * T * (p[0] * E * E * M * M + p[1] * E * M + p[2]) + p[3]

    def gp(p, s, t):
        E, M = s.outputs, t.size
        return p[2] + (p[1] * E * t.points * M * M * t.fitc_iters if t.fitc_iters else p[0] * E * M ** 3)

    c0 = budget.COEFFICIENTS
    ps = log_fit(search_particle, particle, lambda tm: tm.optimize, [c0.variance, c0.kernel, c0.particle, c0.search])
    pp = log_fit(search_pilco, pilco, lambda tm: tm.optimize,
                [c0.pilco_mm, c0.pilco_kernel, c0.pilco_step, c0.pilco_search])
    pg = log_fit(gp, rows, lambda tm: tm.gp, [c0.gp_full, c0.gp_fitc, c0.gp_fixed])
    rest = [(tm.total - tm.gp - tm.optimize) * at_reference(tm) for *_, tm in rows if tm.total is not None]
    # a random trial stores no rate: its file's learned trials' median stands for it
    random = [t.timings.total * file_rate(r) / budget.REFERENCE_GFLOPS
              for r in results for t in r.trials if t.kind == "random" and t.timings.total]
    return budget.Coefficients(
        variance=float(ps[0]), kernel=float(ps[1]), particle=float(ps[2]), search=float(ps[3]),
        pilco_mm=float(pp[0]), pilco_kernel=float(pp[1]), pilco_step=float(pp[2]), pilco_search=float(pp[3]),
        gp_full=float(pg[0]), gp_fitc=float(pg[1]), gp_fixed=float(pg[2]),
        learned_rest=float(np.median(rest)), random_trial=float(np.median(random)))


def held_out(files, coefficients):
    """Per (task, method): each held-out file's predicted / measured experiment seconds."""
    groups: dict = {}
    for p in files:
        status, cfg, n = verify_result(Path(p))
        r = read_result(p, verify=False)
        if status != "complete":
            continue
        predicted = sum(c.total for c in budget.seconds(cfg, coefficients)) * budget.REFERENCE_GFLOPS / file_rate(r)
        groups.setdefault((cfg.task, cfg.method), []).append((predicted / r.wall_seconds, p, predicted,
                                                              r.wall_seconds))
    return groups


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folders", nargs="+")
    args = ap.parse_args(argv)
    files = sorted(p for f in args.folders for p in Path(f).glob("*.h5"))
    files = [p for p in files if usable(p)]
    seed = {p: read_result(p, verify=False).config.seed for p in files}
    train = [p for p in files if seed[p] % 2 == 0]
    test = [p for p in files if seed[p] % 2 == 1]
    print(f"{len(files)} CPU result files: {len(train)} (even seeds) fit, {len(test)} (odd seeds) held out")
    c = fit(train)
    print("budget.Coefficients(")
    for f in dataclasses.fields(c):
        print(f"    {f.name}={getattr(c, f.name):.3g},")
    print(")")
    print("\n| task | method | held-out files | predicted / measured: median | 10–90 % | median abs. error |")
    print("|---|---|---|---|---|---|")
    every = []
    for (task, method), rows in sorted(held_out(test, c).items()):
        ratio = np.array([r for r, *_ in rows])
        every += list(ratio)
        err = np.median(np.abs(ratio - 1))
        print(f"| {task} | {method} | {len(rows)} | {np.median(ratio):.2f} | {np.percentile(ratio, 10):.2f}–"
              f"{np.percentile(ratio, 90):.2f} | {err:.0%} |")
    every = np.array(every)
    print(f"\nall held-out files: median predicted/measured {np.median(every):.2f}, "
          f"median |error| {np.median(np.abs(every - 1)):.0%}, within a factor 1.5: "
          f"{np.mean((every > 1 / 1.5) & (every < 1.5)):.0%}, log-ratio sd {np.std(np.log(every)):.2f} "
          f"(×{math.exp(np.std(np.log(every))):.2f})")


if __name__ == "__main__":
    main()
