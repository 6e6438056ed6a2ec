"""Gradient variance of RP, plain LR, BIW-LR and TP on the kicked rotor (docs/estimator-variance.md).

Fixed protocol (:mod:`pipps.systems.chaotic`): the controlled standard map, ``"chaotic"``
(K = 2) and ``"smooth"`` (K = 0.1), T = 30, the fixed saturated linear policy (4 parameters),
zero epistemic variance. For each setting and P, R replicates of every estimator on common
random numbers (:func:`~pipps.stats.paired_replicate_gradients`: BIW-LR's "previous"
baseline from an independent extra rollout, TP's "previous" k_LR from an independent earlier
estimate). Variance = trace of the covariance over replicates. Ratios come with a 95 % interval
from the delta method on paired replicates (:func:`~pipps.stats.log_variance_ratio`).

Printed (markdown): the finite-time Lyapunov exponents; per setting, the variance table with
TP/BIW-LR; the share of TP's variance owed to its single largest replicate (heavy tails); the
mean difference between the thesis' TP (batch k_LR) and the unbiased BIW-LR on the same particles
(its bias); TP's mean per-step k_LR; and TP's variance for constant k_LR (the λ-mixing of Alg. 5 alone).

    JAX_PLATFORMS=cpu python benchmarks/estimator_variance.py             # the documented numbers
    JAX_PLATFORMS=cpu python benchmarks/estimator_variance.py --quick     # a smoke run
"""

from __future__ import annotations

import argparse
import functools
import time

import jax
import numpy as np

import pipps
from pipps.particles.forward import RolloutConfig
from pipps.propagation.estimators import estimator
from pipps.stats import paired_replicate_gradients, trace_variance, variance_ratio_text
from pipps.systems.chaotic import SETTINGS, finite_time_lyapunov, kicked_rotor_system

pipps.enable_float64()

ESTIMATORS = {
    "RP": estimator("rp"),
    "plain LR": estimator("lr_plain"),
    "BIW-LR": estimator("lr"),
    "TP": estimator("tp", k_lr="previous"),  # k_LR from the previous iteration, as docs/estimator-variance.md measured
    # it (the library default since is leave-one-out, estimator("tp"))
    "TP (batch k)": estimator("tp", k_lr="batch"),  # the thesis' choice (biased)
}


def run_replicates(setting: str, P: int, R: int, seed: int, estimators: dict):
    task, model, policy = kicked_rotor_system(setting)
    cfg = RolloutConfig(num_particles=P, model_variance=False)
    run = jax.jit(
        functools.partial(
            paired_replicate_gradients, problem=task, model=model, policy=policy, config=cfg,
            estimators=estimators, num_replicates=R,
        )
    )
    out = run(jax.random.PRNGKey(seed))
    return {n: np.asarray(g) for n, g in out.grad.items()}, {n: np.asarray(k) for n, k in out.k_lr.items()}



def top_share(g) -> float:
    """Share of the trace variance owed to the single most deviant replicate."""
    d = np.sum((g - g.mean(0)) ** 2, axis=1)
    return float(d.max() / d.sum())


def bias_cell(g_a, g_b) -> str:
    """Mean difference of paired estimates: ‖ḡ_a − ḡ_b‖/‖ḡ_b‖ and the largest per-coordinate |z|."""
    d = g_a - g_b
    z = d.mean(0) / (d.std(0, ddof=1) / np.sqrt(d.shape[0]))
    return f"{np.linalg.norm(d.mean(0)) / np.linalg.norm(g_b.mean(0)):.2f} ({np.max(np.abs(z)):.1f})"


def lyapunov_table(seed: int) -> list[str]:
    lines = ["| setting | K | T | mean λ | 10 % | median | 90 % | max |", "|---|---|---|---|---|---|---|---|"]
    for setting, s in SETTINGS.items():
        task, model, policy = kicked_rotor_system(setting)
        lam = np.asarray(finite_time_lyapunov(jax.random.PRNGKey(seed), task, model, policy, num_particles=2000))
        q = np.quantile(lam, [0.1, 0.5, 0.9])
        lines.append(f"| {setting} | {s['kick']} | {s['horizon']} | {lam.mean():.3f} | {q[0]:.3f} | {q[1]:.3f} | {q[2]:.3f} | {lam.max():.3f} |")
    return lines


def variance_tables(setting: str, particles, replicates, seed: int) -> tuple[list[str], list[str]]:
    names = list(ESTIMATORS)
    head = ["P", "R", *names, "TP / BIW-LR", "TP (batch k) / BIW-LR", "BIW-LR / plain LR", "top replicate's share of TP var",
            "TP (batch k) − BIW-LR: rel. mean diff. (max abs z)"]
    var_lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    k_profiles = {}
    for P in particles:
        R = replicates(P)
        g, k = run_replicates(setting, P, R, seed + P, ESTIMATORS)
        cells = [str(P), str(R), *(f"{trace_variance(g[n]):.3g}" for n in names)]
        cells += [variance_ratio_text(g["TP"], g["BIW-LR"]), variance_ratio_text(g["TP (batch k)"], g["BIW-LR"]), variance_ratio_text(g["BIW-LR"], g["plain LR"])]
        cells += [f"{top_share(g['TP']):.2f}", bias_cell(g["TP (batch k)"], g["BIW-LR"])]
        var_lines.append("| " + " | ".join(cells) + " |")
        k_profiles[P] = (k["TP"].mean(0), k["TP (batch k)"].mean(0))
    T = len(next(iter(k_profiles.values()))[0])
    head = ["t", *(f"TP P={P}" for P in particles), *(f"TP (batch k) P={P}" for P in particles)]
    k_lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for t in range(T):
        row = [str(t + 1), *(f"{k_profiles[P][0][t]:.2f}" for P in particles), *(f"{k_profiles[P][1][t]:.2f}" for P in particles)]
        k_lines.append("| " + " | ".join(row) + " |")
    return var_lines, k_lines


def k_sweep_table(P: int, R: int, ks, seed: int) -> list[str]:
    ests = {f"k={k:g}": estimator("tp", k_lr=float(k)) for k in ks}
    lines = ["| setting | " + " | ".join(ests) + " |", "|---|" + "---|" * len(ests)]
    for setting in SETTINGS:
        g, _ = run_replicates(setting, P, R, seed + 7 * P, ests)
        lines.append(f"| {setting} | " + " | ".join(f"{trace_variance(g[n]):.3g}" for n in ests) + " |")
    return lines


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--particles", type=int, nargs="+", default=[10, 30, 100, 300])
    ap.add_argument("--replicates", type=int, default=1000, help="R per (setting, P)")
    ap.add_argument("--replicates-large-p", type=int, default=400, help="R for P >= 300 (O(P²) BIW)")
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    ap.add_argument("--k-sweep", type=float, nargs="*", default=[0.0, 0.1, 0.25, 0.5, 0.75, 1.0], help="constant k_LR values (empty: skip)")
    ap.add_argument("--k-sweep-particles", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="smoke run: P ∈ {10, 30}, R = 50")
    args = ap.parse_args(argv)
    if args.quick:
        args.particles, args.replicates, args.k_sweep_particles = [10, 30], 50, 30
    replicates = lambda P: args.replicates if P < 300 else min(args.replicates, args.replicates_large_p)  # noqa: E731

    start = time.perf_counter()
    print(f"jax {jax.__version__}, backend {jax.default_backend()}, seed {args.seed}\n")
    print("### Finite-time maximal Lyapunov exponents (per step, 2000 particles)\n")
    print("\n".join(lyapunov_table(args.seed)) + "\n")
    for setting in args.settings:
        var_lines, k_lines = variance_tables(setting, args.particles, replicates, args.seed)
        print(f"### {setting}: trace of the covariance of the gradient estimate over R replicates\n")
        print("\n".join(var_lines) + "\n")
        print(f"### {setting}: TP's mean k_LR per step (over replicates)\n")
        print("\n".join(k_lines) + "\n")
    if args.k_sweep:
        P = args.k_sweep_particles
        R = replicates(P)
        print(f"### TP with a constant k_LR (P = {P}, R = {R}): variance (trace)\n")
        print("\n".join(k_sweep_table(P, R, args.k_sweep, args.seed)) + "\n")
    print(f"wall time: {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
