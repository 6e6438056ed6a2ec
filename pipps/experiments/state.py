"""What an experiment starts from and what each trial leaves for the next (thesis Algorithm 1).

One seed's learning loop carries a :class:`SeedState`: the policy the last trial ran, the GP
training data of every finished trial, and the GP warm start. :func:`advance` moves it past one
trial *from what that trial records* (:class:`~pipps.experiments.records.TrialResult`), and
:func:`restore` is the same fold over a stored result's trials. The loop advances its own state
that way, so resuming an experiment from its file (the loop), rebuilding the model a trial planned
on (:func:`pipps.studies.snapshot.load_snapshot`) and choosing such a trial (the CLI) start from
exactly the state the uninterrupted run had.

Every random draw of trial ``i`` comes from :func:`trial_keys` (``fold_in`` of the seed's trial
key with ``i``), so nothing about a trial depends on how the trials before it were computed.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from pipps.experiments.config import ExperimentConfig
from pipps.experiments.records import ExperimentResult, GPRecord, TrialResult
from pipps.gp import FitState, GPConfig, GPData, GPHyper, make_data, pad_to_capacity
from pipps.policies import init_linear_policy, init_pilco_rbf_policy, init_rbf_policy, init_rbf_policy_uniform
from pipps.rollout import Trajectory, training_pairs
from pipps.tasks.base import Problem, Task

# -- the experiment's fixed pieces -------------------------------------------------------------------


def make_experiment_task(cfg: ExperimentConfig) -> Task:
    """The task of an experiment (task preset, noise multiplier, cost and its scale, horizon): its
    planning problem and its true system, as the task's record builds them
    (:meth:`pipps.tasks.TaskSpec.make`)."""
    overrides = {} if cfg.horizon is None else {"horizon": cfg.horizon}
    return cfg.task_spec.make(cfg.preset, cfg.k, cfg.cost, cfg.cost_scale, **overrides)


def policy_start_moments(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """The planning start distribution in policy-input coordinates (trig-augmented where needed)."""
    mean, cov = np.asarray(problem.model_init_mean), np.asarray(problem.model_init_cov)
    if problem.angle_idx:
        from pipps.gaussian import trig_augment

        m, c, _ = trig_augment(jnp.asarray(mean), jnp.asarray(cov), problem.angle_idx)
        mean, cov = np.asarray(m), np.asarray(c)
    idx = np.asarray(problem.policy_input_idx)
    return mean[idx], cov[np.ix_(idx, idx)]


def init_policy(key: jax.Array, cfg: ExperimentConfig, problem: Problem):
    """The initial policy (docs/experiments.md, "Presets"; the ``quick`` departure)."""
    d = problem.policy_input_dim
    lam = np.asarray(cfg.log_lambda_init, dtype=float)
    if lam.size not in (1, d):
        raise ValueError(f"log_lambda_init: needs 1 or {d} values for this task's policy input, got {lam.size}")
    if cfg.policy == "linear":
        return init_linear_policy(key, d, problem.u_max)
    mean, cov = policy_start_moments(problem)
    if cfg.centre_std is not None:  # the author's demo: centres at the start mean plus N(0, 1) noise
        cov = cfg.centre_std**2 * np.eye(d)
    if cfg.policy == "pilco_rbf":
        return init_pilco_rbf_policy(key, cfg.num_basis, mean, cov, problem.u_max)
    if cfg.policy_init == "uniform":
        box = cfg.task_spec.centre_box
        if box is None or d != len(box[0]):
            raise ValueError(f"policy_init=uniform needs the task's centre box over its {d}-dim policy input; "
                             f"{cfg.task} under task preset {cfg.preset} has " + ("none" if box is None else
                                                                                   f"one of {len(box[0])} dims"))
        return init_rbf_policy_uniform(key, cfg.num_basis, box[0], box[1], problem.u_max,
                                       log_lambda=lam, weight_scale=cfg.weight_scale)
    return init_rbf_policy(key, cfg.num_basis, mean, cov, problem.u_max, log_lambda=lam,
                           weight_scale=cfg.weight_scale)


def gp_config(cfg: ExperimentConfig) -> GPConfig:
    return GPConfig(max_iters=cfg.gp_max_iters, fitc_threshold=cfg.fitc_threshold, num_inducing=cfg.num_inducing,
                    fitc_iters=cfg.fitc_iters, fitc_first_iters=cfg.fitc_first_iters)


# -- keys ----------------------------------------------------------------------------------------------


class TrialKeys(NamedTuple):
    """The keys of one trial: its true-system rollout, its evaluation rollouts' parent, its policy
    optimisation, and its GP training (FITC's first inducing inputs)."""

    trial: jax.Array
    evaluate: jax.Array
    optimize: jax.Array
    gp: jax.Array


def _seed_keys(cfg: ExperimentConfig) -> tuple[jax.Array, jax.Array]:
    """(initial policy key, parent of the trial keys) of ``cfg``'s seed."""
    k_policy, k_trials = jax.random.split(jax.random.PRNGKey(cfg.seed))
    return k_policy, k_trials


def trial_keys(cfg: ExperimentConfig, index: int) -> TrialKeys:
    """Trial ``index``'s keys: ``fold_in`` of the seed's trial key with the index, split four ways."""
    return TrialKeys(*jax.random.split(jax.random.fold_in(_seed_keys(cfg)[1], index), 4))


def evaluation_keys(cfg: ExperimentConfig, index: int) -> jax.Array:
    """The ``eval_rollouts`` keys of trial ``index``'s evaluation rollouts."""
    return jax.random.split(trial_keys(cfg, index).evaluate, cfg.eval_rollouts)


# -- what a trial leaves for the next ----------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class SeedState:
    """What one seed's next trial depends on, besides its configuration and :func:`trial_keys`."""

    trial: int  # the next trial's index
    policy: Any  # pytree: the policy the last trial ran (before trial 0: the initial policy)
    inputs: tuple[np.ndarray, ...]  # GP training inputs, one block per finished trial
    targets: tuple[np.ndarray, ...]  # and their targets
    warm_start: FitState | None  # the last GP's hyperparameters and FITC inducing inputs; None before one

    @property
    def num_points(self) -> int:
        return int(sum(len(a) for a in self.inputs))

    def data(self, capacity: int | None = None, *, chunk: int = 100) -> GPData:
        """All training data, padded with masked rows to ``capacity`` (default: the next multiple of ``chunk``)."""
        return pad_to_capacity(make_data(np.concatenate(self.inputs), np.concatenate(self.targets)), capacity,
                               chunk=chunk)


def initial_state(cfg: ExperimentConfig, task: Task) -> SeedState:
    """The state before trial 0: the initial policy from the seed's key, no data, no GP."""
    return SeedState(0, init_policy(_seed_keys(cfg)[0], cfg, task.problem), (), (), None)


def stored_trajectory(trial: TrialResult) -> Trajectory:
    """A stored trial as the :class:`Trajectory` it was (device arrays), e.g. for :func:`training_pairs`."""
    return Trajectory(*(jnp.asarray(getattr(trial, n)) for n in Trajectory._fields))


def warm_start(gp: GPRecord, previous: FitState | None) -> FitState:
    """The GP warm start a trial's GP leaves: its hyperparameters, and its inducing inputs (FITC) or
    the last ones before it (a full GP keeps them for when the data outgrow it)."""
    hyper = GPHyper(*(jnp.asarray(getattr(gp, n), jnp.float64) for n in GPHyper._fields))
    if gp.inducing is not None:
        return FitState(hyper, jnp.asarray(gp.inducing, jnp.float64))
    return FitState(hyper, None if previous is None else previous.inducing)


def advance(state: SeedState, trial: TrialResult, task: Task) -> SeedState:
    """The state after ``trial`` (which must be trial ``state.trial``): the policy it ran, its
    transitions appended to the data, its GP as the warm start.

    Raises:
      ValueError: the trial is not the next one.
      FloatingPointError: its trajectory gives non-finite training data.
    """
    if trial.index != state.trial:
        raise ValueError(f"trial {trial.index} does not follow trial {state.trial - 1}")
    x_in, y_out = training_pairs(task, stored_trajectory(trial))
    if not (np.isfinite(x_in).all() and np.isfinite(y_out).all()):
        raise FloatingPointError(f"trial {trial.index}: the true-system rollout produced NaN/Inf training data")
    policy = ravel_pytree(state.policy)[1](jnp.asarray(trial.policy))
    fit = state.warm_start if trial.gp is None else warm_start(trial.gp, state.warm_start)
    return SeedState(trial.index + 1, policy, (*state.inputs, x_in), (*state.targets, y_out), fit)


def restore(result: ExperimentResult, trial: int | None = None, *, task: Task | None = None) -> SeedState:
    """The loop's state at the start of ``trial`` (default: after every stored trial), rebuilt from
    a result (a file's :func:`~pipps.experiments.results.read_result`): :func:`advance` over its
    trials ``0..trial−1`` from :func:`initial_state`. ``task``: the experiment's, if built already."""
    n = len(result.trials) if trial is None else trial
    if not 0 <= n <= len(result.trials):
        raise ValueError(f"trial {n}: the result holds trials 0-{len(result.trials) - 1}")
    task = make_experiment_task(result.config) if task is None else task
    state = initial_state(result.config, task)
    for t in result.trials[:n]:
        state = advance(state, t, task)
    return state


def rebuildable_trials(result: ExperimentResult) -> list[int]:
    """The learned trials whose model :func:`restore` and the trial's :class:`GPRecord` rebuild: full
    GPs, and FITC ones whose file stores the inducing inputs (files from before 2026-11-24 do not)."""
    return [t.index for t in result.trials if t.kind == "learned" and t.gp is not None and t.gp.rebuildable]
