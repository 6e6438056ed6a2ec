"""The custom backward pass: RP, LR, BIW-LR, TP, Gaussian shaping and DEL (thesis Alg. 5–6)."""

from pipps.propagation.estimators import ESTIMATORS, Estimator, compose, estimator, thesis_estimator
from pipps.propagation.fixed_seed import optimize_fixed_seed
from pipps.propagation.estimate import Estimate, estimate, estimate_on, init_estimator_state, rollout_for
from pipps.propagation.pieces import EstimatorState, StepDiagnostics
from pipps.propagation.schedules import cross_fitted
from pipps.propagation.update import (
    PolicyOptState,
    UpdateInfo,
    init_policy_opt_state,
    make_policy_optimizer,
    make_policy_update,
    policy_update,
)

__all__ = [
    "ESTIMATORS", "Estimate", "Estimator", "EstimatorState", "PolicyOptState", "StepDiagnostics", "UpdateInfo",
    "compose", "cross_fitted", "estimate", "estimate_on", "estimator", "init_estimator_state", "init_policy_opt_state",
    "make_policy_optimizer", "make_policy_update", "optimize_fixed_seed", "policy_update", "rollout_for", "thesis_estimator",
]
