"""Estimators: compositions of pieces (docs/estimators.md), and the registry of named ones.

An :class:`Estimator` is cost terms (:mod:`~pipps.propagation.cost_terms`: what each particle adds to
the returns and to the pathwise chain), one or two gradient parts (:mod:`~pipps.propagation.parts`:
a step's ζ-cotangents), a combiner (:mod:`~pipps.propagation.combine`: how the parts are weighed,
with a weight source from :mod:`~pipps.propagation.weights`) and a sweep schedule
(:mod:`~pipps.propagation.schedules`: one sweep, or cross-fitted half sweeps). :func:`compose` builds
one and refuses a combination that means nothing. Each piece owns its state; the estimator's state is
the tuple of its pieces' states (:class:`~pipps.propagation.pieces.EstimatorState`). What exists in
the traced program follows from the pieces: an RP estimator contains no LR operations, an LR
estimator no pathwise chain, and nothing computes Gaussian-shaping fits unless the cost terms are
shaped.

:data:`ESTIMATORS` is the one registry of named estimators: each :class:`NamedEstimator` carries its
name, label, colour and description, the library's composition and the thesis' own where it differs.
The CLI's choices and help, the studies' labels and colours and the table in docs/estimators.md are
read from it (:func:`estimator_table`). :func:`estimator` gives the library's, :func:`thesis_estimator`
the thesis' (biased: the eq. 4.3 baseline and ``k_LR`` from the same batch; DEL down the whole pathwise
chain); their settings replace a
piece (:data:`SETTINGS`). :func:`from_spec` reads ``"tp:k_lr=previous"``, a name with settings, as the
studies' ``--estimators`` take it. The rollout variants (``−σ_f``, ``+σ_n``, GR, fixed seed) are
settings of :class:`pipps.particles.RolloutConfig` and of the optimizer, not of the estimator.
"""

from __future__ import annotations

import dataclasses

from pipps.propagation.combine import COMBINERS, action_nodes, inverse_variance, robust, single
from pipps.propagation.cost_terms import (
    DensityEstimationCosts,
    PlainCosts,
    density_estimation_costs,
    plain_costs,
    shaped_costs,
)
from pipps.propagation.lr import WEIGHTINGS
from pipps.propagation.parts import BiwLR, DensityLR, PlainLR, biw_lr, density_lr, pathwise, plain_lr
from pipps.propagation.pieces import (
    LIKELIHOOD_RATIO,
    PATHWISE,
    Combiner,
    CostTerms,
    EstimatorState,
    InitContext,
    Schedule,
)
from pipps.propagation.schedules import OneSweep, cross_fitted
from pipps.propagation.strategy import strategy

_KINDS = ((PATHWISE,), (LIKELIHOOD_RATIO,), (PATHWISE, LIKELIHOOD_RATIO))


def _composition_problem(costs, parts, combiner, schedule) -> str | None:
    """Why (costs, parts, combiner, schedule) is not an estimator, or None."""
    kinds = tuple(p.kind for p in parts)
    if not parts:
        return "an estimator needs a gradient part: pathwise(), biw_lr() or plain_lr(), or a pathwise and an LR part"
    if kinds not in _KINDS:
        return f"an estimator has one pathwise part, one likelihood-ratio part, or one of each (pathwise first); got {kinds}"
    if combiner.num_parts != len(parts):
        if len(parts) == 2:
            return f"a pathwise and an LR part need a combiner that weighs them (inverse_variance() or robust()), not {combiner.name!r}"
        return f"the {combiner.name!r} combiner weighs a pathwise against an LR part; a lone {kinds[0]} part takes single()"
    if LIKELIHOOD_RATIO in kinds and not costs.feeds_likelihood_ratio:
        return ("density-estimation cost terms replace the pathwise cost gradient (DEL, thesis §3.3.1): "
                "compose them with a lone pathwise part")
    if any(isinstance(p, PlainLR) and p.returns == "total" for p in parts) and not isinstance(costs, PlainCosts):
        return ("plain LR with returns='total' weighs each score by the particle's whole cost Σ_t c_t; "
                "shaped or density-estimation cost terms change what the returns hold: use returns='to_go'")
    if len(parts) == 2 and any(isinstance(p, DensityLR) for p in parts):
        return ("DEL's LR part estimates the gradient through the particles' fitted density, not each particle's "
                "own; total propagation does not weigh it against a pathwise part: compose it alone")
    return None


@strategy(traced=("costs", "parts", "combiner", "schedule"))
class Estimator:
    """A gradient estimator: cost terms, one or two gradient parts (pathwise first), a combiner and
    a sweep schedule.

    Hashable (a jit static argument) and a pytree whose leaves are its numbers (a fixed ``k_LR``,
    the robust combiner's ``γ`` and ``z``): passed as a jit argument, a new number does not recompile.
    """

    costs: CostTerms
    parts: tuple
    combiner: Combiner
    schedule: Schedule = OneSweep()

    def __post_init__(self):
        problem = _composition_problem(self.costs, self.parts, self.combiner, self.schedule) or self.schedule.problem(self)
        if problem:
            raise ValueError(problem)

    @property
    def pieces(self) -> tuple:
        """(costs, *parts, combiner): the pieces whose states :class:`EstimatorState` holds."""
        return (self.costs, *self.parts, self.combiner)

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
    def reads_nominal(self) -> bool:
        """A part's baseline is each particle's zero-noise rollout (Suh et al. §II.B): the estimate makes
        that rollout too."""
        return any(r.startswith("nominal") for p in self.parts for r in getattr(p, "reads", ()))

    @property
    def fits_density(self) -> bool:
        """A piece fits a Gaussian to the P particles at every step (DEL's): its unbiased covariance has
        rank at most P − 1, so the estimator needs more particles than the state has dimensions."""
        return any(getattr(piece, "fits_density", False) for piece in self.pieces)

    @property
    def total_propagation(self) -> bool:
        """Two parts, weighed by the combiner (TP and its variants)."""
        return len(self.parts) == 2

    @property
    def cold_start(self) -> bool:
        """A piece's state after :meth:`init` is a cold start: its first estimate falls back on its own
        batch, and an optimizer's later iterations read what an estimate left (e.g. "previous" k_LR)."""
        return any(piece.cold_start for piece in self.pieces)

    def init(self, context: InitContext) -> EstimatorState:
        """Every piece's state before the first estimate."""
        return EstimatorState(self.costs.init(context), tuple(p.init(context) for p in self.parts), self.combiner.init(context))


def compose(costs, *parts, combiner=None, schedule=None) -> Estimator:
    """An estimator from its pieces; ``combiner`` defaults to :func:`single` for one part,
    ``schedule`` to one sweep."""
    parts = tuple(sorted(parts, key=lambda p: p.kind != PATHWISE))
    if combiner is None:
        if len(parts) == 2:
            raise ValueError("a pathwise and an LR part need a combiner that weighs them: inverse_variance() or robust()")
        combiner = single()
    return Estimator(costs, parts, combiner, schedule or OneSweep())


@dataclasses.dataclass(frozen=True)
class NamedEstimator:
    """An entry of :data:`ESTIMATORS`: what a name means, and how it is shown."""

    name: str
    label: str  # in figures and tables (the thesis' name where it has one)
    colour: tuple[int, int, int]  # in figures
    description: str  # what it is; docs/estimators.md's table (Markdown)
    estimator: Estimator  # the library's composition
    thesis: Estimator | None = None  # the thesis' own choices, where they differ (eq. 4.3 baseline, batch k_LR)
    thesis_variant: str | None = None  # how the thesis' differs, where that is not its baseline and k_LR

    @property
    def weighs_parts(self) -> bool:
        """It weighs a pathwise against an LR part: its k_LR is a chosen weight, not 0 or 1."""
        return self.estimator.combiner.num_parts == 2


def _thesis_tp(costs):
    return compose(costs, pathwise(), biw_lr("thesis"), combiner=inverse_variance("batch"))


#: Every named estimator, in the order the CLI and the docs list them.
ESTIMATORS: dict[str, NamedEstimator] = {e.name: e for e in (
    NamedEstimator("rp", "RP", (214, 39, 40),
                   "reparameterization (pathwise) only; with `RolloutConfig(resampling=\"gaussian\")` GR, on a "
                   "fixed key RP_FS / GR_FS",
                   compose(plain_costs(), pathwise())),
    NamedEstimator("lr", "BIW-LR", (44, 160, 44), "batch-importance-weighted LR (thesis eq. 4.2); the thesis' LR",
                   compose(plain_costs(), biw_lr()), compose(plain_costs(), biw_lr("thesis"))),
    NamedEstimator("lr_plain", "LR", (255, 127, 14), "plain LR with the leave-one-out baseline (comparison, tests)",
                   compose(plain_costs(), plain_lr())),
    NamedEstimator("tp", "TP", (31, 119, 180),
                   "total propagation of RP and BIW-LR (thesis Alg. 5); with `model_variance=False` TP−σ_f, with "
                   "`noise_multiplier=100` TP+σ_n",
                   compose(plain_costs(), pathwise(), biw_lr(), combiner=inverse_variance()), _thesis_tp(plain_costs())),
    NamedEstimator("tp_plain", "TP (plain LR)", (23, 190, 207),
                   "total propagation of RP and plain LR (unbiased with the `\"previous\"` k_LR)",
                   compose(plain_costs(), pathwise(), plain_lr(), combiner=inverse_variance())),
    NamedEstimator("tpx", "TPX", (188, 189, 34),
                   "RP and BIW-LR combined at the action nodes: a weight per action coordinate and one for the state "
                   "paths (the idea of TPX, Parmas, Seno, Aoki 2023)",
                   compose(plain_costs(), pathwise(), biw_lr(), combiner=action_nodes())),
    NamedEstimator("gtp", "GTP", (148, 103, 189),
                   "Gaussian-shaped total propagation (thesis §3.3.2, Alg. 6); with `noise_multiplier=25` GTP+σ_n",
                   compose(shaped_costs(), pathwise(), biw_lr(), combiner=inverse_variance()), _thesis_tp(shaped_costs())),
    NamedEstimator("glr", "GLR", (140, 86, 75), "Gaussian-shaped LR (thesis §3.3.2)",
                   compose(shaped_costs(), biw_lr()), compose(shaped_costs(), biw_lr("thesis"))),
    NamedEstimator("del", "DEL", (127, 127, 127),
                   "density-estimation LR (thesis §3.3.1): the score of a Gaussian fitted to the particles, "
                   "taken to θ through each step's own controls",
                   compose(plain_costs(), density_lr()), compose(density_estimation_costs(), pathwise()),
                   "the fit's derivative down the whole pathwise chain (counts a cost once per earlier step)"),
    NamedEstimator("zobg", "ZoBG", (227, 119, 194),
                   "Suh et al.'s zeroth-order batched gradient (their Definition II.1): plain LR weighing every step's "
                   "score by the whole return, less each particle's zero-noise rollout (their §II.B); the RP part "
                   "of the same comparison is `rp`, their FoBG",
                   compose(plain_costs(), plain_lr("zero_noise", "total"))),
    NamedEstimator("aobg", "AoBG", (255, 187, 120),
                   "Suh et al.'s robust interpolation of FoBG (RP) and ZoBG at each step: the inverse-variance "
                   "weight, capped so that ε + α‖ḡ_RP − ḡ_LR‖ ≤ γ (`robust_gamma`, default 1: set it to the "
                   "gradient error your problem tolerates), from this batch",
                   compose(plain_costs(), pathwise(), plain_lr("zero_noise", "total"),
                           combiner=robust(gamma=1.0, z=2.0, k_lr="batch"))),
    NamedEstimator("del_cost", "DEL_c", (0, 110, 110),
                   "DEL with each step's own cost as the weight, the fit's derivative down the whole pathwise chain "
                   "(the LR identity of each step's marginal; a third reading of thesis §3.3.1)",
                   compose(density_estimation_costs(weights="cost"), pathwise())),
)}

NAMED = tuple(ESTIMATORS)

SETTINGS = ("weighting", "baseline", "returns", "k_lr", "combiner", "robust_gamma", "robust_z", "messages")
_COMBINER_SETTINGS = ("k_lr", "combiner", "robust_gamma", "robust_z", "messages")
_COMBINER_FACTORIES = {"inverse_variance": inverse_variance, "robust": robust, "action_nodes": action_nodes}
CROSS_FIT = "cross_fit"  # k_lr="cross_fit": the cross-fitted schedule (schedules.cross_fitted), not a weight source


def _reweighted(name: str, parts: tuple, weighting: str) -> tuple:
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {weighting!r}")
    if LIKELIHOOD_RATIO not in (p.kind for p in parts):
        raise ValueError(f"weighting applies to a likelihood-ratio part, and {name!r} has none")
    if any(isinstance(p, DensityLR) for p in parts):
        raise ValueError(f"weighting: {name!r}'s LR part scores a fitted density, which has no batch weighting")

    def swap(p):
        if p.kind != LIKELIHOOD_RATIO:
            return p
        if weighting == "plain":
            return plain_lr()
        return p if isinstance(p, BiwLR) else biw_lr()

    return tuple(swap(p) for p in parts)


def _rebaselined(name: str, costs, parts: tuple, baseline: str):
    if isinstance(costs, DensityEstimationCosts):
        return density_estimation_costs(baseline, costs.weights), parts
    if any(isinstance(p, DensityLR) for p in parts):
        return costs, tuple(density_lr(baseline) if isinstance(p, DensityLR) else p for p in parts)
    if any(isinstance(p, BiwLR) for p in parts):
        return costs, tuple(biw_lr(baseline) if isinstance(p, BiwLR) else p for p in parts)
    if any(isinstance(p, PlainLR) for p in parts):
        return costs, tuple(plain_lr(baseline, p.returns) if isinstance(p, PlainLR) else p for p in parts)
    raise ValueError(f"baseline applies to BIW-LR or DEL, and {name!r} has neither")


def _recombined(name: str, combiner, num_parts: int, settings: dict):
    if num_parts != 2:
        raise ValueError(f"{sorted(settings)} only apply to total propagation (a pathwise and an LR part); {name!r} has one part")
    rule = settings.get("combiner", combiner.name)
    if rule not in _COMBINER_FACTORIES:
        raise ValueError(f"combiner must be one of {COMBINERS}, got {rule!r}")
    extra = sorted({"robust_gamma", "robust_z"} & set(settings))
    if extra and rule != "robust":
        raise ValueError(f"{extra} belong to the robust combiner; pass combiner='robust' as well")
    if rule == "action_nodes" and "messages" in settings:
        raise ValueError("messages: the action-node combiner mixes the state paths with a weight of their own; it takes no messages setting")
    kept = {f.name: getattr(combiner, f.name) for f in dataclasses.fields(combiner)}  # its source, messages, γ, z
    args = {"k_lr": settings.get("k_lr", kept["source"])}
    if rule != "action_nodes":
        args["messages"] = settings.get("messages", kept.get("messages", "mixed"))
    if rule == "robust":
        args["gamma"] = settings.get("robust_gamma", kept.get("gamma", float("inf")))
        args["z"] = settings.get("robust_z", kept.get("z", 2.0))
    return _COMBINER_FACTORIES[rule](**args)


def with_settings(name: str, est: Estimator, **settings) -> Estimator:
    """``est`` with some of its pieces' settings replaced; a setting no piece takes is refused by name.
    ``k_lr="cross_fit"`` gives the cross-fitted schedule with this combiner's rule."""
    unknown = set(settings) - set(SETTINGS)
    if unknown:
        raise ValueError(f"unknown estimator settings {sorted(unknown)}; the settings are {SETTINGS}, the name chooses the rest")
    if settings.get("k_lr") == CROSS_FIT:
        return cross_fitted(with_settings(name, est, **{**settings, "k_lr": "batch"}))
    costs, parts, combiner = est.costs, est.parts, est.combiner
    if "weighting" in settings:
        parts = _reweighted(name, parts, settings["weighting"])
    if "baseline" in settings:
        costs, parts = _rebaselined(name, costs, parts, settings["baseline"])
    if "returns" in settings:
        if not any(isinstance(p, PlainLR) for p in parts):
            raise ValueError(f"returns: the whole return (Suh et al.'s ZoBG) weighs a plain LR part, and {name!r} has "
                             "none (weighting='plain' gives one)")
        parts = tuple(plain_lr(p.baseline, settings["returns"]) if isinstance(p, PlainLR) else p for p in parts)
    combining = {k: settings[k] for k in _COMBINER_SETTINGS if k in settings}
    if combining:
        combiner = _recombined(name, combiner, len(parts), combining)
    return dataclasses.replace(est, costs=costs, parts=parts, combiner=combiner)


def named(name: str) -> NamedEstimator:
    """The registry's entry of ``name``; a ValueError names the choices."""
    if name not in ESTIMATORS:
        raise ValueError(f"unknown estimator {name!r}; choose one of {NAMED}")
    return ESTIMATORS[name]


def estimator(name: str, **settings) -> Estimator:
    """A named estimator with the library defaults, e.g. ``estimator("tp", k_lr="batch")``."""
    return with_settings(name, named(name).estimator, **settings)


def thesis_estimator(name: str, **settings) -> Estimator:
    """The thesis' own (biased) choices: the eq. 4.3 baseline and k_LR from the same batch; DEL's fit
    derivative down the whole pathwise chain."""
    entry = named(name)
    return with_settings(name, entry.thesis or entry.estimator, **settings)


def parse_spec(spec: str) -> tuple[str, dict]:
    """``"tp:k_lr=previous:messages=pathwise"`` → ("tp", {"k_lr": "previous", "messages": "pathwise"});
    a value that reads as a number is one."""
    name, *items = spec.strip().split(":")
    settings = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"estimator {spec!r}: expected NAME or NAME:SETTING=VALUE[:SETTING=VALUE...], got {item!r}")
        try:
            settings[key.strip()] = float(value)
        except ValueError:
            settings[key.strip()] = value.strip()
    named(name)
    return name, settings


def from_spec(spec: str, choices: str = "library") -> Estimator:
    """The estimator a spec names (:func:`parse_spec`), the library's or (``choices="thesis"``) the thesis' variant."""
    name, settings = parse_spec(spec)
    return (thesis_estimator if choices == "thesis" else estimator)(name, **settings)


def spec_label(spec: str) -> str:
    """``"tp:k_lr=previous"`` → ``"TP (k_lr=previous)"``."""
    name, settings = parse_spec(spec)
    shown = ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in settings.items())
    return named(name).label + (f" ({shown})" if shown else "")


def estimator_help() -> str:
    """The named estimators for a command's help: ``rp: RP, lr: BIW-LR, …``."""
    return ", ".join(f"{e.name}: {e.label}" for e in ESTIMATORS.values())


def estimator_table() -> str:
    """The Markdown table of the named estimators that docs/estimators.md shows."""
    rows = ["| name | label | what it is | the thesis' variant |", "|---|---|---|---|"]
    for e in ESTIMATORS.values():
        variant = e.thesis_variant or ("eq. 4.3 baseline" + (", `\"batch\"` k_LR" if e.weighs_parts else "") if e.thesis else "the same")
        rows.append(f"| `{e.name}` | {e.label} | {e.description} | {variant} |")
    return "\n".join(rows) + "\n"
