"""The tasks: cart-pole swing-up/balancing and unicycle balancing (tasks.md §2–3).

``make_task(name, preset, k, cost, **overrides)`` builds a :class:`Task`: the planning
:class:`Problem` (``task.problem``) and the true system, a :class:`Simulator` (``task.simulator``). The gymnasium
environments (:mod:`pipps.tasks.envs`, ids ``pipps/CartPoleSwingUp-v0``, ``pipps/CartPoleBalance-v0``
and ``pipps/Unicycle-v0``) are registered by :func:`register_envs`, or by naming the module in the
id: ``gymnasium.make("pipps.tasks.envs:pipps/CartPoleSwingUp-v0")``. Importing this package does
neither and does not import gymnasium; ``ENV_IDS`` and ``PippsEnv`` load :mod:`pipps.tasks.envs`
(and with it the registration) when first used.
"""

from pipps.tasks.base import Cost, Problem, Simulator, Task
from pipps.tasks.cartpole import CartPoleParams, cartpole_energy, cartpole_ode
from pipps.tasks.integrate import integrate_interval
from pipps.tasks.presets import PRESETS, TASK_NAMES, make_task
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
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "ENV_IDS",
    "PRESETS",
    "TASK_NAMES",
    "CartPoleParams",
    "Cost",
    "PippsEnv",
    "Problem",
    "Simulator",
    "Task",
    "UnicycleParams",
    "cartpole_energy",
    "cartpole_ode",
    "integrate_interval",
    "make_task",
    "register_envs",
    "unicycle_derived",
    "unicycle_fallen",
    "unicycle_full_state",
    "unicycle_ode",
    "unicycle_sim_to_model",
]
