"""The public entry point: objective, gradient estimate and diagnostics for one policy.

``estimate(key, state, policy, model, problem=..., config=..., estimator=...)`` draws the particle
noise from ``key`` (pass the same key every call for the fixed-seed variants), runs the particle
rollout and the estimator's sweep schedule, and returns the next
:class:`~pipps.propagation.pieces.EstimatorState` and an :class:`Estimate` (blackjax style,
``(state, info)``: the state is what the next call needs — each piece's own — the estimate is what
you use and log). Every function is pure, so ``jax.jit`` and ``jax.vmap`` over a leading axis of
seeds (keys, states, policies and models) work.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from pipps.particles.forward import RolloutConfig, particle_rollout, sample_noise
from pipps.precision import require_float64
from pipps.propagation.backward import mean_returns
from pipps.propagation.estimators import Estimator
from pipps.propagation.pieces import EstimatorState, InitContext, StepDiagnostics
from pipps.tasks.base import Problem


class Estimate(NamedTuple):
    """One gradient estimate."""

    value: jax.Array  # the objective being differentiated: J, or J_GS = Σ_t Ē_t under shaping
    particle_objective: jax.Array  # J = Σ_t mean_i c(x_{i,t}) of this batch
    grad: Any  # ∇θ, same pytree as the policy
    grad_variance: Any  # V[g]: per-parameter variance across particles (ddof 1) / P, same pytree
    diagnostics: StepDiagnostics


def init_estimator_state(
    key: jax.Array, policy, model, *, problem: Problem, config: RolloutConfig, estimator: Estimator
) -> EstimatorState:
    """Every piece's state before the first iteration.

    A piece with the "previous" baseline starts from one extra independent rollout made when the
    optimizer starts (the first iteration has no previous one), made only if a piece asks for it;
    ``key`` must be independent of the estimate keys.
    """
    require_float64("pipps.propagation.init_estimator_state")

    @functools.cache
    def extra_rollout_mean_returns():
        record = particle_rollout(problem, policy, model, sample_noise(key, problem, config), config, jacobian=False)
        return mean_returns(problem, record, estimator.costs)

    return estimator.init(InitContext(config.steps(problem), problem.action_dim, extra_rollout_mean_returns))


def estimate(
    key: jax.Array,
    state: EstimatorState,
    policy,
    model,
    *,
    problem: Problem,
    config: RolloutConfig,
    estimator: Estimator,
) -> tuple[EstimatorState, Estimate]:
    """The next state; and the objective, gradient estimate, V[g] and per-step diagnostics."""
    require_float64("pipps.propagation.estimate")
    if config.resampling == "gaussian" and estimator.likelihood_ratio:
        raise ValueError("Gaussian resampling (GR) is a pathwise method; use it with the 'rp' estimator")
    noise = sample_noise(key, problem, config)
    record = particle_rollout(problem, policy, model, noise, config, jacobian=True)
    state, out = estimator.schedule.sweep(problem, policy, record, config, estimator, state)
    contrib = out.contributions
    P = contrib.shape[0]
    _, unravel = ravel_pytree(policy)
    grad = unravel(jnp.mean(contrib, axis=0))
    grad_var = unravel(jnp.var(contrib, axis=0, ddof=1) / P)
    diag = out.diagnostics
    value = jnp.sum(diag.objective)
    return state, Estimate(value, record.objective, grad, grad_var, diag)
