"""Combiners: how one step's gradient parts become one contribution (thesis Alg. 5: weigh, mix, pass back).

A combiner is a :class:`~pipps.propagation.pieces.Combiner`: ``combine(state, kinds, parts) ->
(state, Combined)`` takes the parts' cotangents (:class:`~pipps.propagation.pieces.PartCotangents`:
each part's cotangent on the GP input z and the pull-back to θ and x), chooses ``k_LR`` — the weight
on the LR part, ``1 − k_LR`` on the pathwise part — and mixes gradients and messages with it.

* :func:`single`: one part, taken as it is (``k_LR`` reported as 0 for RP, 1 for LR).
* :func:`inverse_variance`, :func:`robust` and :func:`action_nodes`: total propagation of a pathwise
  and an LR part (:class:`~pipps.propagation.pieces.WeighsTwoParts`). Each computes this batch's
  weight by its rule and takes the weight it uses from its *weight source*
  (:mod:`~pipps.propagation.weights`: "batch", "previous", a number, "leave_one_out", ...); its
  state is its source's.

* ``inverse_variance`` (thesis Alg. 5): ``k = σ²_RP / (σ²_RP + σ²_LR)`` with ``σ²`` the trace of the
  across-particle variance of the per-particle policy-parameter gradients. Guards: both zero → ½;
  a non-finite variance counts as +∞ (both non-finite → ½, and the caller zeroes the step).
* ``robust`` (AoBG, Suh et al.; beyond the thesis, off by default): the weight on the first-order (RP) estimate is
  ``α = min(α_∞, max(γ − ε, 0)/B)`` with ``α_∞ = σ²_LR/(σ²_LR + σ²_RP)``, ``B = ‖ḡ_RP − ḡ_LR‖`` and
  ``ε = z·sqrt(σ²_LR/P)`` a confidence radius of the LR mean; ``k = 1 − α``.
* ``action_nodes`` (``tpx``): the parts mixed at the action nodes, a weight per action coordinate.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from pipps.propagation.pieces import LIKELIHOOD_RATIO, Combined, InitContext, Stateless, WeightSource
from pipps.propagation.strategy import strategy
from pipps.propagation.weights import DEFAULT_K_LR, weight_source

COMBINERS = ("inverse_variance", "robust", "action_nodes")
MESSAGES = ("mixed", "pathwise")  # what total propagation passes back: λ = k γ^LR + (1 − k) γ^RP, or γ^RP


def variance_trace(g: jax.Array) -> jax.Array:
    """trace(Var_i[g_i]) over particles (ddof 1) for per-particle gradients g (P, n)."""
    return jnp.sum(jnp.var(g, axis=0, ddof=1))


def _as_inf_if_nonfinite(v: jax.Array) -> jax.Array:
    return jnp.where(jnp.isfinite(v), v, jnp.inf)


def inverse_variance_k(var_rp: jax.Array, var_lr: jax.Array) -> jax.Array:
    """k_LR = σ²_RP / (σ²_RP + σ²_LR) with the guards above (both zero → ½; non-finite → +∞)."""
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


@strategy
class Single(Stateless):
    """One gradient part, taken as it is."""

    name = "single"
    num_parts = 1
    k_lr = None

    def combine(self, state, kinds, parts) -> tuple[tuple, Combined]:
        g, messages = parts.gradients_and_messages()
        k = jnp.asarray(1.0 if kinds[0] == LIKELIHOOD_RATIO else 0.0, g.dtype)
        return state, Combined(k, k, (variance_trace(g[0]),), g[0], None if messages is None else messages[0])


def _no_weight_on_nonfinite(k, var_rp, var_lr):
    """k with the guards of :func:`inverse_variance_k`: a part whose variance is not finite gets no weight
    (both not finite: ``k`` as it is, and the caller's update refuses the step)."""
    k = jnp.where(jnp.isfinite(var_rp), k, 1.0)
    return jnp.where(jnp.isfinite(var_lr), k, jnp.where(jnp.isfinite(var_rp), 0.0, k))


def _total_propagation(rule, state, g, messages) -> tuple:
    """Alg. 5's last steps (weigh the parts, mix their gradients, pass back the mixed message) for
    parts (pathwise, LR); a non-finite part gets no weight.
    Returns the source's next state and the :class:`Combined`."""
    g_rp, g_lr = g[0], g[1]
    var_rp, var_lr = variance_trace(g_rp), variance_trace(g_lr)
    k_batch = rule.batch_weight(var_rp, var_lr, g_rp.mean(0), g_lr.mean(0), g_rp.shape[0])
    state, k = rule.source.weight(state, rule, g_rp, g_lr, k_batch)
    k = _no_weight_on_nonfinite(k, var_rp, var_lr)
    kp = k[:, None] if k.ndim == 1 else k  # one weight per particle, or one for the step
    if messages is None:
        message = None
    elif rule.messages == "pathwise":  # the weight mixes the step's contributions only
        message = messages[0]
    else:
        message = mix(kp, messages[1], messages[0])
    return state, Combined(jnp.mean(k), k_batch, (var_rp, var_lr), mix(kp, g_lr, g_rp), message)


class _WeighsTwoParts:
    """What every combiner of a pathwise and an LR part shares: its weights, and its state, come
    from ``source``."""

    num_parts = 2

    @property
    def k_lr(self):
        return self.source.k_lr

    @property
    def cold_start(self) -> bool:
        return self.source.cold_start

    def with_source(self, source):
        return dataclasses.replace(self, source=source)


class _TotalPropagationCombiner(_WeighsTwoParts):
    """What the two total-propagation combiners share: two parts, ``k_LR`` from their ``source``,
    and the combination of :func:`_total_propagation`; each defines its own ``batch_weight``."""

    def init(self, context: InitContext):
        return self.source.init(context, ())  # one weight per step

    def combine(self, state, kinds, parts) -> tuple:
        del kinds
        g, messages = parts.gradients_and_messages()
        return _total_propagation(self, state, g, messages)


@strategy(traced=("source",))
class InverseVariance(_TotalPropagationCombiner):
    """Total propagation with the inverse-variance weight (thesis Alg. 5)."""

    source: WeightSource
    messages: str = "mixed"  # "mixed" (Alg. 5) or "pathwise" (pass γ^RP back; mix the contributions only)

    name = "inverse_variance"

    def batch_weight(self, var_rp, var_lr, mean_rp, mean_lr, num_particles):
        del mean_rp, mean_lr, num_particles
        return inverse_variance_k(var_rp, var_lr)


@strategy(traced=("gamma", "z", "source"))
class Robust(_TotalPropagationCombiner):
    """Total propagation with the bias-aware weight of Suh et al. (AoBG); γ and z are traced."""

    gamma: float
    z: float
    source: WeightSource
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

    source: WeightSource

    name = "action_nodes"

    def init(self, context: InitContext):
        return self.source.init(context, (1 + context.num_actions,))  # [state paths, action coordinates]

    def batch_weight(self, var_rp, var_lr, mean_rp, mean_lr, num_particles):
        del mean_rp, mean_lr, num_particles
        return inverse_variance_k(var_rp, var_lr)

    def _weights(self, state, g_rp, g_lr):
        """The source's weight for one node from the parts' (P, n) values there, with TP's guards."""
        var_rp, var_lr = variance_trace(g_rp), variance_trace(g_lr)
        k_batch = self.batch_weight(var_rp, var_lr, None, None, g_rp.shape[0])
        state, k = self.source.weight(state, self, g_rp, g_lr, k_batch)
        return state, (_no_weight_on_nonfinite(k, var_rp, var_lr), k_batch, var_rp, var_lr)

    def combine(self, state, kinds, parts) -> tuple:
        del kinds
        n_u = parts.num_actions
        ct_rp, ct_lr = parts.z[0], parts.z[1]
        u_rp, u_lr = ct_rp[:, -n_u:], ct_lr[:, -n_u:]

        def node(c_rp, c_lr, node_state):  # one action coordinate: (P,) each
            return self._weights(node_state, c_rp[:, None], c_lr[:, None])

        node_states = jax.tree.map(lambda a: a[1:], state)
        node_states, (K, K_batch, var_rp, var_lr) = jax.vmap(node, in_axes=(1, 1, 0))(u_rp, u_lr, node_states)
        K = K.T if K.ndim == 2 else K  # (P, Du) per particle, or (Du,) per coordinate
        u_mix = mix(K, u_lr, u_rp)

        def only_state(ct):
            return ct.at[:, -n_u:].set(0.0)

        stack = jnp.stack([only_state(ct_rp), only_state(ct_lr), jnp.zeros_like(ct_rp).at[:, -n_u:].set(u_mix)])
        g, cx = parts.pull_back(stack)
        m_rp, m_lr = parts.message(0, cx[0]), parts.message(1, cx[1])
        path_state, (k_s, k_s_batch, _, _) = self._weights(jax.tree.map(lambda a: a[0], state), m_rp, m_lr)
        k_s = k_s[:, None] if k_s.ndim == 1 else k_s
        message = mix(k_s, m_lr, m_rp) + cx[2]
        k_batch = jnp.concatenate([k_s_batch[None], K_batch])
        state = jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), path_state, node_states)
        return state, Combined(jnp.mean(K), k_batch, (jnp.sum(var_rp), jnp.sum(var_lr)), g[2], message)


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
    """The robust combiner (Suh et al.'s AoBG; docs/estimators.md, "Choices the thesis left open"):
    bias bound ``γ ≥ 0`` (∞: inverse variance), confidence ``z ≥ 0``; ``messages`` as for :func:`inverse_variance`."""
    if messages not in MESSAGES:
        raise ValueError(f"messages must be one of {MESSAGES}, got {messages!r}")
    if not float(gamma) >= 0.0:
        raise ValueError(f"robust_gamma must be >= 0 (inf allowed), got {gamma}")
    if not 0.0 <= float(z) < float("inf"):
        raise ValueError(f"robust_z must be finite and >= 0, got {z}")
    return Robust(float(gamma), float(z), weight_source(k_lr), messages)
