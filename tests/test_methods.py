"""The method registry (pipps/experiments/methods.py): every method resolves and builds what it
names, and a setting a method does not use is refused when given and ignored for identity."""

from __future__ import annotations

import dataclasses
import json
import re

import pytest

from pipps.cli import main
from pipps.experiments.config import (
    ConfigError,
    ExperimentConfig,
    config_difference,
    config_hash,
    departures,
    experiment_name,
    preset_values,
    resolve_config,
    same_experiment,
)
from pipps.experiments.loop import ExperimentResult, _check_resumable
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
from pipps.experiments.results import write_result
from pipps.experiments.storage import MANIFEST, OutputError, claim_sweep_folder, existing_result
from pipps.reporting.tables import TABLES, collect, table_configs
from pipps.propagation.estimators import compose, estimator, thesis_estimator
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
    "del-cost": ("del_cost", True, None, "none", MOMENTUM),
    # a composition, the same under either estimator_choices: the thesis TP with the robust combiner
    "tp-robust": (thesis_estimator("tp", combiner="robust", robust_gamma=1.0, robust_z=2.0), True, None, "none", MOMENTUM),
}
LABELS = {"pilco": "PILCO", "rp": "RP", "rp_fs": "RP_FS", "gr": "GR", "gr_fs": "GR_FS", "lr": "LR", "tp": "TP",
          "tp-sf": "TP−σ_f", "tp+sn": "TP+σ_n", "gtp": "GTP", "glr": "GLR", "gtp+sn": "GTP+σ_n", "del": "DEL",
          "del-cost": "DEL_c", "tp-robust": "TP_robust"}
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
    if not isinstance(est_name, str):
        assert est == est_name
    else:
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
    assert METHODS["pilco"].settings == ("pilco_linesearches", "pilco_policy_noise")
    assert set(METHODS["rp_fs"].settings) == {"policy_evals", "num_particles", "store_particles", "variance_tol"}
    assert "variance_tol" not in METHODS["tp-sf"].settings  # no GP variance to approximate
    assert "noise_boost_tp" in METHODS["tp+sn"].settings and "noise_boost_tp" not in METHODS["tp"].settings
    # estimator_choices matters where the thesis' and the library's estimators differ
    assert {n for n, m in METHODS.items() if "estimator_choices" in m.settings} == {
        "lr", "tp", "tp-sf", "tp+sn", "gtp", "glr", "gtp+sn", "del"}


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


# -- a setting the method does not use: refused when given -------------------------------------------


@pytest.mark.parametrize("name", list(METHODS))
def test_an_explicit_unused_setting_is_refused_by_name(name):
    preset = preset_values("thesis", "cartpole_swingup")
    defaults = ExperimentConfig()
    for setting in sorted(METHODS[name].unused):
        value = preset.get(setting, getattr(defaults, setting))  # the preset's own value: the key is refused
        with pytest.raises(ConfigError, match=rf"^{setting}: {re.escape(name)} does not use it"):
            resolve_config("thesis", "cartpole_swingup", method=name, **{setting: value})
    for setting in METHODS[name].settings:  # and what it uses is accepted
        resolve_config("thesis", "cartpole_swingup", method=name, **{setting: getattr(defaults, setting)})


def test_the_issues_example_is_refused_and_preset_values_are_not():
    with pytest.raises(ConfigError, match="^num_particles: pilco does not use it"):
        resolve_config("thesis", "cartpole_swingup", method="pilco", num_particles=7, learning_rate=9)
    assert resolve_config("quick", "cartpole_swingup", method="pilco").num_particles == 50  # the preset's, kept
    assert resolve_config("pilco", "unicycle", method="rp").estimator_choices == "library"


def test_the_cli_refuses_an_unused_setting_by_name(tmp_path, capsys):
    code = main(["run", "--method", "pilco", "--particles", "7", "--out", str(tmp_path / "a.h5")])
    assert code == 2 and "num_particles: pilco does not use it" in capsys.readouterr().err
    code = main(["run", "--method", "tp", "--set", "pilco_linesearches=5", "--out", str(tmp_path / "b.h5")])
    assert code == 2 and "pilco_linesearches: tp does not use it" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_a_sweep_applies_each_setting_to_the_methods_that_use_it():
    cfgs = table_configs("4.1", 1, "thesis", methods=["tp", "pilco"], ks=[1.0], overrides={"num_particles": 7})
    assert {c.method: c.num_particles for c in cfgs} == {"pilco": 300, "tp": 7}
    assert departures(next(c for c in cfgs if c.method == "pilco")) == {}
    with pytest.raises(ConfigError, match=r"^pilco_linesearches: no method of the sweep uses it \(tp\)"):
        table_configs("4.1", 1, "thesis", methods=["tp"], ks=[1.0], overrides={"pilco_linesearches": 5})


def test_a_sweep_folder_holds_each_methods_share_of_its_settings(tmp_path):
    both = table_configs("4.1", 1, "thesis", methods=["tp", "pilco"], ks=[1.0], overrides={"num_particles": 7})
    claim_sweep_folder(tmp_path, both)
    assert json.loads((tmp_path / MANIFEST).read_text()) == {"protocol": "thesis", "settings": {"num_particles": 7}}
    claim_sweep_folder(tmp_path, table_configs("4.1", 1, "thesis", methods=["pilco"], ks=[1.0]))  # PILCO follows it
    with pytest.raises(OutputError, match="holds a sweep run with --preset thesis with num_particles=7"):
        claim_sweep_folder(tmp_path, table_configs("4.1", 1, "thesis", methods=["tp"], ks=[1.0]))


# -- ... and ignored for identity -----------------------------------------------------------------------


IGNORED = [("pilco", dict(num_particles=7, learning_rate=9.0, estimator_choices="library")),
           ("rp", dict(estimator_choices="library", noise_boost_tp=3.0)),
           ("rp_fs", dict(learning_rate=9.0, momentum=0.5)),
           ("tp-sf", dict(variance_tol=1e-2)),
           ("tp", dict(noise_boost_gtp=3.0, pilco_linesearches=5)), ("gr", dict(pilco_policy_noise=True))]
COUNTED = [("pilco", dict(pilco_linesearches=5)), ("pilco", dict(pilco_policy_noise=True)),
           ("tp+sn", dict(noise_boost_tp=3.0)),
           ("tp", dict(estimator_choices="library")), ("rp", dict(num_particles=7))]


@pytest.mark.parametrize("name, changes", IGNORED)
def test_identity_ignores_what_the_method_does_not_use(name, changes):
    cfg = resolve_config("thesis", "cartpole_swingup", method=name)
    other = cfg.replace(**changes)  # as a stored file may hold it
    assert other != cfg and same_experiment(other, cfg) and config_hash(other) == config_hash(cfg)
    assert experiment_name(other) == experiment_name(cfg) and departures(other) == {}
    assert config_difference(other, cfg) == ""


@pytest.mark.parametrize("name, changes", COUNTED)
def test_identity_keeps_what_the_method_uses(name, changes):
    cfg = resolve_config("thesis", "cartpole_swingup", method=name)
    other = cfg.replace(**changes)
    assert not same_experiment(other, cfg) and config_hash(other) != config_hash(cfg)
    assert set(departures(other)) == set(changes) and experiment_name(other) != experiment_name(cfg)


def test_resume_ignores_and_pooling_does_not_warn_about_unused_settings(tmp_path):
    cfg = resolve_config("thesis", "cartpole_swingup", method="pilco")
    stored = cfg.replace(num_particles=7, learning_rate=9.0)
    _check_resumable(cfg, ExperimentResult(stored, []))
    with pytest.raises(ValueError, match="pilco_linesearches"):
        _check_resumable(cfg, ExperimentResult(cfg.replace(pilco_linesearches=5), []))
    path = tmp_path / f"{experiment_name(cfg)}.h5"
    write_result(path, ExperimentResult(stored, []))
    assert existing_result(path, cfg).kind == "unfinished"
    assert existing_result(path, cfg.replace(pilco_linesearches=5)).kind == "other"

    cfgs = table_configs("4.1", 2, "thesis", methods=["pilco"], ks=[1.0])
    summaries = [{"config": c.replace(num_particles=7) if c.seed else c, "success": True, "final_return": 1.0,
                  "wall_seconds": 1.0} for c in cfgs]
    (cell,) = [r for r in collect(TABLES["4.1"], summaries) if r.n]
    assert cell.n == 2 and cell.mixed == ()
    summaries[1]["config"] = cfgs[1].replace(pilco_linesearches=5)
    (cell,) = [r for r in collect(TABLES["4.1"], summaries, custom=True) if r.n]
    assert cell.n == 2 and cell.mixed == ("pilco_linesearches",)


#: Hashes and names of configurations as they were before the methods declared their settings (the
#: quick preset gives PILCO num_particles=50, the pilco preset gives RP estimator_choices=library,
#: settings neither uses): a configuration that leaves such a setting alone keeps both.
KEPT = [
    ("quick", "cartpole_swingup", dict(method="pilco"), "0afe49457a56", "cartpole_swingup_angle_k1_pilco_quick_s0"),
    ("quick", "cartpole_swingup", dict(method="pilco", num_learned=3), "53d2524c4d69",
     "cartpole_swingup_angle_k1_pilco_quick_s0_c53d2524c"),
    ("pilco", "cartpole_swingup", dict(method="rp", cost="angle"), "8cd40812d2bf",
     "cartpole_swingup_angle_k1_rp_pilco_s0"),
    ("pilco", "unicycle", dict(method="rp_fs", num_learned=3), "8d24174c7daa",
     "unicycle_default_k1_rp_fs_pilco_s0_c8d24174c"),
    ("thesis", "cartpole_swingup", dict(method="tp"), "8a4a4c4b8742", "cartpole_swingup_angle_k1_tp_thesis_s0"),
]


@pytest.mark.parametrize("preset, task, values, digest, name", KEPT)
def test_configurations_that_leave_unused_settings_alone_keep_their_hash_and_name(preset, task, values, digest, name):
    cfg = resolve_config(preset, task, **values)
    assert config_hash(cfg)[:12] == digest and experiment_name(cfg) == name
