"""The method registry (pipps/experiments/methods.py): every method resolves and builds what it names."""

from __future__ import annotations

import dataclasses

import pytest

from pipps.experiments.config import ExperimentConfig, resolve_config
from pipps.experiments.methods import (
    FIXED_SEED,
    METHOD_SETTINGS,
    METHODS,
    MOMENTUM,
    PILCO_SEARCH,
    Method,
    Particles,
    method_estimator,
    particle_method,
)
from pipps.propagation.config import compose, estimator, thesis_estimator
from pipps.propagation.cost_terms import plain_costs
from pipps.propagation.parts import pathwise

#: What each method was before the registry (the decoding it replaces): estimator name, GP
#: variance, σ_n² factor (a setting's name), resampling, optimiser.
BEFORE = {
    "pilco": (None, None, None, None, PILCO_SEARCH),
    "rp": ("rp", True, None, "none", MOMENTUM),
    "rp_fs": ("rp", True, None, "none", FIXED_SEED),
    "gr": ("rp", True, None, "gaussian", MOMENTUM),
    "gr_fs": ("rp", True, None, "gaussian", FIXED_SEED),
    "lr": ("lr", True, None, "none", MOMENTUM),
    "tp": ("tp", True, None, "none", MOMENTUM),
    "tp-sf": ("tp", False, None, "none", MOMENTUM),
    "tp+sn": ("tp", True, "noise_boost_tp", "none", MOMENTUM),
    "gtp": ("gtp", True, None, "none", MOMENTUM),
    "glr": ("glr", True, None, "none", MOMENTUM),
    "gtp+sn": ("gtp", True, "noise_boost_gtp", "none", MOMENTUM),
    "del": ("del", True, None, "none", MOMENTUM),
}
LABELS = {"pilco": "PILCO", "rp": "RP", "rp_fs": "RP_FS", "gr": "GR", "gr_fs": "GR_FS", "lr": "LR", "tp": "TP",
          "tp-sf": "TP−σ_f", "tp+sn": "TP+σ_n", "gtp": "GTP", "glr": "GLR", "gtp+sn": "GTP+σ_n", "del": "DEL"}
FIELDS = {f.name for f in dataclasses.fields(ExperimentConfig)}


def test_the_registry_holds_the_thesis_methods_in_column_order_with_their_labels():
    assert {name: m.label for name, m in METHODS.items()} == LABELS and list(METHODS) == list(LABELS)
    assert all(name == m.name for name, m in METHODS.items())
    assert len({m.colour for m in METHODS.values()}) == len(METHODS)


@pytest.mark.parametrize("name", list(METHODS))
@pytest.mark.parametrize("choices", ["thesis", "library"])
def test_every_method_resolves_and_builds_what_it_names(name, choices):
    cfg = resolve_config("thesis", "cartpole_swingup", method=name)
    spec = cfg.method_spec
    est_name, variance, boost, resampling, optimizer = BEFORE[name]
    assert spec is METHODS[name] and spec.optimizer == optimizer and cfg.table_name == LABELS[name]
    assert cfg.is_pilco == (name == "pilco") and cfg.fixed_seed == name.endswith("_fs")
    if name == "pilco":
        assert spec.particles is None and spec.estimator is None
        with pytest.raises(ValueError, match="no particle estimator"):
            method_estimator(spec, choices)
        return
    rollout, est = particle_method(cfg.replace(estimator_choices=choices))
    assert est == (thesis_estimator(est_name) if choices == "thesis" else estimator(est_name))
    assert (rollout.num_particles, rollout.horizon) == (cfg.num_particles, cfg.horizon)
    assert rollout.model_variance == variance and rollout.resampling == resampling
    assert rollout.noise_multiplier == (getattr(cfg, boost) if boost else 1.0)
    assert rollout.noise_multiplier in ((100.0, 25.0) if boost else (1.0,))


def test_each_method_uses_the_settings_of_its_pieces():
    assert set(METHOD_SETTINGS) <= FIELDS
    assert set(METHOD_SETTINGS) == {s for m in METHODS.values() for s in m.settings}
    for m in METHODS.values():
        assert set(m.settings) <= set(METHOD_SETTINGS) and m.unused == set(METHOD_SETTINGS) - set(m.settings)
    assert METHODS["pilco"].settings == ("pilco_linesearches",)
    assert set(METHODS["rp_fs"].settings) == {"policy_evals", "num_particles", "store_particles", "variance_tol"}
    assert "variance_tol" not in METHODS["tp-sf"].settings  # no GP variance to approximate
    assert "noise_boost_tp" in METHODS["tp+sn"].settings and "noise_boost_tp" not in METHODS["tp"].settings
    # estimator_choices matters where the thesis' and the library's estimators differ
    assert {n for n, m in METHODS.items() if "estimator_choices" in m.settings} == {
        "lr", "tp", "tp-sf", "tp+sn", "gtp", "glr", "gtp+sn"}


def test_a_record_that_means_nothing_is_refused():
    with pytest.raises(ValueError, match="moment matching"):
        Method("x", "X", (0, 0, 0), PILCO_SEARCH, Particles(), "tp")
    with pytest.raises(ValueError, match="moment matching"):
        Method("x", "X", (0, 0, 0), MOMENTUM)
    with pytest.raises(ValueError, match="resampling"):
        Particles(resampling="systematic")


def test_a_method_may_name_a_composition_which_estimator_choices_leaves_alone():
    composed = compose(plain_costs(), pathwise())
    m = Method("rp2", "RP2", (1, 2, 3), MOMENTUM, Particles(), composed)
    assert method_estimator(m, "thesis") is composed and method_estimator(m, "library") is composed
    assert "estimator_choices" not in m.settings
