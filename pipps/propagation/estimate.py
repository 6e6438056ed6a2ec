"""The public entry point: objective, gradient estimate and diagnostics for one policy.

``estimate(key, state, policy, model, problem=..., config=..., estimator=...)`` draws the particle
noise from ``key`` (pass the same key every call for the fixed-seed variants), runs the particle
rollout and the estimator's sweep schedule, and returns the next
:class:`~pipps.propagation.pieces.EstimatorState` and an :class:`Estimate` (blackjax style,
``(state, info)``: the state is what the next call needs — each piece's own — the estimate is what
you use and log). Every function is pure, so ``jax.jit`` and ``jax.vmap`` over a leading axis of
seeds (keys, states, policies and models) work.

The ``model`` is a learned dynamics model (the thesis' setting: the noise on the next state), or,
with ``config.action_noise``, a known simulator with ``step(x, u)`` (noise on the actions,
:mod:`pipps.particles.simulator`); the estimator and its pieces are the same.
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
    record = rollout_for(key, policy, model, problem=problem, config=config, estimators=(estimator,))
    return estimate_on(record, state, policy, problem=problem, config=config, estimator=estimator)


def rollout_for(key: jax.Array, policy, model, *, problem: Problem, config: RolloutConfig, estimators) -> Any:
    """The particle record every estimator in ``estimators`` can sweep: the rollout from ``key``'s
    noise, with the model's (or simulator's) Jacobians where one needs them and each particle's
    zero-noise rollout where a baseline reads it. Several estimators swept on one record see the
    same particles (common random numbers) and share its cost."""
    for est in estimators:
        if config.resampling == "gaussian" and est.likelihood_ratio:
            raise ValueError("Gaussian resampling (GR) is a pathwise method; use it with the 'rp' estimator")
    noise = sample_noise(key, problem, config)
    # the thesis' sweep maps every part through the model's Jacobians; at the action node only a
    # pathwise part reads the simulator's (module doc of pipps.particles.simulator)
    pathwise = any(est.pathwise for est in estimators)
    record = particle_rollout(problem, policy, model, noise, config, jacobian=pathwise or not config.noise_on_actions)
    if any(est.reads_nominal for est in estimators):  # the zero-noise baseline: each particle's start, no noise
        nominal = particle_rollout(problem, policy, model, noise.without_noise(), config, jacobian=False)
        record = record._replace(nominal_cost=nominal.cost)
    return record


def estimate_on(record, state: EstimatorState, policy, *, problem: Problem, config: RolloutConfig,
                estimator: Estimator) -> tuple[EstimatorState, Estimate]:
    """:func:`estimate` on a given record (:func:`rollout_for`): the estimator's sweep schedule and the
    mean of the particles' contributions."""
    require_float64("pipps.propagation.estimate_on")
    if estimator.reads_nominal and record.nominal_cost is None:
        raise ValueError("this estimator's baseline is the zero-noise rollout: make the record with rollout_for")
    state, out = estimator.schedule.sweep(problem, policy, record, config, estimator, state)
    contrib = out.contributions
    P = contrib.shape[0]
    _, unravel = ravel_pytree(policy)
    grad = unravel(jnp.mean(contrib, axis=0))
    grad_var = unravel(jnp.var(contrib, axis=0, ddof=1) / P)
    diag = out.diagnostics
    value = jnp.sum(diag.objective)
    return state, Estimate(value, record.objective, grad, grad_var, diag)
