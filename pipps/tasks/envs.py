"""Gymnasium environments around a :class:`~pipps.tasks.base.Task`'s true system.

One ``step`` is one control interval of a true-system rollout (as PILCO's ``rollout.m``):

* the action is the control ``u`` itself (the policy saturates its own output); it must
  be finite, of shape ``(action_dim,)`` and inside ``[-u_max, u_max]``, otherwise
  ``ValueError`` — actions are rejected, never clipped;
* the true state advances by ``Simulator.step`` of the task's simulator (zero-order hold, RK4;
  jitted once per env);
* the observation is the true simulator state plus N(0, diag(obs_noise_std²)) noise,
  drawn from the env's ``np_random`` (k = 0 gives the true state exactly);
* ``reward = −c(x(s_{t+1}))`` on the noise-free next model state (for reporting);
* ``info`` holds ``model_state`` (noise-free x(s_{t+1})), ``obs_model_state`` (the model
  state computed from the noisy observation), ``cost`` and
  ``fallen``;
* ``truncated`` once ``horizon`` steps have been taken.

**Termination (unicycle).** When s_{t+1} violates the constraint (the robot has fallen)
the env still returns that transition, with ``terminated=True`` and
``info["fallen"] = True``. PILCO's ``rollout.m`` discards this transition: a learner that
collects GP training data must drop the transition flagged ``fallen`` (its observation,
reward and cost are reported for inspection only). Stepping after ``terminated`` or
``truncated`` raises ``gymnasium.error.ResetNeeded``, as does stepping before ``reset``.

**Registration.** Importing this module registers :data:`ENV_IDS` with gymnasium; nothing in the
library imports it. It is the module gymnasium imports for an id that names it,
``gymnasium.make("pipps.tasks.envs:pipps/CartPoleSwingUp-v0")``, and the one
:func:`pipps.tasks.register_envs` loads. (Gymnasium 1.x reads no package entry points for
environments, so nothing registers at ``import gymnasium``.) Like the rest of the true system, an
env computes in float64: it raises :class:`~pipps.precision.Float64Required` unless
:func:`pipps.enable_float64` was called.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium import spaces

from pipps.precision import require_float64
from pipps.tasks.base import Task
from pipps.tasks.presets import make_task

#: gymnasium ids and the task each one builds
ENV_IDS: dict[str, str] = {
    "pipps/CartPoleSwingUp-v0": "cartpole_swingup",
    "pipps/CartPoleBalance-v0": "cartpole_balance",
    "pipps/Unicycle-v0": "unicycle",
}


def _transition_fn(task: Task):
    """s, u ↦ (s', x(s'), c(x(s')), fallen(s')): the pure one-step map of the true system."""
    sim, problem = task.simulator, task.problem

    def transition(s, u):
        s_next = sim.step(s, u)
        x_next = sim.sim_to_model(s_next)
        fallen = sim.fallen(s_next) if sim.fallen is not None else jnp.asarray(False)
        return s_next, x_next, problem.cost(x_next), fallen

    return transition


def _sqrt_psd(cov: np.ndarray) -> np.ndarray:
    """A factor L with L Lᵀ = cov for a symmetric PSD cov (singular covariances allowed)."""
    w, v = np.linalg.eigh(cov)
    return v * np.sqrt(np.clip(w, 0.0, None))


class PippsEnv(gymnasium.Env):
    """The true (simulated) system of a Task as a gymnasium environment (module docstring).

    Args:
      task: a :class:`Task` (its simulator steps; its problem gives ``u_max``, the horizon and the
        cost), or a task name for :func:`make_task`.
      preset, k, cost, **overrides: passed to :func:`make_task` when ``task`` is a name
        (``gymnasium.make("pipps/CartPoleSwingUp-v0", preset="pilco", k=0.01)``); defaults
        ``preset="thesis"``, ``k=1``. Not allowed together with a ready Task.
      render_mode: only ``None`` (no rendering).
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        task: Task | str,
        preset: str | None = None,
        k: float | None = None,
        cost: Any = None,
        render_mode: str | None = None,
        **overrides: Any,
    ):
        require_float64("PippsEnv")
        if render_mode is not None:
            raise ValueError(f"render_mode {render_mode!r} is not supported; valid choices: None")
        if isinstance(task, str):
            preset = "thesis" if preset is None else preset
            k = 1.0 if k is None else k
            task = make_task(task, preset=preset, k=k, cost=cost, **overrides)
        elif not isinstance(task, Task):
            raise ValueError(f"task must be a Task or a task name, got {task!r}")
        elif overrides or cost is not None or preset is not None or k is not None:
            raise ValueError("preset, k, cost and Task-field overrides apply only when the task is given by name")
        self.task = task
        self.render_mode = None
        sim = task.simulator
        u_max = np.asarray(task.problem.u_max, dtype=np.float64)
        self.action_space = spaces.Box(-u_max, u_max, dtype=np.float64)
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(sim.sim_dim,), dtype=np.float64)
        self._obs_std = np.asarray(sim.obs_noise_std, dtype=np.float64)
        self._init_mean = np.asarray(sim.init_mean, dtype=np.float64)
        self._init_factor = _sqrt_psd(np.asarray(sim.init_cov, dtype=np.float64))
        # compiled once per env; every step reuses the same executable
        self._transition = jax.jit(_transition_fn(task))
        self._to_model = jax.jit(sim.sim_to_model)
        self.state: np.ndarray | None = None
        self._t = 0
        self._done = True

    # -- helpers ------------------------------------------------------------------------
    def _observe(self, s: np.ndarray) -> np.ndarray:
        """o = s + ε, ε ~ N(0, diag(obs_noise_std²)), on the simulator state."""
        if not np.any(self._obs_std):
            return s.copy()
        return s + self._obs_std * self.np_random.standard_normal(s.shape)

    def _check_action(self, action: Any) -> np.ndarray:
        try:
            u = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise ValueError(f"action must be a numeric array of shape {self.action_space.shape}: {err}") from err
        if u.shape != self.action_space.shape:
            raise ValueError(f"action has shape {u.shape}, expected {self.action_space.shape}")
        if not np.all(np.isfinite(u)):
            raise ValueError(f"action must be finite (no NaN/Inf), got {u}")
        if np.any(np.abs(u) > self.action_space.high):
            raise ValueError(f"action {u} is outside the control limits ±{self.action_space.high}")
        return u

    # -- gymnasium API ------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Sample s0 ~ N(init_mean, init_cov) and return (o0, info)."""
        super().reset(seed=seed)
        del options
        z = self.np_random.standard_normal(self._init_mean.shape)
        self.state = self._init_mean + self._init_factor @ z
        self._t = 0
        self._done = False
        obs = self._observe(self.state)
        info = {
            "model_state": np.asarray(self._to_model(self.state)),
            "obs_model_state": np.asarray(self._to_model(obs)),
        }
        return obs, info

    def step(self, action: Any):
        """Apply control ``action`` for one interval dt (module docstring)."""
        if self._done:
            raise gymnasium.error.ResetNeeded(
                "step() called before reset() or after the episode ended (terminated/truncated); call reset()"
            )
        u = self._check_action(action)
        s_next, x_next, cost, fallen = self._transition(self.state, u)
        self.state = np.array(s_next, dtype=np.float64)
        self._t += 1
        terminated = bool(fallen)
        truncated = (not terminated) and self._t >= self.task.problem.horizon
        self._done = terminated or truncated
        obs = self._observe(self.state)
        cost = float(cost)
        info = {
            "model_state": np.asarray(x_next),
            "obs_model_state": np.asarray(self._to_model(obs)),
            "cost": cost,
            "fallen": terminated,
        }
        return obs, -cost, terminated, truncated, info


def register_envs() -> None:
    """Register the ``ENV_IDS`` with gymnasium (idempotent)."""
    for env_id, task_name in ENV_IDS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point="pipps.tasks.envs:PippsEnv", kwargs={"task": task_name})


register_envs()
