"""Many seeds at once: the R seeds of one table cell as one vectorized computation (issue 7).

``run_batched(cfgs)`` runs experiments whose configurations differ only in the seed as one
program per phase, with the seed as a leading batch axis: the true-system trials and their
evaluation rollouts, the GP training (:func:`pipps.gp.fit_many`), the optimiser's
initialisation and every chunk of policy steps, and the stored particle prediction. Every
random draw is the one :func:`pipps.experiments.loop.run_experiment` makes for that seed (the
same key derivation), so seed s of a batch is the experiment ``run_experiment`` runs for seed s,
up to floating-point reassociation in the batched programs (tested: same trajectories, policies
and returns to tolerance).

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
import time
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from pipps.experiments.config import ExperimentConfig, config_difference
from pipps.experiments.loop import (
    ExperimentResult,
    Progress,
    _check_finite_data,
    _check_resumable,
    _fit_state_from,
    _trial_from,
    balance_settings,
    evaluate_rollouts,
    gp_config,
    init_policy,
    make_experiment_task,
    predict_particles,
    record_gp,
    step_report,
    stored_trajectory,
)
from pipps.experiments.methods import MOMENTUM, particle_method
from pipps.gp import capacity_for, fit_many, make_data, pad_to_capacity
from pipps.gp.linalg import map_outputs, stack_trees
from pipps.precision import require_float64
from pipps.rollout import rollout, training_pairs

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


def _take(tree, i):
    return jax.tree_util.tree_map(lambda a: a[i], tree)


class _BatchedPrograms:
    """One compiled program per phase with the seed as the leading axis; built once per batch."""

    def __init__(self, cfg: ExperimentConfig, task, batching: str):
        from pipps.optimizers.normalized import normalized_momentum
        from pipps.propagation.update import init_policy_opt_state, make_policy_optimizer

        def smap(fn):
            return lambda *xs: map_outputs(lambda a: fn(*a), xs, batching)

        rcfg, est = particle_method(cfg)
        opt = normalized_momentum(cfg.learning_rate, cfg.momentum)
        run = make_policy_optimizer(task, rcfg, est, opt)
        store = cfg.store_particles

        self.trial_random = jax.jit(smap(lambda k: rollout(k, task, None)))
        balance = balance_settings(cfg)
        self.evaluate_random = jax.jit(smap(lambda k: evaluate_rollouts(k, task, None, balance)))
        self.trial = jax.jit(smap(lambda k, p: rollout(k, task, p)))
        self.evaluate = jax.jit(smap(lambda k, p: evaluate_rollouts(k, task, p, balance)))
        self.init = jax.jit(smap(lambda k, p, m: init_policy_opt_state(
            k, p, m, task=task, config=rcfg, estimator=est, optimizer=opt)))
        self.run = jax.jit(lambda k, s, m, n: smap(lambda kk, ss, mm: run(kk, ss, mm, num_steps=n))(k, s, m),
                           static_argnames="n")
        self.predict = jax.jit(smap(lambda k, p, m: predict_particles(k, task, rcfg, store, p, m)))


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
    its file holds (last policy, data, GP warm start), as :func:`pipps.experiments.loop.run_experiment`
    resumes one seed. A GPU job cut off after a few minutes thus loses at most the trial in flight."""
    require_float64("pipps.experiments.batched.run_batched")
    if batching not in BATCHINGS:
        raise ValueError(f"batching must be one of {', '.join(BATCHINGS)}, got {batching!r}")
    check_batchable(cfgs)
    if resumes is not None:
        if len(resumes) != len(cfgs):
            raise ValueError(f"resumes: {len(resumes)} partial results for {len(cfgs)} configurations")
        for c, r in zip(cfgs, resumes):
            _check_resumable(c, r)
        if len({len(r.trials) for r in resumes}) != 1:
            raise ValueError("resumes: every seed of a batch must resume at the same trial, got "
                             f"{sorted({len(r.trials) for r in resumes})}")
    progress = progress or (lambda event: None)
    on_trial = on_trial or (lambda results: None)
    t_start = time.perf_counter()
    cfg = cfgs[0]
    S = len(cfgs)
    task = make_experiment_task(cfg)
    prog = _BatchedPrograms(cfg, task, batching)
    gp_batching = "map" if jax.default_backend() == "cpu" else batching  # module docstring: CPU LAPACK
    gpc = gp_config(cfg)
    results = [ExperimentResult(c, []) for c in cfgs]
    k_policy, k_trials = zip(*(jax.random.split(jax.random.PRNGKey(c.seed)) for c in cfgs))
    policies = [init_policy(k, cfg, task) for k in k_policy]
    flat = lambda p: np.asarray(ravel_pytree(p)[0])  # noqa: E731
    inputs: list[list[np.ndarray]] = [[] for _ in cfgs]
    targets: list[list[np.ndarray]] = [[] for _ in cfgs]
    fit_states: list = [None] * S
    active = list(range(S))  # seeds still running
    chunk = min(cfg.progress_chunk, cfg.policy_evals)
    first, wall_before = 0, [0.0] * S
    if resumes is not None and resumes[0].trials:
        first = len(resumes[0].trials)
        for s, r in enumerate(resumes):
            results[s].trials = list(r.trials)
            results[s].resumed_at = [*r.resumed_at, first]
            wall_before[s] = r.wall_seconds
            policies[s] = ravel_pytree(policies[s])[1](jnp.asarray(r.trials[-1].policy))
            for t in r.trials:
                x_in, y_out = training_pairs(task, stored_trajectory(t))
                inputs[s].append(x_in)
                targets[s].append(y_out)
            fit_states[s] = _fit_state_from(r.trials)

    def finish_trial(i, trials, t0):
        for s, trial in trials.items():
            trial.timings["total"] = time.perf_counter() - t0
            trial.timings["batched_seeds"] = float(len(trials))
            x_in, y_out = training_pairs(task, stored_trajectory(trial))
            _check_finite_data(x_in, y_out, i)
            inputs[s].append(x_in)
            targets[s].append(y_out)
            results[s].trials.append(trial)
        wall = time.perf_counter() - t_start
        for s, r in enumerate(results):
            r.wall_seconds = wall_before[s] + wall

    try:
        for i in range(first, cfg.num_trials):
            if not active:
                break
            keys = [jax.random.split(jax.random.fold_in(k_trials[s], i), 4) for s in active]
            k_trial = jnp.stack([k[0] for k in keys])
            k_eval = jnp.stack([jax.random.split(k[1], cfg.eval_rollouts) for k in keys])
            t0 = time.perf_counter()
            progress(dict(phase="trial", trial=i, trials=cfg.num_trials, seeds=len(active)))
            trials = {}
            if i < cfg.num_random:
                trajs = prog.trial_random(k_trial)
                t1 = time.perf_counter()
                evals = prog.evaluate_random(k_eval)
                t2 = time.perf_counter()
                for j, s in enumerate(active):
                    trials[s] = _trial_from(i, "random", _take(trajs, j), _take(evals, j), flat(policies[s]),
                                            dict(trial=t1 - t0, evaluate=t2 - t1))
            else:
                counts = [sum(len(a) for a in inputs[s]) for s in active]
                capacity = max(capacity_for(n, cfg.gp_chunk) for n in counts)
                datas = [pad_to_capacity(make_data(np.concatenate(inputs[s]), np.concatenate(targets[s])), capacity)
                         for s in active]
                progress(dict(phase="gp", trial=i, points=max(counts), seeds=len(active)))
                fits = fit_many([k[3] for k in keys], datas, [fit_states[s] for s in active], gpc, batching=gp_batching)
                t1 = time.perf_counter()
                act0 = list(active)  # the seeds this trial started with; fits, keys follow this order
                pos = {s: j for j, s in enumerate(act0)}
                new_policy, infos_of, predicted = {}, {}, {}
                for group in _shape_groups([post for post, _, _ in fits]):  # one group unless full and FITC mix
                    idx = [act0[j] for j in group]
                    models = stack_trees([fits[j][0] for j in group])
                    k_opt = [jax.random.split(keys[j][2], 3) for j in group]
                    state = prog.init(jnp.stack([k[0] for k in k_opt]), stack_trees([policies[s] for s in idx]), models)
                    chunks, done, start = [], 0, time.perf_counter()
                    while done < cfg.policy_evals:
                        n = min(chunk, cfg.policy_evals - done)
                        run_keys = jnp.stack([jax.random.fold_in(k[1], done) for k in k_opt])
                        state, info = prog.run(run_keys, state, models, n)
                        info = jax.device_get(info)
                        chunks.append(info)
                        done += n
                        progress(dict(phase="optimize", step=done, steps=cfg.policy_evals,
                                      objective=float(np.mean(info.value[:, -1])), seconds=time.perf_counter() - start))
                    xs, cost = jax.device_get(prog.predict(jnp.stack([k[2] for k in k_opt]), state.policy, models))
                    for j, s in enumerate(idx):
                        new_policy[s] = _take(state.policy, j)
                        infos_of[s] = [_take(c, j) for c in chunks]
                        predicted[s] = {"particles": np.asarray(xs[j]), "cost_mean": np.asarray(cost[j])}
                t2 = time.perf_counter()
                for s in act0:  # a non-finite policy fails its seed only
                    if not np.all(np.isfinite(flat(new_policy[s]))):
                        _fail(results[s], FloatingPointError(f"trial {i}: the optimised policy parameters are not finite"))
                        active.remove(s)
                if not active:
                    break
                keep = jnp.asarray([pos[s] for s in active])
                stacked = stack_trees([new_policy[s] for s in active])
                trajs = prog.trial(k_trial[keep], stacked)
                t3 = time.perf_counter()
                evals = prog.evaluate(k_eval[keep], stacked)
                t4 = time.perf_counter()
                for j, s in enumerate(active):
                    policies[s] = new_policy[s]
                    post, fit_states[s], info = fits[pos[s]]
                    trial = _trial_from(i, "learned", _take(trajs, j), _take(evals, j), flat(policies[s]),
                                        dict(gp=t1 - t0, optimize=t2 - t1, trial=t3 - t2, evaluate=t4 - t3))
                    trial.opt_trace, trial.diagnostics = step_report(infos_of[s])
                    trial.predicted = predicted[s]
                    record_gp(trial, post, info)
                    trial.gp_info["capacity"] = capacity
                    trials[s] = trial
            finish_trial(i, trials, t0)
            progress(dict(phase="evaluated", trial=i, trials=cfg.num_trials, seeds=len(active),
                          eval_return=float(np.mean([trials[s].eval_return for s in active])),
                          upright=float(np.mean([trials[s].upright_fraction for s in active])),
                          balanced=float(np.mean([trials[s].balanced_fraction for s in active])),
                          criterion="balanced" if cfg.task != "unicycle" else "upright",
                          seconds=time.perf_counter() - t0))
            on_trial(results)
    except BaseException as err:  # every seed still running fails with the batch; keep what finished
        for s in active:
            _fail(results[s], err)
        wall = time.perf_counter() - t_start
        for s, r in enumerate(results):
            r.wall_seconds = wall_before[s] + wall
        on_trial(results)
        raise
    for s in active:
        results[s].status = "complete"
    wall = time.perf_counter() - t_start
    for s, r in enumerate(results):
        r.wall_seconds = wall_before[s] + wall
    on_trial(results)
    return results


def _fail(result: ExperimentResult, err: BaseException) -> None:
    result.status, result.error = "failed", f"{type(err).__name__}: {err}"


def _shape_groups(posts) -> list[list[int]]:
    """Indices of the posteriors grouped by pytree structure and leaf shapes (one group per compiled model)."""
    groups: dict = {}
    for j, post in enumerate(posts):
        leaves, tree = jax.tree_util.tree_flatten(post)
        groups.setdefault((tree, tuple(np.shape(a) for a in leaves)), []).append(j)
    return list(groups.values())
