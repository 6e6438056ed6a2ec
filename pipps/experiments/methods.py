"""What each method of the thesis' tables is, in terms of the library's pieces (thesis §4.5).

=========  ============================================================================
method     policy optimisation between trials
=========  ============================================================================
pilco      moment matching (tasks.md §5), quasi-Newton on the exact gradient, PILCO's budget
rp         RP estimator, normalized momentum step (estimators.md §2, §8)
rp_fs      RP on a fixed seed (PEGASUS), quasi-Newton with ``policy_evals`` evaluations
gr         Gaussian resampling each step (§7), RP through it, normalized momentum
gr_fs      GR on a fixed seed, quasi-Newton
lr         BIW-LR (§3)
tp         total propagation of RP and BIW-LR (§4)
tp-sf      TP without the GP's epistemic variance (−σ_f)
tp+sn      TP with σ_n² × ``noise_boost_tp`` (thesis: 100)
gtp, glr   Gaussian-shaped TP and LR (§5)
gtp+sn     GTP with σ_n² × ``noise_boost_gtp`` (thesis: 25)
del        density-estimation LR (§6)
=========  ============================================================================

With ``estimator_choices="thesis"`` the LR parts use the thesis' eq. 4.3 baseline and TP its
same-batch ``k_LR`` (biased, docs/estimator-bias.md); ``"library"`` uses the unbiased defaults.
"""

from __future__ import annotations

from pipps.experiments.config import ExperimentConfig
from pipps.particles.forward import RolloutConfig
from pipps.propagation.config import Estimator, estimator, thesis_estimator

_ESTIMATOR_NAME = {
    "rp": "rp", "rp_fs": "rp", "gr": "rp", "gr_fs": "rp", "lr": "lr", "tp": "tp", "tp-sf": "tp",
    "tp+sn": "tp", "gtp": "gtp", "glr": "glr", "gtp+sn": "gtp", "del": "del",
}


def particle_method(cfg: ExperimentConfig) -> tuple[RolloutConfig, Estimator]:
    """The rollout settings and estimator of a particle method (not ``pilco``)."""
    if cfg.is_pilco:
        raise ValueError("pilco is not a particle method")
    name = _ESTIMATOR_NAME[cfg.method]
    est = thesis_estimator(name) if cfg.estimator_choices == "thesis" else estimator(name)
    noise = {"tp+sn": cfg.noise_boost_tp, "gtp+sn": cfg.noise_boost_gtp}.get(cfg.method, 1.0)
    rollout = RolloutConfig(
        num_particles=cfg.num_particles,
        horizon=cfg.horizon,
        model_variance=cfg.method != "tp-sf",
        noise_multiplier=noise,
        resampling="gaussian" if cfg.method in ("gr", "gr_fs") else "none",
    )
    return rollout, est
