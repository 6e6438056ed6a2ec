"""How total propagation weighs its two estimates at one step (estimators.md §4 step 5, §9).

``k_LR`` is the weight on the LR estimate; ``1 − k_LR`` the weight on RP.

* ``inverse_variance`` (thesis Alg. 5): ``k = σ²_RP / (σ²_RP + σ²_LR)`` with ``σ²`` the trace of the
  across-particle variance of the per-particle policy-parameter gradients. Guards: both zero → ½;
  a non-finite variance counts as +∞ (both non-finite → ½, and the caller zeroes the step).
* ``robust`` (AoBG, Suh et al., estimators.md §9): the weight on the first-order (RP) estimate is
  ``α = min(α_∞, max(γ − ε, 0)/B)`` with ``α_∞ = σ²_LR/(σ²_LR + σ²_RP)``, ``B = ‖ḡ_RP − ḡ_LR‖`` and
  ``ε = z·sqrt(σ²_LR/P)`` a confidence radius of the LR mean; ``k = 1 − α``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

COMBINERS = ("inverse_variance", "robust")


def variance_trace(g: jax.Array) -> jax.Array:
    """trace(Var_i[g_i]) over particles (ddof 1) for per-particle gradients g (P, n)."""
    return jnp.sum(jnp.var(g, axis=0, ddof=1))


def _as_inf_if_nonfinite(v: jax.Array) -> jax.Array:
    return jnp.where(jnp.isfinite(v), v, jnp.inf)


def inverse_variance_k(var_rp: jax.Array, var_lr: jax.Array) -> jax.Array:
    """k_LR = σ²_RP / (σ²_RP + σ²_LR) with the guards of estimators.md §4."""
    vr = _as_inf_if_nonfinite(var_rp)
    vl = _as_inf_if_nonfinite(var_lr)
    both_zero = (vr == 0.0) & (vl == 0.0)
    both_inf = jnp.isinf(vr) & jnp.isinf(vl)
    k = jnp.where(jnp.isinf(vr), 1.0, jnp.where(jnp.isinf(vl), 0.0, vr / jnp.where(both_zero, 1.0, vr + vl)))
    return jnp.where(both_zero | both_inf, 0.5, k)


def robust_k(
    var_rp: jax.Array,
    var_lr: jax.Array,
    mean_rp: jax.Array,
    mean_lr: jax.Array,
    num_particles: int,
    gamma: float,
    z: float,
) -> jax.Array:
    """k_LR = 1 − α_γ of the bias-aware interpolation (Suh et al., Lemma 4.4)."""
    alpha_inf = 1.0 - inverse_variance_k(var_rp, var_lr)
    bias = jnp.linalg.norm(mean_rp - mean_lr)
    eps = z * jnp.sqrt(_as_inf_if_nonfinite(var_lr) / num_particles)
    room = jnp.maximum(gamma - eps, 0.0)
    alpha = jnp.where(alpha_inf * bias <= room, alpha_inf, room / jnp.where(bias > 0, bias, 1.0))
    alpha = jnp.where(jnp.isfinite(alpha), jnp.clip(alpha, 0.0, 1.0), 0.0)
    alpha = jnp.where(jnp.isfinite(var_rp) & jnp.all(jnp.isfinite(mean_rp)), alpha, 0.0)
    return 1.0 - alpha
