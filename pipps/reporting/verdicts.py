"""The verdict on an experiment: its task's success criterion, per rollout, then per seed.

Every place that says whether an experiment succeeded asks :func:`verdict`: a result's
``success`` (:attr:`pipps.experiments.records.ExperimentResult.success`), the result file's
``success`` and ``return_success`` attributes, the tables and their readings, the figures and the
command line. The criterion is the task's (:class:`pipps.tasks.Success`, from its record under the
experiment's settings, :func:`criterion`):

* **per rollout**: the task's rule, applied to each of the final trial's evaluation rollouts on
  the true system when they ran (stored per rollout as ``eval_balanced``); for a rule that is
  "never fell" (:func:`pipps.tasks.never_fell`, the unicycle's) the stored ``eval_upright``
  flags are the same thing and are read instead, so files written before the criterion's flags
  were stored are judged alike;
* **per seed**: the experiment succeeds when at least the criterion's ``fraction`` of those
  rollouts pass; where the task has a return threshold (the cart-pole's, 15), the thesis'
  counting, a mean evaluated return below it, is the second verdict, reported beside the first
  (the physical one decides where they differ; docs/results-analyses.md "The physical criterion").

A cart-pole file written before the per-rollout flags were stored has none: the tables re-simulate
its final evaluation (:class:`pipps.experiments.resimulate.Resimulator`), and a result read without
them falls back to the return verdict (:func:`judge_trial`).

:func:`flip_probability_fraction` and :func:`flip_probability_return` say how sure a verdict is:
the probability that a fresh evaluation of the same policy (as many rollouts) lands on the other
side of the criterion.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np


class Verdict(NamedTuple):
    """One experiment's verdict on its final trial's evaluation rollouts."""

    success: bool  # at least `required` of the rollouts meet the task's criterion (decides)
    fraction: float  # the fraction that does
    required: float  # the criterion's per-seed fraction
    return_success: bool | None  # the mean evaluated return is below the task's threshold; None: it has none
    threshold: float | None  # that threshold


def criterion(cfg):
    """The :class:`pipps.tasks.Success` of ``cfg``'s task under its settings."""
    return cfg.task_spec.success_for(cfg)


def reads_upright(success) -> bool:
    """Whether the criterion's per-rollout flags are the stored ``eval_upright`` (a "never fell" rule)."""
    from pipps.tasks.spec import never_fell

    return success.rule is never_fell


def verdict(cfg, returns, flags) -> Verdict:
    """THE verdict: ``flags`` (the task's rule per final evaluation rollout) against the criterion's
    fraction, and the mean of ``returns`` against the task's threshold where it has one."""
    success = criterion(cfg)
    fraction = float(np.mean(flags))
    threshold = success.threshold
    by_return = None if threshold is None else bool(float(np.mean(returns)) < threshold)
    return Verdict(bool(fraction >= success.fraction), fraction, success.fraction, by_return, threshold)


def final_flags(cfg, trial) -> np.ndarray | None:
    """The criterion's flags per evaluation rollout of a trial (a :class:`TrialResult`), or None for a
    file written before they were stored whose criterion is not "never fell"."""
    return trial.eval_upright if reads_upright(criterion(cfg)) else trial.eval_balanced


def judge_trial(cfg, trial) -> bool:
    """The physical verdict on a trial (:func:`verdict`); without stored flags (a cart-pole file from
    before they were stored) the return verdict (``pipps table`` re-simulates those instead)."""
    flags = final_flags(cfg, trial)
    if flags is None:
        return bool(judge_return(cfg, trial))
    return verdict(cfg, trial.eval_returns, flags).success


def judge_return(cfg, trial) -> bool | None:
    """The thesis' return verdict on a trial: its evaluated return below the task's threshold (None: no threshold)."""
    threshold = criterion(cfg).threshold
    return None if threshold is None else bool(trial.eval_return < threshold)


def system_trial_success(cfg, states, valid) -> bool | None:
    """Whether the trial run on the system (the one the learner saw) meets the criterion's rule;
    None where the summary lacks the trial."""
    if states is None or valid is None:
        return None
    return bool(criterion(cfg).rule(np.asarray(states), np.asarray(valid)))


def flip_probability_fraction(successes: int, n: int, required: float) -> float:
    """The probability that a fresh evaluation with ``n`` rollouts crosses the fraction criterion the
    other way: the predictive (beta-binomial, Jeffreys prior) probability of the fresh count landing
    on the other side of ``ceil(required·n)`` than the observed ``successes``."""
    if n <= 0:
        return math.nan
    from scipy.stats import betabinom

    need = math.ceil(required * n - 1e-12)
    fresh = betabinom(n, successes + 0.5, n - successes + 0.5)
    return float(fresh.cdf(need - 1)) if successes >= need else float(fresh.sf(need - 1))


def flip_probability_return(returns, threshold: float) -> float:
    """The probability that a fresh mean of as many rollouts lands on the other side of ``threshold``:
    fresh − observed mean ~ N(0, 2·SE²) with SE the standard error of the stored mean."""
    r = np.asarray(returns, dtype=float)
    if r.size < 2:
        return math.nan
    se = float(np.std(r, ddof=1) / math.sqrt(r.size))
    gap = abs(float(np.mean(r)) - threshold)
    if se == 0.0:
        return 0.0 if gap > 0 else 0.5
    return 0.5 * math.erfc(gap / (2.0 * se))  # Φ(−gap/(√2·SE)) = ½ erfc(gap/(2·SE))


def standard_error(returns) -> float:
    r = np.asarray(returns, dtype=float)
    return float(np.std(r, ddof=1) / math.sqrt(r.size)) if r.size >= 2 else math.nan

