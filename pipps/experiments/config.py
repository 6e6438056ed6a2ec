"""Experiment configuration: one flat, validated, serialisable record per experiment.

An :class:`ExperimentConfig` holds every setting of one episodic learning experiment
(thesis §4.5.3; docs/experiments.md, "The loop" and "Presets"). It is built by
:func:`resolve_config` from a preset and overrides, validated at once (a bad value raises
:class:`ConfigError` naming the setting), and stored verbatim in the HDF5 result as
attributes, so a result file says exactly what produced it.

Presets:

* ``thesis`` — the thesis protocol (§4.5.3): 1 + 15 trials (cart-pole) or 5 + 30 (unicycle),
  P = 300 particles, 600 policy evaluations per trial, the normalized momentum step
  (α = 5·10⁻⁴, γ = 0.9), 50-centre RBF policy with centres at the start mean plus N(0, I) (the
  author's demo; the start distribution itself does not learn, docs/results-analyses.md), the thesis'
  own estimator choices (eq. 4.3 baseline, same-batch k_LR), 30 evaluation rollouts.
* ``pilco`` — the PILCO MATLAB task defaults (docs/task-cartpole.md, docs/task-unicycle.md) with the library's estimator
  choices (unbiased baselines; TP's leave-one-out k_LR).
* ``quick`` — the thesis protocol shrunk for a few-minute CPU run: fewer trials, particles
  and policy evaluations, and a documented departure (docs/experiments.md, "Presets"): RBF centres spread
  uniformly over the state box and wider initial length-scales.

**Two presets.** The word names two things, kept apart here and only here:

* the *experiment preset* above, which ``--preset`` chooses (:data:`PRESET_NAMES`), is stored
  in the field ``protocol``: every setting of the experiment, from trials to step sizes;
* the *task preset* (:data:`pipps.tasks.presets.PRESETS`: ``thesis``, ``pilco``) is the task's
  physics, noise, cost and horizon, and is stored in the field ``preset``. The experiment preset
  sets it: ``thesis`` and ``quick`` run the thesis task, ``pilco`` PILCO's.

The field ``preset`` keeps its name because result files store it under that name and
``config_hash`` (part of a custom experiment's file name) is computed over the field names:
renaming it would change the hash of every experiment. ``pipps run --set preset=…`` is refused
(``--preset`` is the experiment preset).

Methods and the settings each uses are the registry :mod:`pipps.experiments.methods`.

**The task.** ``task`` is a task's name; its record (:class:`pipps.tasks.TaskSpec`, found by
:func:`pipps.tasks.get_task`) says what else the configuration means for it: the task presets and
costs it takes, its experiment settings under each preset, its success criterion. A task of your
own is given by name once registered, as ``module:attribute``, or as the record itself; the
configuration then stores its name and, in ``task_source``, where it came from (module:attribute),
so that a result file can be resumed and tabulated in another process. ``task_source`` is
provenance, not identity: it is left out of :func:`canonical` (file name, hash, resume checks),
and a built-in task's configuration, which has none, is stored without it.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import typing
from typing import Any

from pipps.experiments.methods import METHODS, Method

PRESET_NAMES = ("thesis", "pilco", "quick")

#: The largest seed. Every draw of an experiment starts from ``jax.random.PRNGKey(seed)``, which
#: refuses integers beyond int64 (``OverflowError``), and the studies key their draws on small
#: offsets of theirs; seeds of 31 bits fit int32 and int64 alike, with or without JAX's 64-bit mode.
MAX_SEED = 2**31 - 1


class ConfigError(ValueError):
    """A configuration value is invalid; the message names the setting."""


class UnavailableTask(ConfigError):
    """The configuration's task cannot be found in this process (:class:`pipps.tasks.TaskUnavailable`):
    reading, resuming or tabulating its results stops here, in one line that says where it was looked for."""


@dataclasses.dataclass(frozen=True)
class ExperimentConfig:
    """Every setting of one experiment. See the module docstring for the presets.

    ``None`` in a field means "the task's own value" where noted.
    """

    # what is learned
    task: str = "cartpole_swingup"  # a task's name (module doc, "The task")
    task_source: str | None = None  # where a task of your own came from (module:attribute); None for a built-in one
    preset: str = "thesis"  # the *task* preset: physics, noise, cost (module doc, "Two presets")
    protocol: str = "thesis"  # the *experiment* preset it was built from, ``--preset`` (module doc)
    cost: str | None = None  # angle | tip | unicycle; None: the task preset's default
    cost_scale: float = 1.0  # Q multiplier of the Angle Cost (the thesis' "Q × 0.01" cell)
    k: float = 1.0  # observation-noise variance multiplier
    method: str = "tp"
    seed: int = 0
    # the protocol
    num_random: int = 1  # random (exploration) trials
    num_learned: int = 15  # learned trials
    horizon: int | None = None  # None: the task preset's horizon
    eval_rollouts: int = 30  # evaluation rollouts per trial (reporting only)
    success_threshold: float = 15.0  # cart-pole: the thesis' return threshold (reported beside the physical verdict)
    upright_fraction: float = 0.95  # unicycle: fraction of evaluation rollouts that must stay upright
    # cart-pole physical success (pipps.tasks.cartpole.balanced): in the last balance_steps states the pole
    # within balance_angle rad of upright and the cart within balance_position m of the centre, in at
    # least balanced_fraction of the final trial's evaluation rollouts
    balance_steps: int = 10
    balance_angle: float = 0.3
    balance_position: float = 0.5
    balanced_fraction: float = 0.5
    # the policy
    policy: str = "rbf"  # rbf (thesis), pilco_rbf, linear
    num_basis: int = 50
    policy_init: str = "start"  # start: centres ~ start distribution; uniform: the quick box
    centre_std: float | None = None  # with policy_init=start: centres ~ N(start mean, centre_std²·I) instead
    log_lambda_init: tuple[float, ...] = (0.0,)  # one value or one per policy input
    weight_scale: float = 0.1
    # particle methods
    num_particles: int = 300
    policy_evals: int = 600  # policy evaluations (gradient estimates, or QN evaluations) per trial
    learning_rate: float = 5e-4
    momentum: float = 0.9
    estimator_choices: str = "thesis"  # thesis: eq. 4.3 baseline and same-batch k_LR; library: "previous" baseline, leave-one-out k_LR
    noise_boost_tp: float = 100.0  # +σ_n factor on σ_n² for TP
    noise_boost_gtp: float = 25.0  # +σ_n factor for GTP
    progress_chunk: int = 50  # policy steps per compiled call (progress granularity)
    # GP variance: 0 = exact; > 0 = the certified low-rank form (pipps.gp.lowrank) with its error below
    # variance_tol·σ² (σ² = σ_n² + the posterior's jitter; σ_n² for FITC) at every input, full-GP and
    # FITC trials alike; docs/performance.md
    variance_tol: float = 0.0
    # PILCO
    pilco_linesearches: int | None = None  # None: PILCO's budget for the task (its settings_*.m)
    # True: the policy sees the predicted state plus the GP noise variances halved, as PILCO's release V0.9
    # did; False: the latent state, as its later code (a0b48b7) and every result before the setting existed
    pilco_policy_noise: bool = False
    # GP model
    gp_chunk: int = 100  # data padded to multiples of this (few compiled sizes; 1: exact sizes)
    gp_max_iters: int = 300
    fitc_threshold: int = 300
    num_inducing: int = 300
    fitc_iters: int = 100
    fitc_first_iters: int = 300
    # what is stored
    store_particles: int = 30  # predicted particle trajectories stored per trial (for plots)

    # -- derived -----------------------------------------------------------------------------
    @property
    def num_trials(self) -> int:
        return self.num_random + self.num_learned

    @property
    def method_spec(self) -> Method:
        """The method's record in the registry (:mod:`pipps.experiments.methods`)."""
        return METHODS[self.method]

    @property
    def is_pilco(self) -> bool:
        return self.method_spec.moment_matching

    @property
    def fixed_seed(self) -> bool:
        return self.method_spec.fixed_seed

    @property
    def table_name(self) -> str:
        return self.method_spec.label

    @property
    def cost_name(self) -> str:
        """The cost the experiment optimises, by name: :attr:`cost`, or where that is ``None`` the
        one its task gives the preset (the cart-pole's thesis preset: ``"angle"``)."""
        return self.cost or self.task_spec.default_cost(self.preset)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def replace(self, **changes) -> "ExperimentConfig":
        return resolve_overrides(self, changes)

    @property
    def task_spec(self):
        """The task's record (:class:`pipps.tasks.TaskSpec`)."""
        from pipps.tasks.registry import get_task

        return get_task(self.task, source=self.task_source)

    def __post_init__(self):
        _normalise_task(self)
        validate(self)


def _normalise_task(c: ExperimentConfig) -> None:
    """``task`` given as a record or as ``module:attribute``: stored as its name, with its source.
    A name alone takes the source the registry knows for it (a task loaded earlier in the process)."""
    from pipps.tasks.registry import TaskUnavailable, get_task, task_source
    from pipps.tasks.spec import TaskSpec

    task = c.task
    if isinstance(task, TaskSpec) or (isinstance(task, str) and ":" in task):
        try:
            spec = get_task(task)
        except TaskUnavailable as err:
            raise UnavailableTask(f"task: {err}") from None
        object.__setattr__(c, "task", spec.name)
        object.__setattr__(c, "task_source", task if isinstance(task, str) else task_source(spec.name))
    elif isinstance(task, str) and c.task_source is None:
        object.__setattr__(c, "task_source", task_source(task))


@functools.cache
def _field_types() -> dict[str, Any]:
    """ExperimentConfig's field types, resolved once: resolving its string annotations compiles each
    of them, and every validation and comparison of a configuration asks (most of `pipps table`'s time)."""
    return typing.get_type_hints(ExperimentConfig)


def _need(cond: bool, name: str, msg: str) -> None:
    if not cond:
        raise ConfigError(f"{name}: {msg}")


def validate(c: ExperimentConfig) -> None:
    """Raise :class:`ConfigError` naming the first bad setting."""
    spec = task_record(c.task, c.task_source)
    _need(c.task_source is None or isinstance(c.task_source, str), "task_source",
          f"must be MODULE:ATTRIBUTE or None, got {c.task_source!r}")
    _need(c.preset in spec.presets, "preset",
          f"unknown task preset {c.preset!r}; choose one of {', '.join(spec.presets)}")
    _need(c.protocol in PRESET_NAMES, "protocol",
          f"unknown experiment preset {c.protocol!r}; choose one of {', '.join(PRESET_NAMES)}")
    _need(c.method in METHODS, "method", f"unknown method {c.method!r}; choose one of {', '.join(METHODS)}")
    if c.cost is not None:
        _need(c.cost in spec.costs, "cost", f"unknown cost {c.cost!r} for {c.task}; choose one of {', '.join(spec.costs)}")
    finite = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)  # noqa: E731
    _need(finite(c.k) and c.k >= 0, "k", f"the noise multiplier must be a finite number >= 0, got {c.k!r}")
    _need(finite(c.cost_scale) and c.cost_scale > 0, "cost_scale", f"must be > 0, got {c.cost_scale!r}")
    for name in ("num_learned", "eval_rollouts", "num_basis", "policy_evals", "gp_chunk", "gp_max_iters",
                 "num_inducing", "fitc_iters", "fitc_first_iters", "progress_chunk"):
        v = getattr(c, name)
        _need(isinstance(v, int) and not isinstance(v, bool) and v >= 1, name, f"must be an integer >= 1, got {v!r}")
    for name in ("num_random", "store_particles", "seed"):
        v = getattr(c, name)
        _need(isinstance(v, int) and not isinstance(v, bool) and v >= 0, name, f"must be an integer >= 0, got {v!r}")
    _need(c.seed <= MAX_SEED, "seed", f"must be an integer in [0, {MAX_SEED}], got {c.seed!r}")
    _need(isinstance(c.num_particles, int) and c.num_particles >= 2, "num_particles",
          f"must be an integer >= 2 (particles estimate variances), got {c.num_particles!r}")
    _need(c.num_random >= 1, "num_random", "at least one random trial is needed to train the first model")
    if c.horizon is not None:
        _need(isinstance(c.horizon, int) and c.horizon >= 1, "horizon", f"must be an integer >= 1, got {c.horizon!r}")
    _need(finite(c.success_threshold), "success_threshold", f"must be finite, got {c.success_threshold!r}")
    _need(finite(c.upright_fraction) and 0 < c.upright_fraction <= 1, "upright_fraction",
          f"must lie in (0, 1], got {c.upright_fraction!r}")
    _need(finite(c.balanced_fraction) and 0 < c.balanced_fraction <= 1, "balanced_fraction",
          f"must lie in (0, 1], got {c.balanced_fraction!r}")
    _need(isinstance(c.balance_steps, int) and not isinstance(c.balance_steps, bool) and c.balance_steps >= 1,
          "balance_steps", f"must be an integer >= 1, got {c.balance_steps!r}")
    for name in ("balance_angle", "balance_position"):
        v = getattr(c, name)
        _need(finite(v) and v > 0, name, f"must be > 0, got {v!r}")
    _need(c.policy in ("rbf", "pilco_rbf", "linear"), "policy", f"choose rbf, pilco_rbf or linear, got {c.policy!r}")
    _need(c.policy_init in ("start", "uniform"), "policy_init", f"choose start or uniform, got {c.policy_init!r}")
    _need(c.policy_init != "uniform" or spec.centre_box is not None, "policy_init",
          f"uniform centres need the task's centre box, and {c.task} has none (TaskSpec.centre_box)")
    if c.centre_std is not None:
        _need(finite(c.centre_std) and c.centre_std > 0, "centre_std", f"must be > 0, got {c.centre_std!r}")
    _need(len(c.log_lambda_init) >= 1 and all(finite(v) for v in c.log_lambda_init), "log_lambda_init",
          f"must be one or more finite numbers, got {c.log_lambda_init!r}")
    _need(finite(c.weight_scale) and c.weight_scale >= 0, "weight_scale", f"must be >= 0, got {c.weight_scale!r}")
    _need(finite(c.learning_rate) and c.learning_rate > 0, "learning_rate", f"must be > 0, got {c.learning_rate!r}")
    _need(finite(c.momentum) and 0 <= c.momentum < 1, "momentum", f"must lie in [0, 1), got {c.momentum!r}")
    _need(c.estimator_choices in ("thesis", "library"), "estimator_choices",
          f"choose thesis or library, got {c.estimator_choices!r}")
    _need(finite(c.variance_tol) and c.variance_tol >= 0, "variance_tol", f"must be >= 0, got {c.variance_tol!r}")
    for name in ("noise_boost_tp", "noise_boost_gtp"):
        v = getattr(c, name)
        _need(finite(v) and v > 0, name, f"must be > 0, got {v!r}")
    _need(isinstance(c.pilco_policy_noise, bool), "pilco_policy_noise",
          f"must be true or false, got {c.pilco_policy_noise!r}")
    if c.pilco_linesearches is not None:
        _need(isinstance(c.pilco_linesearches, int) and c.pilco_linesearches >= 1, "pilco_linesearches",
              f"must be an integer >= 1, got {c.pilco_linesearches!r}")
    _need(c.num_inducing <= c.fitc_threshold, "num_inducing",
          f"{c.num_inducing} exceeds fitc_threshold={c.fitc_threshold}")


# -- presets ---------------------------------------------------------------------------------


def task_record(task, source: str | None = None):
    """The record of ``task`` (a name, ``module:attribute`` or a record), or :class:`ConfigError`
    naming the setting ``task`` with why it is not available."""
    from pipps.tasks.registry import TaskUnavailable, get_task

    try:
        return get_task(task, source=source)
    except TaskUnavailable as err:
        raise UnavailableTask(f"task: {err}") from None


def preset_values(preset: str, task) -> dict[str, Any]:
    """The settings a preset fixes for a task (before the user's overrides): the task's own
    (:meth:`pipps.tasks.TaskSpec.experiment_settings`: its task preset, loop, policy, budget) and
    the protocol's estimator choices and GP capacities. ``task``: a name, ``module:attribute`` or
    a record (:func:`pipps.tasks.get_task`).

    The thesis preset spreads the RBF centres as the start mean plus N(0, I) (``centre_std = 1``):
    the one departure from drawing the centres from the start distribution
    (N(0, 0.1²I), as PILCO does), which barely learns; the author's demo spreads them so. Evidence in
    docs/results-analyses.md ("Why the thesis preset spreads the RBF centres"); ``--set centre_std=none``
    restores the start distribution."""
    if preset not in PRESET_NAMES:
        raise ConfigError(f"preset: unknown preset {preset!r}; choose one of {', '.join(PRESET_NAMES)}")
    from pipps.tasks.registry import task_source

    spec = task_record(task)
    source = task if isinstance(task, str) and ":" in task else task_source(spec.name)
    v: dict[str, Any] = dict(task=spec.name, task_source=source, protocol=preset)
    # the thesis' own estimator choices for its protocol; the library's unbiased ones with PILCO's task defaults
    v.update(estimator_choices="library" if preset == "pilco" else "thesis")
    v.update(spec.experiment_settings(preset))
    if preset != "quick":
        # exact GP capacities: one compiled size per trial (the persistent compilation cache shares
        # them across a sweep's experiments) against ~11 % of a thesis TP experiment's arithmetic
        # spent on padding in steps of 100 (docs/performance.md); quick runs are compilation-bound
        # and keep few sizes
        v.update(gp_chunk=1)
    return v


def _coerce(name: str, value: Any, hint: Any) -> Any:
    """Convert a CLI string (or a Python value) to the field's type, or raise ConfigError."""
    if not isinstance(value, str):
        if isinstance(value, list):
            return tuple(value)
        return value
    text = value.strip()
    origin_args = typing.get_args(hint)
    optional = type(None) in origin_args
    if optional and text.lower() in ("none", "null", ""):
        return None
    base = [a for a in origin_args if a is not type(None)] or [hint]
    kinds = base if typing.get_origin(hint) is not tuple else [hint]
    for kind in kinds:
        try:
            if kind is bool:
                if text.lower() in ("1", "true", "yes", "on"):
                    return True
                if text.lower() in ("0", "false", "no", "off"):
                    return False
                raise ValueError
            if kind is int:
                return int(text)
            if kind is float:
                return float(text)
            if typing.get_origin(kind) is tuple:
                return tuple(float(p) for p in text.split(",") if p.strip())
            if kind is str:
                return text
        except ValueError:
            continue
    raise ConfigError(f"{name}: cannot read {value!r} as {hint}")


def resolve_overrides(base: ExperimentConfig | dict, overrides: dict[str, Any]) -> ExperimentConfig:
    """``base`` with ``overrides`` applied (strings are converted to the field's type)."""
    hints = _field_types()
    values = base.to_dict() if isinstance(base, ExperimentConfig) else dict(base)
    for name, value in overrides.items():
        key = name.replace("-", "_")
        if key not in hints:
            raise ConfigError(f"{name}: unknown setting; valid settings: {', '.join(sorted(hints))}")
        values[key] = _coerce(key, value, hints[key])
    for key in ("log_lambda_init",):
        if key in values and not isinstance(values[key], tuple):
            v = values[key]
            values[key] = tuple(v) if isinstance(v, (list, tuple)) else (float(v),)
    return ExperimentConfig(**values)


def resolve_config(preset: str = "thesis", task="cartpole_swingup", **overrides) -> ExperimentConfig:
    """The configuration of ``preset`` for ``task`` with ``overrides`` (validated). ``task``: a
    name, ``module:attribute`` or a :class:`pipps.tasks.TaskSpec` (module doc, "The task").

    An override of a setting the method does not use is refused by name (:func:`refuse_unused`);
    the preset's own values of such settings stay, since they cannot change the experiment.

    Example: ``resolve_config("thesis", "cartpole_swingup", method="pilco", k=4, seed=3)``.
    """
    cfg = resolve_overrides(preset_values(preset, task), overrides)
    refuse_unused(cfg.method, overrides)
    return cfg


def refuse_unused(method: str, names) -> None:
    """Raise :class:`ConfigError` naming the first of the settings ``names`` that ``method`` does
    not use (:attr:`pipps.experiments.methods.Method.unused`)."""
    spec = METHODS[method]
    for name in names:
        key = name.replace("-", "_")
        if key in spec.unused:
            raise ConfigError(f"{key}: {method} does not use it (its method-specific settings: "
                              f"{', '.join(spec.settings) or 'none'})")


def from_dict(d: dict[str, Any]) -> ExperimentConfig:
    """Rebuild a stored configuration (HDF5 attributes give numpy scalars and arrays)."""
    hints = _field_types()
    values = {}
    for key, hint in hints.items():
        if key not in d:
            continue
        v = d[key]
        if hasattr(v, "tolist"):
            v = v.tolist()
        if isinstance(v, bytes):
            v = v.decode()
        if isinstance(v, str) and v == "__none__":
            v = None
        if isinstance(v, list):
            v = tuple(v)
        values[key] = v
    for key, value in LEGACY_VALUES.items():  # settings added later: what the code did before they existed
        values.setdefault(key, value)
    if "protocol" in values:
        return ExperimentConfig(**values)
    return _legacy_protocol(ExperimentConfig(**values, protocol=values.get("preset", "thesis")))


#: For settings added after result files were first written: the value that reproduces what the
#: code did before the setting existed, used when a stored configuration lacks it (so a later
#: change of a default cannot relabel an old file).
LEGACY_VALUES: dict[str, Any] = {"variance_tol": 0.0, "balance_steps": 10, "balance_angle": 0.3,
                                 "balance_position": 0.5, "balanced_fraction": 0.5, "pilco_policy_noise": False,
                                 "task_source": None}

#: Settings added after result files were first written that :func:`config_hash` leaves out while they
#: hold their :data:`LEGACY_VALUES` value, so that every configuration that leaves them alone keeps the
#: hash, and the file name, it had before they existed. They stay in :func:`canonical` (every
#: configuration has the same keys there), so resume and pooling compare them like any other setting.
HASHED_WHEN_SET = ("pilco_policy_noise",)


def _legacy_protocol(cfg: ExperimentConfig) -> ExperimentConfig:
    """A configuration stored before ``protocol`` existed, with the experiment preset it was built
    from: the one whose protocol it equals (``quick`` runs were stored with ``preset="thesis"``),
    else its task preset (then it departs from that protocol, see :func:`departures`)."""
    best, fewest = cfg, None
    for protocol in PRESET_NAMES:  # the preset it departs from least (a quick run with a --set: quick)
        candidate = dataclasses.replace(cfg, protocol=protocol)
        try:
            n = len(departures(candidate))
        except ConfigError:
            continue
        if fewest is None or n < fewest or (n == fewest and protocol == cfg.preset):
            best, fewest = candidate, n
    return best


#: The settings that say which table cell and seed an experiment is; every other setting is the protocol's.
IDENTITY = ("task", "protocol", "method", "cost", "cost_scale", "k", "seed")

#: Settings that say how an experiment is computed, not what is computed, so they are not part of
#: its identity (:func:`canonical`: its hash, file name, resume and pooling checks). ``gp_chunk``
#: pads the GP data with masked rows whose kernel rows, weights and ``inv`` entries are exact
#: zeros (tests/test_gp.py), so a capacity changes only the rounding of sums over the data and, on
#: the first FITC trial, which uniform random subset of the real rows starts the inducing inputs
#: (same distribution). ``progress_chunk`` splits the policy steps into compiled calls of another
#: length, each call keyed by the step it starts at, so it changes which random numbers are drawn,
#: not their distribution. Both leave an experiment equal in distribution (docs/performance.md,
#: "Exact GP capacities"); each trial stores the capacity it used (``trial.gp.capacity``).
COMPUTATIONAL = ("gp_chunk", "progress_chunk")

#: Settings that say where something came from, not what the experiment is: left out of
#: :func:`canonical` like :data:`COMPUTATIONAL` (a task's ``module:attribute`` may change when
#: its code moves), and out of a stored configuration while they are None (:func:`stored_dict`).
PROVENANCE = ("task_source",)


def canonical(cfg: ExperimentConfig) -> dict[str, Any]:
    """The configuration as a dict with the default cost named (``cost=None`` and ``cost="angle"``
    are the same experiment on the cart-pole's thesis preset), without the :data:`COMPUTATIONAL`
    settings, and with every setting the method does not use
    (:attr:`pipps.experiments.methods.Method.unused`) at the value its experiment preset gives.

    A setting the method does not use cannot change the experiment, so configurations that differ
    only there are one experiment: one name, one hash, and resume and pooling accept them. It
    reads as if it had not been given, rather than being dropped, so that every configuration
    that leaves it alone keeps the ``config_hash`` and file name it had before the methods
    declared the settings they use."""
    d = cfg.to_dict()
    preset = protocol_config(cfg).to_dict()
    d.update({name: preset[name] for name in cfg.method_spec.unused})
    d["cost"] = cfg.cost_name
    for name, hint in _field_types().items():  # k=1 and k=1.0 are one experiment (and one hash)
        v = d[name]
        if float in typing.get_args(hint) + (hint,) and isinstance(v, int) and not isinstance(v, bool):
            d[name] = float(v)
    return {k: v for k, v in d.items() if k not in COMPUTATIONAL + PROVENANCE}


def stored_dict(cfg: ExperimentConfig) -> dict[str, Any]:
    """The configuration as a result file stores it: every setting, but the :data:`PROVENANCE` ones
    only where set (a built-in task's configuration is stored as it always was)."""
    return {k: v for k, v in cfg.to_dict().items() if not (k in PROVENANCE and v is None)}


def same_experiment(a: ExperimentConfig, b: ExperimentConfig) -> bool:
    """Whether two configurations describe the same experiment (equal up to naming the default cost)."""
    return canonical(a) == canonical(b)


def config_hash(cfg: ExperimentConfig) -> str:
    """SHA-256 of the canonical configuration: a result's identity (stored as ``config_hash``). The
    :data:`HASHED_WHEN_SET` settings enter only where they depart from their legacy value."""
    d = canonical(cfg)
    for name in HASHED_WHEN_SET:
        if d[name] == LEGACY_VALUES[name]:
            del d[name]
    text = json.dumps(d, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def protocol_config(cfg: ExperimentConfig) -> ExperimentConfig:
    """What ``cfg``'s experiment preset gives for its table cell and seed, with no other override."""
    ident = {k: getattr(cfg, k) for k in IDENTITY if k not in ("task", "protocol")}
    return resolve_config(cfg.protocol, cfg.task_spec, **ident)


def departures(cfg: ExperimentConfig) -> dict[str, tuple[Any, Any]]:
    """The settings in which ``cfg`` departs from its protocol: ``{name: (value, protocol's value)}``."""
    a, b = canonical(cfg), canonical(protocol_config(cfg))
    return {k: (a[k], b[k]) for k in a if a[k] != b[k]}


def experiment_name(cfg: ExperimentConfig) -> str:
    """The result file's name (without ``.h5``): ``task_cost_kK_method_protocol_sSEED`` for an
    experiment that follows its protocol, with ``_cHASH`` (the first 8 hex digits of
    :func:`config_hash`) appended when any other setting departs from it, so that two different
    configurations never share a name."""
    # the cost's name (the default one named, so that cost=None and cost="angle" share a file);
    # "default" for a task with a single cost
    cost = canonical(cfg)["cost"] if len(cfg.task_spec.costs) > 1 else "default"
    if cfg.cost_scale != 1.0:
        cost += f"x{_number(cfg.cost_scale)}"
    name = f"{cfg.task}_{cost}_k{_number(cfg.k)}_{cfg.method}_{cfg.protocol}_s{cfg.seed}"
    try:
        custom = bool(departures(cfg))
    except ConfigError:  # the protocol cannot express this cell at all
        custom = True
    return f"{name}_c{config_hash(cfg)[:8]}" if custom else name


def _number(x: float) -> str:
    """``x`` short (``1``, ``0.01``, ``16``) where that is exact, else in full (``1.0000001``)."""
    short = f"{x:g}"
    return short if float(short) == float(x) else repr(float(x))


def config_difference(stored: ExperimentConfig, asked: ExperimentConfig) -> str:
    """The settings two configurations disagree on, ``"name: a stored, b asked; ..."`` (the
    default cost and its name count as equal)."""
    a, b = canonical(stored), canonical(asked)
    return "; ".join(f"{k}: {a[k]!r} stored, {b[k]!r} asked" for k in a if a[k] != b[k])
