"""The task description shared by the simulator, the learner and the PILCO baseline.

A :class:`Task` is static configuration (a frozen dataclass of numbers and pure JAX
functions), never a pytree: it is closed over by jitted code. It knows four
representations of the state (tasks.md §0):

* the simulator state ``s`` that the ODE integrates (``sim_dim`` components);
* the model state ``x = sim_to_model(s)`` that the GP predicts and the cost is
  defined on (``model_dim``);
* the augmented model state ``x̃ = [x; sin x_a, cos x_a (a in angle_idx)]``;
* the control ``u = u_max ⊙ sat(ũ)``.

All index sets here are 0-based (tasks.md writes them 1-based).

A planning problem without a true system (the reference systems of :mod:`pipps.systems`, whose
dynamics are their model) has ``ode=None``; its :meth:`Task.step` raises. docs/architecture.md
says what separating the simulator from the planning problem would take.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Protocol

import jax
import jax.numpy as jnp
import numpy as np


class Cost(Protocol):
    """A per-state cost on the model state with its closed-form Gaussian expectation."""

    def __call__(self, x: jax.Array) -> jax.Array:  # c(x) for one model state
        ...

    def expected(self, mean: jax.Array, cov: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(E[c], Var[c]) for x ~ N(mean, cov) (tasks.md §5.6)."""
        ...


@dataclasses.dataclass(frozen=True, eq=False)
class Task:
    """One task under one preset. See the module docstring for the state representations."""

    name: str
    sim_dim: int
    model_dim: int
    action_dim: int
    dt: float
    horizon: int
    u_max: np.ndarray  # (action_dim,) control limits ū
    u_rand: np.ndarray  # (action_dim,) random actions are U[-u_rand, u_rand], unsquashed
    init_mean: np.ndarray  # (sim_dim,) simulator start mean μ0
    init_cov: np.ndarray  # (sim_dim, sim_dim) simulator start covariance Σ0
    model_init_mean: np.ndarray  # (model_dim,) planning start mean μ0^x
    model_init_cov: np.ndarray  # (model_dim, model_dim) planning start covariance Σ0^x
    obs_noise_std: np.ndarray  # (sim_dim,) observation noise std, already scaled by √k
    angle_idx: tuple[int, ...]  # model-state components augmented with (sin, cos)
    gp_input_idx: tuple[int, ...]  # indices into x̃ fed to the GP (the control is appended)
    policy_input_idx: tuple[int, ...]  # indices into x̃ fed to the policy
    ode: Callable[[jax.Array, jax.Array], jax.Array] | None  # ṡ = ode(s, u); None: no true system
    sim_to_model: Callable[[jax.Array], jax.Array]  # x = sim_to_model(s)
    fallen: Callable[[jax.Array], jax.Array] | None  # True where s violates the constraint
    cost: Cost
    substeps: int = 100  # integrator sub-steps per control interval (see integrate.py)
    preset: str = "thesis"
    noise_multiplier: float = 1.0  # k: observation noise variance is k·σ_base²

    # -- state maps ------------------------------------------------------------------
    def augment(self, x: jax.Array) -> jax.Array:
        """x̃ = [x; sin x_a, cos x_a] with each angle's pair in (sin, cos) order (tasks.md §0)."""
        if not self.angle_idx:
            return x
        a = x[..., jnp.asarray(self.angle_idx)]
        trig = jnp.stack([jnp.sin(a), jnp.cos(a)], axis=-1).reshape(*a.shape[:-1], 2 * a.shape[-1])
        return jnp.concatenate([x, trig], axis=-1)

    @property
    def augmented_dim(self) -> int:
        return self.model_dim + 2 * len(self.angle_idx)

    @property
    def gp_input_dim(self) -> int:
        return len(self.gp_input_idx) + self.action_dim

    @property
    def policy_input_dim(self) -> int:
        return len(self.policy_input_idx)

    def gp_input(self, x: jax.Array, u: jax.Array) -> jax.Array:
        """z = [x̃[I]; u], the GP input for model state x and control u."""
        xa = self.augment(x)
        return jnp.concatenate([xa[..., jnp.asarray(self.gp_input_idx)], u], axis=-1)

    def policy_input(self, x: jax.Array) -> jax.Array:
        """x̃[P], the policy input for model state x."""
        return self.augment(x)[..., jnp.asarray(self.policy_input_idx)]

    # -- true system --------------------------------------------------------------------
    def step(self, s: jax.Array, u: jax.Array) -> jax.Array:
        """One control interval of the true system: integrate ṡ = ode(s, u) over dt, u held.

        Raises:
          NotImplementedError: the task is a planning problem only (``ode`` is None).
        """
        from pipps.tasks.integrate import integrate_interval

        if self.ode is None:
            raise NotImplementedError(
                f"task {self.name!r} has no true-system ODE: it is a planning problem whose dynamics are its "
                "model; use the model (particles, pipps.pilco, an exact objective), not Task.step or rollout"
            )

        return integrate_interval(self.ode, s, u, self.dt, self.substeps)
