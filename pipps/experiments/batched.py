"""Many seeds at once: the R seeds of one table cell as one vectorized computation.

``run_batched(cfgs)`` runs experiments whose configurations differ only in the seed through the
one learning loop (:func:`pipps.experiments.loop.run_seeds`) on a batched seed axis,
:class:`SeedBatch`: one program per phase with the seed as a leading batch axis (the true-system
trials and their evaluation rollouts, the GP training through :func:`pipps.gp.fit_many`, the
optimiser's initialisation and every chunk of policy steps, and the stored particle prediction).
Keys, data, warm starts, failures and resuming are the loop's, the same code an unbatched run
goes through, so seed s of a batch is the experiment ``run_experiment`` runs for seed s up to
floating-point reassociation in the batched programs (tested: same trajectories, policies and
returns to tolerance).

``batching`` says how the seed axis is computed: ``"vmap"`` (one batched program: what a GPU
wants), ``"map"`` (``lax.map``, the seeds one after the other inside one compiled program), or
``"auto"`` (map on CPU, vmap elsewhere). On CPU the GP training's seed axis is always mapped:
jaxlib 0.10's batched LAPACK calls deadlock inside loops there once XLA runs two threads
(:func:`pipps.gp.linalg.map_outputs`; a vmapped two-seed GP training hung in this project's CI
check), so ``"vmap"`` on CPU vectorizes the trials, rollouts and optimiser only. (The GR, GS and
DEL estimators factor covariances in the rollout; vmapping them on a multi-threaded CPU risks the
same deadlock.) On one CPU core a batch is not faster than the seeds run one after another anyway
(the GP products already run at the core's peak, docs/performance.md), so the batched mode is
for accelerators.

Scope: the stochastic-gradient particle methods (RP, GR, LR, TP and their variants, GTP, GLR,
DEL). PILCO and the fixed-seed quasi-Newton methods (RP_FS, GR_FS) have data-dependent line
searches per seed and run unbatched (``pipps sweep`` without ``--batched``).

Results are per seed, as :class:`ExperimentResult`: ``on_trial(results)`` is called after every
trial with all of them, so a caller writes each seed's file (the sweep does, atomically). Timings
are the batch's: every seed of a batch records the same phase seconds and wall time, and the
trial timings hold ``batched_seeds``, the batch size. A seed whose optimised policy is not finite
fails alone (its result says so) and leaves the batch; an error in a batched phase fails every
seed still running. ``resumes`` continues seeds that stopped after the same trial from their
files, as a single experiment resumes (the sweep groups unfinished seeds so).
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

import jax

from pipps.experiments.config import ExperimentConfig, config_difference
from pipps.experiments.loop import ExperimentResult, Progress, run_seeds
from pipps.experiments.methods import MOMENTUM
from pipps.gp import fit_many
from pipps.gp.linalg import map_outputs, stack_trees
from pipps.precision import require_float64

BATCHINGS = ("auto", "vmap", "map")


def check_batchable(cfgs: Sequence[ExperimentConfig]) -> None:
    """Raise ValueError unless ``cfgs`` are one cell's distinct seeds of a stochastic particle method."""
    if not cfgs:
        raise ValueError("batched: no configurations")
    base = cfgs[0]
    for c in cfgs[1:]:
        same_seed = dataclasses.replace(c, seed=base.seed)
        if same_seed != base:
            raise ValueError(f"batched: configurations must differ only in the seed ({config_difference(base, same_seed)})")
    seeds = [c.seed for c in cfgs]
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"batched: seeds repeat: {seeds}")
    if base.method_spec.optimizer != MOMENTUM:
        raise ValueError(f"batched: method {base.method!r} optimises with per-seed quasi-Newton line searches and "
                         "runs unbatched; the batched mode takes the stochastic-gradient particle methods")
    if base.variance_tol > 0:
        raise ValueError("batched: variance_tol > 0 (the low-rank variance) has per-seed ranks and runs unbatched")
    from pipps.experiments.state import make_experiment_task

    if make_experiment_task(base).host_stepped:
        raise ValueError(f"batched: {base.task}'s true system is stepped from Python (a HostSimulator) and runs "
                         "seed by seed")


class SeedBatch:
    """The batched seed axis (:mod:`pipps.experiments.programs`): programs over a leading seed axis,
    computed per ``batching``; the GP training's axis is mapped on CPU (module docstring)."""

    batched = True

    def __init__(self, batching: str = "auto"):
        if batching not in BATCHINGS:
            raise ValueError(f"batching must be one of {', '.join(BATCHINGS)}, got {batching!r}")
        self.batching = batching
        self.gp_batching = "map" if jax.default_backend() == "cpu" else batching

    def _over_seeds(self, fn):
        return lambda *xs: map_outputs(lambda a: fn(*a), xs, self.batching)

    def compile(self, fn):
        return jax.jit(self._over_seeds(fn))

    def compile_steps(self, run):
        """``steps(keys, states, models, n)`` from a jitted ``run(key, state, model, num_steps)``."""
        return jax.jit(lambda k, s, m, n: self._over_seeds(lambda kk, ss, mm: run(kk, ss, mm, num_steps=n))(k, s, m),
                       static_argnames="n")

    def stack(self, trees: Sequence):
        return stack_trees(trees)

    def take(self, tree, j: int):
        return jax.tree_util.tree_map(lambda a: a[j], tree)

    def fit(self, keys, datas, prevs, config):
        return fit_many(keys, datas, prevs, config, batching=self.gp_batching)


def run_batched(
    cfgs: Sequence[ExperimentConfig],
    *,
    progress: Progress | None = None,
    on_trial: Callable[[list[ExperimentResult]], None] | None = None,
    batching: str = "auto",
    resumes: Sequence[ExperimentResult] | None = None,
) -> list[ExperimentResult]:
    """Run the seeds of one cell as one batch; see the module docstring. Returns one result per
    configuration, in order. Raises what fails in a batched phase, after ``on_trial`` saw every
    seed marked failed.

    ``resumes``: one partial result per configuration, all with the same number n of finished
    trials (a sweep groups its seeds so): the batch continues every seed at trial n from the state
    its file holds (:func:`pipps.experiments.state.restore`), as :func:`pipps.experiments.loop.run_experiment`
    resumes one seed. A GPU job cut off after a few minutes thus loses at most the trial in flight."""
    require_float64("pipps.experiments.batched.run_batched")
    axis = SeedBatch(batching)
    check_batchable(cfgs)
    return run_seeds(cfgs, axis=axis, progress=progress, on_trial=on_trial, resumes=resumes)
