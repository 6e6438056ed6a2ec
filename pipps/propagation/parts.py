"""Gradient parts: each turns one step's particles into a ζ-cotangent γ_{i,t} (thesis Alg. 5).

A part is a strategy piece with a ``kind`` and ``zeta(state, inputs, config) -> (state, ZetaGrad)``:

* :func:`pathwise` (RP, the reparameterization part of Alg. 5): ``γ^RP_i = a_i ∂x_{i,t}/∂ζ_{i,t}`` with
  ``a_i = ∂G_i/∂x_{i,t} + ∂c_i/∂x_{i,t}`` — for ``x = μ + s ⊙ ε`` that is ``(a, a ⊙ ε)``, for
  Gaussian resampling the VJP of the resampling. It reads the carried x-cotangent, so the sweep
  pulls x-cotangents back only when a pathwise part is present.
* :func:`biw_lr` (BIW-LR, thesis eq. 4.2–4.3) with its baseline, "previous", "thesis" or "none".
* :func:`plain_lr`: no batch weighting, the leave-one-out baseline.

The sweep carries every part's γ to θ through the same direct path and hands the per-particle
θ-gradients to the combiner (:mod:`~pipps.propagation.combine`). Each is a
:class:`~pipps.propagation.pieces.GradientPart`; BIW-LR with the "previous" baseline keeps the
previous iteration's mean return per step as its state (:class:`~pipps.propagation.pieces.MeanReturn`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from pipps.particles.forward import RolloutConfig, gaussian_resample
from pipps.propagation import lr
from pipps.propagation.lr import BASELINES, ZetaGrad
from pipps.propagation.pieces import LIKELIHOOD_RATIO, PATHWISE, InitContext, MeanReturn, Stateless, StepInputs
from pipps.propagation.strategy import strategy


def rp_zeta(a: jax.Array, mean: jax.Array, std: jax.Array, eps: jax.Array, config: RolloutConfig) -> ZetaGrad:
    """γ^RP = a ∂x/∂ζ: ``(a, a ⊙ ε)``, or the VJP of the Gaussian resampling (GR, thesis §4.3.1)."""
    if config.resampling == "gaussian":
        _, vjp = jax.vjp(lambda m, s: gaussian_resample(m, s, eps, config.resample_jitter), mean, std)
        gm, gs = vjp(a)
        return ZetaGrad(gm, gs)
    return ZetaGrad(a, a * eps)


@strategy
class Pathwise(Stateless):
    """The reparameterization part: backpropagation through the rollout, the noise ε held fixed."""

    kind = PATHWISE

    def zeta(self, state, inputs: StepInputs, config: RolloutConfig) -> tuple[tuple, ZetaGrad]:
        return state, rp_zeta(inputs.carried + inputs.cost_gradient, inputs.mean, inputs.std, inputs.eps, config)


@strategy
class BiwLR:
    """Batch-importance-weighted LR (thesis eq. 4.2) with ``baseline`` ("thesis": eq. 4.3)."""

    baseline: str = "previous"

    kind = LIKELIHOOD_RATIO
    cold_start = False  # the first iteration's baseline comes from the extra rollout

    def init(self, context: InitContext) -> MeanReturn | tuple:
        return MeanReturn(context.mean_returns()) if self.baseline == "previous" else ()

    def zeta(self, state, inputs: StepInputs, config: RolloutConfig) -> tuple[MeanReturn | tuple, ZetaGrad]:
        del config
        x, mean, std, returns = inputs.x, inputs.mean, inputs.std, inputs.returns
        if self.baseline != "previous":
            return state, lr.biw_lr(x, mean, std, returns, self.baseline)
        gamma = lr.biw_lr(x, mean, std, returns, self.baseline, state.mean_return)
        return MeanReturn(jnp.mean(returns)), gamma


@strategy
class PlainLR(Stateless):
    """LR without batch weighting, with the leave-one-out baseline (exactly unbiased)."""

    kind = LIKELIHOOD_RATIO

    def zeta(self, state, inputs: StepInputs, config: RolloutConfig) -> tuple[tuple, ZetaGrad]:
        del config
        return state, lr.plain_lr(inputs.x, inputs.mean, inputs.std, inputs.returns)


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
