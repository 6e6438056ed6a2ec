"""What an experiment costs before it runs: core-seconds from a model of measured costs.

The model prices each trial of an experiment (docs/performance.md, "Estimating a run's cost"):

* a learned trial's **policy search**: evaluations × seconds per evaluation, plus a fixed part
  (compiling the step program at the trial's GP size). A particle method's evaluation costs
  ``T·P·(a·E·M² + b·E·M + c)`` — the GP variance product ``A_a k_a`` (2·P·E·M² flops per step,
  docs/performance.md), the kernel and mean, and the per-particle rest — times the method's
  measured ratio to TP; PILCO's costs ``T·(a·E²·M² + b·E·M + c)`` (moment matching). T is the
  horizon, P the particles, E the GP's outputs, M its size (the padded data, or the inducing
  inputs once FITC runs);
* its **GP training**: ``g·E·M³`` for a full GP (warm-started L-BFGS), ``f·E·N·M²·iterations``
  for FITC, plus a fixed part;
* the **rest** of a trial (true-system rollout, evaluation rollouts, their compilation): a
  constant per random and per learned trial;
* **compilation** where the GP is padded to few sizes (``gp_chunk > 1``, the quick preset): a
  constant per size, larger when the persistent compilation cache holds no programs yet (cold)
  than when it does (warm); measured on the quick preset (``pipps run --preset quick``, one pinned
  core: 41 s per size cold, 10 s warm, at 68 Gflop/s). With exact sizes (the thesis and PILCO
  presets) every trial compiles, and the committed files' timings already hold that cost.

The coefficients are seconds on one core at :data:`REFERENCE_GFLOPS`, fitted to the per-trial
``timings`` of committed result files by ``experiments/cost_model_fit.py`` (which prints them and
their error on held-out files); :func:`gemm_gflops` measures this machine's float64 GEMM rate,
and :func:`estimate` scales the reference seconds by the ratio of the two rates. Every particle
method but TP−σ_f is priced as TP's curve times its measured ratio to TP at N = 300
(docs/estimators.md, "Speed"), and its files enter the fit through that ratio; TP−σ_f is priced as
TP without the variance term.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from typing import NamedTuple

from pipps.experiments.config import ExperimentConfig

#: float64 GEMM rate (Gflop/s, one core, 512³, :func:`gemm_gflops`) the coefficients are quoted at:
#: the middle of the 33–52 Gflop/s that one pinned core of the machine the committed files ran on
#: measured (docs/performance.md)
REFERENCE_GFLOPS = 40.0

#: seconds per value-and-gradient relative to the thesis preset's TP, at P = 300, T = 30, N = 300, on
#: one pinned core (docs/estimators.md, "Speed", 2026-11-27: each method's seconds over TP's 0.2305 s);
#: the fixed-seed variants evaluate RP's or GR's objective with their quasi-Newton search; DEL's three
#: readings (the thesis preset's, the library's, DEL_c) measured within 1 % of each other
METHOD_RATIO = {"tp": 1.0, "tp+sn": 1.0, "rp": 0.893, "rp_fs": 0.893, "gr": 0.897, "gr_fs": 0.897, "lr": 0.924,
                "gtp": 1.005, "gtp+sn": 1.005, "glr": 0.938, "del": 0.900, "del-cost": 0.894,
                "tp-robust": 1.0}  # TP's sweep plus two norms per step; priced as TP, not measured apart

#: PILCO's value-and-gradient evaluations per line search (median over the committed cart-pole files:
#: 211 evaluations in 151 line searches); a budget given in evaluations is spent as given
PILCO_EVALS_PER_LINESEARCH = 1.40


@dataclasses.dataclass(frozen=True)
class Coefficients:
    """Seconds on one core at :data:`REFERENCE_GFLOPS` (module doc); the names say per what."""

    variance: float  # per T·P·E·M² (particle methods that use the GP variance)
    kernel: float  # per T·P·E·M
    particle: float  # per T·P
    search: float  # per learned trial, fixed (compiling the policy step at this size)
    pilco_mm: float  # per T·E²·M²
    pilco_kernel: float  # per T·E·M
    pilco_step: float  # per T
    pilco_search: float  # per learned trial, fixed
    gp_full: float  # per E·M³ (full GP)
    gp_fitc: float  # per E·N·M²·iteration (FITC)
    gp_fixed: float  # per learned trial
    learned_rest: float  # per learned trial: its rollout, its evaluation, their compilation
    random_trial: float  # per random trial, everything
    compile_cold: float = 70.0  # per GP size when gp_chunk > 1, empty compilation cache (module doc)
    compile_warm: float = 17.0  # the same with the programs in the cache


#: fitted by ``experiments/cost_model_fit.py`` on the even seeds of the committed CPU result files
#: (docs/performance.md has the run and the held-out error)
COEFFICIENTS = Coefficients(
    variance=3.39e-11, kernel=1.41e-08, particle=6.98e-06, search=9.57e-20,
    pilco_mm=7.73e-09, pilco_kernel=2.28e-41, pilco_step=4.12e-21, pilco_search=7.73,
    gp_full=1.71e-08, gp_fitc=1.45e-09, gp_fixed=0.526,
    learned_rest=0.0183, random_trial=0.835,
)


class TrialShape(NamedTuple):
    """What a trial's cost depends on."""

    index: int
    learned: bool
    points: int  # N, GP training points before the trial (real rows)
    size: int  # M, the GP's padded size, or its inducing inputs under FITC
    fitc_iters: int  # 0: full GP; else FITC line searches (first FITC trial: fitc_first_iters)
    evaluations: float  # policy evaluations of the search (0 for a random trial)
    compiles: bool = False  # its GP size is new and padded sizes are few (gp_chunk > 1): it compiles


@dataclasses.dataclass(frozen=True)
class Shape:
    """An experiment's dimensions: horizon T, GP outputs E, particles P, and every trial's shape."""

    horizon: int
    outputs: int
    particles: int
    method: str
    pilco: bool
    trials: tuple[TrialShape, ...]


def experiment_shape(cfg: ExperimentConfig) -> Shape:
    """The dimensions :func:`seconds` prices, from the configuration alone (no JAX work). The data
    grow by one trial's horizon per trial (a unicycle trial that falls adds fewer: an upper bound)."""
    from pipps.gp import capacity_for
    from pipps.experiments.state import make_experiment_task

    problem = make_experiment_task(cfg).problem
    horizon = int(cfg.horizon or problem.horizon)
    if cfg.is_pilco:
        from pipps.pilco.optimize import pilco_budget

        budget = pilco_budget(problem) if cfg.pilco_linesearches is None else pilco_budget(
            problem, length=cfg.pilco_linesearches)
        evals = -budget.length if budget.length < 0 else budget.length * PILCO_EVALS_PER_LINESEARCH
    else:
        evals = float(cfg.policy_evals)
    trials, fitc_seen, sizes = [], False, set()
    for i in range(cfg.num_trials):
        n = i * horizon
        if i < cfg.num_random:
            trials.append(TrialShape(i, False, n, 0, 0, 0.0))
            continue
        sparse = n > cfg.fitc_threshold
        size = cfg.num_inducing if sparse else capacity_for(n, cfg.gp_chunk)
        iters = (cfg.fitc_iters if fitc_seen else cfg.fitc_first_iters) if sparse else 0
        fitc_seen |= sparse
        trials.append(TrialShape(i, True, n, size, iters, evals, cfg.gp_chunk > 1 and (size, sparse) not in sizes))
        sizes.add((size, sparse))
    return Shape(horizon, problem.model_dim, cfg.num_particles, cfg.method, cfg.is_pilco, tuple(trials))


class TrialCost(NamedTuple):
    """Reference seconds of one trial, by phase."""

    gp: float
    search: float
    rest: float

    @property
    def total(self) -> float:
        return self.gp + self.search + self.rest


def evaluation_seconds(shape: Shape, size: int, c: Coefficients = COEFFICIENTS) -> float:
    """Reference seconds of one policy evaluation (value and gradient) at GP size ``size``."""
    T, E, M = shape.horizon, shape.outputs, size
    if shape.pilco:
        return T * (c.pilco_mm * E * E * M * M + c.pilco_kernel * E * M + c.pilco_step)
    variance = 0.0 if shape.method == "tp-sf" else c.variance * E * M * M
    ratio = METHOD_RATIO.get(shape.method, 1.0)  # TP−σ_f: 1.0, TP without the variance term
    return ratio * T * shape.particles * (variance + c.kernel * E * M + c.particle)


def trial_seconds(shape: Shape, t: TrialShape, c: Coefficients = COEFFICIENTS, cold: bool = False) -> TrialCost:
    """Reference seconds of one trial (module doc); ``cold``: the compilation cache is empty."""
    if not t.learned:
        return TrialCost(0.0, 0.0, c.random_trial)
    E, M = shape.outputs, t.size
    gp = c.gp_fixed + (c.gp_fitc * E * t.points * M * M * t.fitc_iters if t.fitc_iters else c.gp_full * E * M ** 3)
    search = t.evaluations * evaluation_seconds(shape, M, c) + (c.pilco_search if shape.pilco else c.search)
    compile_ = (c.compile_cold if cold else c.compile_warm) if t.compiles else 0.0
    return TrialCost(gp, search, c.learned_rest + compile_)


def seconds(cfg: ExperimentConfig, c: Coefficients = COEFFICIENTS, cold: bool = False) -> list[TrialCost]:
    """Reference seconds of every trial of ``cfg`` (index = trial)."""
    shape = experiment_shape(cfg)
    return [trial_seconds(shape, t, c, cold) for t in shape.trials]


def cache_is_cold() -> bool:
    """Whether JAX's persistent compilation cache (``pipps.cli.enable_compilation_cache``) is off or
    holds no program yet, so this run compiles everything."""
    import os

    folder = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    if not folder or not os.path.isdir(folder):
        return True
    with os.scandir(folder) as entries:
        return not any(True for _ in entries)


# -- this machine ----------------------------------------------------------------------------------


@functools.cache
def _square():
    import jax

    return jax.jit(lambda x: x @ x)


def gemm_gflops(n: int = 512, reps: int = 7) -> float:
    """This machine's float64 GEMM rate on one core (Gflop/s): the median over ``reps`` products of
    two n×n matrices, each timed by the CPU time the process spent on it (so the rate is one
    core's, whether XLA splits the product over threads or the core is shared). Takes ~0.2 s."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    with jax.enable_x64(True):
        a = jnp.asarray(np.random.default_rng(0).standard_normal((n, n)), dtype=jnp.float64)
        f = _square()  # compiled once per process and size: the loop probes after every learned trial
        f(a).block_until_ready()
        times = []
        for _ in range(reps):
            start = time.process_time()
            f(a).block_until_ready()
            times.append(time.process_time() - start)
    spent = float(np.median(times))
    return 2.0 * n ** 3 / max(spent, 1e-9) / 1e9


@dataclasses.dataclass(frozen=True)
class Estimate:
    """Core-seconds of one experiment on this machine, by phase, and the rates behind them."""

    gp: float
    search: float
    rest: float
    gflops: float  # this machine's GEMM rate, measured
    trials: tuple[float, ...]  # per trial, in order

    @property
    def total(self) -> float:
        return self.gp + self.search + self.rest

    def remaining(self, done: int) -> float:
        """Core-seconds of the trials from ``done`` on."""
        return float(sum(self.trials[done:]))


def estimate(cfg: ExperimentConfig, gflops: float, c: Coefficients = COEFFICIENTS, cold: bool = False) -> Estimate:
    """Core-seconds of ``cfg`` on a machine whose GEMM probe gives ``gflops`` (:func:`gemm_gflops`);
    ``cold``: the compilation cache is empty (:func:`cache_is_cold`)."""
    if not (gflops > 0 and math.isfinite(gflops)):
        raise ValueError(f"gflops must be a positive number, got {gflops!r}")
    scale = REFERENCE_GFLOPS / gflops
    parts = seconds(cfg, c, cold)
    return Estimate(scale * sum(p.gp for p in parts), scale * sum(p.search for p in parts),
                    scale * sum(p.rest for p in parts), gflops, tuple(scale * p.total for p in parts))


def minutes(seconds_: float) -> str:
    """``12 min`` / ``3.4 h`` / ``40 s``, for an estimate."""
    if seconds_ < 90:
        return f"{seconds_:.0f} s"
    if seconds_ < 5400:
        return f"{seconds_ / 60:.0f} min" if seconds_ >= 600 else f"{seconds_ / 60:.1f} min"
    return f"{seconds_ / 3600:.1f} h"
