"""The method registry: what each method of the thesis' tables is, in the library's pieces (thesis §4.5).

A :class:`Method` is one record: the name ``--method`` takes, the thesis' table label and a plot
colour, how it predicts (a :class:`Particles` rollout, or PILCO's moment matching), the gradient
estimator it follows, and how it optimises the policy between trials (an :class:`Optimizer`). The
:class:`~pipps.experiments.config.ExperimentConfig` settings it uses follow from those pieces
(:attr:`Method.settings`); the other method-specific settings (:data:`METHOD_SETTINGS`) it does
not use (:attr:`Method.unused`). Validation, resume, tables, figures and the CLI read this
registry, :data:`METHODS`, instead of decoding method names.

=========  ==========  ============================================================================
method     label       prediction, gradient, optimiser
=========  ==========  ============================================================================
pilco      PILCO       moment matching (thesis Alg. 2), its exact gradient, quasi-Newton with PILCO's budget
rp         RP          particles, RP estimator, normalized momentum step (thesis §4.5.1)
rp_fs      RP_FS       fixed seed (PEGASUS), RP by autodiff, quasi-Newton with ``policy_evals`` evaluations
gr         GR          Gaussian resampling each step (thesis §4.3.1), RP through it, normalized momentum
gr_fs      GR_FS       GR on a fixed seed, quasi-Newton
lr         LR          BIW-LR (thesis eq. 4.2–4.3)
tp         TP          total propagation of RP and BIW-LR (thesis Alg. 5)
tp-sf      TP−σ_f      TP without the GP's epistemic variance (−σ_f)
tp+sn      TP+σ_n      TP with σ_n² × ``noise_boost_tp`` (thesis: 100)
gtp, glr   GTP, GLR    Gaussian-shaped TP and LR (thesis §3.3.2, Alg. 6)
gtp+sn     GTP+σ_n     GTP with σ_n² × ``noise_boost_gtp`` (thesis: 25)
del        DEL         density-estimation LR (thesis §3.3.1)
tp-robust  TP_robust   the thesis' TP with Suh et al.'s robust (AoBG) weight, γ = 1 (beyond the thesis)
=========  ==========  ============================================================================

With ``estimator_choices="thesis"`` the LR parts use the thesis' eq. 4.3 baseline and TP its
same-batch ``k_LR`` (biased, docs/estimator-bias.md), and DEL carries its density fit's derivative
down the whole pathwise chain; ``"library"`` uses the library defaults (the unbiased "previous"
baseline, for TP the leave-one-out ``k_LR`` (docs/estimator-variance.md), for DEL the fit's
derivative one step to θ). A method whose estimator is the same either way (RP and its variants)
does not use ``estimator_choices``.

**A setting a method does not use** cannot change its experiment. It is left out of the
experiment's identity (:func:`pipps.experiments.config.canonical`: the file name, ``config_hash``,
resume and pooling checks), and an explicit override of it is refused by name
(:func:`pipps.experiments.config.resolve_config`; a sweep applies each ``--set`` to the methods
that use it).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from pipps.experiments.config import ExperimentConfig


@dataclasses.dataclass(frozen=True)
class Optimizer:
    """How a method optimises the policy between trials, and the settings that configure it."""

    name: str
    description: str
    settings: tuple[str, ...]


#: the estimator's stochastic gradient, normalized momentum step (thesis §4.5.1)
MOMENTUM = Optimizer("momentum", "normalized momentum on the estimator's gradient, policy_evals steps",
                     ("policy_evals", "learning_rate", "momentum", "progress_chunk"))
#: quasi-Newton on one noise draw's particle objective, fixed for the whole search (PEGASUS)
FIXED_SEED = Optimizer("fixed_seed", "quasi-Newton on a fixed seed's particle objective, policy_evals evaluations",
                       ("policy_evals",))
#: PILCO's quasi-Newton on the moment-matching objective, with its line-search budget (its settings_*.m);
#: ``pilco_policy_noise`` adds PILCO V0.9's policy-input noise term to that objective (docs/pilco.md)
PILCO_SEARCH = Optimizer("pilco", "quasi-Newton on the moment-matching objective, PILCO's line-search budget",
                         ("pilco_linesearches", "pilco_policy_noise"))


@dataclasses.dataclass(frozen=True)
class Particles:
    """How a particle method rolls out the model (thesis §4.5.1; :class:`pipps.particles.RolloutConfig`).

    ``model_variance=False`` is the ``−σ_f`` variant (no GP epistemic variance); ``noise_boost``
    names the :class:`~pipps.experiments.config.ExperimentConfig` setting that multiplies σ_n²
    (the ``+σ_n`` variants); ``resampling="gaussian"`` is GR (thesis §4.3.1).
    """

    model_variance: bool = True
    noise_boost: str | None = None
    resampling: str = "none"

    def __post_init__(self):
        if self.resampling not in ("none", "gaussian"):
            raise ValueError(f"resampling must be 'none' or 'gaussian', got {self.resampling!r}")

    @property
    def settings(self) -> tuple[str, ...]:
        """The settings this rollout reads (``variance_tol`` approximates the GP variance it uses)."""
        return (("num_particles", "store_particles") + (("variance_tol",) if self.model_variance else ())
                + ((self.noise_boost,) if self.noise_boost else ()))


@dataclasses.dataclass(frozen=True)
class Method:
    """One method of the tables: its names, prediction, gradient and optimiser.

    ``particles=None`` and ``estimator=None`` mean PILCO's moment matching with its exact
    gradient, which only :data:`PILCO_SEARCH` optimises. ``estimator`` is a name in
    :data:`pipps.propagation.estimators.ESTIMATORS` (its thesis or library variant by
    ``estimator_choices``) or a composition (:func:`pipps.propagation.estimators.compose`), used as is.
    A :data:`FIXED_SEED` method follows its estimator's gradient by differentiating the fixed
    seed's objective.
    """

    name: str
    label: str
    colour: tuple[int, int, int]
    optimizer: Optimizer
    particles: Particles | None = None
    estimator: Any = None
    description: str = ""

    def __post_init__(self):
        moment_matching = self.optimizer == PILCO_SEARCH
        if moment_matching != (self.particles is None) or moment_matching != (self.estimator is None):
            raise ValueError(f"method {self.name!r}: PILCO's search goes with moment matching (no particles, no "
                             "estimator), and every other optimiser with a particle rollout and an estimator")

    @property
    def moment_matching(self) -> bool:
        """PILCO: the policy is optimised on the moment-matched Gaussian prediction."""
        return self.particles is None

    @property
    def fixed_seed(self) -> bool:
        return self.optimizer == FIXED_SEED

    @property
    def settings(self) -> tuple[str, ...]:
        """The method-specific settings it uses (every method uses every setting outside :data:`METHOD_SETTINGS`)."""
        own = self.optimizer.settings + (self.particles.settings if self.particles else ())
        if self.optimizer == MOMENTUM and _choices_matter(self.estimator):
            own += ("estimator_choices",)
        return tuple(dict.fromkeys(own))

    @property
    def unused(self) -> frozenset[str]:
        """The method-specific settings it does not use: they cannot change its experiment."""
        return frozenset(METHOD_SETTINGS) - frozenset(self.settings)


@functools.cache
def _choices_matter(name_or_estimator) -> bool:
    """Whether ``estimator_choices`` changes the estimator: its thesis and library variants differ."""
    if not isinstance(name_or_estimator, str):
        return False
    from pipps.propagation.estimators import estimator, thesis_estimator

    return thesis_estimator(name_or_estimator) != estimator(name_or_estimator)


def _robust_tp():
    """The thesis' TP (eq. 4.3 baseline, this batch's weight) with the robust combiner, γ = 1, z = 2: the
    bound that the thesis preset's TP snapshots put at a middle scale (docs/contact.md, "Through the
    learning loop")."""
    from pipps.propagation.estimators import thesis_estimator

    return thesis_estimator("tp", combiner="robust", robust_gamma=1.0, robust_z=2.0)


def _particle_method(name, label, colour, estimator, description, optimizer=MOMENTUM, **rollout) -> Method:
    return Method(name, label, colour, optimizer, Particles(**rollout), estimator, description)


#: Every method, in the thesis' column order (the CLI's ``--method`` choices).
METHODS: dict[str, Method] = {m.name: m for m in (
    Method("pilco", "PILCO", (214, 39, 40), PILCO_SEARCH,
           description="moment matching (thesis Alg. 2), quasi-Newton on the exact gradient, PILCO's budget"),
    _particle_method("rp", "RP", (255, 127, 14), "rp", "RP estimator, normalized momentum"),
    _particle_method("rp_fs", "RP_FS", (188, 189, 34), "rp", "RP on a fixed seed (PEGASUS), quasi-Newton",
                     optimizer=FIXED_SEED),
    _particle_method("gr", "GR", (148, 103, 189), "rp", "Gaussian resampling each step, RP through it",
                     resampling="gaussian"),
    _particle_method("gr_fs", "GR_FS", (140, 86, 75), "rp", "GR on a fixed seed, quasi-Newton",
                     optimizer=FIXED_SEED, resampling="gaussian"),
    _particle_method("lr", "LR", (44, 160, 44), "lr", "BIW-LR"),
    _particle_method("tp", "TP", (31, 119, 180), "tp", "total propagation of RP and BIW-LR"),
    _particle_method("tp-sf", "TP−σ_f", (23, 190, 207), "tp", "TP without the GP's epistemic variance",
                     model_variance=False),
    _particle_method("tp+sn", "TP+σ_n", (127, 127, 127), "tp", "TP with σ_n² × noise_boost_tp",
                     noise_boost="noise_boost_tp"),
    _particle_method("gtp", "GTP", (227, 119, 194), "gtp", "Gaussian-shaped TP"),
    _particle_method("glr", "GLR", (80, 80, 160), "glr", "Gaussian-shaped LR"),
    _particle_method("gtp+sn", "GTP+σ_n", (100, 100, 100), "gtp", "GTP with σ_n² × noise_boost_gtp",
                     noise_boost="noise_boost_gtp"),
    _particle_method("del", "DEL", (0, 0, 0), "del", "density-estimation LR"),
    _particle_method("del-cost", "DEL_c", (0, 110, 110), "del_cost",
                     "density-estimation LR weighted by each step's own cost, down the whole pathwise chain"),
    _particle_method("tp-robust", "TP_robust", (255, 187, 120), _robust_tp(),
                     "the thesis' TP with Suh et al.'s robust weight (AoBG's bound γ = 1, z = 2) in place of the "
                     "inverse-variance one"),
)}

#: The settings some methods use and others do not: those of each optimiser and particle rollout,
#: and ``estimator_choices``. Every other setting belongs to every method.
METHOD_SETTINGS: tuple[str, ...] = tuple(dict.fromkeys(
    [s for m in METHODS.values() for s in m.optimizer.settings + (m.particles.settings if m.particles else ())]
    + ["estimator_choices"]))


def get_method(name: str) -> Method:
    """The registry's record of ``name``; a ValueError names the choices."""
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; choose one of {', '.join(METHODS)}")
    return METHODS[name]


def method_estimator(method: Method, choices: str):
    """The estimator ``method`` follows with ``estimator_choices=choices`` (thesis or library)."""
    from pipps.propagation.estimators import estimator, thesis_estimator

    if method.estimator is None:
        raise ValueError(f"{method.name} has no particle estimator (it differentiates its moment-matching objective)")
    if not isinstance(method.estimator, str):
        return method.estimator
    return thesis_estimator(method.estimator) if choices == "thesis" else estimator(method.estimator)


def rollout_config(cfg: ExperimentConfig):
    """The :class:`pipps.particles.RolloutConfig` of a particle method's configuration."""
    from pipps.particles.forward import RolloutConfig

    particles = get_method(cfg.method).particles
    if particles is None:
        raise ValueError(f"{cfg.method} is not a particle method")
    return RolloutConfig(
        num_particles=cfg.num_particles,
        horizon=cfg.horizon,
        model_variance=particles.model_variance,
        noise_multiplier=getattr(cfg, particles.noise_boost) if particles.noise_boost else 1.0,
        resampling=particles.resampling,
    )


def particle_method(cfg: ExperimentConfig):
    """The rollout settings and estimator of a particle method's configuration (not ``pilco``)."""
    return rollout_config(cfg), method_estimator(get_method(cfg.method), cfg.estimator_choices)
