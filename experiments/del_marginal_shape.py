"""How far each step's particles are from Gaussian at a snapshot of a learning run (DEL's assumption).

    JAX_PLATFORMS=cpu taskset -c 1 python experiments/del_marginal_shape.py \
        results/thesis/cartpole_balance_angle_k1_del_thesis_s3.h5 --trial 1 --trial 5

DEL fits ``q_t = N(μ̂_t, Σ̂_t)`` to the P particles of each step and uses its score in place of the
marginal's: where the particles are far from Gaussian, that score is a different function, and the
estimate is biased by an amount that does not shrink with P. At the optimisation start of each
``--trial`` (the run's policy and model there), the script draws ``--rollouts`` particle rollouts at
``--particles`` (the run's own P by default) and measures, at every step, Mardia's multivariate
statistics of the particles against their own fit (covariance with 1/P, as Mardia defines them):

* kurtosis ``b₂ = mean_i (d_iᵀ Σ̂⁻¹ d_i)²`` divided by its Gaussian value ``D(D + 2)``: 1 for a
  Gaussian, above 1 for heavy tails, below 1 for a split into separated clusters (bimodal);
* skewness ``b₁ = mean_ij (d_iᵀ Σ̂⁻¹ d_j)³``: 0 for a Gaussian, up to sampling error.

Per snapshot it prints the median over steps and rollouts, the 5 % and 95 % points, and the
fraction of steps whose kurtosis lies outside the central 99 % of the same statistic computed
from as many Gaussian samples of the same P and D (drawn in the same run, printed first), so that
every number sits beside what a Gaussian marginal gives.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from pipps.particles.forward import RolloutConfig, particle_rollout, sample_noise
from pipps.precision import enable_float64
from pipps.studies.snapshot import load_snapshot


def mardia(x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Mardia's (kurtosis / D(D+2), skewness b₁) of samples ``x`` (P, D), against their own ML fit."""
    P, D = x.shape
    d = x - jnp.mean(x, axis=0)
    cov = d.T @ d / P
    g = d @ jnp.linalg.solve(cov, d.T)  # (P, P): d_iᵀ Σ̂⁻¹ d_j
    return jnp.mean(jnp.diag(g) ** 2) / (D * (D + 2)), jnp.mean(g**3)


def shapes(x: jax.Array) -> np.ndarray:
    """(..., 2) Mardia statistics over the leading axes of particles (..., P, D)."""
    flat = x.reshape((-1,) + x.shape[-2:])
    k, s = jax.vmap(mardia)(flat)
    return np.stack([np.asarray(k), np.asarray(s)], axis=-1).reshape(x.shape[:-2] + (2,))


def row(label: str, stats: np.ndarray, gauss_k: tuple[float, float]) -> str:
    k, s = stats[..., 0].ravel(), stats[..., 1].ravel()
    outside = np.mean((k < gauss_k[0]) | (k > gauss_k[1]))
    q = lambda v: f"{np.median(v):.3g} [{np.quantile(v, 0.05):.3g}, {np.quantile(v, 0.95):.3g}]"  # noqa: E731
    return f"| {label} | {q(k)} | {outside:.2f} | {q(s)} |"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("result", nargs="+")
    ap.add_argument("--trial", type=int, action="append", required=True, help="learned trial (repeatable)")
    ap.add_argument("--particles", type=int, default=None, help="default: the run's num_particles")
    ap.add_argument("--rollouts", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.rollouts < 1:
        ap.error("--rollouts must be >= 1")
    enable_float64()
    key = jax.random.PRNGKey(args.seed)
    header = ("| snapshot | kurtosis / D(D+2), median [5 %, 95 %] | steps outside a Gaussian's 99 % "
              "| skewness b₁, median [5 %, 95 %] |\n|---|---|---|---|")
    gaussian = {}  # (P, D, T) → the central 99 % of a Gaussian's kurtosis statistic
    for path in args.result:
        for trial in args.trial:
            snap = load_snapshot(path, trial)
            P = args.particles or snap.config.num_particles
            rcfg = RolloutConfig(num_particles=P, horizon=snap.config.horizon)
            D = snap.task.model_dim
            T = rcfg.steps(snap.task)
            if P <= D + 1:
                ap.error(f"--particles {P}: Mardia's statistics need more than D + 1 = {D + 1} particles")
            if (P, D, T) not in gaussian:
                g = shapes(jax.random.normal(jax.random.fold_in(key, 10_000), (args.rollouts * T, P, D)))
                gaussian[P, D, T] = (float(np.quantile(g[:, 0], 0.005)), float(np.quantile(g[:, 0], 0.995)))
                print(f"\nP = {P}, D = {D}, {T} steps × {args.rollouts} rollouts per snapshot\n\n{header}")
                print(row(f"Gaussian samples ({args.rollouts * T} sets)", g, gaussian[P, D, T]))
            gauss_k = gaussian[P, D, T]
            rollout = jax.jit(lambda k, th: particle_rollout(snap.task, snap.unravel(th), snap.model,
                                                             sample_noise(k, snap.task, rcfg), rcfg,
                                                             jacobian=False).x_next)
            x = np.stack([np.asarray(rollout(jax.random.fold_in(key, r), snap.theta)) for r in range(args.rollouts)])
            print(row(f"{path.split('/')[-1]}, trial {trial}", shapes(jnp.asarray(x)), gauss_k))


if __name__ == "__main__":
    main()
