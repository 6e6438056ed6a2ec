"""The PILCO moment-matching baseline (thesis Algorithm 2). See docs/pilco.md.

Closed-form blocks (each returns ``GaussianMap(M, S, C)`` in the convention of :mod:`pipps.gaussian`):
:func:`saturation_moments` (PILCO's ``gSat.m``), :func:`control_moments` / :func:`unsquashed_moments`
(controller, then saturation), :func:`gp_moments` (a GP at a Gaussian input, full GP and FITC alike),
:func:`dynamics_moments` (GP or any model with ``moments``). Assembly: :func:`propagate` (one step,
PILCO's ``propagated.m``), :func:`objective`
(``J = Σ_{t=1..H} E[c(x_t)]``, one ``lax.scan``), :func:`trajectory`; :func:`policy_input_noise` is
the PILCO V0.9 policy-input noise term their ``policy_noise`` option adds. Policy search:
:func:`optimize_policy`.
"""

from pipps.pilco.controller import (
    RBF_SECOND_MOMENT_JITTER,
    control_moments,
    linear_controller_moments,
    rbf_controller_moments,
    unsquashed_moments,
)
from pipps.pilco.gp_moments import gp_moments, se_moments
from pipps.pilco.optimize import DEFAULT_BUDGET, PolicySearchConfig, optimize_policy, pilco_budget
from pipps.pilco.propagate import (
    PilcoTrajectory,
    dynamics_moments,
    objective,
    policy_input_noise,
    propagate,
    state_control_joint,
    step_moments,
    trajectory,
)
from pipps.pilco.saturation import saturation_moments

__all__ = [
    "DEFAULT_BUDGET", "PilcoTrajectory", "PolicySearchConfig", "RBF_SECOND_MOMENT_JITTER",
    "control_moments", "dynamics_moments", "gp_moments", "linear_controller_moments", "objective",
    "optimize_policy", "pilco_budget", "policy_input_noise", "propagate", "rbf_controller_moments",
    "saturation_moments", "se_moments", "state_control_joint", "step_moments", "trajectory", "unsquashed_moments",
]
