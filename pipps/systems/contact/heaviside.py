"""The Heaviside and its relaxation (Suh et al. 2022, "Pathologies", Examples III.2 and III.5; Figs. 2–3).

* :class:`Heaviside`: ``f(θ + w) = H(θ + w)``, ``H(t) = 1 if t ≥ 0 else 0``. The smoothed objective is
  ``F(θ) = Φ(θ/σ)`` and ``∇F(θ) = φ(θ/σ)/σ`` (the source writes it ``erf(−θ; σ²)``), nonzero at every
  θ, while every first-order sample ``H'(θ + w)`` is 0: the FoBG is exactly 0, with exactly zero
  empirical variance — biased, and confidently so.
* :class:`Relaxed`: the piecewise-linear relaxation of slip tolerance ν,
  ``H̄_ν(t) = 2t/ν if |t| ≤ ν/2 else 2H(t) − 1`` (continuous, Lipschitz 2/ν). In closed form, with
  ``a = (−ν/2 − θ)/σ``, ``b = (ν/2 − θ)/σ`` and ``p = Φ(b) − Φ(a)`` (the probability that a sample
  lands on the slope):
  ``F_ν(θ) = (2/ν)[θ p + σ(φ(a) − φ(b))] + 1 − Φ(b) − Φ(a)`` and ``∇F_ν(θ) = 2p/ν``. A first-order
  sample is ``2/ν`` with probability ``p`` and 0 otherwise: unbiased, with variance
  ``(4/ν²) p (1 − p) ≈ 4 c_σ/ν`` (``c_σ = 1/(√(2π) σ)``, θ near 0), so with ``N ≲ 1/p`` samples the
  FoBG is most often exactly 0 — the empirical bias of the source's Definition III.3. Its
  statement "at θ = ν/2, ∇F_ν = c_σ" holds for a relaxation of a unit jump; ``H̄_ν`` jumps by 2, so
  here ``∇F_ν(ν/2) → 2 c_σ`` as ν → 0 (:func:`empirical_bias`).

Both are one-step problems (:func:`pipps.systems.contact.base.one_step_problem`): the simulator maps
the action to ``f(u)``, the cost reads it. ν is a pytree leaf (a new value does not recompile).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.tree_util import register_dataclass
from scipy import stats

from pipps.systems.contact.base import ContactExample, as_policy, one_step_problem, scalar_of


@register_dataclass
@dataclasses.dataclass(frozen=True)
class Heaviside:
    """``step(x, u) = [H(u)]``."""

    def step(self, x, u):
        del x
        return jnp.where(u >= 0.0, 1.0, 0.0).astype(u.dtype)


@register_dataclass
@dataclasses.dataclass(frozen=True)
class Relaxed:
    """``step(x, u) = [H̄_ν(u)]`` with slip tolerance ``nu`` > 0 (traced)."""

    nu: jax.Array

    def step(self, x, u):
        del x
        return jnp.where(jnp.abs(u) <= 0.5 * self.nu, 2.0 * u / self.nu, jnp.where(u >= 0.0, 1.0, -1.0))


def heaviside_exact(theta: float, sigma: float) -> tuple[float, float]:
    """``(F, ∇F)`` of the Heaviside: ``(Φ(θ/σ), φ(θ/σ)/σ)``."""
    return float(stats.norm.cdf(theta / sigma)), float(stats.norm.pdf(theta / sigma) / sigma)


def relaxed_exact(theta: float, sigma: float, nu: float) -> tuple[float, float]:
    """``(F_ν, ∇F_ν)`` of the relaxation (module doc)."""
    a, b = (-0.5 * nu - theta) / sigma, (0.5 * nu - theta) / sigma
    p = stats.norm.cdf(b) - stats.norm.cdf(a)
    F = 2.0 / nu * (theta * p + sigma * (stats.norm.pdf(a) - stats.norm.pdf(b))) + 1.0 - stats.norm.cdf(b) - stats.norm.cdf(a)
    return float(F), float(2.0 * p / nu)


def slope_probability(theta: float, sigma: float, nu: float) -> float:
    """``p``: the probability that ``θ + σw`` lands on the relaxation's slope, ``|θ + σw| ≤ ν/2``."""
    return float(stats.norm.cdf((0.5 * nu - theta) / sigma) - stats.norm.cdf((-0.5 * nu - theta) / sigma))


def fobg_variance(theta: float, sigma: float, nu: float) -> float:
    """The expected variance of one first-order sample of the relaxation, ``(4/ν²) p (1 − p)``."""
    p = slope_probability(theta, sigma, nu)
    return 4.0 / nu**2 * p * (1.0 - p)


def empirical_bias(sigma: float, nu: float) -> dict:
    """Definition III.3's ``(β, Δ, S)`` at θ = ν/2 with the event "the sample is off the slope": β = p,
    Δ = |E[z | off] − E[z]| = ∇F_ν, S = 0; beside the source's ``(c_σ ν, c_σ, 0)``."""
    theta = 0.5 * nu
    p = slope_probability(theta, sigma, nu)
    c_sigma = 1.0 / (math.sqrt(2.0 * math.pi) * sigma)
    return dict(beta=p, delta=relaxed_exact(theta, sigma, nu)[1], S=0.0, source=(c_sigma * nu, c_sigma, 0.0))


def heaviside(theta: float = 0.5, sigma: float = 1.0) -> ContactExample:
    """Example III.2 at ``θ`` with noise ``σ`` (Fig. 2's setting: the exact ∇F is a Gaussian in θ)."""
    def exact(policy):
        F, g = heaviside_exact(scalar_of(policy), sigma)
        return F, np.array([g]), 0.0

    return ContactExample("heaviside", "Example III.2, Fig. 2 (Heaviside)", one_step_problem("heaviside"), Heaviside(),
                          as_policy(theta), sigma, exact)


def relaxed(nu: float = 0.1, theta: float | None = None, sigma: float = 1.0) -> ContactExample:
    """Example III.5 with slip tolerance ``ν`` at ``θ`` (default ν/2, where the source states its bias)."""
    theta = 0.5 * nu if theta is None else theta

    def exact(policy):
        F, g = relaxed_exact(scalar_of(policy), sigma, nu)
        return F, np.array([g]), 0.0

    return ContactExample(f"relaxed_nu{nu:g}", "Example III.5, Fig. 3 (relaxed Heaviside, Coulomb friction)",
                          one_step_problem("relaxed_heaviside"), Relaxed(jnp.asarray(float(nu))), as_policy(theta), sigma,
                          exact)
