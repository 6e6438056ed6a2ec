"""The episodic learning loop (thesis Algorithm 1, §4.5.3; experiments.md "Episodic learning protocol").

``run_experiment(cfg)`` runs ``num_random`` random trials, then ``num_learned`` times: train one
GP per state dimension on all data → optimise the policy on the model with the chosen method →
run one trial on the true system with the policy and append its transitions. After every trial
the current policy is evaluated by ``eval_rollouts`` extra true-system rollouts that are never
used for learning. Success is judged on the final trial's evaluation (:func:`judge_success`).

I/O stays outside: the loop reports through two callbacks, ``progress(event)`` for a display and
``on_trial(result)`` after every finished trial (the CLI writes the HDF5 file there, so a run that
fails part-way keeps every trial it finished). Each compiled program is built once per experiment
and reused across trials; data are padded to multiples of ``gp_chunk`` so the programs compile
once per capacity, not once per trial.

**Resuming.** ``run_experiment(cfg, resume=partial)`` continues an experiment from the trials a
partial result holds (a killed or failed run's file): the policy is the last stored one, the data
are rebuilt from the stored observations, actions and validity flags, the GP warm start from the
last stored hyperparameters and FITC inducing inputs, and every trial's keys are
``fold_in(seed's trial key, trial index)``. That is everything the next trial depends on, so a
resumed experiment equals an uninterrupted one exactly (tested); ``resumed_at`` records where it
was picked up.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from pipps.experiments.config import QUICK_CENTRE_HIGH, QUICK_CENTRE_LOW, ExperimentConfig, config_difference, same_experiment
from pipps.experiments.methods import FIXED_SEED, MOMENTUM, PILCO_SEARCH, particle_method, rollout_config
from pipps.gp import FitState, GPConfig, GPHyper, fit, make_data, pad_to_capacity
from pipps.policies import init_linear_policy, init_pilco_rbf_policy, init_rbf_policy, init_rbf_policy_uniform
from pipps.precision import require_float64
from pipps.rollout import Trajectory, rollout, training_pairs
from pipps.tasks.base import Task
from pipps.tasks.presets import make_task

Progress = Callable[[dict[str, Any]], None]


@dataclasses.dataclass
class TrialResult:
    """One trial: what was run on the true system, how the policy was found, how it evaluates.

    Array shapes: H steps, S simulator dims, F controls, R evaluation rollouts, n policy steps,
    T planning horizon, D model dims.
    """

    index: int
    kind: str  # "random" or "learned"
    states: np.ndarray  # (H+1, S) the trial's true states
    observations: np.ndarray  # (H+1, S) what the learner saw
    actions: np.ndarray  # (H, F)
    costs: np.ndarray  # (H,) true cost of each transition (0 after a fall)
    valid: np.ndarray  # (H,) bool
    eval_returns: np.ndarray  # (R,) evaluation returns (fallen steps charged cost 1)
    eval_upright: np.ndarray  # (R,) bool: the rollout never fell (always True for the cart-pole)
    policy: np.ndarray  # (n_θ,) flattened policy parameters used for this trial (random: the initial policy)
    timings: dict[str, float]  # seconds: gp, optimize, trial, evaluate, total
    gp_hyper: dict[str, np.ndarray] | None = None  # log_lengthscale (E, Dz), log_signal (E,), log_noise (E,)
    gp_info: dict[str, Any] | None = None  # sparse, num_points, objective, messages
    opt_trace: dict[str, np.ndarray] | None = None  # per policy step (or QN line search) values
    diagnostics: dict[str, np.ndarray] | None = None  # per time step k_LR, σ²_RP, σ²_LR (means over steps)
    predicted: dict[str, np.ndarray] | None = None  # particles (T+1, S_p, D) or PILCO means/covs
    # (R,) bool: the physical criterion per evaluation rollout (cart-pole: balanced at the end,
    # pipps.experiments.criteria; unicycle: upright); None in files written before it was stored
    eval_balanced: np.ndarray | None = None

    @property
    def eval_return(self) -> float:
        return float(np.mean(self.eval_returns))

    @property
    def upright_fraction(self) -> float:
        return float(np.mean(self.eval_upright))

    @property
    def balanced_fraction(self) -> float:
        """Fraction of evaluation rollouts meeting the physical criterion (NaN where not stored)."""
        return float(np.mean(self.eval_balanced)) if self.eval_balanced is not None else math.nan


@dataclasses.dataclass
class ExperimentResult:
    config: ExperimentConfig
    trials: list[TrialResult]
    status: str = "running"  # running | complete | failed
    error: str = ""
    wall_seconds: float = 0.0  # summed over the sessions that ran it (see resumed_at)
    resumed_at: list[int] = dataclasses.field(default_factory=list)  # trial indices a resumed session began at

    @property
    def final_return(self) -> float:
        return self.trials[-1].eval_return if self.trials else math.nan

    @property
    def success(self) -> bool:
        return self.status == "complete" and judge_success(self.config, self.trials[-1])


def judge_success(cfg: ExperimentConfig, trial: TrialResult) -> bool:
    """The physical verdict (pipps.experiments.criteria): cart-pole, at least ``balanced_fraction``
    of the evaluation rollouts end balanced; unicycle, at least ``upright_fraction`` stay upright
    for the episode. A cart-pole trial from a file written before the criterion was stored has no
    per-rollout flags: it falls back to the return verdict (``pipps table`` re-simulates those)."""
    if cfg.task == "unicycle":
        return trial.upright_fraction >= cfg.upright_fraction
    if trial.eval_balanced is None:
        return judge_return(cfg, trial)
    return trial.balanced_fraction >= cfg.balanced_fraction


def judge_return(cfg: ExperimentConfig, trial: TrialResult) -> bool:
    """The thesis' return verdict: the final evaluated return below ``success_threshold`` (cart-pole)."""
    return trial.eval_return < cfg.success_threshold


def make_experiment_task(cfg: ExperimentConfig) -> Task:
    """The task of an experiment (cost, noise multiplier, horizon)."""
    overrides = {} if cfg.horizon is None else {"horizon": cfg.horizon}
    cost = cfg.cost
    if cfg.cost_scale != 1.0:
        import pipps.costs

        if (cost or "angle") != "angle" or cfg.task == "unicycle":
            raise ValueError("cost_scale: only the cart-pole Angle Cost takes a scale")
        cost = pipps.costs.cartpole_angle_cost(scale=cfg.cost_scale)
    return make_task(cfg.task, preset=cfg.preset, k=cfg.k, cost=cost, **overrides)


def policy_start_moments(task: Task) -> tuple[np.ndarray, np.ndarray]:
    """The planning start distribution in policy-input coordinates (trig-augmented where needed)."""
    mean, cov = np.asarray(task.model_init_mean), np.asarray(task.model_init_cov)
    if task.angle_idx:
        from pipps.gaussian import trig_augment

        m, c, _ = trig_augment(jnp.asarray(mean), jnp.asarray(cov), task.angle_idx)
        mean, cov = np.asarray(m), np.asarray(c)
    idx = np.asarray(task.policy_input_idx)
    return mean[idx], cov[np.ix_(idx, idx)]


def init_policy(key: jax.Array, cfg: ExperimentConfig, task: Task):
    """The initial policy (experiments.md "Resolved choices"; the ``quick`` departure)."""
    d = task.policy_input_dim
    lam = np.asarray(cfg.log_lambda_init, dtype=float)
    if lam.size not in (1, d):
        raise ValueError(f"log_lambda_init: needs 1 or {d} values for this task's policy input, got {lam.size}")
    if cfg.policy == "linear":
        return init_linear_policy(key, d, task.u_max)
    mean, cov = policy_start_moments(task)
    if cfg.centre_std is not None:  # the author's demo: centres at the start mean plus N(0, 1) noise
        cov = cfg.centre_std**2 * np.eye(d)
    if cfg.policy == "pilco_rbf":
        return init_pilco_rbf_policy(key, cfg.num_basis, mean, cov, task.u_max)
    if cfg.policy_init == "uniform":
        if d != len(QUICK_CENTRE_LOW):
            raise ValueError("policy_init=uniform needs the raw 4-dim cart-pole policy input (thesis preset)")
        return init_rbf_policy_uniform(key, cfg.num_basis, QUICK_CENTRE_LOW, QUICK_CENTRE_HIGH, task.u_max,
                                       log_lambda=lam, weight_scale=cfg.weight_scale)
    return init_rbf_policy(key, cfg.num_basis, mean, cov, task.u_max, log_lambda=lam, weight_scale=cfg.weight_scale)


def gp_config(cfg: ExperimentConfig) -> GPConfig:
    return GPConfig(max_iters=cfg.gp_max_iters, fitc_threshold=cfg.fitc_threshold, num_inducing=cfg.num_inducing,
                    fitc_iters=cfg.fitc_iters, fitc_first_iters=cfg.fitc_first_iters)


def balance_settings(cfg: ExperimentConfig) -> tuple[int, float, float]:
    """The cart-pole's physical criterion of ``cfg`` as :func:`pipps.experiments.criteria.balanced` takes it."""
    return cfg.balance_steps, cfg.balance_angle, cfg.balance_position


def evaluate_rollouts(keys, task: Task, policy, balance: tuple[int, float, float] | None = None):
    """(returns, upright, balanced) of one true-system rollout per key with ``policy`` (None: random
    actions); fallen steps are charged cost 1. ``balanced``: the cart-pole's physical criterion
    with ``balance = (steps, angle, position)`` (:mod:`pipps.experiments.criteria`); elsewhere, or
    without ``balance``, the same as ``upright``. Pure."""
    from pipps.experiments.criteria import balanced, is_cartpole

    trajs = jax.vmap(lambda k: rollout(k, task, policy))(keys)
    fallen_steps = task.horizon - jnp.sum(trajs.valid, axis=-1)
    upright = jnp.all(trajs.valid, axis=-1)
    ok = balanced(trajs.states, *balance) if balance is not None and is_cartpole(task.name) else upright
    return trajs.total_cost + fallen_steps, upright, ok


class _Programs:
    """The compiled pieces of one experiment, built once and reused across trials."""

    def __init__(self, cfg: ExperimentConfig, task: Task):
        self.cfg, self.task = cfg, task
        balance = balance_settings(cfg)
        self.evaluate = jax.jit(lambda keys, policy: evaluate_rollouts(keys, task, policy, balance))
        self.evaluate_random = jax.jit(lambda keys: evaluate_rollouts(keys, task, None, balance))
        self.trial = jax.jit(lambda key, policy: rollout(key, task, policy))
        self.trial_random = jax.jit(lambda key: rollout(key, task, None))
        self.optimizer = _make_optimizer(cfg, task)


def _make_optimizer(cfg: ExperimentConfig, task: Task):
    """``optimize(key, policy, model, progress) -> (policy, trace dict, diagnostics dict, predicted dict)``."""
    build = {MOMENTUM: _stochastic_optimizer, FIXED_SEED: _fixed_seed_optimizer, PILCO_SEARCH: _pilco_optimizer}
    return build[cfg.method_spec.optimizer](cfg, task)


def predict_particles(key, task: Task, rcfg, store: int, policy, model):
    """The stored prediction of a trial: the first ``store`` particles' states (T+1, store, D) and
    the mean predicted cost per step, from one particle rollout of the optimised policy. Pure."""
    from pipps.particles.forward import particle_rollout, sample_noise

    rec = particle_rollout(task, policy, model, sample_noise(key, task, rcfg), rcfg, jacobian=False)
    xs = jnp.concatenate([rec.x[:1], rec.x_next], axis=0)  # (T+1, P, D)
    return xs[:, :store], jnp.mean(rec.cost, axis=1)


def _particle_prediction(task: Task, rcfg, store: int):
    predict = jax.jit(lambda key, policy, model: predict_particles(key, task, rcfg, store, policy, model))

    def run(key, policy, model):
        xs, cost = predict(key, policy, model)
        return {"particles": np.asarray(xs), "cost_mean": np.asarray(cost)}

    return run


def _stochastic_optimizer(cfg: ExperimentConfig, task: Task):
    from pipps.optimizers.normalized import normalized_momentum
    from pipps.propagation.update import init_policy_opt_state, make_policy_optimizer

    rcfg, est = particle_method(cfg)
    opt = normalized_momentum(cfg.learning_rate, cfg.momentum)
    run = make_policy_optimizer(task, rcfg, est, opt)
    init = jax.jit(lambda key, policy, model: init_policy_opt_state(
        key, policy, model, task=task, config=rcfg, estimator=est, optimizer=opt))
    predict = _particle_prediction(task, rcfg, cfg.store_particles)
    chunk = min(cfg.progress_chunk, cfg.policy_evals)

    def optimize(key, policy, model, progress: Progress):
        k_init, k_run, k_pred = jax.random.split(key, 3)
        state = init(k_init, policy, model)
        infos, done, start = [], 0, time.perf_counter()
        while done < cfg.policy_evals:
            n = min(chunk, cfg.policy_evals - done)
            state, info = run(jax.random.fold_in(k_run, done), state, model, num_steps=n)
            info = jax.device_get(info)
            infos.append(info)
            done += n
            progress(dict(phase="optimize", step=done, steps=cfg.policy_evals, objective=float(info.value[-1]),
                          seconds=time.perf_counter() - start))
        trace, diagnostics = step_report(infos)
        return state.policy, trace, diagnostics, predict(k_pred, state.policy, model)

    return optimize


def step_report(infos) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """(trace, diagnostics) of a policy optimisation from its chunks of per-step infos (host arrays)."""
    cat = lambda f: np.concatenate([f(i) for i in infos])  # noqa: E731
    diag = lambda f: cat(lambda i: np.asarray(f(i.diagnostics)))  # noqa: E731
    trace = {"value": cat(lambda i: i.value), "particle_objective": cat(lambda i: i.particle_objective),
             "grad_norm": cat(lambda i: i.grad_norm), "skipped": cat(lambda i: i.skipped)}
    with np.errstate(all="ignore"):
        k_lr, var_rp, var_lr = diag(lambda d: d.k_lr), diag(lambda d: d.var_rp), diag(lambda d: d.var_lr)
        diagnostics = {
            "k_lr": _nanmean(k_lr, 0), "var_rp": _nanmean(var_rp, 0), "var_lr": _nanmean(var_lr, 0),
            "k_lr_per_iteration": _nanmean(k_lr, 1), "nonfinite_steps": diag(lambda d: d.nonfinite).sum(0),
        }
    return trace, diagnostics


def _nanmean(a: np.ndarray, axis: int) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    finite = np.isfinite(a)
    n = finite.sum(axis)
    return np.where(n > 0, np.where(finite, a, 0.0).sum(axis) / np.maximum(n, 1), np.nan)


def _qn_trace(trace) -> dict[str, np.ndarray]:
    t = jax.device_get(trace)
    n = int(t.num_linesearches) + 1
    return {"value": np.asarray(t.values)[:n], "evaluations": np.asarray(t.evaluations)[:n],
            "failed": np.asarray(t.failed)[:n], "stop_reason": np.asarray(t.stop_reason)}


def _fixed_seed_optimizer(cfg: ExperimentConfig, task: Task):
    from pipps.optimizers.quasi_newton import QuasiNewtonConfig
    from pipps.propagation.fixed_seed import optimize_fixed_seed

    rcfg = rollout_config(cfg)
    qn = QuasiNewtonConfig(length=-cfg.policy_evals, max_evals_per_linesearch=30)
    search = jax.jit(lambda key, policy, model: optimize_fixed_seed(key, policy, model, task=task, config=rcfg,
                                                                     qn_config=qn))
    predict = _particle_prediction(task, rcfg, cfg.store_particles)

    def optimize(key, policy, model, progress: Progress):
        start = time.perf_counter()
        new, trace = search(key, policy, model)
        trace = _qn_trace(trace)
        progress(dict(phase="optimize", step=cfg.policy_evals, steps=cfg.policy_evals,
                      objective=float(trace["value"][-1]), seconds=time.perf_counter() - start))
        return new, trace, None, predict(key, new, model)  # the fixed seed's own particles

    return optimize


def _pilco_optimizer(cfg: ExperimentConfig, task: Task):
    from pipps.pilco import PolicySearchConfig, optimize_policy, pilco_budget, trajectory

    budget = pilco_budget(task) if cfg.pilco_linesearches is None else pilco_budget(task, length=cfg.pilco_linesearches)
    search_cfg = PolicySearchConfig(optimizer=budget, horizon=cfg.horizon)
    predict = jax.jit(lambda policy, model: trajectory(task, policy, model, horizon=cfg.horizon))

    def optimize(key, policy, model, progress: Progress):
        del key
        start = time.perf_counter()
        new, trace = optimize_policy(task, model, policy, search_cfg)
        trace = _qn_trace(trace)
        progress(dict(phase="optimize", step=1, steps=1, objective=float(trace["value"][-1]),
                      seconds=time.perf_counter() - start))
        traj = jax.device_get(predict(new, model))
        pred = {"mean": np.asarray(traj.means), "cov": np.asarray(traj.covs), "cost_mean": np.asarray(traj.cost_mean)}
        return new, trace, None, pred

    return optimize


def _trial_from(index, kind, traj, evals, policy_flat, timings) -> TrialResult:
    traj = jax.device_get(traj)
    returns, upright, ok = (np.asarray(a) for a in jax.device_get(evals))
    return TrialResult(index, kind, np.asarray(traj.states), np.asarray(traj.observations),
                       np.asarray(traj.actions), np.asarray(traj.costs), np.asarray(traj.valid),
                       returns, upright, policy_flat, timings, eval_balanced=ok)


def record_gp(trial: TrialResult, post, info) -> None:
    """Store a learned trial's GP: hyperparameters, training report, and FITC's inducing inputs
    (with the data and hyperparameters they rebuild the model)."""
    hyper = jax.device_get(post.hyper)
    trial.gp_hyper = {"log_lengthscale": np.asarray(hyper.log_lengthscale),
                      "log_signal": np.asarray(hyper.log_signal), "log_noise": np.asarray(hyper.log_noise)}
    trial.gp_info = {"sparse": bool(info.sparse), "num_points": int(info.num_points),
                     "objective": np.asarray(info.hyper.objective), "messages": "\n".join(info.messages)}
    if info.sparse:
        trial.gp_info["inducing"] = np.asarray(post.inputs)


def planning_model(cfg: ExperimentConfig, post, data, info):
    """The model the policy is optimised on: the posterior itself, or with ``variance_tol > 0`` under
    a particle method that uses the variance, its certified low-rank form (:mod:`pipps.gp.lowrank`;
    full GP or FITC). Returns ``(model, ranks or None)``."""
    if cfg.variance_tol <= 0 or "variance_tol" not in cfg.method_spec.settings:
        return post, None
    from pipps.gp.lowrank import low_rank_model

    return low_rank_model(post, data, cfg.variance_tol, sparse=bool(info.sparse), jitter=info.posterior_jitter)


def stored_trajectory(trial: TrialResult) -> Trajectory:
    """A stored trial as the :class:`Trajectory` it was (device arrays), e.g. for :func:`training_pairs`."""
    return Trajectory(*(jnp.asarray(getattr(trial, n)) for n in Trajectory._fields))


def _check_finite_data(inputs: np.ndarray, targets: np.ndarray, trial: int) -> None:
    if not (np.isfinite(inputs).all() and np.isfinite(targets).all()):
        raise FloatingPointError(f"trial {trial}: the true-system rollout produced NaN/Inf training data")


def _check_resumable(cfg: ExperimentConfig, partial: ExperimentResult) -> None:
    if not same_experiment(partial.config, cfg):
        raise ValueError(f"resume: the partial result is of another configuration "
                         f"({config_difference(partial.config, cfg)})")
    if [t.index for t in partial.trials] != list(range(len(partial.trials))):
        raise ValueError(f"resume: the partial result's trials are {[t.index for t in partial.trials]}, "
                         "not 0, 1, ... in order")
    if len(partial.trials) > cfg.num_trials:
        raise ValueError(f"resume: {len(partial.trials)} trials stored, the configuration has {cfg.num_trials}")


def _fit_state_from(trials: list[TrialResult]) -> FitState | None:
    """The GP warm start the loop held after ``trials``: the last hyperparameters, the last inducing inputs."""
    learned = [t for t in trials if t.gp_hyper is not None]
    if not learned:
        return None
    h = learned[-1].gp_hyper
    hyper = GPHyper(*(jnp.asarray(h[n], jnp.float64) for n in ("log_lengthscale", "log_signal", "log_noise")))
    inducing = [t.gp_info["inducing"] for t in learned if t.gp_info and t.gp_info.get("inducing") is not None]
    return FitState(hyper, jnp.asarray(inducing[-1], jnp.float64) if inducing else None)


def run_experiment(
    cfg: ExperimentConfig,
    *,
    progress: Progress | None = None,
    on_trial: Callable[[ExperimentResult], None] | None = None,
    resume: ExperimentResult | None = None,
) -> ExperimentResult:
    """Run one experiment; see the module docstring. Raises what fails, after ``on_trial`` saw
    every finished trial and the result has ``status="failed"`` and the error message.

    ``resume``: a partial result of this same configuration (its trials 0..n−1); the run continues
    at trial n and returns the whole experiment."""
    require_float64("pipps.experiments.run_experiment")
    progress = progress or (lambda event: None)
    on_trial = on_trial or (lambda result: None)
    t_start = time.perf_counter()
    task = make_experiment_task(cfg)
    programs = _Programs(cfg, task)
    result = ExperimentResult(cfg, [])
    key = jax.random.PRNGKey(cfg.seed)
    k_policy, k_trials = jax.random.split(key)
    policy = init_policy(k_policy, cfg, task)
    flat = lambda p: np.asarray(ravel_pytree(p)[0])  # noqa: E731
    inputs, targets = [], []
    fit_state: FitState | None = None
    gpc = gp_config(cfg)
    wall_before = 0.0
    if resume is not None and resume.trials:
        _check_resumable(cfg, resume)
        result.trials = list(resume.trials)
        result.resumed_at = [*resume.resumed_at, len(resume.trials)]
        wall_before = resume.wall_seconds
        unravel = ravel_pytree(policy)[1]
        policy = unravel(jnp.asarray(resume.trials[-1].policy))
        for t in resume.trials:
            x_in, y_out = training_pairs(task, stored_trajectory(t))
            inputs.append(x_in)
            targets.append(y_out)
        fit_state = _fit_state_from(resume.trials)
    elapsed = lambda: wall_before + time.perf_counter() - t_start  # noqa: E731
    try:
        for i in range(len(result.trials), cfg.num_trials):
            k_trial, k_eval, k_opt, k_gp = jax.random.split(jax.random.fold_in(k_trials, i), 4)
            eval_keys = jax.random.split(k_eval, cfg.eval_rollouts)
            t0 = time.perf_counter()
            timings: dict[str, float] = {}
            progress(dict(phase="trial", trial=i, trials=cfg.num_trials))
            if i < cfg.num_random:
                traj = programs.trial_random(k_trial)
                t1 = time.perf_counter()
                evals = programs.evaluate_random(eval_keys)
                trial = _trial_from(i, "random", traj, evals, flat(policy), timings)
                timings.update(trial=t1 - t0, evaluate=time.perf_counter() - t1)
            else:
                data = pad_to_capacity(make_data(np.concatenate(inputs), np.concatenate(targets)), chunk=cfg.gp_chunk)
                progress(dict(phase="gp", trial=i, points=int(sum(len(a) for a in inputs))))
                post, fit_state, info = fit(k_gp, data, prev=fit_state, config=gpc)
                t1 = time.perf_counter()
                model, ranks = planning_model(cfg, post, data, info)
                policy, trace, diagnostics, predicted = programs.optimizer(k_opt, policy, model, progress)
                if not np.all(np.isfinite(flat(policy))):  # the update steps refuse NaN; a guard for the QN paths
                    raise FloatingPointError(f"trial {i}: the optimised policy parameters are not finite")
                t2 = time.perf_counter()
                traj = programs.trial(k_trial, policy)
                t3 = time.perf_counter()
                evals = programs.evaluate(eval_keys, policy)
                trial = _trial_from(i, "learned", traj, evals, flat(policy), timings)
                timings.update(gp=t1 - t0, optimize=t2 - t1, trial=t3 - t2, evaluate=time.perf_counter() - t3)
                record_gp(trial, post, info)
                trial.gp_info["capacity"] = int(data.inputs.shape[0])
                if ranks is not None:
                    trial.gp_info["variance_ranks"] = ranks
                    trial.gp_info["variance_bound"] = np.asarray(model.bound)
                trial.opt_trace, trial.diagnostics, trial.predicted = trace, diagnostics, predicted
            timings["total"] = time.perf_counter() - t0
            x_in, y_out = training_pairs(task, traj)
            _check_finite_data(x_in, y_out, i)
            inputs.append(x_in)
            targets.append(y_out)
            result.trials.append(trial)
            result.wall_seconds = elapsed()
            progress(dict(phase="evaluated", trial=i, trials=cfg.num_trials, eval_return=trial.eval_return,
                          upright=trial.upright_fraction, balanced=trial.balanced_fraction,
                          criterion="balanced" if cfg.task != "unicycle" else "upright", seconds=timings["total"]))
            on_trial(result)
    except BaseException as err:  # keep what finished, say what broke, re-raise
        result.status, result.error = "failed", f"{type(err).__name__}: {err}"
        result.wall_seconds = elapsed()
        on_trial(result)
        raise
    result.status = "complete"
    result.wall_seconds = elapsed()
    on_trial(result)
    return result
