"""The planning problem, the true system, and the task that pairs them.

Two frozen dataclasses of numbers and pure JAX functions, never pytrees (jitted code closes
over them):

* :class:`Problem` — what the learner and PILCO plan on: the model state, the control, the
  horizon, the planning start distribution, the cost and the input maps. Everything that only
  plans (:mod:`pipps.particles`, :mod:`pipps.propagation`, :mod:`pipps.pilco`,
  :mod:`pipps.systems`, :mod:`pipps.studies`, :mod:`pipps.stats`) takes a Problem.
* :class:`Simulator` — the true system that produces data: the ODE, its integration, the
  simulator start distribution, the observation noise, the random actions, the fall condition,
  and ``sim_to_model``, the map from its state into the problem's model state.

A :class:`Task` is one of each (``task.problem``, ``task.simulator``) with the same control
interval ``dt``: what ``make_task`` builds, and what the true-system code (:mod:`pipps.rollout`,
:mod:`pipps.tasks.envs`, the experiment programs) takes, since a rollout on the true system needs
the problem's cost and policy input too. For reading, ``task.<field>`` forwards to the half that
has the field (``task.horizon`` is ``task.problem.horizon``, ``task.step`` is
``task.simulator.step``). A planning problem without a true system (the reference systems of
:mod:`pipps.systems`, whose dynamics are their model) is a Problem only.

The state has four representations (tasks.md §0):

* the simulator state ``s`` that the ODE integrates (``Simulator.sim_dim`` components);
* the model state ``x = sim_to_model(s)`` that the GP predicts and the cost is defined on
  (``Problem.model_dim``);
* the augmented model state ``x̃ = [x; sin x_a, cos x_a (a in angle_idx)]``;
* the control ``u = u_max ⊙ sat(ũ)``.

All index sets here are 0-based (tasks.md writes them 1-based).
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
class Problem:
    """The planning problem: model state, control, horizon, start, cost and input maps."""

    name: str
    model_dim: int
    action_dim: int
    dt: float
    horizon: int
    u_max: np.ndarray  # (action_dim,) control limits ū
    model_init_mean: np.ndarray  # (model_dim,) planning start mean μ0^x
    model_init_cov: np.ndarray  # (model_dim, model_dim) planning start covariance Σ0^x
    angle_idx: tuple[int, ...]  # model-state components augmented with (sin, cos)
    gp_input_idx: tuple[int, ...]  # indices into x̃ fed to the GP (the control is appended)
    policy_input_idx: tuple[int, ...]  # indices into x̃ fed to the policy
    cost: Cost

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


@dataclasses.dataclass(frozen=True, eq=False)
class Simulator:
    """The true system: what a rollout integrates, observes and maps into the model state."""

    name: str
    sim_dim: int
    dt: float  # the control interval; a Task's problem has the same
    init_mean: np.ndarray  # (sim_dim,) simulator start mean μ0
    init_cov: np.ndarray  # (sim_dim, sim_dim) simulator start covariance Σ0
    obs_noise_std: np.ndarray  # (sim_dim,) observation noise std, already scaled by √k
    u_rand: np.ndarray  # (action_dim,) random actions are U[-u_rand, u_rand], unsquashed
    ode: Callable[[jax.Array, jax.Array], jax.Array]  # ṡ = ode(s, u)
    sim_to_model: Callable[[jax.Array], jax.Array]  # x = sim_to_model(s), into the problem's model state
    fallen: Callable[[jax.Array], jax.Array] | None  # True where s violates the constraint
    substeps: int = 100  # integrator sub-steps per control interval (see integrate.py)
    noise_multiplier: float = 1.0  # k: observation noise variance is k·σ_base²

    def step(self, s: jax.Array, u: jax.Array) -> jax.Array:
        """One control interval of the true system: integrate ṡ = ode(s, u) over dt, u held."""
        from pipps.tasks.integrate import integrate_interval

        return integrate_interval(self.ode, s, u, self.dt, self.substeps)


@dataclasses.dataclass(frozen=True, eq=False)
class Task:
    """A planning problem and the true system it describes, under one preset.

    ``task.<field>`` reads the field (or method) of whichever half has it, the problem first
    (``name`` and ``dt``, which both have, agree); code that needs only one half takes that half.

    Raises:
      ValueError: the two halves disagree on ``dt`` or on the number of controls.
    """

    problem: Problem
    simulator: Simulator
    preset: str = "thesis"

    def __post_init__(self):
        if self.problem.dt != self.simulator.dt:
            raise ValueError(f"problem and simulator differ in dt: {self.problem.dt} and {self.simulator.dt}")
        if np.shape(self.simulator.u_rand) != (self.problem.action_dim,):
            raise ValueError(f"simulator.u_rand must have shape ({self.problem.action_dim},) (the problem's "
                             f"action_dim), got {np.shape(self.simulator.u_rand)}")

    def __getattr__(self, attr: str):
        # Only called when ordinary lookup fails: forward reads to the half that has the field.
        if attr.startswith("__"):
            raise AttributeError(attr)
        for half in ("problem", "simulator"):
            part = self.__dict__.get(half)
            if part is not None and hasattr(part, attr):
                return getattr(part, attr)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {attr!r} (neither its problem nor its "
                             "simulator has it)")
