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
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from pipps.particles.forward import ParticleRecord, RolloutConfig
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


def _pull_back(problem: Problem, policy, x_prev, ct_z, *, with_x: bool):
    """Per-particle VJP of x ↦ z(x, θ) for K stacked cotangents ct_z (K, P, Dz).

    Returns (θ-cotangents (K, P, n_θ), x-cotangents (K, P, D) or None).
    """
    z_of = _z_map(problem)
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


def backward_sweep(
    problem: Problem,
    policy,
    record: ParticleRecord,
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

    def step(carry, xs):
        G, cot_x, contrib = carry
        (x_prev, mean, std, eps, x_t, cost, jm, js), st = xs
        cost_state, terms = est.costs.step(st.costs, problem.cost, x_t, cost, G, gradient=est.pathwise)
        G = G + terms.cost

        inputs = StepInputs(x_t, mean, std, eps, G, cot_x, terms.gradient)
        part_states, gammas = zip(*(part.zeta(s, inputs, config) for part, s in zip(est.parts, st.parts)))
        ct_z = jnp.stack([_to_z(g, jm, js) for g in gammas])
        pull_back = partial(_pull_back, problem, policy, x_prev, with_x=est.pathwise)
        step_parts = PartCotangents(gammas, ct_z, problem.action_dim, pull_back)
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

    steps = (record.x, record.mean, record.std, record.eps, record.x_next, record.cost, record.jac_mean, record.jac_std)
    init = (jnp.zeros(P, dtype), jnp.zeros((P, D), dtype), jnp.zeros((P, n_theta), dtype))
    (_, _, contrib), (diag, next_state) = jax.lax.scan(step, init, (steps, state), reverse=True)
    return next_state, SweepOutput(contrib, diag)
