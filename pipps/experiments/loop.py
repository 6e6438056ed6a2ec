"""The episodic learning loop (thesis Algorithm 1, §4.5.3; docs/experiments.md, "The loop").

An experiment runs ``num_random`` random trials, then ``num_learned`` times: train one GP per
state dimension on all data → optimise the policy on the model with the chosen method → run one
trial on the true system with the policy and append its transitions. After every trial the
current policy is evaluated by ``eval_rollouts`` extra true-system rollouts that are never used
for learning. Success is judged on the final trial's evaluation by the task's criterion
(:mod:`pipps.reporting.verdicts`).

**One loop, a seed axis.** :func:`run_seeds` runs the seeds of one configuration together: every
phase of a trial is one program over the seeds' axis (:mod:`pipps.experiments.programs`). An
unbatched experiment, :func:`run_experiment`, is one seed on :data:`ONE_SEED`, the axis whose
programs are the one-seed functions themselves; :func:`pipps.experiments.batched.run_batched` is
the same loop on a batched axis. Each seed carries a :class:`~pipps.experiments.state.SeedState`
and advances it after every trial from what the trial records
(:func:`~pipps.experiments.state.advance`), and every draw of trial ``i`` comes from
:func:`~pipps.experiments.state.trial_keys`; so seed s of a batch is the experiment of seed s.

I/O stays outside: the loop reports through two callbacks, ``progress(event)`` for a display and
``on_trial`` after every finished trial (the CLI writes the HDF5 file there, so a run that fails
part-way keeps every trial it finished). Data are padded to multiples of ``gp_chunk`` so the
programs compile once per capacity, not once per trial.

**Failures.** A seed whose optimised policy is not finite fails alone (its result says so; an
unbatched run raises the error); any other error fails every seed still running and is raised,
after ``on_trial`` saw them marked ``failed`` with everything they finished. A
``KeyboardInterrupt`` (Ctrl-C, or the SIGINT a sweep sends its workers) marks them
``interrupted`` instead: nothing went wrong, and they resume from their last finished trial.

**Resuming.** ``resume`` continues an experiment from the trials a partial result holds (a killed
or failed run's file): :func:`~pipps.experiments.state.restore` rebuilds the state those trials
left (last policy, data, GP warm start), which is everything the next trial depends on, so a
resumed experiment equals an uninterrupted one exactly (tested); ``resumed_at`` records where it
was picked up.
"""

from __future__ import annotations

import time
from typing import Callable, Sequence

import jax
import numpy as np
from jax.flatten_util import ravel_pytree

from pipps.experiments.config import ExperimentConfig, config_difference, same_experiment
from pipps.experiments.programs import ONE_SEED, Programs, Progress
from pipps.experiments.records import ExperimentResult, GPRecord, Timings, TrialResult
from pipps.experiments.state import advance, gp_config, initial_state, make_experiment_task, restore, trial_keys
from pipps.gp import capacity_for
from pipps.precision import require_float64

OnTrial = Callable[[list[ExperimentResult]], None]


def planning_model(cfg: ExperimentConfig, post, data, info):
    """The model the policy is optimised on: the posterior itself, or with ``variance_tol > 0`` under
    a particle method that uses the variance, its certified low-rank form (:mod:`pipps.gp.lowrank`;
    full GP or FITC). Returns ``(model, ranks or None)``."""
    if cfg.variance_tol <= 0 or "variance_tol" not in cfg.method_spec.settings:
        return post, None
    from pipps.gp.lowrank import low_rank_model

    return low_rank_model(post, data, cfg.variance_tol, sparse=bool(info.sparse), jitter=info.posterior_jitter)


def gp_record(post, info, capacity: int, model=None, ranks=None) -> GPRecord:
    """What a learned trial records of its GP: hyperparameters, training report, the capacity it was
    padded to, FITC's inducing inputs (with the data and hyperparameters they rebuild the model), and
    the low-rank variance's ranks and bound where it planned on one."""
    hyper = jax.device_get(post.hyper)
    return GPRecord(np.asarray(hyper.log_lengthscale), np.asarray(hyper.log_signal), np.asarray(hyper.log_noise),
                    sparse=bool(info.sparse), num_points=int(info.num_points),
                    objective=np.asarray(info.hyper.objective), messages="\n".join(info.messages),
                    inducing=np.asarray(post.inputs) if info.sparse else None, capacity=int(capacity),
                    variance_ranks=ranks,
                    variance_bound=None if ranks is None else np.asarray(model.bound))


def _trial_from(index, kind, traj, evals, policy, timings: Timings) -> TrialResult:
    traj = jax.device_get(traj)
    returns, upright, ok = (np.asarray(a) for a in jax.device_get(evals))
    return TrialResult(index, kind, np.asarray(traj.states), np.asarray(traj.observations),
                       np.asarray(traj.actions), np.asarray(traj.costs), np.asarray(traj.valid),
                       returns, upright, _flat(policy), timings, eval_balanced=ok)


def _flat(policy) -> np.ndarray:
    return np.asarray(ravel_pytree(policy)[0])


def _check_resumable(cfg: ExperimentConfig, partial: ExperimentResult) -> None:
    if not same_experiment(partial.config, cfg):
        raise ValueError(f"resume: the partial result is of another configuration "
                         f"({config_difference(partial.config, cfg)})")
    if [t.index for t in partial.trials] != list(range(len(partial.trials))):
        raise ValueError(f"resume: the partial result's trials are {[t.index for t in partial.trials]}, "
                         "not 0, 1, ... in order")
    if len(partial.trials) > cfg.num_trials:
        raise ValueError(f"resume: {len(partial.trials)} trials stored, the configuration has {cfg.num_trials}")


def _check_resumes(cfgs: Sequence[ExperimentConfig], resumes: Sequence[ExperimentResult]) -> None:
    if len(resumes) != len(cfgs):
        raise ValueError(f"resumes: {len(resumes)} partial results for {len(cfgs)} configurations")
    for c, r in zip(cfgs, resumes):
        if r.trials:  # an empty partial result is nothing to resume
            _check_resumable(c, r)
    if len({len(r.trials) for r in resumes}) != 1:
        raise ValueError("resumes: every seed of a batch must resume at the same trial, got "
                         f"{sorted({len(r.trials) for r in resumes})}")


def run_experiment(
    cfg: ExperimentConfig,
    *,
    progress: Progress | None = None,
    on_trial: Callable[[ExperimentResult], None] | None = None,
    resume: ExperimentResult | None = None,
) -> ExperimentResult:
    """Run one experiment: :func:`run_seeds` with one seed on :data:`ONE_SEED`. Raises what fails
    (a non-finite policy included), after ``on_trial`` saw every finished trial and the result has
    ``status="failed"`` (``"interrupted"`` for a ``KeyboardInterrupt``) and the error message.

    ``resume``: a partial result of this same configuration (its trials 0..n−1); the run continues
    at trial n and returns the whole experiment."""
    require_float64("pipps.experiments.run_experiment")
    on_trial = on_trial or (lambda result: None)
    errors: dict[int, BaseException] = {}
    (result,) = run_seeds([cfg], axis=ONE_SEED, progress=progress, on_trial=lambda results: on_trial(results[0]),
                          resumes=None if resume is None else [resume], errors=errors)
    if 0 in errors:
        raise errors[0]
    return result


def run_seeds(
    cfgs: Sequence[ExperimentConfig],
    *,
    axis=ONE_SEED,
    progress: Progress | None = None,
    on_trial: OnTrial | None = None,
    resumes: Sequence[ExperimentResult] | None = None,
    errors: dict[int, BaseException] | None = None,
) -> list[ExperimentResult]:
    """Run the seeds ``cfgs`` (one configuration but for the seed) together on ``axis``; see the
    module docstring. Returns one result per configuration, in order; ``errors`` (if given)
    receives the error of each seed that failed alone, by position. Raises what fails for every
    seed, after ``on_trial(results)`` saw them marked failed.

    ``resumes``: one partial result per configuration, all with the same number n of finished
    trials; every seed continues at trial n from the state its result holds."""
    progress = progress or (lambda event: None)
    on_trial = on_trial or (lambda results: None)
    errors = {} if errors is None else errors
    if not axis.batched and len(cfgs) != 1:
        raise ValueError(f"an unbatched run takes one seed, got {len(cfgs)} configurations")
    if resumes is not None:
        _check_resumes(cfgs, resumes)
    t_start = time.perf_counter()
    cfg = cfgs[0]
    task = make_experiment_task(cfg)
    criterion = cfg.task_spec.success_for(cfg).name  # what the progress display counts
    programs = Programs(cfg, task, axis)
    gpc = gp_config(cfg)
    results = [ExperimentResult(c, []) for c in cfgs]
    wall_before = [0.0] * len(cfgs)
    if resumes is not None and resumes[0].trials:
        states = [restore(r, task=task) for r in resumes]
        for s, r in enumerate(resumes):
            results[s].trials = list(r.trials)
            results[s].resumed_at = [*r.resumed_at, len(r.trials)]
            wall_before[s] = r.wall_seconds
    else:
        states = [initial_state(c, task) for c in cfgs]
    active = list(range(len(cfgs)))  # the seeds still running

    def account_wall():
        wall = time.perf_counter() - t_start
        for s, r in enumerate(results):
            r.wall_seconds = wall_before[s] + wall

    def fail(s, err):
        # Ctrl-C (a sweep's workers get SIGINT from it too) stops a run that resumes as it was: "interrupted"
        stopped = isinstance(err, KeyboardInterrupt)
        results[s].status = "interrupted" if stopped else "failed"
        results[s].error = f"{type(err).__name__}: {err}"
        errors[s] = err

    try:
        for i in range(states[0].trial, cfg.num_trials):
            if not active:
                break
            t0 = time.perf_counter()
            progress(dict(phase="trial", trial=i, trials=cfg.num_trials, seeds=len(active)))
            step = _random_trial if i < cfg.num_random else _learned_trial
            trials = step(i, [cfgs[s] for s in active], [states[s] for s in active], programs, gpc, progress)
            for s, trial in zip(list(active), trials):
                if isinstance(trial, BaseException):  # a non-finite policy fails its seed only
                    fail(s, trial)
                    active.remove(s)
            if not active:
                break
            trials = [t for t in trials if not isinstance(t, BaseException)]
            total = time.perf_counter() - t0
            for s, trial in zip(active, trials):
                trial.timings.total = total
                if axis.batched:
                    trial.timings.batched_seeds = float(len(trials))
                states[s] = advance(states[s], trial, task)
                results[s].trials.append(trial)
            account_wall()
            progress(dict(phase="evaluated", trial=i, trials=cfg.num_trials, seeds=len(active),
                          eval_return=float(np.mean([t.eval_return for t in trials])),
                          upright=float(np.mean([t.upright_fraction for t in trials])),
                          balanced=float(np.mean([t.balanced_fraction for t in trials])),
                          criterion=criterion, passed=float(np.mean([t.balanced_fraction for t in trials])),
                          seconds=total))
            on_trial(results)
    except BaseException as err:  # every seed still running fails; keep what finished, say what broke
        for s in active:
            fail(s, err)
        account_wall()
        on_trial(results)
        raise
    for s in active:
        results[s].status = "complete"
    account_wall()
    on_trial(results)
    return results


def machine_rate() -> dict[str, float]:
    """``{"gemm_gflops": …}``: this core's float64 GEMM rate (:func:`pipps.experiments.budget.gemm_gflops`,
    ~0.1 s), measured after each learned trial outside its timed phases and stored in its
    ``timings.extra``, so that the cost model can set each file's seconds against the machine (and
    the load) that measured them. Empty off the CPU, where the probe's CPU time is not the device's."""
    if jax.default_backend() != "cpu":
        return {}
    from pipps.experiments.budget import gemm_gflops

    return {"gemm_gflops": gemm_gflops()}


def _random_trial(i, cfgs, states, programs: Programs, gpc, progress) -> list[TrialResult]:
    """Trial ``i`` of every seed with random actions, evaluated with random actions."""
    del gpc, progress
    axis = programs.axis
    keys = [trial_keys(c, i) for c in cfgs]
    t0 = time.perf_counter()
    trajs = programs.trial_random(axis.stack([k.trial for k in keys]))
    t1 = time.perf_counter()
    evals = programs.evaluate_random(axis.stack([jax.random.split(k.evaluate, c.eval_rollouts)
                                                 for k, c in zip(keys, cfgs)]))
    t2 = time.perf_counter()
    return [_trial_from(i, "random", axis.take(trajs, j), axis.take(evals, j), st.policy,
                        Timings(trial=t1 - t0, evaluate=t2 - t1)) for j, st in enumerate(states)]


def _learned_trial(i, cfgs, states, programs: Programs, gpc, progress) -> list[TrialResult | BaseException]:
    """Learned trial ``i`` of every seed: GP → policy optimisation → true-system trial → evaluation.
    A seed whose optimised policy is not finite gets its error in place of a trial."""
    axis, cfg = programs.axis, cfgs[0]
    keys = [trial_keys(c, i) for c in cfgs]
    t0 = time.perf_counter()
    counts = [st.num_points for st in states]
    capacity = max(capacity_for(n, cfg.gp_chunk) for n in counts)
    datas = [st.data(capacity) for st in states]
    progress(dict(phase="gp", trial=i, points=max(counts), seeds=len(states)))
    fits = axis.fit([k.gp for k in keys], datas, [st.warm_start for st in states], gpc)
    t1 = time.perf_counter()
    planned = [planning_model(cfg, post, data, info) for (post, _, info), data in zip(fits, datas)]
    optimized = programs.optimize([k.optimize for k in keys], [st.policy for st in states],
                                  [model for model, _ in planned], progress)
    t2 = time.perf_counter()
    ok = [j for j, o in enumerate(optimized) if np.all(np.isfinite(_flat(o.policy)))]
    if ok:
        policies = axis.stack([optimized[j].policy for j in ok])
        trajs = programs.trial(axis.stack([keys[j].trial for j in ok]), policies)
        t3 = time.perf_counter()
        evals = programs.evaluate(axis.stack([jax.random.split(keys[j].evaluate, cfg.eval_rollouts) for j in ok]),
                                  policies)
        t4 = time.perf_counter()
    rate = machine_rate() if ok else {}
    out: list = [FloatingPointError(f"trial {i}: the optimised policy parameters are not finite")] * len(states)
    for n, j in enumerate(ok):
        (post, _, info), (model, ranks), o = fits[j], planned[j], optimized[j]
        trial = _trial_from(i, "learned", axis.take(trajs, n), axis.take(evals, n), o.policy,
                            Timings(gp=t1 - t0, optimize=t2 - t1, trial=t3 - t2, evaluate=t4 - t3, extra=dict(rate)))
        trial.gp = gp_record(post, info, capacity, model, ranks)
        trial.opt_trace, trial.diagnostics, trial.predicted = o.trace, o.diagnostics, o.predicted
        out[j] = trial
    return out
