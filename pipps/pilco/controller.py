"""Controller moments (PILCO's ``conlin.m``, ``congp.m``) composed with saturation (``gSat.m``).

The controller input is ``v = x̃[P] ~ N(mean, cov)``; every routine returns the Gaussian map of
the control in the convention of :mod:`pipps.gaussian`, ``C = cov⁻¹ Cov[v, ·]``.

* :class:`~pipps.policies.LinearPolicy`: ``ũ = W v + b`` is exact — ``M = Wμ + b``,
  ``S = WΣWᵀ``, ``C = Wᵀ``.
* RBF policies (:class:`~pipps.policies.RBFPolicy`, :class:`~pipps.policies.PilcoRBFPolicy`):
  their ``as_rbf()`` form (PILCO's kernel convention, unit signal variance) goes through the
  GP-at-a-Gaussian-input formulas with the centres as inputs and ``β`` as weights, **no**
  model-uncertainty (trace) term, and ``1e-6`` added to the diagonal of ``E[π̃ π̃ᵀ]`` before
  centring (PILCO's ``gp2``).
* Saturation ``u = ū ⊙ sat(ũ)`` (all RBF policies; a linear one unless ``saturated=False``):
  ``C = C_ctrl diag(R)`` by composition, ``R = E[∂u/∂ũ]``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from pipps.gaussian import GaussianMap, linear_map
from pipps.pilco.gp_moments import se_moments
from pipps.pilco.saturation import saturation_moments
from pipps.policies import LinearPolicy, RBFForm

RBF_SECOND_MOMENT_JITTER = 1e-6  # PILCO's: added to diag E[π̃π̃ᵀ] before centring


def linear_controller_moments(policy: LinearPolicy, mean: jax.Array, cov: jax.Array) -> GaussianMap:
    """Linear controller, unsquashed: ``M = Wμ + b``, ``S = WΣWᵀ``, ``C = Wᵀ`` (exact)."""
    return linear_map(mean, cov, policy.W, policy.b)


def rbf_controller_moments(form: RBFForm, mean: jax.Array, cov: jax.Array) -> GaussianMap:
    """RBF controller, unsquashed, as a GP at a Gaussian input (no trace term, +1e-6 on E[π̃π̃ᵀ]'s diagonal)."""
    n_out = form.beta.shape[1]
    return se_moments(
        form.centres,
        form.beta.T,
        jnp.sqrt(form.lengthscale_sq),
        jnp.ones((n_out,), dtype=mean.dtype),
        mean,
        cov,
        inv=None,
        second_moment_jitter=RBF_SECOND_MOMENT_JITTER,
    )


def unsquashed_moments(policy, mean: jax.Array, cov: jax.Array) -> GaussianMap:
    """Moments of the controller output ũ before saturation (dispatch on the policy type)."""
    if isinstance(policy, LinearPolicy):
        return linear_controller_moments(policy, mean, cov)
    if callable(getattr(policy, "as_rbf", None)):
        return rbf_controller_moments(policy.as_rbf(), mean, cov)
    raise TypeError(f"no controller moments for policy type {type(policy).__name__}")


def control_moments(policy, mean: jax.Array, cov: jax.Array) -> GaussianMap:
    """Moments of the applied control ``u = π(v)`` (saturated as the policy is): controller, then saturation."""
    g = unsquashed_moments(policy, mean, cov)
    if isinstance(policy, LinearPolicy) and not policy.saturated:
        return g
    sat = saturation_moments(g.M, g.S, policy.u_max)
    return GaussianMap(sat.M, sat.S, g.C @ sat.C)
