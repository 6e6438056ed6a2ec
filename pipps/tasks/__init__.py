"""The tasks: cart-pole swing-up/balancing, unicycle balancing, and tasks of your own.

A task is one record, a :class:`TaskSpec`: its physics, a :class:`Task` (the planning
:class:`Problem`, ``task.problem``, and the true system, a :class:`Simulator` or a
:class:`HostSimulator`, ``task.simulator``), its :class:`Success` criterion, what its figures need
(:class:`PlotInfo`) and its experiment settings. :func:`get_task` finds one by name, by
``module:attribute`` or by entry point (:mod:`pipps.tasks.registry`); :func:`register` makes one of
your own findable by name (docs/tutorial.md). ``make_task(name, preset, k, cost, **overrides)``
builds a built-in task's :class:`Task` directly. :func:`from_gymnasium` makes a gymnasium
environment the true system of a task.

The gymnasium environments of the built-in tasks (:mod:`pipps.tasks.envs`, ids
``pipps/CartPoleSwingUp-v0``, ``pipps/CartPoleBalance-v0`` and ``pipps/Unicycle-v0``) are
registered by :func:`register_envs`, or by naming the module in the id:
``gymnasium.make("pipps.tasks.envs:pipps/CartPoleSwingUp-v0")``. Importing this package does
neither and does not import gymnasium; ``ENV_IDS``, ``PippsEnv`` and ``from_gymnasium`` load their
modules (and with :mod:`pipps.tasks.envs` the registration) when first used.
"""

from pipps.tasks.base import Cost, HostSimulator, HostSystem, Problem, Simulator, Task
from pipps.tasks.cartpole import CartPoleParams, cartpole_energy, cartpole_ode
from pipps.tasks.integrate import integrate_interval
from pipps.tasks.presets import PRESETS, TASK_NAMES, make_task
from pipps.tasks.registry import ENTRY_POINT_GROUP, TaskUnavailable, get_task, register, task_names, task_source
from pipps.tasks.spec import DEFAULT_SETTINGS, PlotInfo, Success, TaskSpec, never_fell
from pipps.tasks.unicycle import (
    UnicycleParams,
    unicycle_derived,
    unicycle_fallen,
    unicycle_full_state,
    unicycle_ode,
    unicycle_sim_to_model,
)

_ENV_NAMES = ("ENV_IDS", "PippsEnv")


def register_envs() -> None:
    """Register the gymnasium ids of :data:`pipps.tasks.envs.ENV_IDS` (idempotent)."""
    from pipps.tasks import envs

    envs.register_envs()


def __getattr__(name: str):
    if name in _ENV_NAMES:
        from pipps.tasks import envs

        return getattr(envs, name)
    if name == "from_gymnasium":
        from pipps.tasks import gym_task

        return gym_task.from_gymnasium
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "DEFAULT_SETTINGS",
    "ENTRY_POINT_GROUP",
    "ENV_IDS",
    "PRESETS",
    "TASK_NAMES",
    "CartPoleParams",
    "Cost",
    "HostSimulator",
    "HostSystem",
    "PippsEnv",
    "PlotInfo",
    "Problem",
    "Simulator",
    "Success",
    "Task",
    "TaskSpec",
    "TaskUnavailable",
    "UnicycleParams",
    "cartpole_energy",
    "cartpole_ode",
    "from_gymnasium",
    "get_task",
    "integrate_interval",
    "make_task",
    "never_fell",
    "register",
    "register_envs",
    "task_names",
    "task_source",
    "unicycle_derived",
    "unicycle_fallen",
    "unicycle_full_state",
    "unicycle_ode",
    "unicycle_sim_to_model",
]
