"""The tasks: cart-pole swing-up/balancing and unicycle balancing (tasks.md §2–3).

``make_task(name, preset, k, cost, **overrides)`` builds a :class:`Task`; importing this
package also registers the gymnasium ids ``pipps/CartPoleSwingUp-v0``,
``pipps/CartPoleBalance-v0`` and ``pipps/Unicycle-v0`` (see :mod:`pipps.tasks.envs`).
"""

import pipps  # noqa: F401  (enables float64 before any task array is built)
from pipps.tasks.base import Cost, Task
from pipps.tasks.cartpole import CartPoleParams, cartpole_energy, cartpole_ode
from pipps.tasks.envs import ENV_IDS, PippsEnv, register_envs
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

register_envs()

__all__ = [
    "ENV_IDS",
    "PRESETS",
    "TASK_NAMES",
    "CartPoleParams",
    "Cost",
    "PippsEnv",
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
