"""Particle rollouts through a known simulator with noise on the actions (Suh et al. 2022, eq. 1).

The second setting the estimators serve, beside the thesis' learned model with noise on the state
(:mod:`pipps.particles.forward`): a *known* differentiable simulator ``x' = step(x, u)`` (a JAX
function; no GP) whose randomness is injected on the actions,

``u_{i,t} = π(x̃_{i,t}[P]; θ) + σ_u ⊙ w_{i,t}``,  ``x_{i,t+1} = step(x_{i,t}, u_{i,t}) + σ_x ⊙ ε_{i,t+1}``,

``w, ε ~ N(0, I)``, with the cost ``c(x_{i,t+1})`` and the objective
``J = Σ_{t=1..T} (1/P) Σ_i c(x_{i,t})`` of the thesis' rollout (``σ_x = 0`` unless
``RolloutConfig.state_noise`` says otherwise). It is selected by ``RolloutConfig(action_noise=σ_u)``;
:func:`pipps.particles.particle_rollout` and :func:`pipps.particles.sample_noise` dispatch here.

**The sampled node is the action.** At step t the particle's distribution parameters are those of
its action, ``ζ_t = (π(x̃_t[P]; θ), σ_u)``, and its sample is ``u_t``; the next state follows from it
deterministically (up to the state noise, which does not depend on θ, so no likelihood ratio of it is
taken: it is the environment's randomness, reparameterised by the pathwise part). The backward sweep
(:func:`pipps.propagation.backward.backward_sweep`) runs the same gradient parts and combiners on
this node as on the thesis' state node: an LR part scores ``u_t`` under ``N(π(x̃_t[P]), σ_u²)`` — the
zeroth-order batched gradient (ZoBG) of Suh et al. when the weighting is plain — the pathwise part
differentiates through ``step`` — their first-order batched gradient (FoBG) — and a combiner weighs
the two at the action node.

**The simulator** is any object with ``step(x (D,), u (F,)) -> x' (D,)``, a pure JAX function of one
particle (vmapped here); it may be a pytree whose leaves are numbers (a contact stiffness), so that
a new value does not recompile. With ``jacobian`` the record keeps the transition Jacobians
``∂x'/∂x`` and ``∂x'/∂u`` per particle, by forward-mode differentiation (``jax.jacfwd``): the
backward sweep needs no reverse mode through the simulator, which MuJoCo MJX's solver loop refuses.
They are recorded only for an estimator with a pathwise part; an LR estimator needs none.
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import jax
import jax.numpy as jnp

from pipps.particles.forward import Noise, RolloutConfig, controls
from pipps.policies import check_policy
from pipps.tasks.base import Problem


class KnownSimulator(Protocol):
    """A known differentiable transition of one particle: ``step(x (D,), u (F,)) -> x' (D,)``."""

    def step(self, x: jax.Array, u: jax.Array) -> jax.Array: ...


class ActionRecord(NamedTuple):
    """What the backward sweep needs of a rollout with noise on the actions, stacked over t = 0..T−1."""

    x: jax.Array  # (T, P, D) x_t, the state the action is chosen at
    u: jax.Array  # (T, P, F) u_t = π(x̃_t[P]) + σ_u ⊙ w_t, the sampled action
    mean: jax.Array  # (T, P, F) π(x̃_t[P]), the action's mean
    std: jax.Array  # (T, P, F) σ_u
    eps: jax.Array  # (T, P, F) w_t
    x_next: jax.Array  # (T, P, D) x_{t+1}
    cost: jax.Array  # (T, P) c(x_{t+1})
    jac_x: jax.Array | None  # (T, P, D, D) ∂x_{t+1}/∂x_t with u_t held fixed; None without jacobian
    jac_u: jax.Array | None  # (T, P, D, F) ∂x_{t+1}/∂u_t
    nominal_cost: jax.Array | None = None  # (T, P) c of each particle's zero-noise rollout, where a baseline reads it

    @property
    def objective(self) -> jax.Array:
        """J = Σ_t mean_i c(x_{i,t})."""
        return jnp.sum(jnp.mean(self.cost, axis=-1))


def _check(problem: Problem, simulator, noise: Noise, config: RolloutConfig) -> None:
    if not callable(getattr(simulator, "step", None)):
        raise ValueError("with action_noise the model is a known simulator: an object with step(x, u) -> x' "
                         f"(pipps.particles.simulator.KnownSimulator), got {type(simulator).__name__}")
    for name, stds, size, what in (("action_noise", config.action_noise, problem.action_dim, "action_dim"),
                                   ("state_noise", config.state_noise, problem.model_dim, "model_dim")):
        if len(stds) not in (1, size):
            raise ValueError(f"{name} has {len(stds)} entries; give one, or one per component ({what} = {size})")
    if noise.x0.shape[-1] != problem.model_dim or noise.eps.shape[-1] != problem.action_dim:
        raise ValueError(f"noise has state dimension {noise.x0.shape[-1]} and action dimension {noise.eps.shape[-1]}, "
                         f"the problem {problem.model_dim} and {problem.action_dim}")
    out = jax.eval_shape(simulator.step, jax.ShapeDtypeStruct((problem.model_dim,), noise.x0.dtype),
                         jax.ShapeDtypeStruct((problem.action_dim,), noise.x0.dtype))
    if getattr(out, "shape", None) != (problem.model_dim,):
        raise ValueError(f"simulator.step must return the next state, shape ({problem.model_dim},), "
                         f"got {getattr(out, 'shape', type(out).__name__)}")


def sample_action_noise(key: jax.Array, problem: Problem, config: RolloutConfig) -> Noise:
    """x_0 ~ N(μ0^x, Σ0^x), the actions' w ~ N(0, I) (T, P, F) and, with state noise, ε (T, P, D)."""
    k0, kw, ks = jax.random.split(key, 3)
    P, T = config.num_particles, config.steps(problem)
    x0 = jax.random.multivariate_normal(
        k0, jnp.asarray(problem.model_init_mean), jnp.asarray(problem.model_init_cov), (P,), method="svd"
    )
    w = jax.random.normal(kw, (T, P, problem.action_dim))
    state_eps = jax.random.normal(ks, (T, P, problem.model_dim)) if any(config.state_noise) else None
    return Noise(x0, w, state_eps)


def _transition(simulator, jacobian: bool):
    """(x, u) ↦ x' for all particles, with (∂x'/∂x, ∂x'/∂u) by forward mode when ``jacobian``."""
    if not jacobian:
        return lambda x, u: (jax.vmap(simulator.step)(x, u), None, None)

    def with_primal(xi, ui):
        out = simulator.step(xi, ui)
        return out, out

    jac = jax.jacfwd(with_primal, argnums=(0, 1), has_aux=True)

    def both(x, u):
        (jx, ju), x_next = jax.vmap(jac)(x, u)
        return x_next, jx, ju

    return both


def action_rollout(problem: Problem, policy, simulator, noise: Noise, config: RolloutConfig, *,
                   jacobian: bool = True) -> ActionRecord:
    """All particles through all steps with noise on the actions, one scan over time (module doc).

    ``jacobian`` (static) records the transition Jacobians for a pathwise part; a forward-only
    evaluation, or an estimator without a pathwise part, sets it False.
    """
    _check(problem, simulator, noise, config)
    check_policy(policy, problem.policy_input_dim, problem.action_dim)
    dtype = noise.x0.dtype
    sigma_u = jnp.broadcast_to(jnp.asarray(config.action_noise, dtype), (problem.action_dim,))
    sigma_x = jnp.broadcast_to(jnp.asarray(config.state_noise, dtype), (problem.model_dim,))
    transition = _transition(simulator, jacobian)

    def body(x, step_noise):
        w, e = step_noise
        mean = controls(problem, policy, x)
        u = mean + sigma_u * w
        x_next, jx, ju = transition(x, u)
        if e is not None:
            x_next = x_next + sigma_x * e
        cost = jax.vmap(problem.cost)(x_next)
        std = jnp.broadcast_to(sigma_u, mean.shape)
        return x_next, ActionRecord(x, u, mean, std, w, x_next, cost, jx, ju)

    _, record = jax.lax.scan(body, noise.x0, (noise.eps, noise.state_eps))
    return record
