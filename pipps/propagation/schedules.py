"""Sweep schedules: how the reverse sweeps make one estimate (a :class:`~pipps.propagation.pieces.Schedule`).

An estimate runs its estimator's schedule, whichever it is: ``schedule.sweep(problem, policy,
record, config, estimator, state) -> (state, SweepOutput)``.

* :func:`one_sweep` (every estimator's default): one reverse sweep over all particles
  (:func:`~pipps.propagation.backward.backward_sweep`).
* :func:`cross_fitted`: total propagation with cross-fitted weights, exactly unbiased with weights
  from this batch (docs/estimators.md, "Choosing k_LR"):

  1. the batch of P particles is split into halves A (particles 0…P/2−1) and B (the rest); the
     forward rollout is the usual one (particles do not interact forward);
  2. *pilot* sweeps: each half is swept alone — BIW weights over its own P/2 components only — with
     a weight source of its own (``pilot``: "leave_one_out" by default, "batch" or "split"; any
     source that reads only that half would do), and each half's per-step batch weights ``k_A``
     and ``k_B`` are read off: functions of that half's particles alone;
  3. *final* sweeps: half A is swept alone with the weights ``k_B``, half B with ``k_A`` (as a
     "previous" weight);
  4. the estimate is the mean over all P particles' contributions of the final sweeps.

  Half A's final sweep is a total propagation of P/2 particles whose every weight is a function of
  half B only, which is independent of half A: it is exactly unbiased (the "previous" argument),
  and likewise half B's. What it costs: four half sweeps (two full sweeps' VJPs; the BIW terms are
  2·(P/2)²·2 = P² against P², i.e. the same), and BIW mixes only P/2 components, which loses some of
  its variance reduction at small P. The sweeps are :func:`~pipps.propagation.backward.backward_sweep`,
  vmapped over the two halves; the combiner's own weight source is not used, and its state is
  passed on unchanged. The other pieces' states are threaded through the final sweeps and averaged
  over the two halves (for a "previous" baseline: the mean return over all P particles).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from pipps.particles.forward import ParticleRecord, RolloutConfig
from pipps.propagation.backward import backward_sweep
from pipps.propagation.pieces import EstimatorState, InitContext, StepDiagnostics, SweepOutput
from pipps.propagation.strategy import strategy
from pipps.propagation.weights import PreviousBatchWeight, PreviousWeight, weight_source
from pipps.tasks.base import Problem

PILOTS = ("leave_one_out", "batch", "split")


@strategy
class OneSweep:
    """One reverse sweep over all particles."""

    name = "one_sweep"

    def problem(self, estimator) -> None:
        del estimator
        return None

    def sweep(self, problem: Problem, policy, record: ParticleRecord, config: RolloutConfig, estimator,
              state: EstimatorState) -> tuple[EstimatorState, SweepOutput]:
        return backward_sweep(problem, policy, record, config, estimator, state)


def _halves(record: ParticleRecord) -> ParticleRecord:
    """(T, P, ...) fields → (2, T, P/2, ...): half 0 the first P/2 particles, half 1 the rest (any record type)."""

    def split(a):
        if a is None:
            return None
        T, P = a.shape[:2]
        return jnp.moveaxis(a.reshape(T, 2, P // 2, *a.shape[2:]), 1, 0)

    return type(record)(*(split(a) for a in record))


def _over_halves(a: jax.Array) -> jax.Array:
    """A piece's state from the two halves' (leading axis 2): their mean (all, for a flag)."""
    return jnp.all(a, axis=0) if a.dtype == bool else jnp.mean(a, axis=0)


def _no_extra_rollout():
    raise ValueError("a pilot weight source reads this batch only; it has no use for the extra rollout")


@strategy
class CrossFitted:
    """Total propagation with cross-fitted weights: pilot and final sweeps of two half-batches."""

    pilot: str = "leave_one_out"  # the pilot sweeps' weight source (static)

    name = "cross_fit"

    def __post_init__(self):
        if self.pilot not in PILOTS:
            raise ValueError(f"pilot must be one of {PILOTS}, got {self.pilot!r}")

    def problem(self, estimator) -> str | None:
        if estimator.combiner.num_parts != 2:
            return "cross-fitted weights need total propagation: a pathwise and an LR part"
        return None

    def sweep(self, problem: Problem, policy, record: ParticleRecord, config: RolloutConfig, estimator,
              state: EstimatorState) -> tuple[EstimatorState, SweepOutput]:
        """The pilot and final sweeps of the two halves; contributions (P, n_θ) in particle order."""
        T, P = record.x.shape[:2]
        if P % 2 or P < 8:
            raise ValueError(f"cross-fitted TP splits the batch in two halves of at least 4: P must be even and >= 8, got {P}")
        halves = _halves(record)
        pilot_est = dataclasses.replace(estimator, combiner=estimator.combiner.with_source(weight_source(self.pilot)))
        final_est = dataclasses.replace(estimator, combiner=estimator.combiner.with_source(PreviousWeight()))
        pilot_state = state._replace(combiner=pilot_est.combiner.init(InitContext(T, problem.action_dim, _no_extra_rollout)))

        def pilot(rec):
            return backward_sweep(problem, policy, rec, config, pilot_est, pilot_state)[1]

        def final(rec, k):
            given = state._replace(combiner=PreviousBatchWeight(k, jnp.ones(k.shape, bool)))
            return backward_sweep(problem, policy, rec, config, final_est, given)

        k_pilot = jax.vmap(pilot)(halves).diagnostics.k_lr_batch  # (2, T, ...), each a function of its own half
        next_states, out = jax.vmap(final)(halves, k_pilot[::-1])  # half 0 with half 1's weights and vice versa
        d = out.diagnostics
        mean = lambda a: jnp.mean(a, axis=0)  # noqa: E731  (equal halves)
        diag = StepDiagnostics(
            mean(d.k_lr), mean(k_pilot), mean(d.var_rp), mean(d.var_lr), mean(d.mean_return), mean(d.objective),
            jnp.any(d.nonfinite, axis=0),
        )
        next_state = EstimatorState(
            jax.tree.map(_over_halves, next_states.costs), jax.tree.map(_over_halves, next_states.parts), state.combiner,
        )
        return next_state, SweepOutput(out.contributions.reshape(P, -1), diag)


def one_sweep() -> OneSweep:
    """One reverse sweep over all particles (the default schedule)."""
    return OneSweep()


def cross_fitted(estimator, pilot: str = "leave_one_out"):
    """``estimator`` (total propagation) with cross-fitted weights: its combiner's rule, its pieces,
    and the half-batch sweeps above instead of one sweep (its combiner's weight source is not used)."""
    schedule = CrossFitted(pilot)
    problem = schedule.problem(estimator)
    if problem:
        raise ValueError(problem)
    return dataclasses.replace(estimator, schedule=schedule)
