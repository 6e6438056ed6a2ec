"""The records of the built-in tasks: cart-pole swing-up and balancing, unicycle balancing.

Everything the library knows about these tasks beyond their physics (:mod:`pipps.tasks.presets`)
is here, as :class:`~pipps.tasks.spec.TaskSpec` records: the success criterion of each, its
return threshold, its figures' metadata and its experiment settings per experiment preset. The
rest of the library asks the record (:func:`pipps.tasks.registry.get_task`), never the name.

* **Cart-pole** (swing-up and balancing): an evaluation rollout succeeds when it is *balanced at
  the end* (:func:`pipps.tasks.cartpole.balanced`, with the experiment's ``balance_steps``,
  ``balance_angle`` and ``balance_position``), an experiment when ``balanced_fraction`` of its
  final rollouts are; the thesis' return threshold (``success_threshold``, 15) is kept and
  reported beside it (docs/results-analyses.md, "The physical criterion").
* **Unicycle**: a rollout succeeds when the robot *stays upright throughout*
  (:func:`~pipps.tasks.spec.never_fell`), an experiment when ``upright_fraction`` of its final
  rollouts do; the thesis gives the unicycle no return threshold, so only the physical readings
  apply (:mod:`pipps.reporting.readings`).
"""

from __future__ import annotations

import functools
import math

from pipps.tasks import cartpole as cp
from pipps.tasks.base import Task
from pipps.tasks.presets import DEFAULT_COST, PRESETS, TASK_COSTS, make_task
from pipps.tasks.spec import PlotInfo, Success, TaskSpec, never_fell

#: The quick preset's RBF centre box over the cart-pole's [x_c, v, ω, θ] (docs/experiments.md "Presets").
QUICK_CENTRE_LOW = (-1.0, -3.0, -8.0, -math.pi / 2)
QUICK_CENTRE_HIGH = (1.0, 3.0, 8.0, 3 * math.pi / 2)
QUICK_LOG_LAMBDA = (0.0, 2.0, 4.0, 2.0)

CARTPOLE_LABELS = ("cart position x_c (m)", "cart velocity v (m/s)", "pole angular velocity ω (rad/s)",
                   "pole angle θ (rad)")
UNICYCLE_LABELS = ("roll rate θ̇ (rad/s)", "yaw rate φ̇ (rad/s)", "wheel rate ψ̇_w (rad/s)", "pitch rate ψ̇_f (rad/s)",
                   "turntable rate ψ̇_t (rad/s)", "x_c (m)", "y_c (m)", "roll θ (rad)", "yaw φ (rad)",
                   "wheel pitch ψ_f (rad)")

BALANCED_REASON = ("the thesis counts a swing-up when the pendulum was swung up and kept balanced; a return "
                   "threshold alone passes a policy that swings up and then runs the cart away")
UPRIGHT_REASON = "the unicycle's task is to balance: a rollout in which the robot falls has failed it"


def _cartpole_success(settings) -> Success:
    """Balanced at the end, with the experiment's bounds; the thesis' return threshold beside it."""
    rule = functools.partial(_balanced_rule, steps=settings.balance_steps, angle=settings.balance_angle,
                             position=settings.balance_position)
    return Success("balanced", rule, settings.balanced_fraction, settings.success_threshold, BALANCED_REASON)


def _balanced_rule(states, valid, *, steps: int, angle: float, position: float):
    del valid
    return cp.balanced(states, steps, angle, position)


def _unicycle_success(settings) -> Success:
    """Upright throughout, in ``upright_fraction`` of the rollouts; no return threshold."""
    return Success("upright", never_fell, settings.upright_fraction, None, UPRIGHT_REASON)


def _maker(name: str):
    """``make(preset, k, cost, cost_scale, **overrides)`` of a built-in task: :func:`make_task`, with
    ``cost_scale`` multiplying the Angle Cost's weight (the thesis' "Q × 0.01" cell)."""

    def make(preset: str = "thesis", k: float = 1.0, cost=None, cost_scale: float = 1.0, **overrides) -> Task:
        if cost_scale != 1.0:
            if (cost or "angle") != "angle" or "angle" not in TASK_COSTS[name]:
                raise ValueError("cost_scale: only the cart-pole Angle Cost takes a scale")
            import pipps.costs

            cost = pipps.costs.cartpole_angle_cost(scale=cost_scale)
        return make_task(name, preset=preset, k=k, cost=cost, **overrides)

    make.__name__ = make.__qualname__ = f"make_{name}"
    return make


def _spec(name: str, success, plot: PlotInfo, settings: dict, **kw) -> TaskSpec:
    return TaskSpec(_maker(name), success, name=name, plot=plot, settings=settings, presets=PRESETS,
                    costs=TASK_COSTS[name], default_costs={p: DEFAULT_COST[(name, p)] for p in PRESETS}, **kw)


def _cartpole(name: str, description: str) -> TaskSpec:
    return _spec(name, _cartpole_success, PlotInfo(CARTPOLE_LABELS, panel=3, panel_true=3),
                 {"pilco": {"preset": "pilco"},
                  "quick": {"policy_init": "uniform", "log_lambda_init": QUICK_LOG_LAMBDA}},
                 centre_box=(QUICK_CENTRE_LOW, QUICK_CENTRE_HIGH), scalable_costs=("angle",), label="cart-pole",
                 description=description)


def _unicycle() -> TaskSpec:
    linear = dict(policy="linear", centre_std=None)
    return _spec("unicycle", _unicycle_success, PlotInfo(UNICYCLE_LABELS, panel=9, panel_true=10, log_returns=True),
                 {"thesis": dict(num_random=5, num_learned=30, **linear),
                  "quick": dict(num_random=3, num_learned=5, policy_evals=150, **linear),
                  "pilco": dict(preset="pilco", num_random=10, num_learned=40, num_basis=50, **linear)},
                 description="unicycle balancing (thesis Table 4.4)")


#: The built-in tasks' records by name.
BUILTIN: dict[str, TaskSpec] = {
    "cartpole_swingup": _cartpole("cartpole_swingup", "cart-pole swing-up (thesis Tables 4.1-4.3)"),
    "cartpole_balance": _cartpole("cartpole_balance", "cart-pole balancing, the pole starting upright (DEL)"),
    "unicycle": _unicycle(),
}
