"""The compiled pieces of a trial, over a seed axis: true-system rollouts, their evaluation, and the
policy optimisation of each method (thesis §4.5.3).

A *seed axis* (:class:`OneSeed` here, :class:`pipps.experiments.batched.SeedBatch` for many) says
how a program over seeds is computed: ``compile(fn)`` turns a one-seed function into the program,
``stack`` puts the seeds' values on the axis and ``take`` gets one back, ``fit`` trains their GPs.
The one-seed axis is no axis at all: its programs are the one-seed functions jitted, so an
unbatched run computes exactly what it always did. :class:`Programs` builds every program once per
experiment (or batch) and reuses it across trials. The rollouts and their evaluation take the
:class:`~pipps.tasks.base.Task` (its simulator and, for the cost and the policy input, its problem);
the policy optimisation and the prediction plan, so they take only ``task.problem``.

A true system stepped from Python (a :class:`~pipps.tasks.base.HostSimulator`, e.g. a gymnasium
environment) cannot be compiled: its trials and evaluations are plain functions that step it
(:func:`pipps.rollout.host_rollout`), one seed at a time; the compiled path of a simulated system
is the same program it always was.
"""

from __future__ import annotations

import time
from typing import Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from pipps.experiments.config import ExperimentConfig
from pipps.experiments.methods import FIXED_SEED, MOMENTUM, PILCO_SEARCH, particle_method, rollout_config
from pipps.experiments.records import Diagnostics, MomentPrediction, ParticlePrediction, SearchTrace, StepTrace
from pipps.gp import fit
from pipps.rollout import rollout, rollouts
from pipps.tasks.base import Problem, Task

Progress = Callable[[dict[str, Any]], None]


class OneSeed:
    """The seed axis of an unbatched run (module doc): one seed, its values as they are."""

    batched = False

    def compile(self, fn):
        return jax.jit(fn)

    def compile_steps(self, run):
        """``steps(keys, state, models, n)`` from a jitted ``run(key, state, model, num_steps)``."""
        return lambda key, state, model, n: run(key, state, model, num_steps=n)

    def stack(self, trees: Sequence):
        (tree,) = trees
        return tree

    def take(self, tree, j: int):
        del j
        return tree

    def fit(self, keys, datas, prevs, config):
        (key,), (data,), (prev,) = keys, datas, prevs
        return [fit(key, data, prev=prev, config=config)]


ONE_SEED = OneSeed()


def success_rule(cfg: ExperimentConfig):
    """The task's rule per evaluation rollout under ``cfg``'s settings
    (:attr:`pipps.tasks.Success.rule`): what a trial's ``eval_balanced`` records."""
    return cfg.task_spec.success_for(cfg).rule


def evaluate_rollouts(keys, task: Task, policy, rule=None):
    """(returns, upright, criterion) of one true-system rollout per key with ``policy`` (None: random
    actions); fallen steps are charged cost 1. ``criterion``: the task's success rule per rollout
    (``rule(states, valid)``, :func:`success_rule`); without ``rule`` the same as ``upright``. Pure
    for a simulated system (jittable); a host-stepped one is stepped from Python."""
    trajs = rollouts(keys, task, policy)
    fallen_steps = task.problem.horizon - jnp.sum(trajs.valid, axis=-1)
    upright = jnp.all(trajs.valid, axis=-1)
    ok = rule(trajs.states, trajs.valid) if rule is not None else upright
    return trajs.total_cost + fallen_steps, upright, ok


def predict_particles(key, problem: Problem, rcfg, store: int, policy, model):
    """The stored prediction of a trial: the first ``store`` particles' states (T+1, store, D) and
    the mean predicted cost per step, from one particle rollout of the optimised policy. Pure."""
    from pipps.particles.forward import particle_rollout, sample_noise

    rec = particle_rollout(problem, policy, model, sample_noise(key, problem, rcfg), rcfg, jacobian=False)
    xs = jnp.concatenate([rec.x[:1], rec.x_next], axis=0)  # (T+1, P, D)
    return xs[:, :store], jnp.mean(rec.cost, axis=1)


class Optimized(NamedTuple):
    """One seed's policy optimisation: the new policy and what the trial records of it."""

    policy: Any
    trace: StepTrace | SearchTrace
    diagnostics: Diagnostics | None
    predicted: ParticlePrediction | MomentPrediction


#: ``optimize(keys, policies, models, progress) -> [Optimized]``, one entry per seed
Optimize = Callable[[Sequence, Sequence, Sequence, Progress], list[Optimized]]


class Programs:
    """The compiled pieces of one experiment, or one batch of its seeds, built once and reused across trials."""

    def __init__(self, cfg: ExperimentConfig, task: Task, axis=ONE_SEED):
        self.cfg, self.task, self.axis = cfg, task, axis
        rule = success_rule(cfg)
        # a host-stepped system is stepped from Python, seed by seed (batched.check_batchable keeps it unbatched)
        program = (lambda fn: fn) if task.host_stepped else axis.compile
        self.trial_random = program(lambda k: rollout(k, task, None))
        self.evaluate_random = program(lambda keys: evaluate_rollouts(keys, task, None, rule))
        self.trial = program(lambda k, p: rollout(k, task, p))
        self.evaluate = program(lambda keys, p: evaluate_rollouts(keys, task, p, rule))
        build = {MOMENTUM: _momentum_optimizer, FIXED_SEED: _fixed_seed_optimizer, PILCO_SEARCH: _pilco_optimizer}
        self.optimize: Optimize = build[cfg.method_spec.optimizer](cfg, task.problem, axis)


def shape_groups(trees) -> list[list[int]]:
    """Indices of the pytrees grouped by structure and leaf shapes: the seeds one compiled model takes
    (one group unless a batch mixes full GPs and FITC, or low-rank variances of different ranks)."""
    groups: dict = {}
    for j, tree in enumerate(trees):
        leaves, treedef = jax.tree_util.tree_flatten(tree)
        groups.setdefault((treedef, tuple(np.shape(a) for a in leaves)), []).append(j)
    return list(groups.values())


def _momentum_optimizer(cfg: ExperimentConfig, problem: Problem, axis) -> Optimize:
    """The estimator's gradient with normalized momentum, ``policy_evals`` steps in chunks of
    ``progress_chunk`` (each a compiled scan), every seed of a shape group on the axis at once."""
    from pipps.optimizers.normalized import normalized_momentum
    from pipps.propagation.update import init_policy_opt_state, make_policy_optimizer

    rcfg, est = particle_method(cfg)
    opt = normalized_momentum(cfg.learning_rate, cfg.momentum)
    init = axis.compile(lambda k, p, m: init_policy_opt_state(k, p, m, problem=problem, config=rcfg, estimator=est,
                                                               optimizer=opt))
    steps = axis.compile_steps(make_policy_optimizer(problem, rcfg, est, opt))
    predict = axis.compile(lambda k, p, m: predict_particles(k, problem, rcfg, cfg.store_particles, p, m))
    chunk = min(cfg.progress_chunk, cfg.policy_evals)

    def optimize(keys, policies, models, progress: Progress) -> list[Optimized]:
        out: list = [None] * len(keys)
        for group in shape_groups(models):
            k_init, k_run, k_pred = zip(*(jax.random.split(keys[j], 3) for j in group))
            model = axis.stack([models[j] for j in group])
            state = init(axis.stack(k_init), axis.stack([policies[j] for j in group]), model)
            infos, done, start = [], 0, time.perf_counter()
            while done < cfg.policy_evals:
                n = min(chunk, cfg.policy_evals - done)
                state, info = steps(axis.stack([jax.random.fold_in(k, done) for k in k_run]), state, model, n)
                info = jax.device_get(info)
                infos.append(info)
                done += n
                last = [axis.take(info, j).value[-1] for j in range(len(group))]
                progress(dict(phase="optimize", step=done, steps=cfg.policy_evals, objective=float(np.mean(last)),
                              seconds=time.perf_counter() - start))
            xs, cost = jax.device_get(predict(axis.stack(k_pred), state.policy, model))
            for j, s in enumerate(group):
                trace, diagnostics = step_report([axis.take(i, j) for i in infos])
                predicted = ParticlePrediction(np.asarray(axis.take(xs, j)), np.asarray(axis.take(cost, j)))
                out[s] = Optimized(axis.take(state.policy, j), trace, diagnostics, predicted)
        return out

    return optimize


def step_report(infos) -> tuple[StepTrace, Diagnostics]:
    """(trace, diagnostics) of a policy optimisation from its chunks of per-step infos (host arrays)."""
    cat = lambda f: np.concatenate([f(i) for i in infos])  # noqa: E731
    diag = lambda f: cat(lambda i: np.asarray(f(i.diagnostics)))  # noqa: E731
    trace = StepTrace(cat(lambda i: i.value), cat(lambda i: i.particle_objective), cat(lambda i: i.grad_norm),
                      cat(lambda i: i.skipped))
    with np.errstate(all="ignore"):
        k_lr, var_rp, var_lr = diag(lambda d: d.k_lr), diag(lambda d: d.var_rp), diag(lambda d: d.var_lr)
        diagnostics = Diagnostics(k_lr=_nanmean(k_lr, 0), var_rp=_nanmean(var_rp, 0), var_lr=_nanmean(var_lr, 0),
                                  k_lr_per_iteration=_nanmean(k_lr, 1),
                                  nonfinite_steps=diag(lambda d: d.nonfinite).sum(0))
    return trace, diagnostics


def _nanmean(a: np.ndarray, axis: int) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    finite = np.isfinite(a)
    n = finite.sum(axis)
    return np.where(n > 0, np.where(finite, a, 0.0).sum(axis) / np.maximum(n, 1), np.nan)


def _search_trace(trace) -> SearchTrace:
    t = jax.device_get(trace)
    n = int(t.num_linesearches) + 1
    return SearchTrace(np.asarray(t.values)[:n], np.asarray(t.evaluations)[:n], np.asarray(t.failed)[:n],
                       np.asarray(t.stop_reason))


def _per_seed(optimize_one) -> Optimize:
    """A quasi-Newton search has data-dependent line searches: the seeds of a batch run one by one."""
    return lambda keys, policies, models, progress: [optimize_one(k, p, m, progress)
                                                     for k, p, m in zip(keys, policies, models)]


def _fixed_seed_optimizer(cfg: ExperimentConfig, problem: Problem, axis) -> Optimize:
    from pipps.optimizers.quasi_newton import QuasiNewtonConfig
    from pipps.propagation.fixed_seed import optimize_fixed_seed

    del axis
    rcfg = rollout_config(cfg)
    qn = QuasiNewtonConfig(length=-cfg.policy_evals, max_evals_per_linesearch=30)
    search = jax.jit(lambda key, policy, model: optimize_fixed_seed(key, policy, model, problem=problem, config=rcfg,
                                                                     qn_config=qn))
    predict = jax.jit(lambda key, policy, model: predict_particles(key, problem, rcfg, cfg.store_particles, policy, model))

    def optimize_one(key, policy, model, progress: Progress) -> Optimized:
        start = time.perf_counter()
        new, trace = search(key, policy, model)
        trace = _search_trace(trace)
        progress(dict(phase="optimize", step=cfg.policy_evals, steps=cfg.policy_evals,
                      objective=float(trace.value[-1]), seconds=time.perf_counter() - start))
        xs, cost = predict(key, new, model)  # the fixed seed's own particles
        return Optimized(new, trace, None, ParticlePrediction(np.asarray(xs), np.asarray(cost)))

    return _per_seed(optimize_one)


def check_moment_matching(cfg: ExperimentConfig, problem: Problem) -> None:
    """Raise ``ValueError`` when ``cfg``'s method plans by moment matching and the task's cost has no
    Gaussian expectation (``cost.expected(mean, cov)``) to plan with."""
    if cfg.is_pilco and not callable(getattr(problem.cost, "expected", None)):
        raise ValueError(f"method {cfg.method}: the cost of {cfg.task} has no Gaussian expectation (expected(mean, "
                         "cov)) to plan with; use a particle method, or a cost that has one (pipps.costs.SaturatingCost)")


def _pilco_optimizer(cfg: ExperimentConfig, problem: Problem, axis) -> Optimize:
    from pipps.pilco import PolicySearchConfig, optimize_policy, pilco_budget, trajectory

    del axis
    check_moment_matching(cfg, problem)
    budget = pilco_budget(problem) if cfg.pilco_linesearches is None else pilco_budget(problem, length=cfg.pilco_linesearches)
    search_cfg = PolicySearchConfig(optimizer=budget, horizon=cfg.horizon, policy_noise=cfg.pilco_policy_noise)
    predict = jax.jit(lambda policy, model: trajectory(problem, policy, model, horizon=cfg.horizon,
                                                       policy_noise=cfg.pilco_policy_noise))

    def optimize_one(key, policy, model, progress: Progress) -> Optimized:
        del key
        start = time.perf_counter()
        new, trace = optimize_policy(problem, model, policy, search_cfg)
        trace = _search_trace(trace)
        progress(dict(phase="optimize", step=1, steps=1, objective=float(trace.value[-1]),
                      seconds=time.perf_counter() - start))
        traj = jax.device_get(predict(new, model))
        pred = MomentPrediction(np.asarray(traj.means), np.asarray(traj.covs), np.asarray(traj.cost_mean))
        return Optimized(new, trace, None, pred)

    return _per_seed(optimize_one)
