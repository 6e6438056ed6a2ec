"""Estimators composed from pieces: cost terms, gradient parts and a combiner (estimators.md §2–§9).

An :class:`Estimator` is the strategy the backward sweep runs: its cost terms
(:mod:`~pipps.propagation.cost_terms`) say what each particle adds to the returns and to the
pathwise chain, its parts (:mod:`~pipps.propagation.parts`) turn a step into ζ-cotangents, and its
combiner (:mod:`~pipps.propagation.combine`) weighs the parts. :func:`compose` builds one and refuses
a combination that means nothing. What exists in the traced program follows from the pieces: an RP
estimator contains no LR operations, an LR estimator no pathwise chain, and nothing computes
Gaussian-shaping fits unless the cost terms are shaped.

Named estimators (:func:`estimator`), with the thesis' table names:

=========  ==========================================================================
``rp``     reparameterization (pathwise) only (§2)
``lr``     batch-importance-weighted LR (§3)
``lr_plain`` plain LR with the leave-one-out baseline (§3, for comparison and tests)
``tp``     total propagation of RP and BIW-LR (§4, Alg. 5)
``tp_plain`` total propagation of RP and plain LR (§3–§4; unbiased with the "previous" k_LR)
``tpx``    total propagation at the action nodes: a weight per action coordinate (the idea of TPX)
``gtp``    Gaussian-shaped total propagation (§5, Alg. 6)
``glr``    Gaussian-shaped LR (§5)
``del``    density-estimation LR (§6)
=========  ==========================================================================

:func:`thesis_estimator` gives the thesis' own (biased) variants: the eq. 4.3 baseline and
``k_LR`` from the same batch. The rollout variants (``−σ_f``, ``+σ_n``, GR, fixed seed) are
settings of :class:`pipps.particles.RolloutConfig` and of the optimizer, not of the estimator.
"""

from __future__ import annotations

from typing import Any

from pipps.propagation.combine import COMBINERS, action_nodes, inverse_variance, robust, single
from pipps.propagation.cost_terms import (
    DensityEstimationCosts,
    density_estimation_costs,
    plain_costs,
    shaped_costs,
)
from pipps.propagation.lr import WEIGHTINGS
from pipps.propagation.parts import LIKELIHOOD_RATIO, PATHWISE, BiwLR, PlainLR, biw_lr, pathwise, plain_lr
from pipps.propagation.strategy import strategy

_KINDS = ((PATHWISE,), (LIKELIHOOD_RATIO,), (PATHWISE, LIKELIHOOD_RATIO))


def _composition_problem(costs, parts, combiner) -> str | None:
    """Why (costs, parts, combiner) is not an estimator, or None."""
    kinds = tuple(getattr(p, "kind", None) for p in parts)
    if not parts:
        return "an estimator needs a gradient part: pathwise(), biw_lr() or plain_lr(), or a pathwise and an LR part"
    if kinds not in _KINDS:
        return f"an estimator has one pathwise part, one likelihood-ratio part, or one of each (pathwise first); got {kinds}"
    if combiner.num_parts != len(parts):
        if len(parts) == 2:
            return f"a pathwise and an LR part need a combiner that weighs them (inverse_variance() or robust()), not {combiner.name!r}"
        return f"the {combiner.name!r} combiner weighs a pathwise against an LR part; a lone {kinds[0]} part takes single()"
    if LIKELIHOOD_RATIO in kinds and not costs.feeds_likelihood_ratio:
        return "density-estimation cost terms replace the pathwise cost gradient (estimators.md §6): compose them with a lone pathwise part"
    return None


@strategy(traced=("costs", "parts", "combiner"))
class Estimator:
    """A gradient estimator: cost terms, one or two gradient parts (pathwise first) and a combiner.

    Hashable (a jit static argument) and a pytree whose leaves are its numbers (a fixed ``k_LR``,
    the robust combiner's ``γ`` and ``z``): passed as a jit argument, a new number does not recompile.
    """

    costs: Any
    parts: tuple
    combiner: Any

    def __post_init__(self):
        problem = _composition_problem(self.costs, self.parts, self.combiner)
        if problem:
            raise ValueError(problem)

    @property
    def kinds(self) -> tuple[str, ...]:
        return tuple(p.kind for p in self.parts)

    @property
    def pathwise(self) -> bool:
        """A pathwise part is present: the sweep carries ∂G/∂x and asks for the cost gradient."""
        return PATHWISE in self.kinds

    @property
    def likelihood_ratio(self) -> bool:
        return LIKELIHOOD_RATIO in self.kinds

    @property
    def total_propagation(self) -> bool:
        return len(self.parts) == 2

    @property
    def needs_previous_baseline(self) -> bool:
        """A piece reads the previous iteration's mean return (estimators.md §3, §6)."""
        return any(piece.uses_previous_baseline for piece in (self.costs, *self.parts))

    @property
    def baseline(self) -> str | None:
        """The BIW-LR part's or DEL's baseline; None where no piece takes one."""
        for piece in (self.costs, *self.parts):
            if isinstance(piece, (BiwLR, DensityEstimationCosts)):
                return piece.baseline
        return None

    @property
    def needs_previous_k(self) -> bool:
        """The combiner reads the previous iteration's per-step k_LR ("previous", "guarded")."""
        return self.combiner.uses_previous_k

    @property
    def k_lr(self) -> str | float | None:
        """Where total propagation's weight comes from ("batch", "previous" or a number); None for one part."""
        return self.combiner.k_lr


def compose(costs, *parts, combiner=None) -> Estimator:
    """An estimator from its pieces; ``combiner`` defaults to :func:`single` for one part."""
    parts = tuple(sorted(parts, key=lambda p: getattr(p, "kind", None) != PATHWISE))
    if combiner is None:
        if len(parts) == 2:
            raise ValueError("a pathwise and an LR part need a combiner that weighs them: inverse_variance() or robust()")
        combiner = single()
    return Estimator(costs, parts, combiner)


ESTIMATORS = {
    "rp": compose(plain_costs(), pathwise()),
    "lr": compose(plain_costs(), biw_lr()),
    "lr_plain": compose(plain_costs(), plain_lr()),
    "tp": compose(plain_costs(), pathwise(), biw_lr(), combiner=inverse_variance()),
    "tp_plain": compose(plain_costs(), pathwise(), plain_lr(), combiner=inverse_variance()),
    "tpx": compose(plain_costs(), pathwise(), biw_lr(), combiner=action_nodes()),
    "gtp": compose(shaped_costs(), pathwise(), biw_lr(), combiner=inverse_variance()),
    "glr": compose(shaped_costs(), biw_lr()),
    "del": compose(density_estimation_costs(), pathwise()),
}

THESIS_ESTIMATORS = {
    "lr": compose(plain_costs(), biw_lr("thesis")),
    "tp": compose(plain_costs(), pathwise(), biw_lr("thesis"), combiner=inverse_variance("batch")),
    "gtp": compose(shaped_costs(), pathwise(), biw_lr("thesis"), combiner=inverse_variance("batch")),
    "glr": compose(shaped_costs(), biw_lr("thesis")),
}

NAMED = tuple(ESTIMATORS)

SETTINGS = ("weighting", "baseline", "k_lr", "combiner", "robust_gamma", "robust_z", "messages")
_COMBINER_SETTINGS = ("k_lr", "combiner", "robust_gamma", "robust_z", "messages")


def _reweighted(name: str, parts: tuple, weighting: str) -> tuple:
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {weighting!r}")
    if LIKELIHOOD_RATIO not in (p.kind for p in parts):
        raise ValueError(f"weighting applies to a likelihood-ratio part, and {name!r} has none")

    def swap(p):
        if p.kind != LIKELIHOOD_RATIO:
            return p
        if weighting == "plain":
            return plain_lr()
        return p if isinstance(p, BiwLR) else biw_lr()

    return tuple(swap(p) for p in parts)


def _rebaselined(name: str, costs, parts: tuple, baseline: str):
    if isinstance(costs, DensityEstimationCosts):
        return density_estimation_costs(baseline), parts
    if any(isinstance(p, BiwLR) for p in parts):
        return costs, tuple(biw_lr(baseline) if isinstance(p, BiwLR) else p for p in parts)
    if any(isinstance(p, PlainLR) for p in parts):
        raise ValueError(f"baseline: plain LR always uses the leave-one-out mean (estimators.md §3), so {name!r} takes none")
    raise ValueError(f"baseline applies to BIW-LR or DEL, and {name!r} has neither")


def _recombined(name: str, combiner, num_parts: int, settings: dict):
    if num_parts != 2:
        raise ValueError(f"{sorted(settings)} only apply to total propagation (a pathwise and an LR part); {name!r} has one part")
    rule = settings.get("combiner", combiner.name)
    k_lr = settings.get("k_lr", combiner.k_lr)
    messages = settings.get("messages", getattr(combiner, "messages", "mixed"))
    if rule == "robust":
        gamma = settings.get("robust_gamma", getattr(combiner, "gamma", float("inf")))
        z = settings.get("robust_z", getattr(combiner, "z", 2.0))
        return robust(gamma, z, k_lr=k_lr, messages=messages)
    extra = sorted({"robust_gamma", "robust_z"} & set(settings))
    if extra:
        raise ValueError(f"{extra} belong to the robust combiner; pass combiner='robust' as well")
    if rule == "inverse_variance":
        return inverse_variance(k_lr, messages)
    if rule == "action_nodes":
        if "messages" in settings:
            raise ValueError("messages: the action-node combiner mixes the state paths with a weight of their own; it takes no messages setting")
        return action_nodes(k_lr)
    raise ValueError(f"combiner must be one of {COMBINERS}, got {rule!r}")


def with_settings(name: str, est: Estimator, **settings) -> Estimator:
    """``est`` with some of its pieces' settings replaced; a setting no piece takes is refused by name."""
    unknown = set(settings) - set(SETTINGS)
    if unknown:
        raise ValueError(f"unknown estimator settings {sorted(unknown)}; the settings are {SETTINGS}, the name chooses the rest")
    costs, parts, combiner = est.costs, est.parts, est.combiner
    if "weighting" in settings:
        parts = _reweighted(name, parts, settings["weighting"])
    if "baseline" in settings:
        costs, parts = _rebaselined(name, costs, parts, settings["baseline"])
    combining = {k: settings[k] for k in _COMBINER_SETTINGS if k in settings}
    if combining:
        combiner = _recombined(name, combiner, len(parts), combining)
    return Estimator(costs, parts, combiner)


def _check_name(name: str) -> None:
    if name not in ESTIMATORS:
        raise ValueError(f"unknown estimator {name!r}; choose one of {NAMED}")


def estimator(name: str, **settings) -> Estimator:
    """A named estimator with the library defaults, e.g. ``estimator("tp", k_lr="batch")``.

    ``k_lr="cross_fit"`` gives a :class:`~pipps.propagation.cross_fit.CrossFitted` estimator (a
    schedule of half-batch sweeps, not a weight source): exactly unbiased with weights from this batch.
    """
    _check_name(name)
    if settings.get("k_lr") == "cross_fit":
        from pipps.propagation.cross_fit import cross_fitted  # it builds on this module

        return cross_fitted(with_settings(name, ESTIMATORS[name], **{**settings, "k_lr": "batch"}))
    return with_settings(name, ESTIMATORS[name], **settings)


def thesis_estimator(name: str, **settings) -> Estimator:
    """The thesis' own (biased) choices: the eq. 4.3 baseline and k_LR from the same batch."""
    _check_name(name)
    return with_settings(name, THESIS_ESTIMATORS.get(name, ESTIMATORS[name]), **settings)
