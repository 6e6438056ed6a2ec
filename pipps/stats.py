"""Statistics of Monte Carlo checks and of replicate gradient estimates, shared by the tests, the
benchmarks and the studies.

* :func:`z_bound` — the normal quantile a family of z-scores is held to (Bonferroni);
* :func:`mean_z`, :func:`cov_z`, :func:`cross_z` — z-scores of sample moments against exact ones,
  standard errors estimated from the samples;
* :func:`replicate_gradients` — ``num`` independent estimates of ∇θJ from one estimator;
* :func:`paired_replicate_gradients` — the same for several estimators on common random numbers;
* :func:`trace_variance`, :func:`log_variance_ratio` — their variance and a paired comparison.

A replicate splits its key into (state key, earlier-batch key, estimate key): the "previous"
baseline comes from the extra rollout of :func:`~pipps.propagation.init_estimator_state`, and an
estimator whose initial state is a cold start (TP's "previous" ``k_LR``) takes one earlier estimate
first, as an optimizer's second iteration would have them (docs/estimators.md, "Choices the thesis left open").
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import numpy as np
from jax.flatten_util import ravel_pytree

from pipps.particles.forward import RolloutConfig
from pipps.propagation.estimate import estimate, init_estimator_state
from pipps.propagation.estimators import Estimator
from pipps.propagation.pieces import EstimatorState
from pipps.tasks.base import Problem


def z_bound(num_comparisons: int, alpha: float = 1e-3, *, two_sided: bool = True) -> float:
    """The normal quantile for ``num_comparisons`` z-scores at family-wise level ``alpha`` (Bonferroni)."""
    import scipy.stats

    tail = alpha / num_comparisons / (2 if two_sided else 1)
    return float(scipy.stats.norm.isf(tail))


def mean_z(samples, expected):
    """z-scores of sample means against ``expected``."""
    se = samples.std(axis=0, ddof=1) / np.sqrt(len(samples))
    return np.abs(samples.mean(axis=0) - expected) / se


def cov_z(samples, expected):
    """z-scores of every sample-covariance entry; SE² = (E[a_c² b_c²] − cov²)/n."""
    n = len(samples)
    centred = samples - samples.mean(axis=0)
    cov_hat = centred.T @ centred / (n - 1)
    sq = centred**2
    se = np.sqrt(np.maximum(sq.T @ sq / n - cov_hat**2, 0.0) / n)
    iu = np.triu_indices(samples.shape[1])
    return np.abs(cov_hat - expected)[iu] / se[iu]


def cross_z(u, y, expected):
    """z-scores of the Stein estimate mean(u yᵀ), u = Σ⁻¹(x − μ), of C = Σ⁻¹Cov[x, y]."""
    n = len(u)
    yc = y - y.mean(axis=0)
    c_hat = u.T @ yc / n
    se = np.sqrt(np.maximum((u**2).T @ (yc**2) / n - c_hat**2, 0.0) / n)
    return np.abs(c_hat - expected).ravel() / se.ravel()


def replicate_state(
    k_state: jax.Array, k_earlier: jax.Array, policy, model, *, problem: Problem, config: RolloutConfig,
    estimator: Estimator,
) -> EstimatorState:
    """The :class:`EstimatorState` a replicate starts from, from keys independent of its estimate: the
    initial state, after one earlier estimate where that is a cold start."""
    state = init_estimator_state(k_state, policy, model, problem=problem, config=config, estimator=estimator)
    if estimator.cold_start:
        state, _ = estimate(k_earlier, state, policy, model, problem=problem, config=config, estimator=estimator)
    return state


def replicate_gradients(
    key: jax.Array, problem: Problem, model, policy, config: RolloutConfig, estimator: Estimator, num: int
) -> np.ndarray:
    """(num, n_θ) independent estimates of ∇θJ: jit + vmap over keys, in chunks with chunk·P² ≤ 5e6."""

    def one(k):
        k_state, k_earlier, k_batch = jax.random.split(k, 3)
        state = replicate_state(k_state, k_earlier, policy, model, problem=problem, config=config, estimator=estimator)
        _, e = estimate(k_batch, state, policy, model, problem=problem, config=config, estimator=estimator)
        return ravel_pytree(e.grad)[0]

    fn = jax.jit(jax.vmap(one))
    P = config.num_particles
    chunk = int(min(num, max(16, 5_000_000 // P**2)))
    keys = jax.random.split(key, -(-num // chunk) * chunk)
    return np.concatenate([np.asarray(fn(keys[i : i + chunk])) for i in range(0, len(keys), chunk)])[:num]


class Replicates(NamedTuple):
    """R independent gradient estimates per estimator, on common random numbers."""

    grad: dict  # name -> (R, n_θ) flattened gradient estimates
    k_lr: dict  # name -> (R, T) the per-step k_LR each estimate used


def paired_replicate_gradients(
    key: jax.Array, problem: Problem, model, policy, config: RolloutConfig, estimators: dict, num_replicates: int,
    *, batch_size: int = 25,
) -> Replicates:
    """``num_replicates`` independent estimates of ∇θJ for each named :class:`Estimator`.

    Every estimator gets the same three keys in a replicate, so within a replicate all see the
    same particles (common random numbers: paired comparisons of their variances are tighter), and
    across replicates everything is independent. Un-jitted; ``jax.jit`` it with the static
    arguments closed over. ``batch_size`` replicates run vectorised at a time (memory: BIW is O(P²)).
    """

    def one(k):
        kp, ks, ke = jax.random.split(k, 3)
        grads, ks_lr = {}, {}
        for name, est in estimators.items():
            state = replicate_state(kp, ks, policy, model, problem=problem, config=config, estimator=est)
            _, e = estimate(ke, state, policy, model, problem=problem, config=config, estimator=est)
            grads[name] = ravel_pytree(e.grad)[0]
            ks_lr[name] = e.diagnostics.k_lr
        return grads, ks_lr

    keys = jax.random.split(key, num_replicates)
    grads, k_lr = jax.lax.map(one, keys, batch_size=batch_size)
    return Replicates(grads, k_lr)


def trace_variance(g) -> float:
    """trace Cov_r[g_r] (ddof 1) of (R, n) replicate estimates."""
    g = np.asarray(g)
    return float(np.sum(np.var(g, axis=0, ddof=1)))


def log_variance_ratio(g_a, g_b) -> tuple[float, float]:
    """``(log(V_a/V_b), its standard error)`` for the trace variances of paired replicates.

    ``V = mean_r d_r`` with ``d_r = ‖g_r − ḡ‖²·R/(R−1)`` is a mean over replicates, so by the delta
    method ``log V̂_a − log V̂_b ≈ log(V_a/V_b) + mean_r(d_{a,r}/V_a − d_{b,r}/V_b)`` and its
    standard error is ``sd_r(d_a/V̂_a − d_b/V̂_b)/√R``. This uses the empirical fourth moments and
    the pairing, so unlike an F-test it assumes neither Gaussian gradients (it is exact in the
    large-R limit for any distribution with finite fourth moments) nor independent estimators.
    """
    a, b = np.asarray(g_a), np.asarray(g_b)
    R = a.shape[0]
    if b.shape[0] != R or R < 3:
        raise ValueError(f"need paired replicates (same R >= 3), got {a.shape} and {b.shape}")
    d_a = np.sum((a - a.mean(0)) ** 2, axis=1) * R / (R - 1)
    d_b = np.sum((b - b.mean(0)) ** 2, axis=1) * R / (R - 1)
    v_a, v_b = d_a.mean(), d_b.mean()
    influence = d_a / v_a - d_b / v_b
    return float(np.log(v_a / v_b)), float(np.std(influence, ddof=1) / np.sqrt(R))



def variance_ratio_text(g_a, g_b) -> str:
    """``"r [lo, hi]"``: the variance ratio of :func:`log_variance_ratio` with its 95 % interval, for tables."""
    log_ratio, se = log_variance_ratio(g_a, g_b)
    lo, hi = np.exp(log_ratio - 1.96 * se), np.exp(log_ratio + 1.96 * se)
    return f"{np.exp(log_ratio):.3g} [{lo:.3g}, {hi:.3g}]"