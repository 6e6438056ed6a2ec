"""Gradient parts: each turns one step's particles into a ζ-cotangent γ_{i,t} (thesis Alg. 5).

A part is a strategy piece with a ``kind`` and ``zeta(state, inputs, config) -> (state, ZetaGrad)``:

* :func:`pathwise` (RP, the reparameterization part of Alg. 5): ``γ^RP_i = a_i ∂x_{i,t}/∂ζ_{i,t}`` with
  ``a_i = ∂G_i/∂x_{i,t} + ∂c_i/∂x_{i,t}`` — for ``x = μ + s ⊙ ε`` that is ``(a, a ⊙ ε)``, for
  Gaussian resampling the VJP of the resampling. It reads the carried x-cotangent, so the sweep
  pulls x-cotangents back only when a pathwise part is present.
* :func:`biw_lr` (BIW-LR, thesis eq. 4.2–4.3) with its baseline, "previous", "thesis" or "none".
* :func:`plain_lr`: no batch weighting, the leave-one-out baseline (or the zero-noise rollout's, or
  none), weighing each step's score by the return-to-go or by the whole return (Suh et al.'s ZoBG).
* :func:`density_lr` (DEL, thesis §3.3.1): the LR gradient of a Gaussian ``q_t`` fitted to the
  particles, ``γ_j = a_j ∂x_{j,t}/∂ζ_{j,t}`` with ``a_j = P·∂S_t/∂x_{j,t}`` and
  ``S_t = (1/P) Σ_i (G_{i,t} − b_t) log q_t(x_{i,t})``, the samples in ``log q_t`` held fixed. Like
  every LR part it reaches θ through step t's own controls only (``x_{t−1}`` held fixed), so a
  cost reaches θ once through the controls of each step before it, as in the LR identity
  ``∇J = Σ_t E[G_t ∇_θ log p(x_t | x_{t−1}; θ)]`` with the fitted marginal in place of the
  conditional density.

The sweep carries every part's γ to θ through the same direct path and hands the per-particle
θ-gradients to the combiner (:mod:`~pipps.propagation.combine`). Each is a
:class:`~pipps.propagation.pieces.GradientPart`; BIW-LR with the "previous" baseline keeps the
previous iteration's mean return per step as its state (:class:`~pipps.propagation.pieces.MeanReturn`).
"""

from __future__ import annotations

import jax

from pipps.particles.forward import RolloutConfig, gaussian_resample
from pipps.propagation import lr
from pipps.propagation.cost_terms import DEL_BASELINES, del_gradient
from pipps.propagation.lr import BASELINES, ZetaGrad
from pipps.propagation.pieces import LIKELIHOOD_RATIO, PATHWISE, MeanReturn, PreviousBaseline, Stateless, StepInputs
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
class BiwLR(PreviousBaseline):
    """Batch-importance-weighted LR (thesis eq. 4.2) with ``baseline`` ("thesis": eq. 4.3)."""

    baseline: str = "previous"

    kind = LIKELIHOOD_RATIO
    needs_state_sample = True  # G_j must depend on the sample alone (the thesis' node), not on the state before it

    def zeta(self, state, inputs: StepInputs, config: RolloutConfig) -> tuple[MeanReturn | tuple, ZetaGrad]:
        del config
        x, mean, std, returns = inputs.x, inputs.mean, inputs.std, inputs.returns
        if self.baseline != "previous":
            return state, lr.biw_lr(x, mean, std, returns, self.baseline)
        b, next_state = self.previous_baseline(state, returns)
        return next_state, lr.biw_lr(x, mean, std, returns, self.baseline, b)


@strategy
class PlainLR(Stateless):
    """LR without batch weighting: each sample scored under its own distribution.

    ``returns``: "to_go" weighs step t's score by the return-to-go ``G_{i,t}`` (the default), "total"
    by the whole return ``V_i`` (Suh et al.'s ZoBG, Definition II.1). ``baseline``: "leave_one_out"
    (the mean of the other particles' values; the default), "zero_noise" (the particle's rollout from
    its own start without noise, Suh et al. §II.B) or "none". Every combination is exactly unbiased.
    """

    baseline: str = "leave_one_out"
    returns: str = "to_go"

    kind = LIKELIHOOD_RATIO

    @property
    def reads(self) -> tuple[str, ...]:
        """The sweep inputs beyond ``G_{i,t}`` this part reads (:class:`~pipps.propagation.pieces.StepInputs`)."""
        total = self.returns == "total"
        own = ("total_returns",) if total else ()
        if self.baseline == "zero_noise":
            own += ("nominal_total_returns",) if total else ("nominal_returns",)
        return own

    def zeta(self, state, inputs: StepInputs, config: RolloutConfig) -> tuple[tuple, ZetaGrad]:
        del config
        if self.baseline == "leave_one_out" and self.returns == "to_go":
            return state, lr.plain_lr(inputs.x, inputs.mean, inputs.std, inputs.returns)
        total = self.returns == "total"
        values = inputs.total_returns if total else inputs.returns
        if self.baseline == "leave_one_out":
            baseline = lr.leave_one_out_mean(values)
        elif self.baseline == "zero_noise":
            baseline = inputs.nominal_total_returns if total else inputs.nominal_returns
        else:
            baseline = 0.0
        return state, lr.own_score(values - baseline, inputs.x, inputs.mean, inputs.std)


@strategy
class DensityLR(PreviousBaseline):
    """DEL's likelihood-ratio part (thesis §3.3.1): the fitted density's score, one step to θ.

    ``baseline``: ``b_t``, "previous" (the previous iteration's mean return, the state) or "none".
    """

    baseline: str = "previous"

    kind = LIKELIHOOD_RATIO
    fits_density = True  # a Gaussian fitted to the particles at every step
    needs_state_sample = True  # the fitted density is the marginal of the next state

    def zeta(self, state, inputs: StepInputs, config: RolloutConfig) -> tuple[MeanReturn | tuple, ZetaGrad]:
        b, next_state = self.previous_baseline(state, inputs.returns)
        a = del_gradient(inputs.x, inputs.returns, b)
        return next_state, rp_zeta(a, inputs.mean, inputs.std, inputs.eps, config)


def pathwise() -> Pathwise:
    """The RP part."""
    return Pathwise()


def biw_lr(baseline: str = "previous") -> BiwLR:
    """The BIW-LR part; ``baseline`` is "previous" (unbiased, the default), "thesis" (eq. 4.3) or "none"."""
    if baseline not in BASELINES:
        raise ValueError(f"baseline must be one of {BASELINES}, got {baseline!r}")
    return BiwLR(baseline)


def plain_lr(baseline: str = "leave_one_out", returns: str = "to_go") -> PlainLR:
    """The plain-LR part (:class:`PlainLR`): ``baseline`` "leave_one_out", "zero_noise" or "none";
    ``returns`` "to_go" or "total"."""
    if baseline not in lr.PLAIN_BASELINES:
        raise ValueError(f"plain LR's baseline must be one of {lr.PLAIN_BASELINES}, got {baseline!r}")
    if returns not in lr.RETURNS:
        raise ValueError(f"returns must be one of {lr.RETURNS}, got {returns!r}")
    return PlainLR(baseline, returns)


def density_lr(baseline: str = "previous") -> DensityLR:
    """DEL's LR part; ``baseline`` is "previous" (the default) or "none"."""
    if baseline not in DEL_BASELINES:
        raise ValueError(f"DEL's baseline must be one of {DEL_BASELINES}, got {baseline!r}")
    return DensityLR(baseline)
