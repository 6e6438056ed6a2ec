"""A pendulum to swing up: a task of your own for pipps (docs/tutorial.md)."""
import jax.numpy as jnp
import numpy as np

from pipps.costs import SaturatingCost
from pipps.tasks import Problem, Simulator, Success, Task, TaskSpec

G, L, M, B = 9.81, 1.0, 1.0, 0.1  # gravity (m/s²), length (m), mass (kg), friction (N m s)
U_MAX = 5.0  # the largest torque (N m), below M·G·L: the pendulum must be swung up, not lifted


def ode(s, u):
    """ṡ for s = [ω, θ] (θ = 0 hangs, θ = π is upright) under the torque u = [τ]."""
    omega, theta = s[0], s[1]
    return jnp.stack([(u[0] - B * omega - M * G * L * jnp.sin(theta)) / (M * L**2), omega])


def upright(states, valid):
    """Per rollout: within 0.5 rad of upright in each of the last 10 states (the last second)."""
    return jnp.all(jnp.cos(states[..., -10:, 1]) <= -jnp.cos(0.5), axis=-1)


# the cost on [ω, θ, sin θ, cos θ]: 1 − exp(−d²/4), d the tip's distance from upright (L = 1)
cost = SaturatingCost(W=np.diag([0.0, 0.0, 0.5, 0.5]), target=[0.0, np.pi, 0.0, -1.0], angle_idx=(1,))
start = np.zeros(2), np.diag([0.1, 0.1]) ** 2  # hanging at rest, give or take 0.1
problem = Problem(name="pendulum", dt=0.1, horizon=30, u_max=[U_MAX], model_init_mean=start[0],
                  model_init_cov=start[1], cost=cost, angle_idx=(1,), gp_input_idx=(0, 2, 3),
                  policy_input_idx=(0, 2, 3))  # the GP and the policy see ω, sin θ, cos θ
simulator = Simulator(name="pendulum", dt=0.1, ode=ode, init_mean=start[0], init_cov=start[1],
                      obs_noise_std=0.01)
pendulum = TaskSpec(Task(problem, simulator),
                    Success("upright", upright, fraction=0.5, reason="swung up and held for the last second"))
