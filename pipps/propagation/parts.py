"""Gradient parts: each turns one step's particles into a ζ-cotangent γ_{i,t} (estimators.md §2–§4).

A part is a strategy piece with a ``kind`` and ``zeta(inputs, config) -> ZetaGrad``:

* :func:`pathwise` (RP, §2; step 2 of §4): ``γ^RP_i = a_i ∂x_{i,t}/∂ζ_{i,t}`` with
  ``a_i = ∂G_i/∂x_{i,t} + ∂c_i/∂x_{i,t}`` — for ``x = μ + s ⊙ ε`` that is ``(a, a ⊙ ε)``, for
  Gaussian resampling the VJP of the resampling. It reads the carried x-cotangent, so the sweep
  pulls x-cotangents back only when a pathwise part is present.
* :func:`biw_lr` (BIW-LR, §3, eq. 4.2–4.3) with its baseline, "previous", "thesis" or "none".
* :func:`plain_lr` (§3): no batch weighting, the leave-one-out baseline.

The sweep carries every part's γ to θ through the same direct path and hands the per-particle
θ-gradients to the combiner (:mod:`~pipps.propagation.combine`).
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax

from pipps.particles.forward import RolloutConfig, gaussian_resample
from pipps.propagation import lr
from pipps.propagation.lr import BASELINES, ZetaGrad
from pipps.propagation.strategy import strategy

PATHWISE = "pathwise"
LIKELIHOOD_RATIO = "likelihood_ratio"


class StepInputs(NamedTuple):
    """What a gradient part reads at step t of the sweep, per particle."""

    x: jax.Array  # x_{i,t}, (P, D)
    mean: jax.Array  # μ_{i,t}, (P, D)
    std: jax.Array  # s_{i,t}, (P, D)
    eps: jax.Array  # ε_{i,t}, (P, D)
    returns: jax.Array  # G_{i,t}, (P,)
    previous_baseline: jax.Array  # b_t of the previous iteration, scalar
    carried: jax.Array  # ∂G_i/∂x_{i,t} passed back from step t+1, (P, D)
    cost_gradient: jax.Array | None  # the cost terms' ∂c_i/∂x_i, (P, D)


class PartCotangents(NamedTuple):
    """One step's gradient parts as the combiner receives them (in the parts' order)."""

    zeta: tuple  # each part's ζ-cotangent γ_{i,t} (ZetaGrad of (P, D) arrays)
    z: jax.Array  # (K, P, Dz) each part's cotangent on the GP input z = [x̃[I]; u], u last
    num_actions: int  # the last num_actions entries of z are the action u_{t−1} (static)
    pull_back: Callable  # (K', P, Dz) z-cotangents → (θ-cotangents (K', P, n_θ), x-cotangents (K', P, D) or None)

    def gradients_and_messages(self):
        """Every part pulled back at once: θ-gradients (K, P, n_θ) and, where a pathwise part reads
        them, the messages ``∂G/∂x_{i,t−1} = (∂z/∂x)ᵀ c_z + γ_μ`` of each part (else None)."""
        g, cx = self.pull_back(self.z)
        messages = None if cx is None else [cx[i] + gam.mean for i, gam in enumerate(self.zeta)]
        return g, messages


def rp_zeta(a: jax.Array, mean: jax.Array, std: jax.Array, eps: jax.Array, config: RolloutConfig) -> ZetaGrad:
    """γ^RP = a ∂x/∂ζ: ``(a, a ⊙ ε)``, or the VJP of the Gaussian resampling (estimators.md §4 step 2, §7)."""
    if config.resampling == "gaussian":
        _, vjp = jax.vjp(lambda m, s: gaussian_resample(m, s, eps, config.resample_jitter), mean, std)
        gm, gs = vjp(a)
        return ZetaGrad(gm, gs)
    return ZetaGrad(a, a * eps)


@strategy
class Pathwise:
    """The reparameterization part (estimators.md §2)."""

    kind = PATHWISE
    uses_previous_baseline = False

    def zeta(self, s: StepInputs, config: RolloutConfig) -> ZetaGrad:
        return rp_zeta(s.carried + s.cost_gradient, s.mean, s.std, s.eps, config)


@strategy
class BiwLR:
    """Batch-importance-weighted LR (estimators.md §3, eq. 4.2) with ``baseline`` (§3, eq. 4.3)."""

    baseline: str = "previous"

    kind = LIKELIHOOD_RATIO

    @property
    def uses_previous_baseline(self) -> bool:
        return self.baseline == "previous"

    def zeta(self, s: StepInputs, config: RolloutConfig) -> ZetaGrad:
        del config
        return lr.biw_lr(s.x, s.mean, s.std, s.returns, self.baseline, s.previous_baseline)


@strategy
class PlainLR:
    """LR without batch weighting, with the leave-one-out baseline (estimators.md §3)."""

    kind = LIKELIHOOD_RATIO
    uses_previous_baseline = False

    def zeta(self, s: StepInputs, config: RolloutConfig) -> ZetaGrad:
        del config
        return lr.plain_lr(s.x, s.mean, s.std, s.returns)


def pathwise() -> Pathwise:
    """The RP part."""
    return Pathwise()


def biw_lr(baseline: str = "previous") -> BiwLR:
    """The BIW-LR part; ``baseline`` is "previous" (unbiased, the default), "thesis" (eq. 4.3) or "none"."""
    if baseline not in BASELINES:
        raise ValueError(f"baseline must be one of {BASELINES}, got {baseline!r}")
    return BiwLR(baseline)


def plain_lr() -> PlainLR:
    """The plain-LR part."""
    return PlainLR()
