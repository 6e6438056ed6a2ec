"""Combiners: how one step's gradient parts become one contribution (estimators.md §4 steps 5–7, §9).

A combiner is a strategy piece with ``combine(kinds, g, messages, k_previous, has_previous) ->
Combined``: from the parts' per-particle θ-gradients (and, where a pathwise part is present, the
x-cotangents each part would pass back) it chooses ``k_LR`` — the weight on the LR part, ``1 − k_LR``
on the pathwise part — and mixes gradients and messages with it.

* :func:`single`: one part, taken as it is (``k_LR`` reported as 0 for RP, 1 for LR).
* :func:`inverse_variance` and :func:`robust`: total propagation of a pathwise and an LR part, the
  weight of this batch from the rule below and the weight used from ``k_lr``: "batch" (the thesis),
  "previous" (the previous iteration's batch weight; this batch's on the first) or a fixed number.

* ``inverse_variance`` (thesis Alg. 5): ``k = σ²_RP / (σ²_RP + σ²_LR)`` with ``σ²`` the trace of the
  across-particle variance of the per-particle policy-parameter gradients. Guards: both zero → ½;
  a non-finite variance counts as +∞ (both non-finite → ½, and the caller zeroes the step).
* ``robust`` (AoBG, Suh et al., estimators.md §9): the weight on the first-order (RP) estimate is
  ``α = min(α_∞, max(γ − ε, 0)/B)`` with ``α_∞ = σ²_LR/(σ²_LR + σ²_RP)``, ``B = ‖ḡ_RP − ḡ_LR‖`` and
  ``ε = z·sqrt(σ²_LR/P)`` a confidence radius of the LR mean; ``k = 1 − α``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from pipps.propagation.parts import LIKELIHOOD_RATIO
from pipps.propagation.strategy import strategy

COMBINERS = ("inverse_variance", "robust")
K_SOURCES = ("batch", "previous")


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


def mix(k: jax.Array, lr: jax.Array, rp: jax.Array) -> jax.Array:
    """k·lr + (1 − k)·rp, exactly lr at k = 1 and exactly rp at k = 0 even if the other is not finite."""
    return jnp.where(k == 1.0, lr, jnp.where(k == 0.0, rp, k * lr + (1.0 - k) * rp))


class Combined(NamedTuple):
    """One step's combination of the gradient parts."""

    k: jax.Array  # the weight used on the LR part
    k_batch: jax.Array  # the weight this batch's statistics give (what "previous" reads next time)
    variances: tuple  # σ² = trace Var_i[g_{i,t}] of each part, in the parts' order
    gradient: jax.Array  # (P, n_θ) each particle's contribution at this step
    message: jax.Array | None  # (P, D) ∂G_i/∂x_{i,t−1} passed back; None where no part reads it


@strategy
class BatchWeight:
    """k_LR from this batch's variances (the thesis, Alg. 5; biased, estimators.md §4)."""

    k_lr = "batch"

    def choose(self, k_batch, k_previous, has_previous):
        del k_previous, has_previous
        return k_batch


@strategy
class PreviousWeight:
    """k_LR from the previous optimizer iteration's batch, this batch's on the first (estimators.md §4)."""

    k_lr = "previous"

    def choose(self, k_batch, k_previous, has_previous):
        return jnp.where(has_previous, k_previous, k_batch)


@strategy(traced=("k",))
class FixedWeight:
    """A fixed k_LR (0 is RP, 1 is LR); a traced number."""

    k: float

    @property
    def k_lr(self):
        return self.k

    def choose(self, k_batch, k_previous, has_previous):
        del k_previous, has_previous
        return jnp.asarray(self.k, dtype=k_batch.dtype)


@strategy
class Single:
    """One gradient part, taken as it is."""

    name = "single"
    num_parts = 1
    k_lr = None

    def combine(self, kinds, g, messages, k_previous, has_previous) -> Combined:
        del k_previous, has_previous
        k = jnp.asarray(1.0 if kinds[0] == LIKELIHOOD_RATIO else 0.0, g.dtype)
        return Combined(k, k, (variance_trace(g[0]),), g[0], None if messages is None else messages[0])


def _total_propagation(rule, g, messages, k_previous, has_previous) -> Combined:
    """Steps 5–7 of estimators.md §4 for parts (pathwise, LR); a non-finite part gets no weight."""
    g_rp, g_lr = g[0], g[1]
    var_rp, var_lr = variance_trace(g_rp), variance_trace(g_lr)
    k_batch = rule.batch_weight(var_rp, var_lr, g_rp.mean(0), g_lr.mean(0), g_rp.shape[0])
    k = rule.source.choose(k_batch, k_previous, has_previous)
    k = jnp.where(jnp.isfinite(var_rp), k, 1.0)
    k = jnp.where(jnp.isfinite(var_lr), k, jnp.where(jnp.isfinite(var_rp), 0.0, k))
    message = None if messages is None else mix(k, messages[1], messages[0])
    return Combined(k, k_batch, (var_rp, var_lr), mix(k, g_lr, g_rp), message)


class _TotalPropagationCombiner:
    """What the two total-propagation combiners share: two parts, ``k_LR`` from their ``source``,
    and the combination of :func:`_total_propagation`; each defines its own ``batch_weight``."""

    num_parts = 2

    @property
    def k_lr(self):
        return self.source.k_lr

    def combine(self, kinds, g, messages, k_previous, has_previous) -> Combined:
        del kinds
        return _total_propagation(self, g, messages, k_previous, has_previous)


@strategy(traced=("source",))
class InverseVariance(_TotalPropagationCombiner):
    """Total propagation with the inverse-variance weight (thesis Alg. 5; estimators.md §4)."""

    source: BatchWeight | PreviousWeight | FixedWeight

    name = "inverse_variance"

    def batch_weight(self, var_rp, var_lr, mean_rp, mean_lr, num_particles):
        del mean_rp, mean_lr, num_particles
        return inverse_variance_k(var_rp, var_lr)


@strategy(traced=("gamma", "z", "source"))
class Robust(_TotalPropagationCombiner):
    """Total propagation with the bias-aware weight of Suh et al. (estimators.md §9); γ and z are traced."""

    gamma: float
    z: float
    source: BatchWeight | PreviousWeight | FixedWeight

    name = "robust"

    def batch_weight(self, var_rp, var_lr, mean_rp, mean_lr, num_particles):
        return robust_k(var_rp, var_lr, mean_rp, mean_lr, num_particles, self.gamma, self.z)


def weight_source(k_lr: str | float = "previous") -> BatchWeight | PreviousWeight | FixedWeight:
    """Where total propagation's k_LR comes from: "batch", "previous" or a number in [0, 1]."""
    if isinstance(k_lr, str):
        if k_lr == "batch":
            return BatchWeight()
        if k_lr == "previous":
            return PreviousWeight()
        raise ValueError(f"k_lr must be one of {K_SOURCES} or a number in [0, 1], got {k_lr!r}")
    if not 0.0 <= float(k_lr) <= 1.0:
        raise ValueError(f"a fixed k_lr must lie in [0, 1], got {k_lr}")
    return FixedWeight(float(k_lr))


def single() -> Single:
    """The combiner of a one-part estimator."""
    return Single()


def inverse_variance(k_lr: str | float = "previous") -> InverseVariance:
    """Total propagation's inverse-variance combiner (thesis Alg. 5) with the given k_LR source."""
    return InverseVariance(weight_source(k_lr))


def robust(gamma: float = float("inf"), z: float = 2.0, k_lr: str | float = "previous") -> Robust:
    """The robust combiner (estimators.md §9): bias bound ``γ ≥ 0`` (∞: inverse variance), confidence ``z ≥ 0``."""
    if not float(gamma) >= 0.0:
        raise ValueError(f"robust_gamma must be >= 0 (inf allowed), got {gamma}")
    if not 0.0 <= float(z) < float("inf"):
        raise ValueError(f"robust_z must be finite and >= 0, got {z}")
    return Robust(float(gamma), float(z), weight_source(k_lr))
