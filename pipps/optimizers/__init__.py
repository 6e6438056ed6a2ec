"""Optimisers: the quasi-Newton minimiser of Rasmussen's minimize.m (PILCO's policy search,
fixed-seed objectives) and the thesis' normalized momentum step (thesis §4.5.1)."""

from pipps.optimizers.normalized import NormalizedMomentumState, normalized_momentum
from pipps.optimizers.quasi_newton import (
    STOP_BUDGET,
    STOP_FAILED,
    STOP_GRADIENT,
    STOP_NONFINITE_START,
    QuasiNewtonConfig,
    QuasiNewtonTrace,
    minimize,
)

__all__ = [
    "NormalizedMomentumState", "QuasiNewtonConfig", "QuasiNewtonTrace", "STOP_BUDGET", "STOP_FAILED",
    "STOP_GRADIENT", "STOP_NONFINITE_START", "minimize", "normalized_momentum",
]
