"""Likelihood-ratio gradients in distribution-parameter space (thesis eq. 4.2–4.3).

At a step t the particles ``x_j`` were drawn from ``N(μ_j, diag(s_j²))``. The LR gradient
with respect to each component's parameters ``ζ_i = (μ_i, s_i)`` is

``γ_i = Σ_j w_ij (G_j − b_ij) ∇_{ζ_i} log p(x_j | ζ_i)``,

with ``∇_μ log p = (x − μ)/s²`` and ``∇_s log p = ((x − μ)² − s²)/s³`` (diagonal Gaussian).

* plain LR: ``w_ij = δ_ij`` and the leave-one-out mean baseline (exactly unbiased);
* batch importance weighting (BIW): ``w_ij = p(x_j|ζ_i) / Σ_k p(x_j|ζ_k)``, computed in log
  space as a softmax over ``i`` for each ``j`` — raw densities are never formed.

BIW baselines: ``"previous"`` (a per-step constant from the previous optimizer iteration; unbiased),
``"thesis"`` (eq. 4.3, an importance-weighted leave-one-out baseline per component; biased, see
docs/estimators.md) and ``"none"``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

WEIGHTINGS = ("biw", "plain")
BASELINES = ("previous", "thesis", "none")
#: plain LR's baselines: the leave-one-out mean (exactly unbiased), each particle's zero-noise rollout
#: (Suh et al. §II.B; unbiased: it depends on the particle's start only), or none
PLAIN_BASELINES = ("leave_one_out", "zero_noise", "none")
#: what plain LR weighs step t's score by: the return-to-go ``G_{i,t}`` or the whole return ``V_i``
#: (Suh et al.'s ZoBG, Definition II.1); both unbiased, the return-to-go has less variance
RETURNS = ("to_go", "total")


class ZetaGrad(NamedTuple):
    """A cotangent on ζ = (μ, s), per particle."""

    mean: jax.Array  # (P, D)
    std: jax.Array  # (P, D)


def _centred(x: jax.Array, mean: jax.Array) -> tuple[jax.Array, jax.Array]:
    """x and μ shifted by the mean of μ over particles (see :func:`log_density_matrix`)."""
    c = jnp.mean(mean, axis=0)
    return x - c, mean - c


def log_density_matrix(x: jax.Array, mean: jax.Array, std: jax.Array) -> jax.Array:
    """L[i, j] = log N(x_j | μ_i, diag(s_i²)) up to the constant −(D/2) log 2π, shape (P, P).

    Expanded into one (P, 2D) × (2D, P) matrix product,
    ``Σ_d (x_jd − μ_id)²/s_id² = Σ_d [x_jd²/s_id² − 2 x_jd μ_id/s_id²] + Σ_d μ_id²/s_id²``,
    instead of forming the (P, P, D) differences: an order of magnitude faster at P = 300
    (docs/performance.md). The expansion loses about ε·(spread/s)² in absolute terms, where
    spread is the particles' distance from their centre, so x and μ are centred first;
    at s = 10⁻⁴·spread that is ~10⁻⁸ in float64.
    """
    xc, mc = _centred(x, mean)
    prec = 1.0 / std**2
    a = jnp.concatenate([prec, -2.0 * prec * mc], axis=1)  # (P, 2D)
    b = jnp.concatenate([xc**2, xc], axis=1)  # (P, 2D)
    quad = a @ b.T + jnp.sum(prec * mc**2, axis=1)[:, None]
    quad = jnp.maximum(quad, 0.0)  # a sum of squares; rounding may not make it negative
    return -0.5 * quad - jnp.sum(jnp.log(std), axis=-1)[:, None]


def biw_weights(x: jax.Array, mean: jax.Array, std: jax.Array) -> jax.Array:
    """w[i, j] = p(x_j | ζ_i) / Σ_k p(x_j | ζ_k): a softmax over i of the log densities (eq. 4.2)."""
    return jax.nn.softmax(log_density_matrix(x, mean, std), axis=0)


def leave_one_out_mean(values: jax.Array) -> jax.Array:
    """b_i = mean_{j≠i} values_j."""
    P = values.shape[0]
    return (jnp.sum(values) - values) / (P - 1)


def thesis_baseline(weights: jax.Array, returns: jax.Array, *, tiny: float = 1e-300) -> jax.Array:
    """Eq. 4.3: b_i = Σ_{j≠i} w_ij G_j / Σ_{j≠i} w_ij, the plain leave-one-out mean where that underflows."""
    off = weights * (1.0 - jnp.eye(weights.shape[0], dtype=weights.dtype))
    den = jnp.sum(off, axis=1)
    num = off @ returns
    ok = den > tiny
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), leave_one_out_mean(returns))


def score_weighted(coef: jax.Array, x: jax.Array, mean: jax.Array, std: jax.Array) -> ZetaGrad:
    """γ_i = Σ_j coef_ij ∇_{ζ_i} log p(x_j | ζ_i) for a (P, P) coefficient matrix.

    With centred x, μ: ``Σ_j c_ij (x_j − μ_i) = (c x)_i − μ_i Σ_j c_ij`` and
    ``Σ_j c_ij (x_j − μ_i)² = (c x²)_i − 2 μ_i (c x)_i + μ_i² Σ_j c_ij`` — one (P, P) × (P, 2D)
    product instead of (P, P, D) differences.
    """
    xc, mc = _centred(x, mean)
    D = x.shape[1]
    moments = coef @ jnp.concatenate([xc, xc**2], axis=1)  # (P, 2D)
    m1, m2 = moments[:, :D], moments[:, D:]
    total = jnp.sum(coef, axis=1)[:, None]
    first = m1 - mc * total
    second = m2 - 2.0 * mc * m1 + mc**2 * total
    s2 = std**2
    return ZetaGrad(first / s2, (second - s2 * total) / (s2 * std))


def plain_lr(x: jax.Array, mean: jax.Array, std: jax.Array, returns: jax.Array) -> ZetaGrad:
    """Plain LR with the leave-one-out baseline: γ_i = (G_i − b_i) ∇_{ζ_i} log p(x_i | ζ_i)."""
    return own_score(returns - leave_one_out_mean(returns), x, mean, std)


def own_score(advantage: jax.Array, x: jax.Array, mean: jax.Array, std: jax.Array) -> ZetaGrad:
    """γ_i = A_i ∇_{ζ_i} log p(x_i | ζ_i) for advantages A (P,): each sample scored under its own component.

    Uses the standardised noise directly: ``(x − μ)/s² = ε/s`` and ``((x−μ)² − s²)/s³ = (ε² − 1)/s``.
    """
    adv = advantage[:, None]
    eps = (x - mean) / std
    return ZetaGrad(adv * eps / std, adv * (eps**2 - 1.0) / std)


def biw_lr(
    x: jax.Array,
    mean: jax.Array,
    std: jax.Array,
    returns: jax.Array,
    baseline: str,
    previous_baseline: jax.Array | None = None,
) -> ZetaGrad:
    """Batch-importance-weighted LR (eq. 4.2) with the chosen baseline (static string)."""
    w = biw_weights(x, mean, std)
    if baseline == "thesis":
        b = thesis_baseline(w, returns)[:, None]  # b_ij = b_i
    elif baseline == "previous":
        if previous_baseline is None:
            raise ValueError("the 'previous' baseline needs the previous iteration's mean return")
        b = previous_baseline
    elif baseline == "none":
        b = 0.0
    else:
        raise ValueError(f"unknown baseline {baseline!r}; choose one of {BASELINES}")
    coef = w * (returns[None, :] - b)
    return score_weighted(coef, x, mean, std)
