"""A gymnasium environment as the true system of a task: :func:`from_gymnasium`.

Any environment with ``Box`` observation and action spaces (a bounded, symmetric action space)
becomes a :class:`~pipps.tasks.spec.TaskSpec` whose true system is the environment itself, stepped
from Python with its own ``reset(seed=…)`` and ``step`` (a :class:`~pipps.tasks.base.HostSimulator`;
:func:`pipps.rollout.host_rollout`). What pipps needs besides the environment:

* a **cost** on the model state (a JAX function of one state; a
  :class:`~pipps.costs.SaturatingCost` as the common case, whose ``expected(mean, cov)`` is what
  PILCO plans with — without one, only the particle methods apply);
* a **success** criterion (:class:`~pipps.tasks.spec.Success`), judged on the environment's
  observations;
* the **horizon** in control intervals, and optionally a map ``to_model`` from the observation
  into the model state the GP learns (default: the observation itself), with ``angle_idx``
  (components fed to the GP and the policy as sin/cos), ``periodic`` (components ``to_model``
  returns wrapped, whose one-step differences are wrapped too) and the GP and policy inputs.

The control interval is the environment's own ``dt`` (``env.unwrapped.dt``; give ``dt`` where it
has none) times ``action_repeat`` steps with the control held. The planning start distribution
is the environment's own, moment-matched: the mean and covariance of ``to_model`` over
``start_samples`` seeded resets. An episode that the environment *terminates* ends as a fall (the
transition is not used for learning and the rest of the rollout is invalid); one it *truncates*
before the horizon is an error (the horizon exceeds its time limit). The reward is not used: the
cost is the task's.

This module is a front end: it imports gymnasium (``pipps.tasks.from_gymnasium`` loads it).
"""

from __future__ import annotations

from typing import Any, Callable, Mapping

import gymnasium
import jax
import numpy as np
from gymnasium import spaces

from pipps.tasks.base import HostSimulator, Problem, Task, identity
from pipps.tasks.spec import PlotInfo, Success, TaskSpec


class GymnasiumSystem:
    """A gymnasium environment as a :class:`~pipps.tasks.base.HostSystem`: ``reset(seed)`` returns the
    first observation, ``step(u)`` holds ``u`` for ``action_repeat`` environment steps and returns the
    last observation and whether the environment terminated the episode."""

    def __init__(self, env: gymnasium.Env, action_repeat: int = 1):
        self.env, self.action_repeat = env, action_repeat
        self.dtype = env.action_space.dtype

    def reset(self, seed: int) -> np.ndarray:
        obs, _ = self.env.reset(seed=seed)
        return np.asarray(obs, dtype=np.float64)

    def step(self, u: np.ndarray) -> tuple[np.ndarray, bool]:
        action = np.asarray(u, dtype=self.dtype)
        for _ in range(self.action_repeat):
            obs, _, terminated, truncated, _ = self.env.step(action)
            if terminated:
                return np.asarray(obs, dtype=np.float64), True
            if truncated:
                raise RuntimeError(f"{self.env.spec.id if self.env.spec else self.env}: the environment truncated the "
                                   "episode before the task's horizon (its time limit is shorter)")
        return np.asarray(obs, dtype=np.float64), False


def _factory(env: str | Callable[[], gymnasium.Env], make_kwargs: Mapping[str, Any]) -> Callable[[], gymnasium.Env]:
    if isinstance(env, str):
        return lambda: gymnasium.make(env, disable_env_checker=True, **make_kwargs)
    if callable(env):
        if make_kwargs:
            raise ValueError("make_kwargs: only with an environment id (a factory makes its own environment)")
        return env
    raise ValueError(f"env: a gymnasium id or a function of no arguments returning an environment, got {env!r}")


def _box(space, what: str) -> spaces.Box:
    if not isinstance(space, spaces.Box) or len(space.shape) != 1:
        raise ValueError(f"{what}: needs a 1-d Box space, got {space}")
    return space


def start_moments(make_env: Callable[[], gymnasium.Env], to_model, samples: int) -> tuple[np.ndarray, ...]:
    """(observation mean, observation covariance, model-state mean, model-state covariance) of the
    environment's start distribution, from ``samples`` resets seeded 0, 1, …"""
    env = make_env()
    try:
        obs = np.stack([np.asarray(env.reset(seed=i)[0], dtype=np.float64) for i in range(samples)])
    finally:
        env.close()
    x = np.asarray(jax.vmap(to_model)(obs), dtype=np.float64)
    cov = lambda a: np.atleast_2d(np.cov(a, rowvar=False))  # noqa: E731
    return obs.mean(0), cov(obs), x.mean(0), cov(x)


def from_gymnasium(
    env: str | Callable[[], gymnasium.Env],
    *,
    name: str,
    cost: Callable,
    success: Success,
    horizon: int,
    to_model: Callable = identity,
    angle_idx: tuple[int, ...] = (),
    periodic: tuple[int, ...] = (),
    gp_input_idx: tuple[int, ...] | None = None,
    policy_input_idx: tuple[int, ...] | None = None,
    obs_noise_std: float | np.ndarray = 0.0,
    action_repeat: int = 1,
    dt: float | None = None,
    start_samples: int = 1000,
    u_rand: np.ndarray | None = None,
    pilco_budget: tuple[int, int] | None = None,
    plot: PlotInfo | None = None,
    settings: Mapping[str, Mapping[str, Any]] | None = None,
    make_kwargs: Mapping[str, Any] | None = None,
) -> TaskSpec:
    """A task whose true system is the gymnasium environment ``env`` (module docstring).

    Args:
      env: a gymnasium id (made with ``gymnasium.make(env, **make_kwargs)``) or a function of no
        arguments that returns an environment.
      name: the task's name.
      cost: the cost of one model state (JAX); with ``expected(mean, cov)`` PILCO can plan on it.
      success: the criterion, judged on the observations (:class:`~pipps.tasks.spec.Success`).
      horizon: control intervals per episode (at most the environment's time limit / ``action_repeat``).
      to_model: observation -> model state (JAX); default the observation itself.
      angle_idx, periodic, gp_input_idx, policy_input_idx: as in :class:`~pipps.tasks.base.Problem`
        and :class:`~pipps.tasks.base.Simulator`.
      obs_noise_std: noise pipps adds to what the learner observes (0: the observation as it is).
      action_repeat: environment steps per control interval, the control held.
      dt: the environment's step in seconds, where ``env.unwrapped.dt`` does not say.
      start_samples: resets whose moments are the planning start distribution.
      u_rand: the random trials' action range (default: the action space's bound).
      pilco_budget, plot, settings: as in :class:`~pipps.tasks.base.Problem` and :class:`TaskSpec`.

    Raises:
      ValueError: spaces that are not 1-d Boxes, an unbounded or asymmetric action space, a
        horizon beyond the time limit, or any field the task records refuse (naming it).
    """
    make_env = _factory(env, dict(make_kwargs or {}))
    probe = make_env()
    try:
        obs_space = _box(probe.observation_space, "observation_space")
        act_space = _box(probe.action_space, "action_space")
        high, low = np.asarray(act_space.high, np.float64), np.asarray(act_space.low, np.float64)
        if not (np.all(np.isfinite(high)) and np.array_equal(low, -high) and np.all(high > 0)):
            raise ValueError(f"action_space: pipps' policies act in a bounded box symmetric about 0, got {act_space}")
        step = dt if dt is not None else getattr(probe.unwrapped, "dt", None)
        if step is None:
            raise ValueError(f"dt: {probe.unwrapped} does not say its time step (env.unwrapped.dt); give dt=")
        limit = probe.spec.max_episode_steps if probe.spec is not None else None
    finally:
        probe.close()
    if isinstance(action_repeat, bool) or not isinstance(action_repeat, int) or action_repeat < 1:
        raise ValueError(f"action_repeat: must be an integer >= 1, got {action_repeat!r}")
    if limit is not None and int(horizon) * action_repeat > limit:
        raise ValueError(f"horizon: {horizon} intervals of {action_repeat} step(s) exceed the environment's time limit "
                         f"of {limit} steps")
    obs_mean, obs_cov, x_mean, x_cov = start_moments(make_env, to_model, start_samples)
    interval = float(step) * action_repeat
    problem = Problem(name=name, dt=interval, horizon=horizon, u_max=high, model_init_mean=x_mean, model_init_cov=x_cov,
                      cost=cost, angle_idx=angle_idx, gp_input_idx=gp_input_idx, policy_input_idx=policy_input_idx,
                      pilco_budget=pilco_budget)
    simulator = HostSimulator(name=name, dt=interval, make_system=lambda: GymnasiumSystem(make_env(), action_repeat),
                              init_mean=obs_mean, init_cov=obs_cov, obs_noise_std=obs_noise_std, u_rand=u_rand,
                              sim_to_model=to_model, sim_dim=obs_space.shape[0], periodic=periodic)
    task = Task(problem, simulator, preset="default")
    return TaskSpec(task, success, name=name, plot=plot or PlotInfo(), settings=dict(settings or {}),
                    description=f"gymnasium {env if isinstance(env, str) else 'environment'}, {interval:g} s steps")
