"""Task presets: ``make_task(name, preset, k, cost, **overrides) -> Task``, a planning problem and its simulator.

Two presets (docs/task-cartpole.md and docs/task-unicycle.md, "Presets"):

* ``"thesis"`` — the PIPPS thesis protocol: 10 Hz control for both tasks, cart-pole
  H = 30 (3 s) with the thesis' per-component observation noise and raw 4-dim GP and
  policy inputs (no sin/cos), the Angle Cost; unicycle H = 20 (2 s).
* ``"pilco"`` — the PILCO MATLAB defaults (``settings_cp.m``, ``settings_unicycle.m``): cart-pole H = 40 with
  sin/cos augmentation of θ and the tip cost; unicycle dt = 0.15 s, H = 67.

Observation-noise standard deviations are ``√k`` times the preset's base std
(thesis §4.5.2: variance k·σ_base²). Indices are 0-based (PILCO's code writes them 1-based).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from pipps.tasks import cartpole as cp
from pipps.tasks import unicycle as uc
from pipps.tasks.base import Cost, Problem, Simulator, Task

TASK_NAMES: tuple[str, ...] = ("cartpole_swingup", "cartpole_balance", "unicycle")
PRESETS: tuple[str, ...] = ("thesis", "pilco")

#: valid cost names per task and the ``pipps.costs`` factory each one calls
COST_FACTORIES: dict[str, str] = {
    "angle": "cartpole_angle_cost",
    "tip": "cartpole_tip_cost",
    "unicycle": "unicycle_cost",
}
TASK_COSTS: dict[str, tuple[str, ...]] = {
    "cartpole_swingup": ("angle", "tip"),
    "cartpole_balance": ("angle", "tip"),
    "unicycle": ("unicycle",),
}
DEFAULT_COST: dict[tuple[str, str], str] = {
    ("cartpole_swingup", "thesis"): "angle",
    ("cartpole_swingup", "pilco"): "tip",
    ("cartpole_balance", "thesis"): "angle",
    ("cartpole_balance", "pilco"): "tip",
    ("unicycle", "thesis"): "unicycle",
    ("unicycle", "pilco"): "unicycle",
}

#: Largest RK4 sub-step (s) per task: ``substeps = ceil(dt / h_max)`` unless overridden.
#: Chosen from the accuracy study in ``pipps/tasks/integrate.py`` (reference steps to < 1e-10).
MAX_SUBSTEP: dict[str, float] = {"cartpole": 1e-3, "unicycle": 0.75e-3}

# Fields that make_task sets from its own arguments, not from **overrides.
_ARGUMENT_FIELDS = {"preset": "preset", "noise_multiplier": "k", "cost": "cost"}
_ARRAY_FIELDS = (
    "u_max",
    "u_rand",
    "init_mean",
    "init_cov",
    "model_init_mean",
    "model_init_cov",
    "obs_noise_std",
)


def substeps_for(dt: float, max_substep: float) -> int:
    """The smallest sub-step count whose sub-step is at most ``max_substep``."""
    return max(1, int(math.ceil(dt / max_substep - 1e-9)))


def _cartpole_fields(name: str, preset: str) -> dict[str, Any]:
    """Task fields of the cart-pole (docs/task-cartpole.md, "Presets")."""
    mean = cp.CARTPOLE_BALANCE_MEAN if name == "cartpole_balance" else cp.CARTPOLE_SWINGUP_MEAN
    fields: dict[str, Any] = dict(
        name=name,
        sim_dim=4,
        model_dim=4,
        action_dim=1,
        dt=0.1,
        u_max=np.array([10.0]),
        u_rand=np.array([10.0]),
        init_mean=mean,
        init_cov=cp.CARTPOLE_INIT_COV,
        model_init_mean=mean,
        model_init_cov=cp.CARTPOLE_INIT_COV,
        ode=cp.cartpole_ode,
        sim_to_model=cp.cartpole_sim_to_model,
        fallen=None,
        pilco_budget=(150, 30),  # PILCO's: 150 line searches of at most 30 evaluations (``settings_cp.m``)
    )
    if preset == "thesis":
        # raw state into GP and policy (the thesis' 104-parameter count, §4.2.1: 20·4 + 20 + 4)
        fields.update(
            horizon=30,
            obs_noise_std=cp.CARTPOLE_OBS_STD_THESIS,
            angle_idx=(),
            gp_input_idx=(0, 1, 2, 3),
            policy_input_idx=(0, 1, 2, 3),
        )
    else:
        # x̃ = [x_c, v, ω, θ, sin θ, cos θ]; θ itself is not an input (as in PILCO)
        fields.update(
            horizon=40,
            obs_noise_std=cp.CARTPOLE_OBS_STD_PILCO,
            angle_idx=(3,),
            gp_input_idx=(0, 1, 2, 4, 5),
            policy_input_idx=(0, 1, 2, 4, 5),
        )
    return fields


def _unicycle_fields(preset: str) -> dict[str, Any]:
    """Task fields of the unicycle (docs/task-unicycle.md, "Presets")."""
    dt, horizon = (0.1, 20) if preset == "thesis" else (0.15, 67)
    return dict(
        name="unicycle",
        sim_dim=uc.SIM_DIM,
        model_dim=uc.MODEL_DIM,
        action_dim=2,
        dt=dt,
        horizon=horizon,
        u_max=np.array([10.0, 50.0]),
        u_rand=np.array([2.0, 10.0]),
        init_mean=uc.UNICYCLE_INIT_MEAN,
        init_cov=uc.UNICYCLE_INIT_COV,
        model_init_mean=uc.UNICYCLE_MODEL_INIT_MEAN,
        model_init_cov=uc.UNICYCLE_MODEL_INIT_COV,
        obs_noise_std=uc.UNICYCLE_OBS_STD,
        angle_idx=(),
        gp_input_idx=(0, 1, 2, 3, 4, 5, 6, 7, 9),  # all but yaw φ
        policy_input_idx=tuple(range(10)),
        ode=uc.unicycle_ode,
        sim_to_model=uc.unicycle_sim_to_model,
        fallen=uc.unicycle_fallen,
        pilco_budget=(-150, 20),  # PILCO's: 150 evaluations, at most 20 per line search (``settings_unicycle.m``)
    )


def _check_choice(kind: str, value: Any, choices: tuple[str, ...]) -> str:
    if not isinstance(value, str) or value not in choices:
        raise ValueError(f"unknown {kind} {value!r}; valid choices: {', '.join(choices)}")
    return value


def _check_k(k: Any) -> float:
    """k must be a finite real number ≥ 0 (the observation-noise variance multiplier)."""
    if isinstance(k, bool) or not isinstance(k, (int, float, np.integer, np.floating)):
        raise ValueError(f"noise multiplier k must be a finite number >= 0, got {k!r}")
    k = float(k)
    if not math.isfinite(k) or k < 0.0:
        raise ValueError(f"noise multiplier k must be a finite number >= 0, got {k!r}")
    return k


def make_cost(task_name: str, cost: str | Cost | None, preset: str) -> Cost:
    """The cost object for ``task_name``: a name (see ``TASK_COSTS``), a Cost, or the preset default.

    Names resolve lazily to ``pipps.costs`` factories (``cartpole_angle_cost``,
    ``cartpole_tip_cost``, ``unicycle_cost``). A ready Cost object (callable with an
    ``expected(mean, cov)`` method) is passed through, e.g.
    ``pipps.costs.cartpole_angle_cost(scale=0.01)`` for the thesis' "Q × 0.01" cell.
    """
    if cost is None:
        cost = DEFAULT_COST[(task_name, preset)]
    if not isinstance(cost, str):
        if callable(cost) and callable(getattr(cost, "expected", None)):
            return cost
        raise ValueError(
            f"cost must be a name ({', '.join(TASK_COSTS[task_name])}) or an object with __call__ and "
            f"expected(mean, cov); got {cost!r}"
        )
    _check_choice(f"cost for task {task_name!r}:", cost, TASK_COSTS[task_name])
    import pipps.costs  # lazy: written separately, only needed once a task is built

    return getattr(pipps.costs, COST_FACTORIES[cost])()


def _normalise(fields: dict[str, Any]) -> dict[str, Any]:
    """Copy arrays to read-only float64 numpy arrays and index sets to tuples of int."""
    out = dict(fields)
    for key in _ARRAY_FIELDS:
        arr = np.array(out[key], dtype=np.float64)  # a copy
        arr.setflags(write=False)
        out[key] = arr
    for key in ("angle_idx", "gp_input_idx", "policy_input_idx"):
        out[key] = tuple(int(i) for i in out[key])
    for key in ("sim_dim", "model_dim", "action_dim", "horizon", "substeps"):
        value = out[key]
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise ValueError(f"{key} must be an integer, got {value!r}")
        out[key] = int(value)
    try:
        out["dt"] = float(out["dt"])
    except (TypeError, ValueError) as err:
        raise ValueError(f"dt must be a number, got {out['dt']!r}") from err
    return out


def _validate(f: dict[str, Any]) -> None:
    """Shapes and ranges of a task's fields; raises ValueError naming the bad field."""
    def need(cond: bool, msg: str) -> None:
        if not cond:
            raise ValueError(msg)

    need(math.isfinite(f["dt"]) and f["dt"] > 0, f"dt must be finite and > 0, got {f['dt']!r}")
    for key in ("horizon", "substeps"):
        need(f[key] >= 1, f"{key} must be >= 1, got {f[key]!r}")
    shapes = {
        "u_max": (f["action_dim"],),
        "u_rand": (f["action_dim"],),
        "init_mean": (f["sim_dim"],),
        "init_cov": (f["sim_dim"], f["sim_dim"]),
        "model_init_mean": (f["model_dim"],),
        "model_init_cov": (f["model_dim"], f["model_dim"]),
        "obs_noise_std": (f["sim_dim"],),
    }
    for key, shape in shapes.items():
        need(f[key].shape == shape, f"{key} must have shape {shape}, got {f[key].shape}")
        need(bool(np.all(np.isfinite(f[key]))), f"{key} must be finite")
    need(bool(np.all(f["u_max"] > 0)), f"u_max must be > 0, got {f['u_max']}")
    need(bool(np.all(f["u_rand"] >= 0)), f"u_rand must be >= 0, got {f['u_rand']}")
    need(bool(np.all(f["obs_noise_std"] >= 0)), f"obs_noise_std must be >= 0, got {f['obs_noise_std']}")
    for key in ("init_cov", "model_init_cov"):
        c = f[key]
        need(np.allclose(c, c.T, rtol=0, atol=1e-12), f"{key} must be symmetric")
        need(np.linalg.eigvalsh(c).min() >= -1e-12, f"{key} must be positive semi-definite")
    aug_dim = f["model_dim"] + 2 * len(f["angle_idx"])
    need(all(0 <= i < f["model_dim"] for i in f["angle_idx"]), f"angle_idx out of range: {f['angle_idx']}")
    for key in ("gp_input_idx", "policy_input_idx"):
        need(all(0 <= i < aug_dim for i in f[key]), f"{key} out of range [0, {aug_dim}): {f[key]}")


def _fields_of(cls) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls))


def make_task(name: str, preset: str = "thesis", k: float = 1.0, cost: str | Cost | None = None, **overrides) -> Task:
    """Build the :class:`Task` (problem and simulator) for ``name`` under ``preset``.

    Args:
      name: one of ``TASK_NAMES``.
      preset: one of ``PRESETS``.
      k: observation-noise variance multiplier, finite and >= 0; the std is √k·base std.
      cost: a cost name (cart-pole: ``"angle"``, thesis default, or ``"tip"``, pilco
        default; unicycle: ``"unicycle"``), or a ready Cost object (see :func:`make_cost`).
      **overrides: replace any other field of the problem or the simulator verbatim (e.g. ``horizon=10``,
        ``substeps=50``, ``obs_noise_std=...`` — the final std, not scaled by k). If ``dt``
        is overridden and ``substeps`` is not, ``substeps`` follows the new ``dt`` so the
        sub-step stays at most ``MAX_SUBSTEP``. ``name`` and ``dt`` go to both halves.

    Raises:
      ValueError: unknown task, preset, cost or override name (listing the valid
        choices), k negative/non-finite, or fields of inconsistent shape.
    """
    _check_choice("task", name, TASK_NAMES)
    _check_choice("preset", preset, PRESETS)
    k = _check_k(k)
    both = _fields_of(Problem) + tuple(f for f in _fields_of(Simulator) if f not in _fields_of(Problem))
    valid = tuple(f for f in both if f not in _ARGUMENT_FIELDS)
    for key in overrides:
        if key in _ARGUMENT_FIELDS:
            raise ValueError(f"set {key!r} through make_task's {_ARGUMENT_FIELDS[key]!r} argument, not as an override")
        if key not in valid:
            raise ValueError(f"unknown Task field {key!r}; valid overrides: {', '.join(valid)}")

    family = "unicycle" if name == "unicycle" else "cartpole"
    fields = _unicycle_fields(preset) if family == "unicycle" else _cartpole_fields(name, preset)
    fields["obs_noise_std"] = math.sqrt(k) * np.asarray(fields["obs_noise_std"])
    fields.update(overrides)
    if "substeps" not in overrides:
        fields["substeps"] = substeps_for(float(fields["dt"]), MAX_SUBSTEP[family])
    fields = _normalise(fields)
    _validate(fields)
    fields["cost"] = make_cost(name, cost, preset)
    fields["noise_multiplier"] = k
    problem = Problem(**{f: fields[f] for f in _fields_of(Problem) if f in fields})
    simulator = Simulator(**{f: fields[f] for f in _fields_of(Simulator) if f in fields})
    return Task(problem, simulator, preset=preset)
