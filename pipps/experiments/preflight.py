"""Checks before any work: will an experiment fit in memory, and can its noise be represented?

:func:`memory_bytes` estimates the largest arrays an experiment holds at once: one policy
evaluation's program (particles × steps × the Jacobians kept for the backward sweep, particles ×
the GP's size per output, the P × P batch importance weights of the likelihood-ratio estimators),
PILCO's moment-matching program (E² · M² per step, rematerialised), the GP training's M × M
matrices per output and the evaluation rollouts. The per-element counts were read off XLA's
buffer assignment of the compiled programs (``benchmarks/estimator_memory.py``, on the cart-pole
shapes, within 30 % there); they are scaled to other shapes by the dimensions they hold.
:func:`check_memory` refuses a configuration whose estimate exceeds the machine's memory, before
anything is compiled (``--particles 10000000000`` used to abort in C++ after trial 0).

:func:`noise_limit` is the largest noise multiplier ``k`` whose observations stay representable
where they go: the GP trains on them, squaring differences and summing over the data
(:func:`pipps.gp.make_data` refuses data beyond ``sqrt(max / 4N)``), so an observation-noise
standard deviation ``√k·σ`` whose 10-σ draws reach that bound fails the experiment at its first
model, after the random trial has run. :func:`check_noise` refuses it before.
"""

from __future__ import annotations

import math
import os
from typing import NamedTuple

import numpy as np

from pipps.experiments.config import ConfigError, ExperimentConfig

BYTES = 8  # float64

#: float64 elements per unit, read off XLA's buffer assignment on the cart-pole shapes
#: (benchmarks/estimator_memory.py: D = 4, Dz = 5, E = 4, the 50-centre RBF policy)
PER_PARTICLE_STEP = 3.1  # × D·Dz per particle and horizon step (61 at D·Dz = 20)
PER_PARTICLE_OUTPUT_POINT = 1.8  # per particle, GP output and GP point (kernel rows kept for the backward sweep)
PER_PARTICLE_PAIR = 0.3  # per pair of particles (batch importance weights; likelihood-ratio estimators)
PER_PARTICLE_FEATURE = 9.0  # × centres·policy inputs per particle (1,800 at 50 × 4)
PER_MODEL_ENTRY = 0.4  # per E·M² (the GP's matrices)
PILCO_PER_PAIR_ENTRY = 1.4  # per E²·M² (PILCO's moment matching, rematerialised per step)
GP_TRAINING_PER_ENTRY = 6.0  # per E·M² (Gram matrix, Cholesky factor, gradients per output)

#: the fraction of the machine's memory an experiment may plan for
MEMORY_FRACTION = 0.9


def machine_memory() -> int | None:
    """Bytes this process may use: the smaller of physical memory and a cgroup limit (None if unknown)."""
    found = []
    try:
        found.append(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        pass
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = open(path).read().strip()
        except OSError:
            continue
        if text.isdigit() and int(text) < 1 << 60:
            found.append(int(text))
    return min(found) if found else None


def evaluation_bytes(estimator: str | None, particles: int, horizon: int, size: int, *, state_dim: int,
                     input_dim: int, outputs: int, features: int = 200) -> float:
    """Bytes of one policy evaluation's program: a particle estimator (``estimator`` its name:
    ``rp`` has no likelihood-ratio part) or, with ``estimator=None``, PILCO's moment matching.
    ``size``: the GP's points or inducing inputs; ``features``: policy centres × policy inputs."""
    P, T, M, E = float(particles), float(horizon), float(size), float(outputs)
    if estimator is None:
        return BYTES * (PILCO_PER_PAIR_ENTRY * E * E * M * M + PER_MODEL_ENTRY * E * M * M)
    elements = (PER_PARTICLE_STEP * state_dim * input_dim * P * T + PER_PARTICLE_OUTPUT_POINT * P * E * M
                + PER_PARTICLE_FEATURE * features * P + PER_MODEL_ENTRY * E * M * M)
    if estimator != "rp":
        elements += PER_PARTICLE_PAIR * P * P
    return BYTES * elements


class MemoryTerm(NamedTuple):
    """One of the largest arrays :func:`memory_bytes` counts: what it is, and the settings that grow
    it (keys of :data:`SHRINK`), first the one a message names when the configuration raises none of
    them above its preset."""

    what: str
    settings: tuple[str, ...]


#: per setting (or pair of settings, ``gp``) that grows a memory term: how to spell it on the
#: command line (``None``: the particles option the caller names) and what to do about it
SHRINK = {
    "num_particles": (None, "fewer particles"),
    "horizon": ("--set horizon", "a shorter horizon"),
    "eval_rollouts": ("--set eval_rollouts", "fewer evaluation rollouts"),
    "gp": ("--set num_inducing/fitc_threshold", "a smaller GP (--set num_inducing=…, fitc_threshold=…)"),
    "num_learned": ("--set num_learned", "fewer learned trials"),
}


def memory_bytes(cfg: ExperimentConfig, seeds: int = 1) -> tuple[float, MemoryTerm]:
    """The estimated peak bytes of ``cfg`` (``seeds`` of them batched together), and the term that
    dominates them."""
    from pipps.experiments.state import make_experiment_task

    task = make_experiment_task(cfg)
    problem = task.problem
    T = int(cfg.horizon or problem.horizon)
    E, D, Dz = problem.model_dim, problem.model_dim, problem.gp_input_dim
    points = cfg.num_trials * T  # the most data the GP can hold
    sparse = points > cfg.fitc_threshold
    size = cfg.num_inducing if sparse else points
    full = min(points, cfg.fitc_threshold)  # the largest full GP trained
    features = (cfg.num_basis if cfg.policy != "linear" else 1) * problem.policy_input_dim
    model = ("gp",) if sparse else ("gp", "num_learned", "horizon")  # what sets the GP's size M
    if cfg.is_pilco:
        search = evaluation_bytes(None, 0, T, size, state_dim=D, input_dim=Dz, outputs=E)
        what = MemoryTerm(f"PILCO's moment matching at M = {size}", model)
    else:
        est = cfg.method_spec.estimator
        search = evaluation_bytes(est, cfg.num_particles, T, size, state_dim=D, input_dim=Dz, outputs=E,
                                  features=features)
        what = MemoryTerm(f"{cfg.num_particles:,} particles × {T:,} steps at M = {size}"
                          + ("" if est == "rp" else f", {cfg.num_particles:,}² importance weights"),
                          tuple(dict.fromkeys(("num_particles", "horizon", *model))))
    gp = BYTES * GP_TRAINING_PER_ENTRY * E * max(full, size) ** 2
    rollouts = BYTES * 4.0 * cfg.eval_rollouts * (T + 1) * task.simulator.sim_dim
    parts = {what: search, MemoryTerm(f"GP training on {max(full, size)} points", model): gp,
             MemoryTerm(f"{cfg.eval_rollouts:,} evaluation rollouts of {T + 1:,} states", ("eval_rollouts", "horizon")):
             rollouts}
    top = max(parts, key=parts.get)
    return seeds * float(sum(parts.values())), top


def _grown(cfg: ExperimentConfig, settings: tuple[str, ...]) -> tuple[str, ...]:
    """Those of ``settings`` (keys of :data:`SHRINK`) that ``cfg`` sets above its experiment preset's
    value (all of them when the preset cannot be rebuilt)."""
    from pipps.experiments.config import protocol_config
    from pipps.experiments.state import make_experiment_task

    try:
        base = protocol_config(cfg)
    except ConfigError:
        return settings

    def values(c: ExperimentConfig, name: str) -> tuple:
        if name == "gp":
            return c.num_inducing, c.fitc_threshold
        if name == "horizon":
            return (int(c.horizon or make_experiment_task(c).problem.horizon),)
        return (getattr(c, name),)

    return tuple(n for n in settings if any(a > b for a, b in zip(values(cfg, n), values(base, n))))


def gib(n: float) -> str:
    return f"{n / 2**30:.3g} GiB" if n < 2**50 else f"{n:.2g} bytes"


def check_memory(cfg: ExperimentConfig, *, seeds: int = 1, processes: int = 1, particles: str = "--particles",
                 available: int | None = None) -> float:
    """Raise :class:`ConfigError` when ``processes`` experiments (each ``seeds`` batched) would need
    more than :data:`MEMORY_FRACTION` of the machine's memory; return the estimate (bytes, one process).

    The message names the settings behind the largest term that the configuration raises above its
    preset (``particles`` spells the particles option), or, where it raises none, the term's first,
    and says what shrinks the term."""
    need, top = memory_bytes(cfg, seeds)
    available = machine_memory() if available is None else available
    if available is not None and processes * need > MEMORY_FRACTION * available:
        named = _grown(cfg, top.settings)
        advice = [SHRINK[name][1] for name in (named or top.settings)]
        options = [SHRINK[name][0] or particles for name in (named or top.settings[:1])]
        many = f"{processes} experiments at once × " if processes > 1 else ""
        raise ConfigError(f"{' and '.join(options)}: the experiment needs about {many}{gib(need)} for its largest "
                          f"arrays ({top.what}), more than this machine's {gib(available)}; use "
                          + (", ".join(advice[:-1]) + " or " + advice[-1] if len(advice) > 1 else advice[0]))
    return need


def _base_noise(task: str, preset: str) -> float:
    """The largest observation-noise standard deviation of ``task`` at k = 1."""
    from pipps.tasks.registry import get_task

    return float(np.max(get_task(task).make(preset, 1.0).simulator.obs_noise_std))


def noise_limit(task: str, preset: str, data_points: int) -> float:
    """The largest noise multiplier k whose observation noise stays representable (module doc);
    infinite for a task without observation noise (any k leaves it at 0)."""
    base = _base_noise(task, preset)
    if base == 0.0:
        return math.inf
    bound = math.sqrt(np.finfo(np.float64).max / (4.0 * max(data_points, 1)))
    try:
        return (bound / (10.0 * base)) ** 2
    except OverflowError:  # a small noise and few data points: no k of a float64 overflows
        return math.inf


def check_noise(task: str, preset: str, k: float, data_points: int, option: str = "--k") -> None:
    """Raise :class:`ConfigError` when ``k``'s observation-noise standard deviation is not finite or
    overflows the arithmetic the observations go through (:func:`noise_limit`)."""
    if not (isinstance(k, (int, float)) and math.isfinite(k) and k >= 0):
        raise ConfigError(f"{option}: the noise multiplier must be a finite number >= 0, got {k!r}")
    limit = noise_limit(task, preset, data_points)
    if k > limit:
        base = _base_noise(task, preset)
        raise ConfigError(f"{option} {k:g}: the observation noise's standard deviation √k·σ reaches "
                          f"{math.sqrt(k) * base:.3g}, and observations that large overflow float64 when squared "
                          f"and summed over {data_points} data points; k must stay below {limit:.3g}")


def check_experiment(cfg: ExperimentConfig, *, seeds: int = 1, processes: int = 1, particles: str = "--particles",
                     k: str = "--k") -> float:
    """Both checks for one configuration, naming the options ``particles`` and ``k`` when they fail;
    returns the memory estimate (bytes)."""
    from pipps.experiments.programs import check_moment_matching
    from pipps.experiments.state import make_experiment_task

    problem = make_experiment_task(cfg).problem
    try:
        check_moment_matching(cfg, problem)
    except ValueError as err:
        raise ConfigError(f"method: {err}") from None
    if not cfg.is_pilco:
        from pipps.experiments.methods import method_estimator

        spec = cfg.method_spec.estimator
        label = spec if isinstance(spec, str) else cfg.method
        check_density_fit({label: method_estimator(cfg.method_spec, cfg.estimator_choices)}, cfg.num_particles,
                          problem.model_dim, option=particles)
    horizon = int(cfg.horizon or problem.horizon)
    check_noise(cfg.task, cfg.preset, cfg.k, cfg.num_trials * horizon, option=k)
    return check_memory(cfg, seeds=seeds, processes=processes, particles=particles)


def _fits_density(estimator) -> bool:
    """Whether ``estimator`` (a spec such as ``"del:baseline=none"``, or a composition) fits a Gaussian
    to the particles at every step; an unparseable spec is left to the code that reads it."""
    from pipps.propagation.estimators import from_spec

    if not isinstance(estimator, str):
        return estimator.fits_density
    try:
        return from_spec(estimator).fits_density
    except ValueError:
        return False


def check_density_fit(estimators, particles: int, state_dim: int, option: str = "--particles") -> None:
    """An estimator that fits a Gaussian to the P particles at each step (DEL's readings, any
    composition with such a piece) needs P > D: the unbiased covariance has rank at most P − 1, so
    P ≤ D (the model state's dimension) makes the fitted density degenerate. Raises
    :class:`ConfigError` naming ``option`` before anything runs, instead of at the first policy search.
    ``estimators``: specs (``"del:baseline=none"``) and compositions, or a ``{label: estimator}`` mapping
    whose labels the message names."""
    pairs = estimators.items() if isinstance(estimators, dict) else \
        [(e.split(":")[0] if isinstance(e, str) else "the composed estimator", e) for e in estimators]
    fitting = [label for label, e in pairs if _fits_density(e)]
    if fitting and particles <= state_dim:
        names = ", ".join(dict.fromkeys(fitting))
        raise ConfigError(f"{option} {particles}: {names} fits a Gaussian to the particles in the "
                          f"model's {state_dim} state dimensions and needs more particles than that "
                          f"(at least {state_dim + 1})")


def check_study(cfg: ExperimentConfig, size: int, particles: int, estimators, *, option: str = "--particles",
                available: int | None = None) -> float:
    """The memory check for a gradient study on a snapshot of ``cfg`` whose GP has ``size`` points (or
    inducing inputs): one evaluation of the most demanding of ``estimators`` (names, ``NAME:SETTING=…``
    allowed) at ``particles``. Raises :class:`ConfigError` naming ``option``; returns the estimate."""
    from pipps.experiments.state import make_experiment_task

    problem = make_experiment_task(cfg).problem
    check_density_fit(estimators, particles, problem.model_dim, option=option)
    T = int(cfg.horizon or problem.horizon)
    features = (cfg.num_basis if cfg.policy != "linear" else 1) * problem.policy_input_dim
    kinds = {str(e).split(":")[0] for e in estimators}
    est = "rp" if kinds <= {"rp"} else "lr"
    need = evaluation_bytes(est, particles, T, size, state_dim=problem.model_dim, input_dim=problem.gp_input_dim,
                            outputs=problem.model_dim, features=features)
    available = machine_memory() if available is None else available
    if available is not None and need > MEMORY_FRACTION * available:
        raise ConfigError(f"{option}: one estimate at P = {particles:,} needs about {gib(need)} "
                          f"({particles:,} particles × {T} steps at M = {size}"
                          + ("" if est == "rp" else f", {particles:,}² importance weights")
                          + f"), more than this machine's {gib(available)}; use fewer particles")
    return need
