"""One policy-update step built on :func:`~pipps.propagation.estimate.estimate`, and a scan of them.

``make_policy_update(problem, config, estimator, optimizer)`` returns a jitted
``step(key, state, model) -> (state, info)``; ``make_policy_optimizer`` a jitted
``run(key, state, model, num_steps)`` that scans ``num_steps`` of them (the 600 policy
evaluations between trials). Shapes do not change between calls, so neither recompiles.

No NaN or Inf reaches the policy, the optimizer state or the estimator state: a step whose
gradient, V[g] or updated parameters are not finite is skipped (everything is kept as it
was) and reported in ``info.skipped``.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from pipps.particles.forward import RolloutConfig
from pipps.propagation.estimate import estimate, init_estimator_state
from pipps.propagation.estimators import Estimator
from pipps.propagation.pieces import EstimatorState, StepDiagnostics
from pipps.tasks.base import Problem


class PolicyOptState(NamedTuple):
    policy: Any
    opt_state: Any
    estimator_state: EstimatorState


class UpdateInfo(NamedTuple):
    value: jax.Array  # objective of this batch (J, or J_GS under shaping)
    particle_objective: jax.Array
    grad_norm: jax.Array
    skipped: jax.Array  # bool: the step was not applied because something was not finite
    diagnostics: StepDiagnostics


def _all_finite(tree) -> jax.Array:
    leaves = jax.tree.leaves(tree)
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves]))


def _select(ok, new, old):
    return jax.tree.map(lambda a, b: jnp.where(ok, a, b), new, old)


def init_policy_opt_state(
    key: jax.Array, policy, model, *, problem: Problem, config: RolloutConfig, estimator: Estimator, optimizer
) -> PolicyOptState:
    """Fresh optimizer state (momentum reset) and estimator state for a warm-started policy."""
    est_state = init_estimator_state(key, policy, model, problem=problem, config=config, estimator=estimator)
    return PolicyOptState(policy, optimizer.init(policy), est_state)


def policy_update(
    key: jax.Array,
    state: PolicyOptState,
    model,
    *,
    problem: Problem,
    config: RolloutConfig,
    estimator: Estimator,
    optimizer: optax.GradientTransformationExtraArgs,
) -> tuple[PolicyOptState, UpdateInfo]:
    """Estimate the gradient at the current policy and take one optimizer step (pure)."""
    est_state, est = estimate(
        key, state.estimator_state, state.policy, model, problem=problem, config=config, estimator=estimator
    )
    updates, opt_state = optimizer.update(est.grad, state.opt_state, state.policy, grad_variance=est.grad_variance)
    policy = optax.apply_updates(state.policy, updates)
    ok = _all_finite((est.grad, est.grad_variance, policy, opt_state))
    new = PolicyOptState(policy, opt_state, est_state)
    new = PolicyOptState(*(_select(ok, n, o) for n, o in zip(new, state)))
    grad_norm = jnp.sqrt(sum(jnp.sum(g**2) for g in jax.tree.leaves(est.grad)))
    return new, UpdateInfo(est.value, est.particle_objective, grad_norm, ~ok, est.diagnostics)


def make_policy_update(problem: Problem, config: RolloutConfig, estimator: Estimator, optimizer):
    """A jitted ``step(key, state, model) -> (state, info)`` closed over the static configuration."""

    @jax.jit
    def step(key, state, model):
        return policy_update(key, state, model, problem=problem, config=config, estimator=estimator, optimizer=optimizer)

    return step


def make_policy_optimizer(problem: Problem, config: RolloutConfig, estimator: Estimator, optimizer, *, fixed_seed: bool = False):
    """A jitted ``run(key, state, model, num_steps) -> (state, info stacked over steps)``.

    Each step draws fresh particle noise from ``fold_in(key, i)``; with ``fixed_seed`` every
    step reuses ``key`` (the PEGASUS-style fixed-seed objective).
    """

    def run(key, state, model, num_steps: int):
        def body(st, i):
            k = key if fixed_seed else jax.random.fold_in(key, i)
            return policy_update(k, st, model, problem=problem, config=config, estimator=estimator, optimizer=optimizer)

        return jax.lax.scan(body, state, jnp.arange(num_steps))

    return jax.jit(run, static_argnames="num_steps")
