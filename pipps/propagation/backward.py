"""The custom backward pass: one reverse sweep over time (thesis Alg. 5; docs/estimators.md).

The sweep runs ``t = T, …, 1`` over the :class:`~pipps.particles.forward.ParticleRecord` and
carries, per particle, the returns ``G_{i,t}`` and — when the estimator has a pathwise part — the
pathwise derivative of the return with respect to the particle, ``∂G_i/∂x_{i,t}``. It runs the
estimator's pieces (:mod:`~pipps.propagation.pieces`) and threads their states: at each step it
hands every piece its own state's slice for step t and stacks the slices it returns into the
next state. At each step the sweep

1. asks the cost terms for ``c_{i,t}`` and ``∂c_i/∂x_{i,t}`` and sets ``G_{i,t} = G_{i,t+1} + c_{i,t}``
   (:mod:`~pipps.propagation.cost_terms`);
2. asks each gradient part for a ζ-cotangent ``γ_{i,t}`` (:mod:`~pipps.propagation.parts`);
3. turns every γ into a cotangent on the GP input ``z = [x̃[I]; π(x̃[P]; θ)]`` with the model
   Jacobians the forward pass recorded, and hands these (:class:`~pipps.propagation.pieces.PartCotangents`)
   with the pull-back — one per-particle VJP of the (cheap) map ``x ↦ z`` for a stack of
   cotangents, giving θ-gradients and, when a pathwise part reads them, messages ``∂G/∂x_{i,t−1}`` —
   to the combiner;
4. the combiner chooses ``k_LR`` and returns the step's contribution and the message ``λ`` passed
   back (:mod:`~pipps.propagation.combine`): total propagation pulls every part back at once and
   mixes the θ-gradients; a combiner at the action nodes mixes the z-cotangents first.

The sweep itself does not depend on which estimator it runs. How many sweeps make an estimate, over
which particles, is the estimator's schedule (:mod:`~pipps.propagation.schedules`).

**Where the noise enters.** The sampled node of a step is the thesis' next state, drawn from the
model's Gaussian (a :class:`~pipps.particles.forward.ParticleRecord`), or — with noise on the actions
through a known simulator (a :class:`~pipps.particles.simulator.ActionRecord`, Suh et al.'s setting) —
the action ``u_t ~ N(π(x̃_t[P]), σ_u²)``, after which ``x_{t+1} = step(x_t, u_t)``. The sweep asks the
record's node (:func:`_state_node`, :func:`_action_node`) for the three things that differ: the
state the step's cost is on, the parts' inputs (the sample, its ζ, and ∂G/∂sample), and the
cotangents the combiner mixes (the z-cotangents, the pull-back to θ and to the previous state, and
the path of the message that bypasses ζ). At the action node ``z`` is the action mean itself, the
pull-back is the VJP of ``x ↦ π(x̃[P]; θ)``, the parts' pathwise input is ``(∂x'/∂u)ᵀ ∂G/∂x'`` and
the message to ``x_t`` adds the simulator's direct path ``(∂x'/∂x)ᵀ ∂G/∂x'``, the same for every
part (it is pathwise: the action's likelihood ratio does not cover it).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from pipps.particles.forward import ParticleRecord, RolloutConfig
from pipps.particles.simulator import ActionRecord
from pipps.propagation.lr import ZetaGrad
from pipps.propagation.pieces import (
    LIKELIHOOD_RATIO,
    PATHWISE,
    CostTerms,
    EstimatorState,
    PartCotangents,
    StepDiagnostics,
    StepInputs,
    SweepOutput,
)
from pipps.tasks.base import Problem


def _z_map(problem: Problem):
    def z_of(x, policy):
        return problem.gp_input(x, policy(problem.policy_input(x)))

    return z_of


def _action_map(problem: Problem):
    def u_of(x, policy):
        return policy(problem.policy_input(x))

    return u_of


def _pull_back(z_of, policy, x_prev, ct_z, *, with_x: bool):
    """Per-particle VJP of x ↦ z(x, θ) for K stacked cotangents ct_z (K, P, Dz).

    Returns (θ-cotangents (K, P, n_θ), x-cotangents (K, P, D) or None).
    """
    flat = lambda tree: ravel_pytree(tree)[0]  # noqa: E731

    if with_x:
        def one(x, cts):
            _, vjp = jax.vjp(z_of, x, policy)
            cx, cpol = jax.vmap(vjp)(cts)
            return jax.vmap(flat)(cpol), cx

        g, cx = jax.vmap(one, in_axes=(0, 1), out_axes=1)(x_prev, ct_z)
        return g, cx

    def one_theta(x, cts):
        _, vjp = jax.vjp(lambda pol: z_of(x, pol), policy)
        (cpol,) = jax.vmap(vjp)(cts)
        return jax.vmap(flat)(cpol)

    return jax.vmap(one_theta, in_axes=(0, 1), out_axes=1)(x_prev, ct_z), None


def _to_z(gam: ZetaGrad, jac_mean, jac_std) -> jax.Array:
    """ζ-cotangent → z-cotangent: Jμᵀ γμ + Jsᵀ γs (s is constant in z under −σ_f)."""
    ct = jnp.einsum("pd,pdz->pz", gam.mean, jac_mean)
    if jac_std is not None:
        ct = ct + jnp.einsum("pd,pdz->pz", gam.std, jac_std)
    return ct


def mean_returns(problem: Problem, record: ParticleRecord, costs: CostTerms) -> jax.Array:
    """Per-step mean return-to-go of a forward record under ``costs``, (T,): the "previous" baseline's
    first value, from the extra rollout made when the optimizer starts."""
    c = jax.vmap(lambda x_t, c_t: costs.returns(problem.cost, x_t, c_t))(record.x_next, record.cost)  # (T, P)
    returns = jnp.cumsum(c[::-1], axis=0)[::-1]
    return jnp.mean(returns, axis=-1)


def _state_node(problem: Problem, policy, record: ParticleRecord, est):
    """The thesis' node: the next state ``x_t ~ N(μ_t, s_t²)`` with ``ζ_t`` from the model at ``z_{t−1}``."""
    steps = (record.x, record.mean, record.std, record.eps, record.x_next, record.cost, record.jac_mean, record.jac_std)

    def cost_on(xs):
        return xs[4], xs[5]  # x_t and its cost

    def at(xs, G, cot_x, cost_gradient):
        x_prev, mean, std, eps, x_t, _, jm, js = xs
        inputs = StepInputs(x_t, mean, std, eps, G, cot_x, cost_gradient)

        def cotangents(gammas):
            ct_z = jnp.stack([_to_z(g, jm, js) for g in gammas])
            pull_back = partial(_pull_back, _z_map(problem), policy, x_prev, with_x=est.pathwise)
            return PartCotangents(gammas, ct_z, problem.action_dim, pull_back)

        return inputs, cotangents

    return steps, cost_on, at


def _action_node(problem: Problem, policy, record: ActionRecord, est):
    """The action node (noise on the actions, a known simulator): ``u_t ~ N(π(x̃_t[P]), σ_u²)``, then
    ``x_{t+1} = step(x_t, u_t)``; the sweep's carried message is ∂G/∂x_{t+1} (module doc)."""
    if est.pathwise and record.jac_u is None:
        raise ValueError("the pathwise part needs the simulator's Jacobians: roll out with jacobian=True")
    scores_others = [type(p).__name__ for p in est.parts if getattr(p, "needs_state_sample", False)]
    if scores_others:
        raise ValueError(
            f"{', '.join(scores_others)} scores each sample under the other particles' distributions, which is "
            "valid where the sample is the whole next state (the thesis' node); an action's return also depends "
            "on the state it was taken in, so with noise on the actions use plain LR (weighting='plain': "
            "tp_plain, lr_plain)")
    steps = (record.x, record.u, record.mean, record.std, record.eps, record.x_next, record.cost,
             record.jac_x, record.jac_u)

    def cost_on(xs):
        return xs[5], xs[6]  # x_{t+1} and its cost

    def at(xs, G, cot_x, cost_gradient):
        x_t, u, mean, std, eps, _, _, jx, ju = xs
        direct = None
        if est.pathwise:  # ∂G/∂u_t and the simulator's direct path to x_t, from ∂G/∂x_{t+1}
            inputs = StepInputs(u, mean, std, eps, G, jnp.einsum("pd,pdf->pf", cot_x, ju),
                                jnp.einsum("pd,pdf->pf", cost_gradient, ju))
            direct = jnp.einsum("pd,pde->pe", cot_x + cost_gradient, jx)
        else:
            inputs = StepInputs(u, mean, std, eps, G, jnp.zeros_like(u), None)

        def cotangents(gammas):
            ct_u = jnp.stack([g.mean for g in gammas])  # ζ = (π(x̃[P]), σ_u): σ_u does not depend on θ or x
            pull_back = partial(_pull_back, _action_map(problem), policy, x_t, with_x=est.pathwise)
            return PartCotangents(gammas, ct_u, problem.action_dim, pull_back, direct)

        return inputs, cotangents

    return steps, cost_on, at


def _node(problem: Problem, policy, record, est):
    if isinstance(record, ActionRecord):
        return _action_node(problem, policy, record, est)
    return _state_node(problem, policy, record, est)


def backward_sweep(
    problem: Problem,
    policy,
    record: ParticleRecord | ActionRecord,
    config: RolloutConfig,
    est,
    state: EstimatorState,
) -> tuple[EstimatorState, SweepOutput]:
    """Run the reverse sweep of ``est``'s pieces from their ``state``; returns their next state, and
    the per-particle contributions and per-step diagnostics."""
    T, P, D = record.x.shape
    n_theta = ravel_pytree(policy)[0].size
    dtype = record.x.dtype
    nan = jnp.asarray(jnp.nan, dtype)
    kinds = est.kinds
    steps, cost_on, at = _node(problem, policy, record, est)
    extra = _extra_returns(record, est)

    def step(carry, xs):
        G, cot_x, contrib = carry
        xs, xs_extra, st = xs
        x_t, cost = cost_on(xs)
        cost_state, terms = est.costs.step(st.costs, problem.cost, x_t, cost, G, gradient=est.pathwise)
        G = G + terms.cost

        inputs, cotangents = at(xs, G, cot_x, terms.gradient)
        if xs_extra is not None:
            inputs = inputs._replace(**xs_extra)
        part_states, gammas = zip(*(part.zeta(s, inputs, config) for part, s in zip(est.parts, st.parts)))
        step_parts = cotangents(gammas)
        combiner_state, out = est.combiner.combine(st.combiner, kinds, step_parts)
        variance = dict(zip(kinds, out.variances))
        new_cot_x = cot_x if out.message is None else out.message

        finite = jnp.all(jnp.isfinite(out.gradient))
        diag = StepDiagnostics(
            out.k, out.k_batch, variance.get(PATHWISE, nan), variance.get(LIKELIHOOD_RATIO, nan),
            jnp.mean(G), terms.objective, ~finite,
        )
        next_state = EstimatorState(cost_state, part_states, combiner_state)
        return (G, new_cot_x, contrib + out.gradient), (diag, next_state)

    init = (jnp.zeros(P, dtype), jnp.zeros((P, D), dtype), jnp.zeros((P, n_theta), dtype))
    (_, _, contrib), (diag, next_state) = jax.lax.scan(step, init, (steps, extra, state), reverse=True)
    return next_state, SweepOutput(contrib, diag)


def _extra_returns(record, est) -> dict | None:
    """Per step, the returns some LR part reads besides ``G_{i,t}``: each particle's whole return
    ``V_i = Σ_t c_{i,t}`` (``total_returns``), its zero-noise rollout's return-to-go
    (``nominal_returns``) and whole return (``nominal_total_returns``); None when no part reads any
    (nothing is computed)."""
    reads = set().union(*(getattr(p, "reads", ()) for p in est.parts))
    if not reads:
        return None
    extra = {}
    if "total_returns" in reads:
        extra["total_returns"] = jnp.broadcast_to(jnp.sum(record.cost, axis=0), record.cost.shape)
    if reads & {"nominal_returns", "nominal_total_returns"}:
        if record.nominal_cost is None:
            raise ValueError("the zero-noise baseline needs the record's nominal_cost (estimate() adds it)")
        to_go = jnp.cumsum(record.nominal_cost[::-1], axis=0)[::-1]
        if "nominal_returns" in reads:
            extra["nominal_returns"] = to_go
        if "nominal_total_returns" in reads:
            extra["nominal_total_returns"] = jnp.broadcast_to(to_go[0], to_go.shape)
    return extra
