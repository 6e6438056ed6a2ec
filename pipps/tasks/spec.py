"""What is specific to a task, in one record: :class:`TaskSpec`.

A :class:`~pipps.tasks.base.Task` is the physics (a planning problem and a true system). An
experiment needs more of a task than its physics, and the rest of the library asks the task's
record for it instead of decoding its name:

* how to build the :class:`Task` for an experiment's task preset, noise multiplier ``k``, cost and
  horizon (``make``);
* its :class:`Success` criterion: a rule per evaluation rollout with its reason, the fraction of
  an experiment's final rollouts that must pass, and the return threshold if it has one;
* what the figures need (:class:`PlotInfo`: the state labels and which component is drawn
  against the real rollout);
* its experiment settings per experiment preset (``thesis``, ``pilco``, ``quick``), and the box
  the ``quick`` preset's RBF centres may spread over.

The built-in tasks' records are in :mod:`pipps.tasks.builtin`; a task of your own is one record,
usually from a :class:`Task` (docs/tutorial.md)::

    pendulum = TaskSpec(Task(problem, simulator), Success("upright", upright, fraction=0.5,
                                                          reason="held upright over the last second"))

and :mod:`pipps.tasks.registry` finds it by name (``register``, an entry point of the
``pipps.tasks`` group) or by its ``module:attribute`` path (``pipps run --task mymod:pendulum``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Mapping

import jax.numpy as jnp
import numpy as np

from pipps.tasks.base import Task

#: A rule per rollout: ``rule(states, valid) -> bool`` for states (..., H+1, S) of the true system
#: (the simulator states, noise-free) and valid (..., H) transitions; numpy and JAX arrays alike.
Rule = Callable[[Any, Any], Any]


def never_fell(states, valid):
    """Per rollout: every transition valid, the system never fell (the unicycle's criterion). A
    result file stores this per evaluation rollout as ``eval_upright``, so a verdict with this rule
    reads it there even in files written before the criterion's flags were stored."""
    del states
    xp = np if isinstance(valid, np.ndarray) else jnp
    return xp.all(valid, axis=-1)


@dataclasses.dataclass(frozen=True)
class Success:
    """How a task's experiments are judged (docs/experiments.md, "Success").

    Attributes:
      name: one word for a rollout that passes ("balanced", "upright"); the progress display and
        the tables say it.
      rule: :data:`Rule`, per evaluation rollout on the true system, pure and vectorised.
      fraction: an experiment succeeds when at least this fraction of its final trial's evaluation
        rollouts pass.
      threshold: the return threshold of the thesis' counting (an evaluated return below it counts
        as a success, docs/results.md), or None: the task is judged by its rule alone and the
        tables show only the physical readings.
      reason: why this rule, in a sentence (shown by the documentation and the tables' notes).
    """

    name: str
    rule: Rule
    fraction: float
    threshold: float | None = None
    reason: str = ""

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"Success.name: must be a non-empty string, got {self.name!r}")
        if not callable(self.rule):
            raise ValueError(f"Success.rule: must be callable (states, valid) -> bool per rollout, got {self.rule!r}")
        f = self.fraction
        if isinstance(f, bool) or not isinstance(f, (int, float)) or not 0 < f <= 1:
            raise ValueError(f"Success.fraction: must lie in (0, 1], got {f!r}")
        t = self.threshold
        if t is not None and (isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t)):
            raise ValueError(f"Success.threshold: must be a finite number or None, got {t!r}")


@dataclasses.dataclass(frozen=True)
class PlotInfo:
    """What the figures need to know of a task.

    Attributes:
      state_labels: a label per model-state component, with its unit (axes and legends).
      panel: the model-state component the predictions figure draws against the real rollout
        (the cart-pole's pole angle, the unicycle's wheel pitch).
      panel_true: its index in the true system's state, or None: the real rollout is mapped into
        the model state (``sim_to_model``) first.
      log_returns: draw the evaluated return on a log scale (returns spanning decades).
    """

    state_labels: tuple[str, ...] = ()
    panel: int = 0
    panel_true: int | None = None
    log_returns: bool = False

    def label(self, i: int) -> str:
        return self.state_labels[i] if i < len(self.state_labels) else f"model state x[{i}]"


#: The experiment settings a task of your own starts from, per experiment preset: the thesis
#: protocol's loop and policy (RBF centres spread as the start mean plus N(0, I)), PILCO's policy,
#: and the ``quick`` preset's few-minute budget. A record's ``settings`` add to them or replace them.
DEFAULT_SETTINGS: dict[str, dict[str, Any]] = {
    "thesis": dict(num_random=1, num_learned=15, policy="rbf", num_basis=50, centre_std=1.0),
    "pilco": dict(num_random=1, num_learned=15, policy="pilco_rbf", num_basis=10),
    "quick": dict(num_random=1, num_learned=5, policy="rbf", num_basis=50, centre_std=1.0, num_particles=50,
                  policy_evals=300, eval_rollouts=10, learning_rate=5e-3, gp_max_iters=100),
}


@dataclasses.dataclass(frozen=True, eq=False)
class TaskSpec:
    """A task: its physics and everything else the library needs to know of it (module docstring).

    Attributes:
      task: the :class:`Task` itself (a system of your own: one task preset and one cost, both
        called ``"default"``; ``k`` scales its observation noise, an override replaces a field of
        either half), or a factory ``make(preset, k, cost, cost_scale, **overrides) -> Task``.
      success: a :class:`Success`, or a function of the experiment's settings (an object with the
        :class:`~pipps.experiments.config.ExperimentConfig` attributes) returning one, for a
        criterion whose bounds are experiment settings (the built-in tasks').
      name: the task's name in configurations and file names; default the problem's name.
      plot: :class:`PlotInfo`.
      settings: experiment settings per experiment preset, over :data:`DEFAULT_SETTINGS`; the
        task preset an experiment preset runs goes in as ``preset``.
      presets: the task presets ``make`` takes (a factory's; the first is the default).
      costs: the cost names ``make`` takes (a factory's).
      default_costs: the default cost per task preset (a factory's; default: the first cost).
      centre_box: ``(low, high)`` in policy-input coordinates, ``policy_input_dim`` values each: the
        box ``policy_init="uniform"`` spreads RBF centres over; None: the task has none.
      scalable_costs: the costs whose weight the setting ``cost_scale`` multiplies (a factory
        applies it).
      label: the task in words, for a sentence about its results (default: its name).
      description: one line for listings.

    Raises:
      ValueError: a field of the wrong kind, naming it.
    """

    task: Task | Callable[..., Task]
    success: Success | Callable[[Any], Success]
    name: str | None = None
    plot: PlotInfo = PlotInfo()
    settings: Mapping[str, Mapping[str, Any]] = dataclasses.field(default_factory=dict)
    presets: tuple[str, ...] | None = None
    costs: tuple[str, ...] | None = None
    default_costs: Mapping[str, str] | None = None
    centre_box: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    scalable_costs: tuple[str, ...] = ()
    label: str | None = None
    description: str = ""

    def __post_init__(self):
        own = type(self).__name__
        fixed = isinstance(self.task, Task)
        if not fixed and not callable(self.task):
            raise ValueError(f"{own}.task: must be a Task or a factory make(preset, k, cost, cost_scale, **overrides), "
                             f"got {self.task!r}")
        name = self.name if self.name is not None else (self.task.problem.name if fixed else None)
        if not isinstance(name, str) or not name or ":" in name or "/" in name or name != name.strip():
            raise ValueError(f"{own}.name: must be a non-empty name without ':' or '/' (a factory's task needs one), "
                             f"got {name!r}")
        object.__setattr__(self, "name", name)
        object.__setattr__(self, "label", self.label or name)
        if not isinstance(self.success, Success) and not callable(self.success):
            raise ValueError(f"{own}.success: must be a Success or a function of the experiment's settings, "
                             f"got {self.success!r}")
        if not isinstance(self.plot, PlotInfo):
            raise ValueError(f"{own}.plot: must be a PlotInfo, got {self.plot!r}")
        presets = ("default",) if fixed else self.presets
        costs = ("default",) if fixed else self.costs
        if fixed and (self.presets not in (None, presets) or self.costs not in (None, costs)):
            raise ValueError(f"{own}.presets/costs: a Task has one task preset and one cost, both 'default'; "
                             "give a factory for more")
        for field, value in (("presets", presets), ("costs", costs)):
            if not value or not all(isinstance(v, str) and v for v in value):
                raise ValueError(f"{own}.{field}: a factory needs the names it takes, got {value!r}")
        object.__setattr__(self, "presets", tuple(presets))
        object.__setattr__(self, "costs", tuple(costs))
        defaults = dict(self.default_costs or {})
        for preset in self.presets:
            defaults.setdefault(preset, self.costs[0])
        if set(defaults) != set(self.presets) or not set(defaults.values()) <= set(self.costs):
            raise ValueError(f"{own}.default_costs: one of {self.costs} per task preset {self.presets}, got {defaults}")
        object.__setattr__(self, "default_costs", defaults)
        if not all(isinstance(v, Mapping) for v in self.settings.values()):
            raise ValueError(f"{own}.settings: a mapping of settings per experiment preset, got {self.settings!r}")
        for protocol, values in self.settings.items():
            preset = values.get("preset", self.presets[0])
            if preset not in self.presets:
                raise ValueError(f"{own}.settings[{protocol!r}]: task preset {preset!r} is not one of {self.presets}")
        if self.centre_box is not None:
            low, high = (tuple(float(v) for v in side) for side in self.centre_box)
            if len(low) != len(high) or not low or not all(math.isfinite(a) and math.isfinite(b) and a < b
                                                            for a, b in zip(low, high)):
                raise ValueError(f"{own}.centre_box: (low, high) of one finite length with low < high, "
                                 f"got {self.centre_box!r}")
            object.__setattr__(self, "centre_box", (low, high))
            if fixed and len(low) != self.task.problem.policy_input_dim:
                raise ValueError(f"{own}.centre_box: has {len(low)} components per side, expected "
                                 f"{self.task.problem.policy_input_dim} (the problem's policy_input_dim)")
        if fixed:
            _check_policy_settings(own, self.settings, self.task.problem.policy_input_dim)
        if not set(self.scalable_costs) <= set(self.costs):
            raise ValueError(f"{own}.scalable_costs: {self.scalable_costs} are not all costs of the task {self.costs}")

    # -- what the library asks ------------------------------------------------------------------------

    def make(self, preset: str | None = None, k: float = 1.0, cost: str | None = None, cost_scale: float = 1.0,
             **overrides) -> Task:
        """The :class:`Task` under task preset ``preset`` (default: the first), noise multiplier
        ``k``, the named cost (None: the preset's default) scaled by ``cost_scale``, and
        ``overrides`` of fields of either half (``horizon=…``).

        Raises:
          ValueError: an unknown preset, cost or field; a scale for a cost that takes none.
        """
        if not isinstance(self.task, Task):
            return self.task(preset or self.presets[0], k, cost, cost_scale, **overrides)
        preset = self.presets[0] if preset is None else preset
        if preset not in self.presets:
            raise ValueError(f"unknown task preset {preset!r} for {self.name}; valid choices: {', '.join(self.presets)}")
        if cost not in (None, *self.costs):
            raise ValueError(f"unknown cost {cost!r} for {self.name}; valid choices: {', '.join(self.costs)}")
        if cost_scale != 1.0:
            raise ValueError(f"cost_scale: the cost of {self.name} takes no scale")
        return _vary(self.task, k, overrides)

    def success_for(self, settings: Any) -> Success:
        """The task's :class:`Success` under an experiment's ``settings``."""
        return self.success if isinstance(self.success, Success) else self.success(settings)

    def default_cost(self, preset: str) -> str:
        """The cost an experiment of task preset ``preset`` uses when it names none."""
        return self.default_costs[preset]

    def experiment_settings(self, protocol: str) -> dict[str, Any]:
        """The settings experiment preset ``protocol`` gives this task: the task preset it runs
        (``preset``) and :data:`DEFAULT_SETTINGS` with the record's own on top."""
        return {"preset": self.presets[0], **DEFAULT_SETTINGS.get(protocol, {}), **self.settings.get(protocol, {})}


def _check_policy_settings(own: str, settings: Mapping[str, Mapping[str, Any]], input_dim: int) -> None:
    """The settings that size the initial policy fit the problem's policy input: ``log_lambda_init``
    one value or one per input component (a factory's problems are sized per task preset and are
    checked when the policy is made, :func:`pipps.experiments.state.init_policy`)."""
    for protocol, values in settings.items():
        if values.get("log_lambda_init") is not None:
            size = np.size(values["log_lambda_init"])
            if size not in (1, input_dim):
                raise ValueError(f"{own}.settings[{protocol!r}]: log_lambda_init has {size} values, expected 1 or "
                                 f"{input_dim} (the problem's policy_input_dim)")


def _vary(task: Task, k: float, overrides: dict[str, Any]) -> Task:
    """``task`` with its observation noise scaled by √k and fields replaced (``name`` and ``dt`` in
    both halves); the same object when nothing changes (its compiled programs are reused)."""
    if isinstance(k, bool) or not isinstance(k, (int, float, np.integer, np.floating)) or not (math.isfinite(k) and k >= 0):
        raise ValueError(f"noise multiplier k must be a finite number >= 0, got {k!r}")
    if float(k) == 1.0 and not overrides:
        return task
    p_fields = {f.name for f in dataclasses.fields(task.problem)}
    s_fields = {f.name for f in dataclasses.fields(task.simulator)}
    for name in overrides:
        if name in ("noise_multiplier", "obs_noise_std") or name not in p_fields | s_fields:
            valid = sorted((p_fields | s_fields) - {"noise_multiplier", "obs_noise_std"})
            raise ValueError(f"unknown Task field {name!r}; valid overrides: {', '.join(valid)} (k scales the noise)")
    sim = task.simulator
    base = np.asarray(sim.obs_noise_std) / math.sqrt(sim.noise_multiplier) if sim.noise_multiplier > 0 \
        else np.asarray(sim.obs_noise_std)
    problem = dataclasses.replace(task.problem, **{n: v for n, v in overrides.items() if n in p_fields})
    simulator = dataclasses.replace(sim, obs_noise_std=math.sqrt(float(k)) * base, noise_multiplier=float(k),
                                    **{n: v for n, v in overrides.items() if n in s_fields})
    return Task(problem, simulator, preset=task.preset)
