"""The unicycle's return threshold (docs/experiments.md, "The unicycle's success criterion").

Success on the unicycle is judged on the final trial's evaluation rollouts: at least
``upright_fraction`` of them stay upright. The thesis judges success by a return threshold, so we
also document the return threshold that matches this criterion: the τ for which "evaluated
return < τ" agrees best with that criterion over learned policies. :func:`fit_return_threshold`
finds it exactly (it is a one-dimensional classification with a step function, so every
candidate τ is checked), and
``experiments/calibrate_unicycle.py --results`` applies it to the learned trials of result files.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class ThresholdFit:
    """The best τ for "return < τ ⇔ success": every τ in ``(low, high]`` misclassifies exactly
    ``false_pass + false_fail`` of the ``n`` policies (``low = -inf`` or ``high = inf`` at the ends)."""

    low: float
    high: float
    false_pass: int  # failing policies whose return is below τ
    false_fail: int  # successful policies whose return is not below τ
    n: int

    @property
    def errors(self) -> int:
        return self.false_pass + self.false_fail

    @property
    def agreement(self) -> float:
        return 1.0 - self.errors / self.n


def fit_return_threshold(returns, success) -> ThresholdFit:
    """The interval of thresholds τ for which the rule "return < τ" misclassifies the fewest policies.

    Ties between intervals with equally few errors go to the one with fewer false passes (calling a
    failing policy a success is the worse mistake for a success rate), then to the lowest.
    """
    r = np.asarray(returns, dtype=float)
    s = np.asarray(success, dtype=bool)
    if r.ndim != 1 or r.shape != s.shape:
        raise ValueError(f"returns and success must be 1-d arrays of one length, got shapes {r.shape} and {s.shape}")
    if r.size == 0:
        raise ValueError("no policies to calibrate on")
    if not np.all(np.isfinite(r)):
        raise ValueError(f"returns must be finite, got {r[~np.isfinite(r)][:3].tolist()}")
    # τ only matters through which returns lie below it: the candidates are "below every return"
    # and "just above the j-th distinct return", i.e. the intervals (u_{j-1}, u_j] between them.
    u = np.unique(r)
    edges = np.concatenate([[-np.inf], u, [np.inf]])
    best = None
    for j in range(len(u) + 1):
        low, high = edges[j], edges[j + 1]  # τ ∈ (low, high]: passes are returns ≤ low
        passed = r <= low
        fp = int(np.sum(passed & ~s))
        ff = int(np.sum(~passed & s))
        key = (fp + ff, fp, low)
        if best is None or key < best[0]:
            best = (key, ThresholdFit(float(low), float(high), fp, ff, int(r.size)))
    return best[1]
