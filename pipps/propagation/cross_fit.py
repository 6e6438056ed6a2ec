"""Cross-fitted total propagation: a k_LR per half-batch from a sweep of the other half alone (issue 20).

Total propagation is unbiased for any per-step ``k_LR`` that is independent of the particles it
weighs (docs/estimators.md, "Choosing k_LR"). A weight computed from this batch is not, because
the variances it reads depend on the particles' futures and — through the batch-importance
weights and the messages λ — on every other particle. The cross-fit makes the independence exact
instead of approximate:

1. the batch of P particles is split into halves A (particles 0…P/2−1) and B (the rest); the
   forward rollout is the usual one (particles do not interact forward);
2. *pilot* sweeps: each half is swept alone — BIW weights over its own P/2 components only — with
   a weight rule of its own (``pilot``: "leave_one_out" by default, or "batch"; any rule that reads
   only that half would do), and each half's per-step batch weights ``k_A`` and ``k_B`` are read
   off: functions of that half's particles alone;
3. *final* sweeps: half A is swept alone with the weights ``k_B``, half B with ``k_A`` (as a
   "previous" weight);
4. the estimate is the mean over all P particles' contributions of the final sweeps.

Half A's final sweep is a total propagation of P/2 particles whose every weight is a function of
half B only, which is independent of half A: it is exactly unbiased (the "previous" argument), and
likewise half B's. What it costs: four half sweeps (two full sweeps' VJPs; the BIW terms are
2·(P/2)²·2 = P² against P², i.e. the same), and BIW mixes only P/2 components, which loses some of
its variance reduction at small P. The sweeps themselves are the library's
:func:`~pipps.propagation.backward.backward_sweep`, vmapped over the two halves.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from pipps.particles.forward import ParticleRecord, RolloutConfig
from pipps.propagation.backward import PreviousIteration, StepDiagnostics, SweepOutput, backward_sweep
from pipps.propagation.combine import PreviousWeight, weight_source
from pipps.propagation.config import Estimator
from pipps.propagation.strategy import strategy
from pipps.tasks.base import Problem


PILOTS = ("leave_one_out", "batch", "split")


def _halves(record: ParticleRecord) -> ParticleRecord:
    """(T, P, ...) fields → (2, T, P/2, ...): half 0 the first P/2 particles, half 1 the rest."""

    def split(a):
        if a is None:
            return None
        T, P = a.shape[:2]
        return jnp.moveaxis(a.reshape(T, 2, P // 2, *a.shape[2:]), 1, 0)

    return ParticleRecord(*(split(a) for a in record))


@strategy(traced=("inner",))
class CrossFitted:
    """Total propagation with cross-fitted weights; ``inner`` gives its pieces and its weight rule
    (inverse variance or robust); the inner weight source is replaced by the schedule above."""

    inner: Estimator
    pilot: str = "leave_one_out"  # the pilot sweeps' weight source (static)

    k_lr = "cross_fit"

    def __post_init__(self):
        if not self.inner.total_propagation:
            raise ValueError("cross-fitted weights need total propagation: a pathwise and an LR part")
        if self.pilot not in PILOTS:
            raise ValueError(f"pilot must be one of {PILOTS}, got {self.pilot!r}")

    # what the rest of the library reads from an estimator
    costs = property(lambda self: self.inner.costs)
    parts = property(lambda self: self.inner.parts)
    combiner = property(lambda self: self.inner.combiner)
    kinds = property(lambda self: self.inner.kinds)
    pathwise = property(lambda self: self.inner.pathwise)
    likelihood_ratio = property(lambda self: self.inner.likelihood_ratio)
    total_propagation = property(lambda self: True)
    needs_previous_k = property(lambda self: False)
    needs_previous_baseline = property(lambda self: self.inner.needs_previous_baseline)
    baseline = property(lambda self: self.inner.baseline)

    def _with_source(self, source) -> Estimator:
        return dataclasses.replace(self.inner, combiner=dataclasses.replace(self.inner.combiner, source=source))

    def sweep(self, task: Problem, policy, record: ParticleRecord, config: RolloutConfig, previous: PreviousIteration) -> SweepOutput:
        """The pilot and final sweeps of the two halves; contributions (P, n_θ) in particle order."""
        T, P = record.x.shape[:2]
        if P % 2 or P < 8:
            raise ValueError(f"cross-fitted TP splits the batch in two halves of at least 4: P must be even and >= 8, got {P}")
        halves = _halves(record)
        pilot_est, final_est = self._with_source(weight_source(self.pilot)), self._with_source(PreviousWeight())

        def pilot(rec):
            return backward_sweep(task, policy, rec, config, pilot_est, previous)

        def final(rec, k):
            return backward_sweep(task, policy, rec, config, final_est, PreviousIteration(previous.baseline, k, jnp.asarray(True)))

        k_pilot = jax.vmap(pilot)(halves).diagnostics.k_lr_batch  # (2, T), each a function of its own half
        out = jax.vmap(final)(halves, k_pilot[::-1])  # half 0 with half 1's weights and vice versa
        d = out.diagnostics
        mean = lambda a: jnp.mean(a, axis=0)  # noqa: E731  (equal halves)
        diag = StepDiagnostics(
            mean(d.k_lr), mean(k_pilot), mean(d.var_rp), mean(d.var_lr), mean(d.mean_return), mean(d.objective),
            jnp.any(d.nonfinite, axis=0),
        )
        return SweepOutput(out.contributions.reshape(P, -1), diag)


def cross_fitted(inner: Estimator, pilot: str = "leave_one_out") -> CrossFitted:
    """Cross-fitted total propagation built from the TP estimator ``inner`` (its source is ignored)."""
    return CrossFitted(inner, pilot)
