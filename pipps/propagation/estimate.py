"""The public entry point: objective, gradient estimate and diagnostics for one policy.

``estimate(key, state, policy, model, task=..., config=..., estimator=...)`` draws the particle
noise from ``key`` (pass the same key every call for the fixed-seed variants), runs the
particle rollout and the reverse sweep, and returns the next :class:`EstimatorState` and an
:class:`Estimate` (blackjax style, ``(state, info)``: the state is what the next call needs, the
estimate is what you use and log). Every function is pure, so ``jax.jit`` and ``jax.vmap`` over a
leading axis of seeds (keys, states, policies and models) work.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from pipps.particles.forward import RolloutConfig, particle_rollout, sample_noise
from pipps.precision import require_float64
from pipps.propagation.config import Estimator
from pipps.propagation.backward import PreviousIteration, StepDiagnostics, backward_sweep, mean_returns
from pipps.propagation.cross_fit import CrossFitted
from pipps.tasks.base import Problem


class EstimatorState(NamedTuple):
    """What an estimator carries between optimizer iterations (each (T,) unless noted)."""

    baseline: jax.Array  # mean return-to-go per step of the previous iteration (or the extra rollout)
    k_lr: jax.Array  # the previous iteration's per-step batch weight, (T,) or (T, *combiner.weight_shape)
    has_previous: jax.Array  # bool scalar: False until the first estimate

    def previous(self) -> PreviousIteration:
        return PreviousIteration(self.baseline, self.k_lr, self.has_previous)


class Estimate(NamedTuple):
    """One gradient estimate."""

    value: jax.Array  # the objective being differentiated: J, or J_GS = Σ_t Ē_t under shaping
    particle_objective: jax.Array  # J = Σ_t mean_i c(x_{i,t}) of this batch
    grad: Any  # ∇θ, same pytree as the policy
    grad_variance: Any  # V[g]: per-parameter variance across particles (ddof 1) / P, same pytree
    diagnostics: StepDiagnostics


def init_estimator_state(
    key: jax.Array, policy, model, *, task: Problem, config: RolloutConfig, estimator: Estimator
) -> EstimatorState:
    """The state before the first iteration: the "previous" baseline from one extra rollout.

    estimators.md §3: for the first iteration the baseline comes from one extra independent
    rollout made when the optimizer starts. ``key`` must be independent of the estimate keys.
    """
    require_float64("pipps.propagation.init_estimator_state")
    T = config.steps(task)
    if estimator.needs_previous_baseline:
        record = particle_rollout(task, policy, model, sample_noise(key, task, config), config, jacobian=False)
        baseline = mean_returns(task, record, estimator)
    else:
        baseline = jnp.zeros(T)
    k_shape = (T, *estimator.combiner.weight_shape(task.action_dim))  # one weight per step, or per node
    return EstimatorState(baseline, jnp.zeros(k_shape), jnp.asarray(False))


def estimate(
    key: jax.Array,
    state: EstimatorState,
    policy,
    model,
    *,
    task: Problem,
    config: RolloutConfig,
    estimator: Estimator | CrossFitted,
) -> tuple[EstimatorState, Estimate]:
    """The next state; and the objective, gradient estimate, V[g] and per-step diagnostics."""
    require_float64("pipps.propagation.estimate")
    if config.resampling == "gaussian" and estimator.likelihood_ratio:
        raise ValueError("Gaussian resampling (GR) is a pathwise method; use it with the 'rp' estimator")
    noise = sample_noise(key, task, config)
    record = particle_rollout(task, policy, model, noise, config, jacobian=True)
    if isinstance(estimator, CrossFitted):  # a schedule of sweeps, not a piece of one
        out = estimator.sweep(task, policy, record, config, state.previous())
    else:
        out = backward_sweep(task, policy, record, config, estimator, state.previous())
    contrib = out.contributions
    P = contrib.shape[0]
    _, unravel = ravel_pytree(policy)
    grad = unravel(jnp.mean(contrib, axis=0))
    grad_var = unravel(jnp.var(contrib, axis=0, ddof=1) / P)
    diag = out.diagnostics
    value = jnp.sum(diag.objective)
    result = Estimate(value, record.objective, grad, grad_var, diag)
    next_state = EstimatorState(diag.mean_return, diag.k_lr_batch, jnp.asarray(True))
    return next_state, result
