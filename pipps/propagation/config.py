"""Estimator configuration: choosing an estimator is configuration (estimators.md §2–§9).

An :class:`Estimator` is static (a jit static argument). Which parts of the backward sweep
exist is decided at trace time from it: an RP estimator contains no LR operations, an LR
estimator no pathwise chain, and nothing computes Gaussian-shaping fits unless shaping is on.

Named estimators (:func:`estimator`), with the thesis' table names:

=========  ==========================================================================
``rp``     reparameterization (pathwise) only (§2)
``lr``     batch-importance-weighted LR (§3)
``lr_plain`` plain LR with the leave-one-out baseline (§3, for comparison and tests)
``tp``     total propagation of RP and BIW-LR (§4, Alg. 5)
``gtp``    Gaussian-shaped total propagation (§5, Alg. 6)
``glr``    Gaussian-shaped LR (§5)
``del``    density-estimation LR (§6)
=========  ==========================================================================

The rollout variants (``−σ_f``, ``+σ_n``, GR, fixed seed) are settings of
:class:`pipps.particles.RolloutConfig` and of the optimizer, not of the estimator.
"""

from __future__ import annotations

import dataclasses

from pipps.propagation.combine import COMBINERS
from pipps.propagation.cost_terms import density_estimation_costs, plain_costs, shaped_costs
from pipps.propagation.lr import BASELINES, WEIGHTINGS
from pipps.propagation.parts import biw_lr, pathwise, plain_lr

K_SOURCES = ("batch", "previous")


@dataclasses.dataclass(frozen=True)
class Estimator:
    """Static description of a gradient estimator.

    Attributes:
      pathwise: the RP part (pathwise derivatives through model and policy) is on.
      likelihood_ratio: the LR part is on. Both on is total propagation.
      weighting: "biw" (batch importance weights, eq. 4.2) or "plain".
      baseline: BIW baseline, "previous" (library default, unbiased), "thesis" (eq. 4.3, biased)
        or "none". Plain LR always uses the leave-one-out mean.
      k_lr: where TP's per-step weight comes from: "batch" (the thesis), "previous" (library
        default: the previous iteration's per-step weight; the first iteration uses the batch),
        or a number in [0, 1] (fixed; 0 is RP and 1 is LR, for tests).
      combiner: "inverse_variance" (thesis) or "robust" (estimators.md §9).
      robust_gamma, robust_z: the robust combiner's bias threshold γ and confidence multiplier.
      shaping: Gaussian shaping (GTP/GLR, §5).
      density_estimation: DEL (§6); uses ``baseline`` ("previous" or "none").
    """

    pathwise: bool = True
    likelihood_ratio: bool = False
    weighting: str = "biw"
    baseline: str = "previous"
    k_lr: str | float = "previous"
    combiner: str = "inverse_variance"
    robust_gamma: float = float("inf")
    robust_z: float = 2.0
    shaping: bool = False
    density_estimation: bool = False

    def __post_init__(self):
        if not (self.pathwise or self.likelihood_ratio):
            raise ValueError("an estimator needs the pathwise part, the LR part, or both")
        if self.weighting not in WEIGHTINGS:
            raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {self.weighting!r}")
        if self.baseline not in BASELINES:
            raise ValueError(f"baseline must be one of {BASELINES}, got {self.baseline!r}")
        if isinstance(self.k_lr, str):
            if self.k_lr not in K_SOURCES:
                raise ValueError(f"k_lr must be one of {K_SOURCES} or a number in [0, 1], got {self.k_lr!r}")
        elif not 0.0 <= float(self.k_lr) <= 1.0:
            raise ValueError(f"a fixed k_lr must lie in [0, 1], got {self.k_lr}")
        if self.combiner not in COMBINERS:
            raise ValueError(f"combiner must be one of {COMBINERS}, got {self.combiner!r}")
        if self.density_estimation and (self.likelihood_ratio or self.shaping or not self.pathwise):
            raise ValueError("DEL is its own estimator: pathwise through the density fit, no LR part, no shaping")
        if self.density_estimation and self.baseline == "thesis":
            raise ValueError("DEL takes the 'previous' or 'none' baseline")

    @property
    def costs(self):
        """The cost terms the sweep asks at each step (:mod:`~pipps.propagation.cost_terms`)."""
        if self.shaping:
            return shaped_costs()
        if self.density_estimation:
            return density_estimation_costs(self.baseline)
        return plain_costs()

    @property
    def parts(self) -> tuple:
        """The gradient parts, pathwise first (:mod:`~pipps.propagation.parts`)."""
        lr_part = (plain_lr() if self.weighting == "plain" else biw_lr(self.baseline),)
        return (pathwise(),) * self.pathwise + lr_part * self.likelihood_ratio

    @property
    def total_propagation(self) -> bool:
        return self.pathwise and self.likelihood_ratio

    @property
    def needs_previous_baseline(self) -> bool:
        lr_biw = self.likelihood_ratio and self.weighting == "biw"
        return (lr_biw or self.density_estimation) and self.baseline == "previous"


NAMED = ("rp", "lr", "lr_plain", "tp", "gtp", "glr", "del")


def estimator(name: str, **overrides) -> Estimator:
    """A named estimator with the library defaults, e.g. ``estimator("tp", k_lr="batch")``."""
    base = {
        "rp": dict(pathwise=True, likelihood_ratio=False),
        "lr": dict(pathwise=False, likelihood_ratio=True),
        "lr_plain": dict(pathwise=False, likelihood_ratio=True, weighting="plain"),
        "tp": dict(pathwise=True, likelihood_ratio=True),
        "gtp": dict(pathwise=True, likelihood_ratio=True, shaping=True),
        "glr": dict(pathwise=False, likelihood_ratio=True, shaping=True),
        "del": dict(pathwise=True, likelihood_ratio=False, density_estimation=True),
    }
    if name not in base:
        raise ValueError(f"unknown estimator {name!r}; choose one of {NAMED}")
    unknown = set(overrides) - {f.name for f in dataclasses.fields(Estimator)}
    if unknown:
        raise ValueError(f"unknown estimator settings {sorted(unknown)}")
    return Estimator(**{**base[name], **overrides})


def thesis_estimator(name: str, **overrides) -> Estimator:
    """The thesis' own (biased) choices: the eq. 4.3 baseline and k_LR from the same batch."""
    extra = {}
    if name in ("lr", "tp", "gtp", "glr"):
        extra["baseline"] = "thesis"
    if name in ("tp", "gtp"):
        extra["k_lr"] = "batch"
    return estimator(name, **{**extra, **overrides})
