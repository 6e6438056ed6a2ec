"""Combiners: how one step's gradient parts become one contribution (estimators.md §4 steps 5–7, §9).

A combiner is a strategy piece with ``combine(kinds, parts, k_previous, has_previous) -> Combined``:
from the parts' cotangents (:class:`~pipps.propagation.parts.PartCotangents`: each part's
cotangent on the GP input z and the pull-back to θ and x) it chooses ``k_LR`` — the weight on the LR
part, ``1 − k_LR`` on the pathwise part — and mixes gradients and messages with it. ``weight_shape``
is the shape of one step's weight that the next iteration's "previous" rule reads.

* :func:`single`: one part, taken as it is (``k_LR`` reported as 0 for RP, 1 for LR).
* :func:`inverse_variance` and :func:`robust`: total propagation of a pathwise and an LR part, the
  weight of this batch from the rule below and the weight used from ``k_lr``: "batch" (the thesis),
  "previous" (the previous iteration's batch weight; this batch's on the first) or a fixed number;
  and the rules of issue 20 (docs/estimators.md, "Choosing k_LR"): "leave_one_out" (the library
  default, :data:`DEFAULT_K_LR`) and "split"
  (a weight per particle from the other particles of this batch: particle i's from the other P − 1,
  or from the other half) and "guarded" (the previous weight, but 1 where this batch's weight is
  above a threshold). ``"cross_fit"`` (exactly unbiased, two half-batch sweeps each) is not a
  weight source but a sweep schedule: :mod:`~pipps.propagation.cross_fit`.

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

COMBINERS = ("inverse_variance", "robust", "action_nodes")
K_SOURCES = ("batch", "previous", "leave_one_out", "split", "guarded")
#: The library's k_LR (issue 20; docs/estimator-variance.md, "Choosing k_LR"): each particle's weight
#: from the other P − 1 particles' variances. Not exactly unbiased (O(1/P): 1.0 % of ‖∇J‖ at P = 30
#: on the linear-Gaussian system), but without "previous"'s heavy tail in chaos (cart-pole at
#: Δ = 1.5, P = 300: 0.99× BIW-LR's variance against 34×). "previous" stays available, exact.
DEFAULT_K_LR = "leave_one_out"
MESSAGES = ("mixed", "pathwise")  # what total propagation passes back: λ = k γ^LR + (1 − k) γ^RP, or γ^RP
GUARD_THRESHOLD = 0.99  # "guarded": k_LR = 1 where this batch's weight says σ²_RP > 99 σ²_LR


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
    """k·lr + (1 − k)·rp, exactly lr at k = 1 and exactly rp at k = 0 even if the other is not finite.

    ``k`` is a scalar or one weight per particle, shape (P, 1) against (P, n)."""
    return jnp.where(k == 1.0, lr, jnp.where(k == 0.0, rp, k * lr + (1.0 - k) * rp))


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


class Combined(NamedTuple):
    """One step's combination of the gradient parts."""

    k: jax.Array  # the weight used on the LR part (its mean over particles for a per-particle weight)
    k_batch: jax.Array  # the weight this batch's statistics give (what "previous" reads next time)
    variances: tuple  # σ² = trace Var_i[g_{i,t}] of each part, in the parts' order
    gradient: jax.Array  # (P, n_θ) each particle's contribution at this step
    message: jax.Array | None  # (P, D) ∂G_i/∂x_{i,t−1} passed back; None where no part reads it


class _ScalarSource:
    """A source whose weight is one number per step, chosen from this batch's and the previous
    iteration's batch weights."""

    uses_previous_k = False  # reads the previous iteration's weight (the state must carry one)

    def weight(self, rule, g_rp, g_lr, k_batch, k_previous, has_previous):
        del rule, g_rp, g_lr
        return self.choose(k_batch, k_previous, has_previous)


@strategy
class BatchWeight(_ScalarSource):
    """k_LR from this batch's variances (the thesis, Alg. 5; biased, estimators.md §4)."""

    k_lr = "batch"

    def choose(self, k_batch, k_previous, has_previous):
        del k_previous, has_previous
        return k_batch


@strategy
class PreviousWeight(_ScalarSource):
    """k_LR from the previous optimizer iteration's batch, this batch's on the first (estimators.md §4)."""

    k_lr = "previous"
    uses_previous_k = True

    def choose(self, k_batch, k_previous, has_previous):
        return jnp.where(has_previous, k_previous, k_batch)


@strategy(traced=("k",))
class FixedWeight(_ScalarSource):
    """A fixed k_LR (0 is RP, 1 is LR); a traced number."""

    k: float

    @property
    def k_lr(self):
        return self.k

    def choose(self, k_batch, k_previous, has_previous):
        del k_previous, has_previous
        return jnp.asarray(self.k, dtype=k_batch.dtype)


@strategy(traced=("threshold",))
class GuardedWeight(_ScalarSource):
    """The previous iteration's k_LR, but 1 (LR only) at a step where this batch's weight is at or
    above ``threshold`` — a batch whose pathwise spread is far beyond its LR spread (heavy tails).

    Biased only through the switch (estimators.md, "Choosing k_LR"): its bias is
    ``E[(1 − k_prev)·1{switch}·(γ^LR − γ^RP)]``, measured, not bounded a priori.
    """

    threshold: float = GUARD_THRESHOLD

    k_lr = "guarded"
    uses_previous_k = True

    def choose(self, k_batch, k_previous, has_previous):
        k = jnp.where(has_previous, k_previous, k_batch)
        return jnp.where(k_batch >= self.threshold, jnp.ones_like(k), k)


class _OthersSource:
    """A weight per particle from the other particles' per-step θ-gradients (this batch only)."""

    uses_previous_k = False

    def weight(self, rule, g_rp, g_lr, k_batch, k_previous, has_previous):
        del k_batch, k_previous, has_previous
        rp, lr_ = self.statistics(g_rp), self.statistics(g_lr)
        one = lambda vr, vl, mr, ml: rule.batch_weight(vr, vl, mr, ml, rp.count)  # noqa: E731
        return jax.vmap(one)(rp.var, lr_.var, rp.mean, lr_.mean)


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


@strategy
class Single:
    """One gradient part, taken as it is."""

    name = "single"
    num_parts = 1
    k_lr = None
    uses_previous_k = False

    def weight_shape(self, num_actions: int) -> tuple:
        del num_actions
        return ()

    def combine(self, kinds, parts, k_previous, has_previous) -> Combined:
        del k_previous, has_previous
        g, messages = parts.gradients_and_messages()
        k = jnp.asarray(1.0 if kinds[0] == LIKELIHOOD_RATIO else 0.0, g.dtype)
        return Combined(k, k, (variance_trace(g[0]),), g[0], None if messages is None else messages[0])


Source = BatchWeight | PreviousWeight | FixedWeight | GuardedWeight | LeaveOneOutWeight | SplitWeight


def _no_weight_on_nonfinite(k, var_rp, var_lr):
    """k with the guards of estimators.md §4: a part whose variance is not finite gets no weight
    (both not finite: ``k`` as it is, and the caller's update refuses the step)."""
    k = jnp.where(jnp.isfinite(var_rp), k, 1.0)
    return jnp.where(jnp.isfinite(var_lr), k, jnp.where(jnp.isfinite(var_rp), 0.0, k))


def _total_propagation(rule, g, messages, k_previous, has_previous) -> Combined:
    """Steps 5–7 of estimators.md §4 for parts (pathwise, LR); a non-finite part gets no weight."""
    g_rp, g_lr = g[0], g[1]
    var_rp, var_lr = variance_trace(g_rp), variance_trace(g_lr)
    k_batch = rule.batch_weight(var_rp, var_lr, g_rp.mean(0), g_lr.mean(0), g_rp.shape[0])
    k = _no_weight_on_nonfinite(rule.source.weight(rule, g_rp, g_lr, k_batch, k_previous, has_previous), var_rp, var_lr)
    kp = k[:, None] if k.ndim == 1 else k  # one weight per particle, or one for the step
    if messages is None:
        message = None
    elif rule.messages == "pathwise":  # the weight mixes the step's contributions only
        message = messages[0]
    else:
        message = mix(kp, messages[1], messages[0])
    return Combined(jnp.mean(k), k_batch, (var_rp, var_lr), mix(kp, g_lr, g_rp), message)


class _WeighsTwoParts:
    """What every combiner of a pathwise and an LR part shares: its weights come from ``source``."""

    num_parts = 2

    @property
    def k_lr(self):
        return self.source.k_lr

    @property
    def uses_previous_k(self) -> bool:
        return self.source.uses_previous_k


class _TotalPropagationCombiner(_WeighsTwoParts):
    """What the two total-propagation combiners share: two parts, ``k_LR`` from their ``source``,
    and the combination of :func:`_total_propagation`; each defines its own ``batch_weight``."""

    def weight_shape(self, num_actions: int) -> tuple:
        del num_actions
        return ()  # one weight per step

    def combine(self, kinds, parts, k_previous, has_previous) -> Combined:
        del kinds
        g, messages = parts.gradients_and_messages()
        return _total_propagation(self, g, messages, k_previous, has_previous)


@strategy(traced=("source",))
class InverseVariance(_TotalPropagationCombiner):
    """Total propagation with the inverse-variance weight (thesis Alg. 5; estimators.md §4)."""

    source: Source
    messages: str = "mixed"  # "mixed" (Alg. 5) or "pathwise" (pass γ^RP back; mix the contributions only)

    name = "inverse_variance"

    def batch_weight(self, var_rp, var_lr, mean_rp, mean_lr, num_particles):
        del mean_rp, mean_lr, num_particles
        return inverse_variance_k(var_rp, var_lr)


@strategy(traced=("gamma", "z", "source"))
class Robust(_TotalPropagationCombiner):
    """Total propagation with the bias-aware weight of Suh et al. (estimators.md §9); γ and z are traced."""

    gamma: float
    z: float
    source: Source
    messages: str = "mixed"

    name = "robust"

    def batch_weight(self, var_rp, var_lr, mean_rp, mean_lr, num_particles):
        return robust_k(var_rp, var_lr, mean_rp, mean_lr, num_particles, self.gamma, self.z)


@strategy(traced=("source",))
class ActionNodes(_WeighsTwoParts):
    """Total propagation at the action nodes (the idea of TPX, Parmas, Seno and Aoki 2023; derived for
    this sweep in docs/estimators.md, "Combination at the action nodes").

    Each part's cotangent on z = [x̃[I]; u] splits into a state part ``c^p_x̃`` and an action part
    ``c^p_u``. The θ-gradient reads only the action part, so the two parts are mixed there,
    coordinate by coordinate: ``c_u = K ⊙ c^LR_u + (1 − K) ⊙ c^RP_u`` with
    ``K_d = σ²_{RP,d} / (σ²_{RP,d} + σ²_{LR,d})`` from the across-particle variances of ``c^p_{u,d}``
    (action space: the cost does not grow with n_θ). The state paths of the message,
    ``γ^p_μ + (∂x̃/∂x)ᵀ c^p_x̃``, are mixed with one weight ``k_s`` from the trace variances of the two
    parts' state messages. One pull-back of three cotangents — the two state parts and the mixed
    action part — gives the θ-gradient and the message
    ``λ = k_s m^LR + (1 − k_s) m^RP + (∂u/∂x)ᵀ c_u``.

    ``source`` says where every weight comes from, as in :class:`InverseVariance`, applied to each
    action coordinate and to the state paths separately; a step's weights are ``[k_s, K_1 … K_Du]``
    (what "previous" reads next time). With every weight 0 it is RP, with every weight 1 LR, and
    with every weight k total propagation with k, each up to rounding (tests/test_action_nodes.py).
    Diagnostics: ``k`` is the mean action weight, and the variances are the action cotangents'
    (summed over coordinates), not the θ-gradients'.
    """

    source: Source

    name = "action_nodes"

    def weight_shape(self, num_actions: int) -> tuple:
        return (1 + num_actions,)  # [state paths, action coordinates]

    def batch_weight(self, var_rp, var_lr, mean_rp, mean_lr, num_particles):
        del mean_rp, mean_lr, num_particles
        return inverse_variance_k(var_rp, var_lr)

    def _weights(self, g_rp, g_lr, k_previous, has_previous):
        """The source's weight for one node from the parts' (P, n) values there, with TP's guards."""
        var_rp, var_lr = variance_trace(g_rp), variance_trace(g_lr)
        k_batch = self.batch_weight(var_rp, var_lr, None, None, g_rp.shape[0])
        k = _no_weight_on_nonfinite(self.source.weight(self, g_rp, g_lr, k_batch, k_previous, has_previous), var_rp, var_lr)
        return k, k_batch, var_rp, var_lr

    def combine(self, kinds, parts, k_previous, has_previous) -> Combined:
        del kinds
        n_u = parts.num_actions
        ct_rp, ct_lr = parts.z[0], parts.z[1]
        u_rp, u_lr = ct_rp[:, -n_u:], ct_lr[:, -n_u:]

        def node(c_rp, c_lr, k_prev):  # one action coordinate: (P,) each
            return self._weights(c_rp[:, None], c_lr[:, None], k_prev, has_previous)

        K, K_batch, var_rp, var_lr = jax.vmap(node, in_axes=(1, 1, 0))(u_rp, u_lr, k_previous[1:])
        K = K.T if K.ndim == 2 else K  # (P, Du) per particle, or (Du,) per coordinate
        u_mix = mix(K, u_lr, u_rp)

        def only_state(ct):
            return ct.at[:, -n_u:].set(0.0)

        stack = jnp.stack([only_state(ct_rp), only_state(ct_lr), jnp.zeros_like(ct_rp).at[:, -n_u:].set(u_mix)])
        g, cx = parts.pull_back(stack)
        m_rp, m_lr = cx[0] + parts.zeta[0].mean, cx[1] + parts.zeta[1].mean
        k_s, k_s_batch, _, _ = self._weights(m_rp, m_lr, k_previous[0], has_previous)
        k_s = k_s[:, None] if k_s.ndim == 1 else k_s
        message = mix(k_s, m_lr, m_rp) + cx[2]
        k_batch = jnp.concatenate([k_s_batch[None], K_batch])
        return Combined(jnp.mean(K), k_batch, (jnp.sum(var_rp), jnp.sum(var_lr)), g[2], message)


_NAMED_SOURCES = {
    "batch": BatchWeight,
    "previous": PreviousWeight,
    "leave_one_out": LeaveOneOutWeight,
    "split": SplitWeight,
    "guarded": GuardedWeight,
}


def weight_source(k_lr: str | float = DEFAULT_K_LR) -> Source:
    """Where total propagation's k_LR comes from: one of :data:`K_SOURCES` or a number in [0, 1]."""
    if isinstance(k_lr, str):
        if k_lr in _NAMED_SOURCES:
            return _NAMED_SOURCES[k_lr]()
        raise ValueError(f"k_lr must be one of {K_SOURCES} or a number in [0, 1], got {k_lr!r}")
    if not 0.0 <= float(k_lr) <= 1.0:
        raise ValueError(f"a fixed k_lr must lie in [0, 1], got {k_lr}")
    return FixedWeight(float(k_lr))


def single() -> Single:
    """The combiner of a one-part estimator."""
    return Single()


def inverse_variance(k_lr: str | float = DEFAULT_K_LR, messages: str = "mixed") -> InverseVariance:
    """Total propagation's inverse-variance combiner (thesis Alg. 5) with the given k_LR source.

    ``messages="pathwise"`` passes the pathwise message γ^RP back instead of λ = k γ^LR + (1 − k) γ^RP
    and uses k only for the step's contribution: no LR noise enters the earlier pathwise terms
    (unbiased under the same condition on k; docs/estimators.md, "Choosing k_LR"). A non-finite
    pathwise message is then passed back as it is, and the update refuses the estimate.
    """
    if messages not in MESSAGES:
        raise ValueError(f"messages must be one of {MESSAGES}, got {messages!r}")
    return InverseVariance(weight_source(k_lr), messages)


def action_nodes(k_lr: str | float = DEFAULT_K_LR) -> ActionNodes:
    """Total propagation at the action nodes, a weight per action coordinate and one for the state
    paths (:class:`ActionNodes`), each from the given k_LR source."""
    return ActionNodes(weight_source(k_lr))


def robust(gamma: float = float("inf"), z: float = 2.0, k_lr: str | float = DEFAULT_K_LR, messages: str = "mixed") -> Robust:
    """The robust combiner (estimators.md §9): bias bound ``γ ≥ 0`` (∞: inverse variance), confidence
    ``z ≥ 0``; ``messages`` as for :func:`inverse_variance`."""
    if messages not in MESSAGES:
        raise ValueError(f"messages must be one of {MESSAGES}, got {messages!r}")
    if not float(gamma) >= 0.0:
        raise ValueError(f"robust_gamma must be >= 0 (inf allowed), got {gamma}")
    if not 0.0 <= float(z) < float("inf"):
        raise ValueError(f"robust_z must be finite and >= 0, got {z}")
    return Robust(float(gamma), float(z), weight_source(k_lr), messages)
