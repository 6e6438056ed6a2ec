"""The exactness reference of the known-simulator setting: a linear simulator with noise on the actions.

``x_{t+1} = A x_t + B u_t + σ_x ε``, ``u_t = W x̃_t + b + σ_u w`` (an unsaturated linear policy),
quadratic cost. Every state distribution is Gaussian, so the objective and its gradient are closed
form (:func:`exact_objective`, differentiated by ``jax.grad``), and every estimator through the
action node (:mod:`pipps.particles.simulator`) — RP (Suh et al.'s FoBG), plain LR (their ZoBG), BIW-LR,
total propagation, the action-node and the robust combiners — is checked against it
(``tests/test_known_simulator.py``), as the thesis' setting is checked on
:mod:`pipps.systems.linear_gaussian`.

The recursion: with ``M = A + B W``, ``μ' = M μ + B b``, ``Σ' = M Σ Mᵀ + B diag(σ_u²) Bᵀ + diag(σ_x²)``,
``J = Σ_{t=1..T} E[c(x_t)]``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax.tree_util import register_dataclass

from pipps.policies import LinearPolicy
from pipps.systems.linear_gaussian import frozen
from pipps.systems.quadratic_cost import QuadraticCost
from pipps.tasks.base import Problem


@register_dataclass
@dataclasses.dataclass(frozen=True)
class LinearSimulator:
    """The known transition ``step(x, u) = A x + B u`` (a pytree: A and B are traced)."""

    A: jax.Array  # (D, D)
    B: jax.Array  # (D, F)

    def step(self, x: jax.Array, u: jax.Array) -> jax.Array:
        return self.A @ x + self.B @ u


def exact_objective(problem: Problem, simulator: LinearSimulator, policy: LinearPolicy, action_std, state_std=0.0,
                    horizon: int | None = None) -> jax.Array:
    """``J = Σ_{t=1..T} E[c(x_t)]`` in closed form (module doc); differentiable in the policy and the simulator."""
    if policy.saturated:
        raise ValueError("the closed form needs the unsaturated linear policy (LinearPolicy(saturated=False))")
    D, F = problem.model_dim, problem.action_dim
    su = jnp.broadcast_to(jnp.asarray(action_std, float), (F,))
    sx = jnp.broadcast_to(jnp.asarray(state_std, float), (D,))
    M = simulator.A + simulator.B @ policy.W
    c = simulator.B @ policy.b
    noise = simulator.B @ jnp.diag(su**2) @ simulator.B.T + jnp.diag(sx**2)

    def step(carry, _):
        mu, S = carry
        mu, S = M @ mu + c, M @ S @ M.T + noise
        return (mu, S), problem.cost.expected(mu, S)[0]

    T = problem.horizon if horizon is None else horizon
    init = (jnp.asarray(problem.model_init_mean), jnp.asarray(problem.model_init_cov))
    _, costs = jax.lax.scan(step, init, None, length=T)
    return jnp.sum(costs)


def reference_system(horizon: int = 8):
    """The fixed instance the tests share: D = 3, F = 2, a slightly unstable A, a random linear policy.

    Returns ``(problem, simulator, policy)``."""
    rng = np.random.default_rng(7)
    D, F = 3, 2
    A = np.eye(D) + 0.15 * rng.standard_normal((D, D))
    B = 0.5 * rng.standard_normal((D, F))
    cost = QuadraticCost(Q=np.diag([1.0, 0.5, 0.25]), target=np.array([0.5, -0.2, 0.1]))
    problem = Problem(name="linear_actions", dt=1.0, horizon=horizon, u_max=np.ones(F),
                      model_init_mean=np.array([0.3, -0.1, 0.2]), model_init_cov=0.05 * np.eye(D), cost=cost)
    simulator = LinearSimulator(jnp.asarray(frozen(A, (D, D), "A")), jnp.asarray(frozen(B, (D, F), "B")))
    policy = LinearPolicy(jnp.asarray(0.2 * rng.standard_normal((F, D))), jnp.asarray(0.1 * rng.standard_normal(F)),
                          u_max=(1.0,) * F, saturated=False)
    return problem, simulator, policy
