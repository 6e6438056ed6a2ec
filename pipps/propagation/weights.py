"""Weight sources: where a two-part combiner's ``k_LR`` comes from (thesis Alg. 5 takes this batch's).

A weight source is a :class:`~pipps.propagation.pieces.WeightSource`. Given this batch's weight
``k_batch`` (the combiner's rule applied to this batch's variances) and the per-particle
θ-gradients of the two parts, it returns the weight used: one per step, or one per particle.

* ``"batch"`` (:class:`BatchWeight`): this batch's weight (the thesis, Alg. 5; biased, docs/estimator-bias.md);
* ``"previous"`` (:class:`PreviousWeight`): the previous iteration's batch weight, this batch's on the
  first iteration (exactly unbiased); its state is that weight per step;
* a number in [0, 1] (:class:`FixedWeight`, traced);
* ``"leave_one_out"`` (:class:`LeaveOneOutWeight`, the library default :data:`DEFAULT_K_LR`):
  particle i's weight from the other P − 1 particles' variances; ``"split"`` (:class:`SplitWeight`):
  from the other half's (docs/estimators.md, "Choosing k_LR");
* ``"guarded"`` (:class:`GuardedWeight`): "previous", but 1 where this batch's weight is above a threshold;
* ``"moving_average"`` (:class:`~pipps.propagation.moving_average.MovingAverageWeight`): an exponential
  moving average of the earlier iterations' batch weights.

``"cross_fit"`` (exactly unbiased, from half-batch sweeps) is not a weight source but a sweep
schedule: :func:`pipps.propagation.schedules.cross_fitted`.

A source with memory keeps it per step (``weight_shape`` is one step's weight: ``()``, or one per
node at the action nodes); the combiner hands it step t's slice.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from pipps.propagation.moving_average import MovingAverageWeight, moving_average
from pipps.propagation.pieces import InitContext, WeightSource
from pipps.propagation.strategy import strategy

#: The library's k_LR (docs/estimator-variance.md, "Choosing k_LR"): each particle's weight from the
#: other P − 1 particles' variances. Not exactly unbiased (O(1/P): 1.0 % of ‖∇J‖ at P = 30 on the
#: linear-Gaussian system), but without "previous"'s heavy tail in chaos (cart-pole at Δ = 1.5,
#: P = 300: 0.99× BIW-LR's variance against 34×). "previous" stays available, exact.
DEFAULT_K_LR = "leave_one_out"
GUARD_THRESHOLD = 0.99  # "guarded": k_LR = 1 where this batch's weight says σ²_RP > 99 σ²_LR


class OthersStatistics(NamedTuple):
    """Per-particle statistics of the *other* particles' gradients, each with a leading axis P."""

    var: jax.Array  # (P,) trace of the variance (ddof 1) over the others
    mean: jax.Array  # (P, n) mean over the others
    count: int  # how many others each particle's statistics use


def leave_one_out_statistics(g: jax.Array) -> OthersStatistics:
    """trace Var and mean over j ≠ i for every i, in O(P·n) from one centred sum of squares.

    ``SS_{−i} = SS − P/(P−1)·‖g_i − ḡ‖²`` (the exact downdate of the centred sum of squares). It
    cancels catastrophically only for the particle that dominates SS; that particle's statistics
    are computed directly over the others (one more masked pass). Needs P ≥ 3.
    """
    P = g.shape[0]
    if P < 3:
        raise ValueError(f"leave-one-out variances need at least 3 particles, got {P}")
    mean = jnp.mean(g, axis=0)
    dev2 = jnp.sum((g - mean) ** 2, axis=1)
    top = jnp.argmax(jnp.where(jnp.isnan(dev2), jnp.inf, dev2))
    others = (jnp.arange(P) != top)[:, None]
    mean_top = jnp.sum(jnp.where(others, g, 0.0), axis=0) / (P - 1)
    ss_top = jnp.sum(jnp.where(others, (g - mean_top) ** 2, 0.0))
    ss = jnp.sum(dev2) - P / (P - 1) * dev2
    ss = jnp.where(others[:, 0], jnp.maximum(ss, 0.0), ss_top)
    means = jnp.where(others, (P * mean - g) / (P - 1), mean_top)
    return OthersStatistics(ss / (P - 2), means, P - 1)


def split_statistics(g: jax.Array) -> OthersStatistics:
    """Each particle gets the statistics of the other half: halves by parity of the index (i mod 2)."""
    P = g.shape[0]
    if P < 4:
        raise ValueError(f"split-batch variances need at least 4 particles, got {P}")
    half = jnp.arange(P) % 2
    stats = []
    for h in (0, 1):
        sel = (half == h)[:, None]
        n = (P + 1 - h) // 2
        m = jnp.sum(jnp.where(sel, g, 0.0), axis=0) / n
        v = jnp.sum(jnp.where(sel, (g - m) ** 2, 0.0)) / (n - 1)
        stats.append((v, m, n))
    (v0, m0, n0), (v1, m1, n1) = stats
    other_is_1 = (half == 0)
    var = jnp.where(other_is_1, v1, v0)
    means = jnp.where(other_is_1[:, None], m1, m0)
    return OthersStatistics(var, means, min(n0, n1))


class _NoMemory:
    """A source that reads this batch only: no state."""

    cold_start = False

    def init(self, context: InitContext, weight_shape: tuple) -> tuple:
        del context, weight_shape
        return ()


@strategy
class BatchWeight(_NoMemory):
    """k_LR from this batch's variances (the thesis, Alg. 5; biased: the weight correlates with the parts it weighs)."""

    k_lr = "batch"

    def weight(self, state, rule, g_rp, g_lr, k_batch):
        del rule, g_rp, g_lr
        return state, k_batch


@strategy(traced=("k",))
class FixedWeight(_NoMemory):
    """A fixed k_LR (0 is RP, 1 is LR); a traced number."""

    k: float

    @property
    def k_lr(self):
        return self.k

    def weight(self, state, rule, g_rp, g_lr, k_batch):
        del rule, g_rp, g_lr
        return state, jnp.asarray(self.k, dtype=k_batch.dtype)


class PreviousBatchWeight(NamedTuple):
    """The state of a source that reads the previous iteration's batch weight, per step."""

    k_batch: jax.Array  # (T, *weight_shape) the previous iteration's batch weight
    has_previous: jax.Array  # (T, *weight_shape) bool: False before the first estimate


def _remember(k_batch) -> PreviousBatchWeight:
    return PreviousBatchWeight(k_batch, jnp.ones(jnp.shape(k_batch), bool))


class _PreviousIteration:
    """A source whose state is the previous iteration's batch weight (a cold start before the first)."""

    cold_start = True  # the first estimate falls back on this batch's weight

    def init(self, context: InitContext, weight_shape: tuple) -> PreviousBatchWeight:
        shape = (context.steps, *weight_shape)
        return PreviousBatchWeight(jnp.zeros(shape), jnp.zeros(shape, bool))


@strategy
class PreviousWeight(_PreviousIteration):
    """k_LR from the previous optimizer iteration's batch, this batch's on the first (exactly unbiased after it)."""

    k_lr = "previous"

    def weight(self, state, rule, g_rp, g_lr, k_batch):
        del rule, g_rp, g_lr
        return _remember(k_batch), jnp.where(state.has_previous, state.k_batch, k_batch)


@strategy(traced=("threshold",))
class GuardedWeight(_PreviousIteration):
    """The previous iteration's k_LR, but 1 (LR only) at a step where this batch's weight is at or
    above ``threshold`` — a batch whose pathwise spread is far beyond its LR spread (heavy tails).

    Biased only through the switch (docs/estimators.md, "Choosing k_LR"): its bias is
    ``E[(1 − k_prev)·1{switch}·(γ^LR − γ^RP)]``, measured, not bounded a priori.
    """

    threshold: float = GUARD_THRESHOLD

    k_lr = "guarded"

    def weight(self, state, rule, g_rp, g_lr, k_batch):
        del rule, g_rp, g_lr
        k = jnp.where(state.has_previous, state.k_batch, k_batch)
        return _remember(k_batch), jnp.where(k_batch >= self.threshold, jnp.ones_like(k), k)


class _OthersSource(_NoMemory):
    """A weight per particle from the other particles' per-step θ-gradients (this batch only)."""

    def weight(self, state, rule, g_rp, g_lr, k_batch):
        del k_batch
        rp, lr_ = self.statistics(g_rp), self.statistics(g_lr)
        one = lambda vr, vl, mr, ml: rule.batch_weight(vr, vl, mr, ml, rp.count)  # noqa: E731
        return state, jax.vmap(one)(rp.var, lr_.var, rp.mean, lr_.mean)


@strategy
class LeaveOneOutWeight(_OthersSource):
    """Particle i's k_LR from the other P − 1 particles' variances (approximately unbiased)."""

    k_lr = "leave_one_out"

    def statistics(self, g):
        return leave_one_out_statistics(g)


@strategy
class SplitWeight(_OthersSource):
    """Particle i's k_LR from the other half's variances, halves by parity (approximately unbiased)."""

    k_lr = "split"

    def statistics(self, g):
        return split_statistics(g)


#: The named sources, by their ``k_lr`` setting (each factory takes no argument).
WEIGHT_SOURCES = {
    "batch": BatchWeight,
    "previous": PreviousWeight,
    "leave_one_out": LeaveOneOutWeight,
    "split": SplitWeight,
    "guarded": GuardedWeight,
    "moving_average": moving_average,
}


def weight_source(k_lr=DEFAULT_K_LR):
    """Where total propagation's k_LR comes from: a name of :data:`WEIGHT_SOURCES`, a number in [0, 1],
    or a weight source itself (e.g. ``moving_average(0.5)``)."""
    if isinstance(k_lr, str):
        if k_lr in WEIGHT_SOURCES:
            return WEIGHT_SOURCES[k_lr]()
        raise ValueError(f"k_lr must be one of {tuple(WEIGHT_SOURCES)} or a number in [0, 1], got {k_lr!r}")
    if isinstance(k_lr, WeightSource):  # a source built by its factory
        return k_lr
    if not 0.0 <= float(k_lr) <= 1.0:
        raise ValueError(f"a fixed k_lr must lie in [0, 1], got {k_lr}")
    return FixedWeight(float(k_lr))


__all__ = [
    "DEFAULT_K_LR", "WEIGHT_SOURCES", "BatchWeight", "FixedWeight", "GuardedWeight", "LeaveOneOutWeight",
    "MovingAverageWeight", "PreviousBatchWeight", "PreviousWeight", "SplitWeight", "leave_one_out_statistics",
    "split_statistics", "weight_source",
]
