"""Bias of the thesis' own estimator choices on the linear-Gaussian benchmark (docs/estimator-bias.md).

The benchmark is :func:`pipps.systems.reference_system` (3 states, 1 control, T = 10, linear
policy, saturating cost) at two noise levels, where ``jax.grad(exact_objective)`` is the exact
gradient of ``J = Σ_{t=1..T} E[c(x_t)]``. For each estimator and particle count P we draw R
independent replicate estimates and report the relative bias of their mean,

    rel. bias = ‖ḡ − ∇J‖ / ‖∇J‖,

with a delta-method standard error ``sqrt(dᵀ Σ̄ d)/(‖d‖ ‖∇J‖)`` (``d = ḡ − ∇J``, ``Σ̄`` the sample
covariance of the replicates over R). Because ``E‖d‖² = ‖bias‖² + tr Σ̄``, the plug-in ``‖d‖`` reads
about the *noise floor* ``sqrt(tr Σ̄)/‖∇J‖`` even for an exactly unbiased estimator; the table also
gives the floor-corrected value ``sqrt(max(‖d‖² − tr Σ̄, 0))/‖∇J‖``. A bias counts as *detected*
when some coordinate's ``|z| = |d_k|/SE_k`` exceeds the Bonferroni bound for all rows × coordinates
at family-wise α = 1e-3; for rows without a detected bias the delta-method error is not meaningful
(``‖d‖`` is then pure noise).

Replicate r uses three independent keys from ``split(fold_in(PRNGKey(seed), config), R)[r]``:
one for the extra rollout of ``init_estimator_state`` (the first iteration's "previous" baseline),
one for an earlier, independent estimate whose state carries the "previous" ``k_LR`` (only where
the estimator uses it), and one for the estimate that is recorded. So "previous" quantities are
independent of the batch they enter, as in the optimizer at a fixed policy.

R scales as ``--budget / P`` (R·P particles per configuration; default 1.2e6: R = 40,000 at P = 30,
12,000 at P = 100, 4,000 at P = 300).

    python benchmarks/estimator_bias.py                     # the numbers in docs/estimator-bias.md
    python benchmarks/estimator_bias.py --json bias.json    # also write every number (bias vectors, SEs)
    python benchmarks/estimator_bias.py --quick             # a smoke run (R·P = 3e4, P ≤ 100)

An existing ``--json`` file is refused before any work unless ``--overwrite`` is given.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
import zlib
from pathlib import Path

import jax
import numpy as np
from jax.flatten_util import ravel_pytree

import pipps
from pipps.experiments.storage import OutputError, check_new_file, publish
from pipps.particles.forward import RolloutConfig
from pipps.propagation.cost_terms import density_estimation_costs
from pipps.propagation.estimators import compose, estimator, thesis_estimator
from pipps.propagation.parts import pathwise
from pipps.stats import replicate_gradients, z_bound
from pipps.systems import exact_objective, reference_system

pipps.enable_float64()

# name: (estimator, particle counts, what the row shows)
ESTIMATORS = {
    "lr thesis-baseline": (estimator("lr", baseline="thesis"), (30, 100, 300), "BIW-LR, eq. 4.3 baseline"),
    "lr (default)": (estimator("lr"), (30, 100, 300), "BIW-LR, previous baseline (unbiased control)"),
    "tp thesis-baseline": (estimator("tp", baseline="thesis", k_lr="previous"), (30, 100, 300), "TP, eq. 4.3 baseline, previous k"),
    "tp thesis preset": (thesis_estimator("tp"), (30, 100, 300), "TP, eq. 4.3 baseline, batch k (thesis)"),
    "tp k=batch": (estimator("tp", k_lr="batch"), (30, 100), "TP, previous baseline, batch k"),
    "tp previous": (estimator("tp", k_lr="previous"), (30, 100), "TP, previous baseline, previous k (unbiased control)"),
    "del thesis preset": (thesis_estimator("del"), (30, 100), "DEL (thesis §3.3.1), pathwise fit derivative, returns-to-go"),
    "del (default)": (estimator("del"), (30, 100, 300), "DEL, the fit's derivative one step to θ (consistent: bias O(1/P))"),
    "del own-cost": (compose(density_estimation_costs(weights="cost"), pathwise()), (30, 100, 300),
                     "DEL, pathwise fit derivative, each step's own cost as the weight"),
}
NOISE_STDS = (0.1, 0.3)
COST = "saturating"


def exact_gradient(task, model, policy, config: RolloutConfig) -> np.ndarray:
    grad = jax.grad(exact_objective, argnums=2)(task, model, policy, noise_scale=config.noise_multiplier)
    return np.asarray(ravel_pytree(grad)[0])


def bias_summary(grads: np.ndarray, exact: np.ndarray) -> dict:
    """Relative bias of the replicate mean, its delta-method SE, the noise floor, per-coordinate z."""
    R = grads.shape[0]
    mean = grads.mean(axis=0)
    cov_mean = np.cov(grads, rowvar=False, ddof=1) / R
    se = np.sqrt(np.diag(cov_mean))
    d = mean - exact
    norm_g, norm_d = np.linalg.norm(exact), np.linalg.norm(d)
    return {
        "replicates": R,
        "exact": exact.tolist(),
        "mean": mean.tolist(),
        "bias": d.tolist(),
        "bias_se": se.tolist(),
        "z": (d / se).tolist(),
        "rel_bias": norm_d / norm_g,
        "rel_bias_corrected": float(np.sqrt(max(norm_d**2 - np.trace(cov_mean), 0.0))) / norm_g,
        "rel_bias_se": float(np.sqrt(d @ cov_mean @ d)) / (norm_d * norm_g),
        "noise_floor": float(np.sqrt(np.trace(cov_mean))) / norm_g,
        "rel_se_per_replicate": float(np.sqrt(np.trace(cov_mean) * R)) / norm_g,
    }


def config_key(seed: int, label: str) -> jax.Array:
    """A fixed key per configuration, independent of the order in which configurations run."""
    return jax.random.fold_in(jax.random.PRNGKey(seed), zlib.crc32(label.encode()) & 0x7FFFFFFF)


def run(budget: int, seed: int, names, particles, noise_stds, log=print) -> list[dict]:
    rows = []
    for noise in noise_stds:
        task, model, policy = reference_system(noise, COST)
        for name in names:
            est, counts, _ = ESTIMATORS[name]
            for P in (p for p in counts if p in particles):
                config = RolloutConfig(num_particles=P)
                R = max(2, budget // P)
                label = f"{name}|P={P}|noise={noise}"
                t0 = time.perf_counter()
                grads = replicate_gradients(config_key(seed, label), task, model, policy, config, est, R)
                row = {"estimator": name, "P": P, "noise_std": noise, "seconds": time.perf_counter() - t0}
                row.update(bias_summary(grads, exact_gradient(task, model, policy, config)))
                rows.append(row)
                log(f"# {label}: R={R} rel.bias={row['rel_bias']:.4f}±{row['rel_bias_se']:.4f} "
                    f"floor={row['noise_floor']:.4f} max|z|={np.max(np.abs(row['z'])):.1f} ({row['seconds']:.0f} s)")
    return rows


def markdown_table(rows: list[dict]) -> str:
    bound = z_bound(sum(len(r["z"]) for r in rows))
    lines = [
        f"Bias detected: max |z| > {bound:.2f} (Bonferroni, α = 1e-3 over {sum(len(r['z']) for r in rows)} coordinates).",
        "",
        "| estimator | noise σ | P | R | rel. bias ± SE | floor-corrected | noise floor | max \\|z\\| (coord) | detected | bias vector ± SE |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        z = np.abs(r["z"])
        vec = ", ".join(f"{b:+.4f}±{s:.4f}" for b, s in zip(r["bias"], r["bias_se"]))
        lines.append(
            f"| {r['estimator']} | {r['noise_std']} | {r['P']} | {r['replicates']} | "
            f"{100 * r['rel_bias']:.2f} % ± {100 * r['rel_bias_se']:.2f} % | {100 * r['rel_bias_corrected']:.2f} % | "
            f"{100 * r['noise_floor']:.2f} % | {z.max():.1f} ({int(z.argmax())}) | {'yes' if z.max() > bound else 'no'} | {vec} |"
        )
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--budget", type=int, default=1_200_000, help="R·P per configuration (R = budget // P)")
    ap.add_argument("--seed", type=int, default=20240611)
    ap.add_argument("--estimators", nargs="+", default=list(ESTIMATORS), choices=list(ESTIMATORS))
    ap.add_argument("--particles", type=int, nargs="+", default=[30, 100, 300])
    ap.add_argument("--noise", type=float, nargs="+", default=list(NOISE_STDS))
    ap.add_argument("--json", help="write every number (bias vectors, SEs, timings) to this file "
                                   "(an existing file is refused without --overwrite)")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing --json file")
    ap.add_argument("--quick", action="store_true", help="R·P = 3e4, P ≤ 100: a smoke run")
    args = ap.parse_args(argv)
    command = Path(__file__).name
    if args.json:  # before any work: an existing file is kept unless --overwrite (docs/reliability.md)
        try:
            check_new_file(args.json, overwrite=args.overwrite, option="--json", suffix=".json", command=command)
        except OutputError as err:
            ap.exit(2, f"{command}: error: {err}\n")
    if args.quick:
        args.budget, args.particles = 30_000, [p for p in args.particles if p <= 100]
    t0 = time.perf_counter()
    print(f"# estimator bias: reference_system({COST!r}, T=10), R = {args.budget} // P, seed {args.seed}")
    print(f"# machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"jax {jax.__version__}, {jax.devices()[0].platform}")
    rows = run(args.budget, args.seed, args.estimators, args.particles, args.noise)
    wall = time.perf_counter() - t0
    print()
    print(markdown_table(rows))
    print(f"\n# wall time {wall:.0f} s")
    if args.json:
        record = {k: v for k, v in vars(args).items() if k != "overwrite"}
        try:  # written beside it and moved into place whole; a file that appeared meanwhile is kept
            with publish(args.json, overwrite=args.overwrite, command=command) as tmp, open(tmp, "w") as f:
                json.dump({"args": record, "wall_seconds": wall, "rows": rows}, f, indent=1)
        except OutputError as err:
            ap.exit(1, f"{command}: error: {err}\n")


if __name__ == "__main__":
    main()
