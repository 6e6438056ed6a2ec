"""The learning loop, HDF5 results, sweeps, tables and the CLI (docs/experiments.md).

The tiny experiments here use the quick preset shrunk further (a few particles, policy steps and
rollouts): they test the plumbing exactly — determinism, resumption, the schema, failure
handling — not learning. Learning itself is checked by ``test_quick_preset_learns`` (a reduced
quick run in the default suite) and by the full quick preset under ``-m slow``.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import time

import h5py
import jax
import numpy as np
import pytest

from pipps.experiments import ConfigError, resolve_config, run_experiment
from pipps.experiments.config import config_hash, departures, same_experiment
from pipps.experiments.results import (
    ResultError,
    check_result,
    is_complete,
    read_result,
    read_summary,
    write_result,
)
from pipps.experiments.sweep import (accelerator_installed, cpu_layout, experiment_name, ray_task, run_sweep,
                                     worker_pool)
from pipps.reporting.tables import (TABLES, collect, render_cell_curves, render_curves, render_seeds, render_table,
                                     table_configs, wilson_interval)

TINY = dict(num_learned=1, num_particles=8, policy_evals=6, eval_rollouts=3, gp_max_iters=10, progress_chunk=3,
            store_particles=4)


def tiny(**kw):
    return resolve_config("quick", kw.pop("task", "cartpole_swingup"), **{**TINY, **kw})


def assert_same_results(a, b):
    assert a.config == b.config
    assert len(a.trials) == len(b.trials)
    for ta, tb in zip(a.trials, b.trials):
        for name in ("states", "actions", "eval_returns", "policy"):
            np.testing.assert_array_equal(getattr(ta, name), getattr(tb, name), err_msg=name)


# -- configuration -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "overrides, setting",
    [
        (dict(method="sgd"), "method"),
        (dict(k=-1.0), "k"),
        (dict(k=float("nan")), "k"),
        (dict(num_particles=0), "num_particles"),
        (dict(num_particles=1), "num_particles"),
        (dict(policy_evals=0), "policy_evals"),
        (dict(cost="tip"), None),  # valid
        (dict(cost="height"), "cost"),
        (dict(momentum=1.0), "momentum"),
        (dict(learning_rate=0.0), "learning_rate"),
        (dict(num_random=0), "num_random"),
        (dict(no_such_setting=1), "no_such_setting"),
        (dict(num_particles="many"), "num_particles"),
        (dict(centre_std=0.0), "centre_std"),
    ],
)
def test_invalid_settings_fail_at_once_naming_the_setting(overrides, setting):
    if setting is None:
        assert resolve_config("thesis", "cartpole_swingup", **overrides).cost == "tip"
        return
    with pytest.raises(ConfigError, match=rf"^{setting}:"):
        resolve_config("thesis", "cartpole_swingup", **overrides)


def test_bad_preset_and_task_are_named():
    with pytest.raises(ConfigError, match="^preset:"):
        resolve_config("fast", "cartpole_swingup")
    with pytest.raises(ConfigError, match="^task:"):
        resolve_config("thesis", "acrobot")


def test_thesis_preset_is_the_thesis_protocol():
    """The thesis preset (docs/experiments.md, "Presets"): 1 + 15 trials / 5 + 30, P = 300, 600 evaluations,
    α = 5e-4, γ = 0.9, 50 centres, 30 evals."""
    c = resolve_config("thesis", "cartpole_swingup")
    assert (c.num_random, c.num_learned, c.num_particles, c.policy_evals) == (1, 15, 300, 600)
    assert (c.learning_rate, c.momentum, c.num_basis, c.eval_rollouts) == (5e-4, 0.9, 50, 30)
    assert (c.policy, c.policy_init, c.log_lambda_init, c.estimator_choices) == ("rbf", "start", (0.0,), "thesis")
    assert c.centre_std == 1.0  # the documented departure (docs/results.md)
    assert resolve_config("thesis", "cartpole_swingup", centre_std="none").centre_std is None
    assert c.success_threshold == 15.0
    u = resolve_config("thesis", "unicycle")
    assert (u.num_random, u.num_learned, u.policy) == (5, 30, "linear")


def test_string_overrides_are_typed():
    c = resolve_config("thesis", "cartpole_swingup", k="4", num_particles="100", log_lambda_init="0,2,4,2",
                       horizon="none")
    assert (c.k, c.num_particles, c.log_lambda_init, c.horizon) == (4.0, 100, (0.0, 2.0, 4.0, 2.0), None)


# -- tables ----------------------------------------------------------------------------------------


def test_wilson_interval_matches_scipy():
    from scipy.stats import binomtest

    for s, n in [(0, 10), (5, 10), (99, 100), (1, 3), (20, 20)]:
        ci = binomtest(s, n).proportion_ci(confidence_level=0.95, method="wilson")
        np.testing.assert_allclose(wilson_interval(s, n), (ci.low, ci.high), atol=1e-12)


def test_tables_hold_the_thesis_values_and_expand_to_configs():
    t41 = TABLES["4.1"]
    assert len(t41.cells) == 5 * 7 + 4 + 1  # 7 methods in every row; TP−σ_f in 4 rows, TP+σ_n in 1
    cell = next(c for c in t41.cells if c.method == "tp" and dict(c.values)["k"] == 1.0)
    assert cell.thesis == 0.99
    cfgs = table_configs("4.1", 3, "thesis", methods=["tp", "pilco"], ks=[1.0])
    assert [(c.method, c.seed) for c in cfgs] == [("pilco", 0), ("tp", 0), ("pilco", 1), ("tp", 1), ("pilco", 2), ("tp", 2)]
    assert all(c.k == 1.0 and c.cost == "angle" and c.num_particles == 300 for c in cfgs)
    assert len(table_configs("4.3", 1)) == 30
    q = table_configs("q001", 1)
    assert {c.cost_scale for c in q} == {0.01}
    with pytest.raises(ValueError, match="method"):
        table_configs("4.1", 1, methods=["nope"])


def _per_seed(seed, passes, balanced=None, rollouts=10):
    """Per-seed readings of a final trial with ``passes`` of ``rollouts`` below the threshold and
    ``balanced`` of them balanced (default: the same ones)."""
    from pipps.reporting.readings import seed_values

    balanced = passes if balanced is None else balanced
    i = np.arange(rollouts)
    return seed_values(seed, np.where(i < passes, 10.0, 20.0), i < balanced, 10.0, 15.0, 0.5)


def test_table_counts_cells_and_flags_disagreement():
    from pipps.reporting.readings import clustered_interval

    cfgs = table_configs("4.1", 10, "thesis", methods=["tp"], ks=[1.0, 16.0])
    # k = 1: half the seeds pass every rollout, half none (0.50); k = 16: every seed 4 of 10 (0.40)
    summaries = [{"config": c, "success": c.seed < (9 if c.k == 1.0 else 1), "final_return": 10.0 + c.seed,
                  "wall_seconds": 60.0, "per_seed": _per_seed(c.seed, (10 if c.seed < 5 else 0) if c.k == 1.0 else 4)}
                 for c in cfgs]
    cells = {(r.cell.row, r.cell.method): r for r in collect(TABLES["4.1"], summaries)}
    k1, k16 = cells[("k = 1", "tp")], cells[("k = 16", "tp")]
    assert (k1.successes, k1.n, k16.successes, k16.n) == (9, 10, 1, 10)  # the per-seed physical verdicts
    assert (k1.rate, k16.rate) == (0.5, 0.4)  # the headline: per trial, return
    lo1, hi1 = clustered_interval([10] * 5 + [0] * 5, [10] * 10)
    lo16, hi16 = clustered_interval([4] * 10, [10] * 10)
    assert k1.interval == (lo1, hi1) and hi1 < 0.99 and lo16 < 0.40 < hi16
    assert k1.agrees is False and k16.agrees is True
    text = render_table(TABLES["4.1"], list(cells.values()))
    assert f"0.50 [{lo1:.2f}, {hi1:.2f}] (10) / 0.99 !" in text and f"0.40 [{lo16:.2f}, {hi16:.2f}] (10) / 0.40 |" in text
    assert "| k = 16 | TP | 10 | 0.40 | 0.40 [" in text  # the every-reading table
    assert cells[("k = 4", "tp")].n == 0
    assert k1.mixed == () and "Warning" not in text
    summaries[1] = dict(summaries[1], config=summaries[1]["config"].replace(cost=None))  # None ≡ the preset's angle
    assert next(r for r in collect(TABLES["4.1"], summaries) if r.cell.row == "k = 1").mixed == ()
    summaries[0] = dict(summaries[0], config=summaries[0]["config"].replace(centre_std=None))
    # a result departing from the thesis preset is not counted by default (docs/reliability.md) ...
    assert next(r for r in collect(TABLES["4.1"], summaries) if r.cell.row == "k = 1" and r.cell.method == "tp").n == 9
    # ... and with custom=True it is, and the pooled settings are named
    mixed = collect(TABLES["4.1"], summaries, custom=True)
    assert next(r for r in mixed if r.cell.row == "k = 1" and r.cell.method == "tp").mixed == ("centre_std",)
    assert "pools results whose settings differ in centre_std" in render_table(TABLES["4.1"], mixed)
    empty = render_table(TABLES["4.4"], collect(TABLES["4.4"], summaries))  # cart-pole results only
    assert empty == "**Table 4.4 — unicycle balancing**: no complete results for this table."


def test_table_names_seeds_near_the_line_and_the_command_that_checks_them():
    """A seed whose verdict a fresh evaluation would flip with probability above 5 % is named under
    the table, and the re-simulation command that checks it is named once; with no such seed, neither."""
    from pipps.reporting.tables import RESIMULATE_HINT

    cfgs = table_configs("4.1", 4, "thesis", methods=["tp", "pilco"], ks=[1.0])
    summaries = [{"config": c, "success": True, "final_return": 10.0, "wall_seconds": 60.0,
                  "per_seed": _per_seed(c.seed, 10), "flip": 0.3 if c.seed in (1, 3) else 0.01} for c in cfgs]
    text = render_table(TABLES["4.1"], collect(TABLES["4.1"], summaries))
    assert "k = 1, TP: a fresh evaluation would flip the per-seed physical verdict with probability > 5 % on seed(s) 1, 3." in text
    assert "k = 1, PILCO: a fresh evaluation would flip" in text
    assert text.count(RESIMULATE_HINT) == 1 and text.rstrip().endswith(RESIMULATE_HINT)
    calm = [dict(s, flip=0.01) for s in summaries]
    text = render_table(TABLES["4.1"], collect(TABLES["4.1"], calm))
    assert "a fresh evaluation would flip" not in text and RESIMULATE_HINT not in text


def test_seed_rows_list_each_counted_seed_in_order_with_both_counts():
    cfgs = table_configs("4.1", 6, "thesis", methods=["tp"], ks=[9.0])
    summaries = [{"config": c, "success": c.seed == 4, "return_success": c.seed < 3, "final_return": 12.0 + c.seed / 4,
                  "final_balanced": 0.1 * c.seed, "wall_seconds": 60.0, "per_seed": _per_seed(c.seed, 10 - c.seed)}
                 for c in cfgs if c.seed != 3]
    summaries.reverse()  # the rows come out in seed order whatever the order read
    summaries.append(dict(summaries[0], config=summaries[0]["config"].replace(centre_std=None)))  # not counted
    text = render_seeds(TABLES["4.1"], summaries).splitlines()
    assert text[2].count("|") == 9 and len(text) == 5
    assert text[4] == ("| k = 9 | TP | 0–2, 4–5 | 12.00, 12.25, 12.50, 13.00, 13.25 | 1.00, 0.90, 0.80, 0.60, 0.50 "
                       "| 0.00, 0.10, 0.20, 0.40, 0.50 "
                       "| 1 / 5 | 3 / 5 |")
    assert render_seeds(TABLES["4.4"], summaries) == ""



def test_a_comparison_by_a_setting_counts_each_value_apart_with_the_difference():
    """pipps table --by (e.g. the library's TP rule next to the thesis'): the groups follow the
    stored setting, a result departing from the preset only there counts without --custom, and the
    difference and p are those of the two groups' counts."""
    from scipy.stats import binomtest, mannwhitneyu, wilcoxon

    from pipps.reporting.tables import (counts, difference_interval, fisher_exact, render_comparison, render_paired,
                                         split_by)
    from pipps.reporting.readings import clustered_interval, newcombe_interval

    cfgs = table_configs("4.1", 10, "thesis", methods=["tp"], ks=[1.0, 9.0])
    lib = [c.replace(estimator_choices="library") for c in cfgs if c.k == 1.0]
    summaries = ([{"config": c, "success": c.seed < 9, "return_success": True, "final_return": 8.0 + c.seed / 10,
                   "final_balanced": 1.0, "wall_seconds": 60.0, "per_seed": _per_seed(c.seed, 10)} for c in lib]
                 + [{"config": c, "success": c.seed < (5 if c.k == 1.0 else 2), "return_success": c.seed < 8,
                     "final_return": 9.0 + c.seed, "final_balanced": 0.9, "wall_seconds": 60.0,
                     "per_seed": _per_seed(c.seed, 6 + c.seed % 3)} for c in cfgs])
    assert counts(lib[0], "thesis") and not counts(lib[0], "thesis", vary="estimator_choices")
    assert counts(lib[0].replace(centre_std=None), "thesis", vary="estimator_choices")  # another departure still excludes
    groups = split_by(summaries, "estimator_choices")
    assert [(v, len(rows)) for v, rows in groups] == [("library", 10), ("thesis", 20)]  # in the order met
    text = render_comparison(TABLES["4.1"], "estimator_choices",
                             [(v, collect(TABLES["4.1"], rows, custom=True)) for v, rows in groups])
    lines = text.splitlines()

    def cells(line):
        return [c.strip() for c in line.split("|")[1:-1]]

    assert cells(lines[2]) == ["", "method", "thesis", "estimator_choices = library", "estimator_choices = thesis",
                               "headline: library − thesis [95 %], permutation p",
                               "per seed, physical: library − thesis [95 %], Fisher p",
                               "per seed, return: library − thesis [95 %], Fisher p",
                               "final return, median: library vs thesis, Mann–Whitney p",
                               "balanced, median: library vs thesis, Mann–Whitney p"]
    k1 = cells(next(line for line in lines if line.startswith("| k = 1 |")))
    lo, hi = difference_interval(9, 10, 5, 10)
    thesis_passes = [6 + s % 3 for s in range(10)]  # 6, 7, 8, ...: 69 of 100 rollouts
    lo_t, hi_t = clustered_interval(thesis_passes, [10] * 10)
    lo_l, hi_l = clustered_interval([10] * 10, [10] * 10)
    assert k1[:5] == ["k = 1", "TP", "0.99", f"1.00 [{lo_l:.2f}, {hi_l:.2f}] (10) · physical 9/10",
                      f"0.69 [{lo_t:.2f}, {hi_t:.2f}] (10) · physical 5/10"]
    # every library seed (1.0) lies above every thesis seed (0.6–0.8): the permutation p of complete
    # separation, 2 / C(20, 10) = 1.1e-5, prints as below 1e-4; the interval is Newcombe's from the two seed-level ones
    d_lo, d_hi = newcombe_interval(1.0, (lo_l, hi_l), 0.69, (lo_t, hi_t))
    assert k1[5] == f"+0.31 [{d_lo:+.2f}, {d_hi:+.2f}], p < 1e-4"
    assert k1[6] == f"+0.40 [{lo:+.2f}, {hi:+.2f}], p = {fisher_exact(9, 10, 5, 10):.2g}"
    assert k1[7].startswith("+0.20 [") and k1[7].endswith(f"p = {fisher_exact(10, 10, 8, 10):.2g}")
    # every library return (8.0–8.9) lies below every thesis one (9–18): the exact Mann–Whitney p of
    # complete separation at 10 and 10 is 2 / C(20, 10); the balanced fractions are constant per group
    assert k1[8] == f"8.45 vs 13.50, p = {2 / math.comb(20, 10):.2g}"
    tied = mannwhitneyu([1.0] * 10, [0.9] * 10, method="asymptotic").pvalue  # ties: the normal approximation
    assert k1[9] == f"1.00 vs 0.90, p = {tied:.2g}"
    k9 = cells(next(line for line in lines if line.startswith("| k = 9 |")))
    assert k9[3] == "—" and k9[5:] == ["", "", "", "", ""]  # no library results at k = 9: nothing to difference
    assert len([line for line in lines if line.startswith("| k =")]) == 2
    # paired by seed: k = 1 only (no library seeds at k = 9); both succeed on 0–4, only library on 5–8, neither on 9
    paired = render_paired(TABLES["4.1"], "estimator_choices",
                           [(v, collect(TABLES["4.1"], rows, custom=True)) for v, rows in groups]).splitlines()
    assert [cells(line) for line in paired if line.startswith("| k =")] == [[
        "k = 1", "TP", "0–9", "5 / 4 / 0 / 1", f"{binomtest(4, 4).pvalue:.2g}",  # McNemar: 4 of 4 discordant one way
        f"-5.05, p = {2 / 2 ** 10:.2g}",  # every difference −1 − 0.9·seed < 0: the exact signed-rank p is 2 / 2^10
        f"+0.10, p = {wilcoxon(np.full(10, 0.1)).pvalue:.2g}"]]
    assert render_paired(TABLES["4.1"], "estimator_choices", [(v, collect(TABLES["4.1"], rows, custom=True))
                                                              for v, rows in groups[:1]]) == ""
    with pytest.raises(ValueError, match="cannot group by 'seed'"):
        split_by(summaries, "seed")


def test_cell_curves_give_each_cells_median_and_quartiles_per_trial():
    """The curves figure's median and band as numbers: percentiles over the counted seeds, per trial."""
    cfgs = table_configs("4.1", 4, "thesis", methods=["tp", "pilco"], ks=[9.0])
    returns = {0: [30.0, 20.0, 10.0], 1: [30.0, 22.0, 14.0], 2: [30.0, 24.0, 12.0], 3: [30.0, 26.0, 16.0]}
    summaries = [{"config": c, "eval_return": np.array(returns[c.seed]) + (5.0 if c.method == "pilco" else 0.0)}
                 for c in cfgs]
    summaries.append(dict(summaries[0], config=summaries[0]["config"].replace(centre_std=None),
                          eval_return=np.array([0.0, 0.0, 0.0])))  # not counted
    lines = render_cell_curves(TABLES["4.1"], summaries).splitlines()
    assert lines[2] == "| | method | seeds | 0 | 1 | 2 |" and lines[3].count("|---") == 6 and len(lines) == 6
    rows = {line.split(" | ")[1]: line for line in lines[4:]}
    # trial 1 over seeds (20, 22, 24, 26): median 23, quartiles 21.5 and 24.5 (linear interpolation)
    assert rows["TP"] == "| k = 9 | TP | 4 | 30.00 [30.00, 30.00] | 23.00 [21.50, 24.50] | 13.00 [11.50, 14.50] |"
    assert rows["PILCO"].startswith("| k = 9 | PILCO | 4 | 35.00 [35.00, 35.00] | 28.00 [26.50, 29.50] |")
    assert render_cell_curves(TABLES["4.4"], summaries) == ""


def test_curves_show_each_trial_and_the_unicycles_final_upright_fraction():
    cart = table_configs("4.1", 1, "thesis", methods=["tp"], ks=[1.0])[0]
    uni = table_configs("4.4", 1, "thesis", methods=["tp"])[0]
    summaries = [
        {"config": cart, "success": True, "return_success": True, "eval_return": np.array([29.9, 8.25]),
         "final_return": 8.25, "final_se": 0.1, "final_balanced": 0.9, "upright_fraction": np.ones(2),
         "wall_seconds": 120.0},
        {"config": uni, "success": False, "eval_return": np.array([15.4, 3.0, 1.5]), "final_return": 1.5,
         "final_se": 0.2, "final_balanced": 0.9333, "upright_fraction": np.array([0.0, 0.9, 0.9333]),
         "wall_seconds": 600.0},
    ]
    lines = render_curves(summaries).splitlines()
    assert lines[0] == ("| experiment | success (return) | 0 | 1 | 2 | final ± SE | final balanced / upright "
                        "| wall (min) |")
    assert lines[1].count("|---") == 8
    assert lines[2] == "| cartpole_swingup TP k=1 seed 0 | yes (yes) | 29.9 | 8.2 |  | 8.2 ± 0.1 | 0.90 | 2 |"
    assert lines[3] == "| unicycle TP k=1 seed 0 | no | 15.4 | 3.0 | 1.5 | 1.5 ± 0.2 | 0.93 | 10 |"


# -- the loop and its results ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_result(tmp_path_factory):
    path = tmp_path_factory.mktemp("run") / "tiny.h5"
    result = run_experiment(tiny(), on_trial=lambda r: write_result(path, r))
    return result, path


def test_code_version_keeps_a_declared_commit_apart_from_what_git_found(monkeypatch):
    """A copied tree (a lent GPU) declares its commit; the file must say it was declared, not checked."""
    from pipps.experiments import results as res

    monkeypatch.delenv("PIPPS_CODE_VERSION", raising=False)
    res.code_version.cache_clear()
    found = res.code_version()
    assert found == res._git_version() and "declared" not in found
    monkeypatch.setenv("PIPPS_CODE_VERSION", "abc123")
    res.code_version.cache_clear()
    declared = res.code_version()
    assert declared.startswith("abc123 (declared")
    assert declared == ("abc123 (declared)" if found == "unknown" else f"abc123 (declared; git there: {found})")
    monkeypatch.setattr(res, "_git_version", lambda: "unknown")
    res.code_version.cache_clear()
    assert res.code_version() == "abc123 (declared)"
    res.code_version.cache_clear()


def test_result_file_schema_and_round_trip(tiny_result):
    result, path = tiny_result
    assert check_result(path) == "complete"
    back = read_result(path)
    assert_same_results(result, back)
    with h5py.File(path, "r") as f:
        assert f.attrs["schema_version"] == 1 and f.attrs["status"] == "complete"
        assert json.loads(f.attrs["config_json"])["method"] == "tp"
        assert set(f["versions"].attrs) >= {"pipps", "jax", "jaxlib", "numpy", "h5py", "python", "platform"}
        assert f["eval_return"].shape == (2,)
        learned = f["trials/001"]
        H, S = 30, 4
        assert learned["states"].shape == (H + 1, S) and learned["actions"].shape == (H, 1)
        assert learned["eval_returns"].shape == (3,) and learned["policy"].shape == (50 * 4 + 50 + 4,)
        assert learned["gp/log_lengthscale"].shape == (4, 5) and learned["gp"].attrs["num_points"] == 30
        assert learned["opt_trace/value"].shape == (6,)
        assert learned["diagnostics/k_lr"].shape == (H,)
        assert learned["predicted/particles"].shape == (H + 1, 4, 4)
        assert set(learned["timings"].attrs) >= {"gp", "optimize", "trial", "evaluate", "total"}
        # the core's GEMM rate after each learned trial, for the cost model (experiments/cost_model_fit.py);
        # on a GPU backend the probe's CPU time would not be the device's, and nothing is stored
        if jax.default_backend() == "cpu":
            assert 0.1 < learned["timings"].attrs["gemm_gflops"] < 1e4
        else:
            assert "gemm_gflops" not in learned["timings"].attrs
        assert "gemm_gflops" not in f["trials/000/timings"].attrs
    # the stored evaluation is what the policy does on the true system
    np.testing.assert_allclose(f_eval := back.trials[1].eval_return, np.mean(result.trials[1].eval_returns))
    assert math.isfinite(f_eval)


def test_computational_settings_are_not_part_of_an_experiments_identity():
    """gp_chunk and progress_chunk say how an experiment is computed: same experiment, hash and file
    name, no departure from the protocol; the thesis and PILCO presets use exact GP capacities."""
    a = resolve_config("thesis", "cartpole_swingup", seed=3)
    assert a.gp_chunk == 1 and resolve_config("pilco", "unicycle").gp_chunk == 1
    assert resolve_config("quick", "cartpole_swingup").gp_chunk == 100
    for b in (a.replace(gp_chunk=100), a.replace(progress_chunk=7), a.replace(gp_chunk=30, progress_chunk=600)):
        assert a != b and same_experiment(a, b) and config_hash(a) == config_hash(b)
        assert experiment_name(b) == experiment_name(a) == "cartpole_swingup_angle_k1_tp_thesis_s3"
        assert departures(b) == {}
    assert not same_experiment(a, a.replace(num_inducing=200))


def test_exact_gp_capacities_change_only_the_rounding(tiny_result):
    """The tiny run with its 30 points padded to 100 (quick preset) and unpadded: padded rows are exact
    zeros, so the GP training, the policy steps and the true-system trials agree to the rounding that
    L-BFGS and a few policy steps amplify (the batched path's bound, tests/test_batched.py)."""
    padded, _ = tiny_result
    exact = run_experiment(tiny(gp_chunk=1))
    assert [t.gp.capacity for t in exact.trials[1:]] == [30]
    assert [t.gp.capacity for t in padded.trials[1:]] == [100]
    for ta, tb in zip(padded.trials, exact.trials):
        np.testing.assert_allclose(ta.policy, tb.policy, rtol=1e-7, atol=1e-9, err_msg="policy")
        # the true-system trials follow those policies through a swing-up, which magnifies a policy
        # difference: bound each by the policies' own difference times a growth factor of 10⁴ for
        # the rollout (measured: states differ by 61× the policies' largest difference). A bound
        # relative to the policy difference follows the rounding of whatever CPU runs it; a fixed
        # rtol did not (1.6e-7 at one state on an AVX-512 machine).
        scale = float(np.max(np.abs(np.asarray(ta.policy) - np.asarray(tb.policy))))
        for name in ("states", "actions", "eval_returns"):
            np.testing.assert_allclose(getattr(ta, name), getattr(tb, name), rtol=0,
                                       atol=max(1e-9, 1e4 * scale), err_msg=name)
    for name in ("log_lengthscale", "log_signal", "log_noise"):
        np.testing.assert_allclose(getattr(padded.trials[1].gp, name), getattr(exact.trials[1].gp, name), rtol=1e-7)


def test_results_are_deterministic_in_the_config(tiny_result):
    result, _ = tiny_result
    again = run_experiment(tiny())
    assert_same_results(result, again)


def test_corrupt_and_partial_files_are_detected(tiny_result, tmp_path):
    result, path = tiny_result
    # truncated (a half-written file under the final name)
    bad = tmp_path / "truncated.h5"
    data = path.read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(ResultError, match="unreadable"):
        check_result(bad)
    # altered after writing: the checksum catches it
    altered = tmp_path / "altered.h5"
    shutil.copy(path, altered)
    with h5py.File(altered, "r+") as f:
        f["trials/001/eval_returns"][0] += 1.0
    with pytest.raises(ResultError, match="checksum"):
        check_result(altered)
    # a trial group removed
    missing = tmp_path / "missing.h5"
    shutil.copy(path, missing)
    with h5py.File(missing, "r+") as f:
        del f["trials/001"]
    with pytest.raises(ResultError, match="1 trials stored"):
        check_result(missing)
    # still running
    running = tmp_path / "running.h5"
    write_result(running, type(result)(result.config, result.trials[:1], "running"))
    with pytest.raises(ResultError, match="running"):
        check_result(running)
    assert not is_complete(running) and not is_complete(tmp_path / "absent.h5")
    with pytest.raises(ResultError):
        read_summary(bad)


def test_a_failure_part_way_keeps_the_finished_trials(tmp_path):
    path = tmp_path / "fails.h5"

    def progress(event):
        if event["phase"] == "gp" and event["trial"] == 2:
            raise RuntimeError("simulated crash in trial 2")

    with pytest.raises(RuntimeError, match="simulated"):
        run_experiment(tiny(num_learned=2), progress=progress, on_trial=lambda r: write_result(path, r))
    with pytest.raises(ResultError, match="failed.*simulated crash"):
        check_result(path)
    partial = read_result(path, verify=False)
    assert partial.status == "failed" and [t.index for t in partial.trials] == [0, 1]


def test_unicycle_evaluation_charges_fallen_steps():
    """Evaluation return = summed cost of the valid steps + 1 per step after a fall; upright = never fell."""
    from pipps.experiments.loop import Programs, make_experiment_task
    from pipps.rollout import rollout

    cfg = tiny(task="unicycle")
    task = make_experiment_task(cfg)
    keys = jax.random.split(jax.random.PRNGKey(3), 4)
    returns, upright, _ = Programs(cfg, task).evaluate_random(keys)
    for key, ret, up in zip(keys, np.asarray(returns), np.asarray(upright)):
        traj = rollout(key, task, None)
        valid = np.asarray(traj.valid)
        assert ret == pytest.approx(float(traj.total_cost) + (task.horizon - valid.sum()), abs=1e-12)
        assert bool(up) == bool(valid.all())
    assert not np.asarray(upright).all()  # random torques topple it within 2 s


def test_a_non_finite_state_ends_a_unicycle_episode_as_a_fall():
    """An integrator that leaves the valid region mid-fall (NaN state) must end the episode, not
    put NaN into the costs, the returns or the training data."""
    import jax.numpy as jnp

    from pipps.rollout import rollout, training_pairs
    from pipps.tasks.presets import make_task
    from pipps.tasks.unicycle import unicycle_ode

    def brittle_ode(s, u):  # NaN once roll or pitch passes 0.3 rad, well before the ±π/2 fall check
        return jnp.where(jnp.maximum(jnp.abs(s[7]), jnp.abs(s[10])) > 0.3, jnp.nan, unicycle_ode(s, u))

    task = make_task("unicycle", "thesis", ode=brittle_ode)
    trajs = jax.vmap(lambda k: rollout(k, task, None))(jax.random.split(jax.random.PRNGKey(0), 8))
    valid = np.asarray(trajs.valid)
    assert np.isfinite(np.asarray(trajs.costs)).all() and np.isfinite(np.asarray(trajs.states)).all()
    assert (valid.sum(-1) < task.horizon).all()  # every episode ended early
    for i in range(2):
        x, y = training_pairs(task, jax.tree.map(lambda a: a[i], trajs))
        assert np.isfinite(x).all() and np.isfinite(y).all() and len(x) == valid[i].sum()


# -- sweeps ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def local_pair(tmp_path_factory):
    """Two tiny experiments swept by the local backend with two workers: the reference results."""
    cfgs = [tiny(seed=0), tiny(seed=1, method="rp")]
    out = tmp_path_factory.mktemp("full")
    full = run_sweep(cfgs, out, jobs=2)
    assert not full.failed and len(full.ran) == 2
    return cfgs, out


def test_killed_and_resumed_sweep_equals_uninterrupted(local_pair, tiny_result, tmp_path):
    cfgs, full = local_pair
    # "killed": the first experiment had finished (the worker's own writer produced its file),
    # the second was in flight (its file says running)
    part = tmp_path / "resumed"
    first = part / f"{experiment_name(cfgs[0])}.h5"
    assert tiny_result[0].config == cfgs[0]
    write_result(first, tiny_result[0])
    stamp = first.stat().st_mtime_ns
    in_flight = part / f"{experiment_name(cfgs[1])}.h5"
    whole = read_result(full / in_flight.name)
    write_result(in_flight, type(whole)(cfgs[1], whole.trials[:1], "running", wall_seconds=1.0))
    resumed = run_sweep(cfgs, part, jobs=1)
    assert resumed.skipped == [str(first)] and resumed.ran == [str(in_flight)]
    assert first.stat().st_mtime_ns == stamp  # not rerun
    for cfg in cfgs:
        name = f"{experiment_name(cfg)}.h5"
        assert_same_results(read_result(full / name), read_result(part / name))
    back = read_result(in_flight)
    assert back.resumed_at == [1] and back.wall_seconds > 1.0  # picked up at trial 1, wall time summed
    again = run_sweep(cfgs, part, jobs=1)
    assert again.ran == [] and len(again.skipped) == 2


def test_a_sweep_refuses_a_folder_holding_other_settings(local_pair, tmp_path):
    """Same cell and seed, other settings: neither skipped as done nor overwritten nor resumed."""
    cfgs, full = local_pair
    other = tiny(seed=0, policy_evals=9)
    # other settings now get another file name (docs/reliability.md), so the folder's manifest refuses them
    with pytest.raises(ValueError, match=r"holds a sweep run with .*policy_evals=6.*policy_evals=9"):
        run_sweep([other], full, jobs=1)
    partial = tmp_path / f"{experiment_name(cfgs[0])}.h5"
    write_result(partial, type(read_result(full / partial.name))(cfgs[0], read_result(full / partial.name).trials[:1]))
    with pytest.raises(ValueError, match="policy_evals"):  # no manifest yet: the files already there decide
        run_sweep([other], tmp_path, jobs=1)


RESUME = dict(num_learned=3, fitc_threshold=40, num_inducing=20, fitc_iters=5, fitc_first_iters=5)


@pytest.fixture(scope="module")
def fitc_run(tmp_path_factory):
    """A tiny run whose GP turns FITC at trial 2 (60 points > 40): warm starts of both kinds."""
    path = tmp_path_factory.mktemp("fitc") / "whole.h5"
    result = run_experiment(tiny(**RESUME), on_trial=lambda r: write_result(path, r))
    assert [t.gp.sparse for t in result.trials[1:]] == [False, True, True]
    return result, path


@pytest.mark.parametrize("at", [pytest.param(2, marks=pytest.mark.slow), 3])
def test_a_resumed_experiment_equals_an_uninterrupted_one(fitc_run, tmp_path, at):
    """Killed after trial ``at``−1, continued from the file: the same trials, bit for bit. At 2 the
    warm start is a full GP's hyperparameters; at 3 also FITC's stored inducing inputs."""
    whole, path = fitc_run
    stored = read_result(path)
    cut = tmp_path / "cut.h5"
    write_result(cut, type(stored)(stored.config, stored.trials[:at], "failed", "KeyboardInterrupt: ", 5.0))
    partial = read_result(cut, verify=False)
    resumed = run_experiment(tiny(**RESUME), resume=partial)
    assert resumed.status == "complete" and resumed.resumed_at == [at]
    assert_same_results(whole, resumed)
    for a, b in zip(whole.trials[at:], resumed.trials[at:]):
        for name in ("log_lengthscale", "log_signal", "log_noise"):
            np.testing.assert_array_equal(getattr(a.gp, name), getattr(b.gp, name))
        np.testing.assert_array_equal(a.gp.inducing, b.gp.inducing)


def test_resume_refuses_another_configuration(fitc_run):
    whole, _ = fitc_run
    with pytest.raises(ValueError, match="seed: 0 stored, 1 asked"):
        run_experiment(tiny(**RESUME, seed=1), resume=type(whole)(whole.config, whole.trials[:2]))


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="needs Linux CPU affinity and two CPUs")
def test_sweep_workers_are_pinned_to_distinct_cpus():
    """XLA sizes its thread pool from the CPU affinity; two jobs must not each run two threads."""
    with worker_pool(2) as pool:
        for f in [pool.submit(time.sleep, 0.5) for _ in range(4)]:
            f.result()
        pinned = [os.sched_getaffinity(pid) for pid in pool._processes]
    assert len(pinned) == 2 and all(len(c) == 1 for c in pinned)
    assert pinned[0] != pinned[1]


def test_cpu_layout_gives_every_cpu_work_and_never_more_workers_than_experiments(monkeypatch):
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    assert not accelerator_installed()
    assert cpu_layout(None, 40, 2) == (2, 1)  # a table on two cores: two pinned one-thread workers
    assert cpu_layout(None, 1, 2) == (1, 2)  # a lone experiment: every core
    assert cpu_layout(None, 2, 8) == (2, 4) and cpu_layout(None, 3, 8) == (3, 2)
    assert cpu_layout(1, 40, 8) == (1, 8) and cpu_layout(3, 40, 8) == (3, 2)
    assert cpu_layout(16, 40, 8) == (16, 1)
    with pytest.raises(ValueError, match="jobs"):
        cpu_layout(0, 4, 2)


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="needs two CPUs")
def test_a_wide_worker_holds_distinct_cpus_and_a_second_gets_none_of_them():
    with worker_pool(1, width=2) as pool:
        pool.submit(time.sleep, 0.2).result()
        (wide,) = [os.sched_getaffinity(pid) for pid in pool._processes]
        with worker_pool(1) as other:  # a free CPU if there is one; else it shares one, one thread
            other.submit(time.sleep, 0.2).result()
            (narrow,) = [os.sched_getaffinity(pid) for pid in other._processes]
    assert len(wide) == 2 and len(narrow) == 1
    assert not narrow & wide or len(os.sched_getaffinity(0)) == 2


# -- the Ray backend, on a local Ray instance started by the test ----------------------------------


@pytest.fixture
def ray_session():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False)
    yield ray
    ray.shutdown()


@pytest.mark.slow  # ~4 min of CI (two fresh Ray workers import JAX and compile); the default run keeps Ray
# through the failure and CPU-pinning tests below
def test_ray_sweep_equals_local_sweep_resumes_and_reruns_skip(local_pair, tmp_path):
    """Two experiments on Ray (one missing, one half-written) equal the local backend's; a complete
    file is skipped untouched; run_sweep shuts down the local Ray instance it started."""
    ray = pytest.importorskip("ray")
    cfgs, local = local_pair
    paths = [tmp_path / f"{experiment_name(cfg)}.h5" for cfg in cfgs]
    reference = [read_result(local / p.name) for p in paths]
    write_result(paths[1], type(reference[1])(cfgs[1], reference[1].trials[:1], "running"))
    complete_cfg = tiny(seed=2)
    complete = tmp_path / f"{experiment_name(complete_cfg)}.h5"
    write_result(complete, type(reference[0])(complete_cfg, reference[0].trials, "complete"))
    stamp = complete.stat().st_mtime_ns
    assert not ray.is_initialized()
    ended = []
    report = run_sweep([*cfgs, complete_cfg], tmp_path, jobs=2, backend="ray",
                       on_done=lambda path, err, finished, total: ended.append((path, finished, total)))
    assert not report.failed and report.skipped == [str(complete)]
    assert sorted(report.ran) == sorted(map(str, paths))
    assert sorted(ended, key=lambda e: e[1]) == [(report.ran[0], 1, 2), (report.ran[1], 2, 2)]
    assert complete.stat().st_mtime_ns == stamp  # not rerun
    for path, ref in zip(paths, reference):
        assert_same_results(ref, read_result(path))
    assert not ray.is_initialized()
    again = run_sweep([*cfgs, complete_cfg], tmp_path, jobs=2, backend="ray")
    assert again.ran == [] and len(again.skipped) == 3


def test_ray_sweep_reports_failures_like_the_local_backend(ray_session, tmp_path):
    broken = tiny(cost="tip", cost_scale=2.0)  # valid settings the loop refuses at its start
    on_ray = run_sweep([broken], tmp_path / "ray", backend="ray")
    local = run_sweep([broken], tmp_path / "local")
    name = f"{experiment_name(broken)}.h5"
    assert on_ray.ran == [] and list(on_ray.failed) == [str(tmp_path / "ray" / name)]
    assert list(on_ray.failed.values()) == list(local.failed.values())
    assert next(iter(on_ray.failed.values())).startswith("ValueError: cost_scale:")
    assert ray_session.is_initialized()  # a session the caller started is left to the caller


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="needs Linux CPU affinity and two CPUs")
def test_concurrent_ray_tasks_are_pinned_to_distinct_cpus(ray_session, tmp_path):
    def affinity_once_both_run(folder):
        (folder / str(os.getpid())).touch()
        deadline = time.time() + 60
        while len(list(folder.iterdir())) < 2 and time.time() < deadline:
            time.sleep(0.05)
        return os.sched_getaffinity(0)

    task = ray_task(ray_session)
    pinned = ray_session.get([task.remote(affinity_once_both_run, tmp_path) for _ in range(2)])
    assert all(len(cpus) == 1 for cpus in pinned) and pinned[0] != pinned[1]


def test_ray_backend_without_ray_says_how_to_install_it(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray now raises ImportError
    with pytest.raises(ImportError, match=r"pip install 'pipps\[ray\]'"):
        run_sweep([tiny()], tmp_path, backend="ray")
    with pytest.raises(ValueError, match="address"):
        run_sweep([tiny()], tmp_path, address="auto")


# -- CLI ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "argv, option",
    [
        (["run", "--method", "sgd"], "--method"),
        (["run", "--k", "-1"], "--k"),
        (["run", "--particles", "0"], "--particles"),
        (["run", "--preset", "fast"], "--preset"),
        (["sweep", "--table", "4.1", "--jobs", "0"], "--jobs"),
        (["sweep", "--table", "4.1", "--backend", "dask"], "--backend"),
    ],
)
def test_cli_rejects_bad_values_naming_the_option(argv, option, capsys):
    from pipps.cli import main

    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert option in capsys.readouterr().err


def test_cli_rejects_bad_settings_and_tables(capsys):
    from pipps.cli import main

    assert main(["run", "--set", "num_particles=0"]) == 2
    assert "num_particles" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:  # read by argparse: refused before anything else
        main(["sweep", "--table", "9.9"])
    assert exc.value.code == 2 and "unknown table '9.9'" in capsys.readouterr().err
    assert main(["run", "--set", "momentum=2"]) == 2
    assert "momentum" in capsys.readouterr().err
    assert main(["sweep", "--table", "4.1", "--address", "auto"]) == 2
    assert "--address needs --backend ray" in capsys.readouterr().err


def test_cli_run_writes_the_result_and_shows_progress(tmp_path, capsys):
    from pipps.cli import main

    out = tmp_path / "run.h5"
    sets = [x for k, v in TINY.items() if k != "num_particles" for x in ("--set", f"{k}={v}")]
    assert main(["run", "--preset", "quick", "--seed", "2", "--particles", "8", "--out", str(out), *sets]) == 0
    cap = capsys.readouterr()
    assert "trial 1 of 0-1" in cap.err and "policy step 6/6 objective" in cap.err and "ETA" in cap.err
    r = read_result(out)
    assert r.config.seed == 2 and r.config.num_particles == 8
    assert f"final evaluated return {r.final_return:.3f}" in cap.out


def test_cli_table_reads_results_and_skips_corrupt(tiny_result, tmp_path, capsys):
    from pipps.cli import main

    _, path = tiny_result
    folder = tmp_path / "res"
    folder.mkdir()
    cfg = resolve_config("thesis", "cartpole_swingup", method="tp", k=1.0)
    result = read_result(path)
    result.config = cfg.replace(num_learned=1)
    write_result(folder / "a.h5", result)
    (folder / "broken.h5").write_bytes(b"not hdf5")
    assert main(["table", str(folder), "--table", "4.1", "--curves", "--per-seed", "--custom"]) == 0
    out = capsys.readouterr().out
    assert f"| k = 1 | TP | 0 | {result.final_return:.2f} |" in out  # the seed rows (render_seeds)
    curve_row = next(line for line in out.splitlines() if line.startswith("| cartpole_swingup TP k=1 seed 0 |"))
    assert curve_row.split("|")[3:5] == [f" {t.eval_return:.1f} " for t in result.trials]
    row = next(line for line in out.splitlines() if line.startswith("| k = 1 |"))
    assert "(1) / 0.99" in row
    assert "1 complete results of the thesis preset counted; 0 complete results of other settings and 1 incomplete or corrupt" in out
    assert main(["table", str(folder), "--table", "4.4", "--curves", "--custom"]) == 0
    assert "cartpole_swingup TP k=1 seed 0" not in capsys.readouterr().out  # --table 4.4's curves: the unicycle's only


def _two_estimator_choices(tiny_result, tmp_path):
    """A folder of two copies of the tiny result as a thesis-preset TP run, one per estimator_choices."""
    _, path = tiny_result
    folder = tmp_path / "res"
    folder.mkdir()
    cfg = resolve_config("thesis", "cartpole_swingup", method="tp", k=1.0, num_learned=1)
    result = read_result(path)
    for name, choices in (("lib.h5", "library"), ("thesis.h5", "thesis")):
        result.config = cfg.replace(estimator_choices=choices)
        write_result(folder / name, result)
    return folder


def test_cli_table_by_a_setting_prints_each_value_and_names_a_bad_setting(tiny_result, tmp_path, capsys):
    from pipps.cli import main

    folder = _two_estimator_choices(tiny_result, tmp_path)
    # --custom: the tiny result departs from the preset in more than estimator_choices
    assert main(["table", str(folder), "--table", "4.1", "--by", "estimator_choices", "--per-seed", "--custom"]) == 0
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("| k = 1 |"))
    assert row.count("(1)") == 2 and "p = 1" in row  # one seed of each value, side by side
    assert "estimator_choices = library:" in out and "estimator_choices = thesis:" in out  # each value's seed rows
    assert "2 complete results of the thesis preset counted" in out
    assert main(["table", str(folder), "--by", "estimator"]) == 2
    assert "--by estimator: not a setting" in capsys.readouterr().err


def test_cli_plot_by_a_setting_draws_each_value_apart(tiny_result, tmp_path, capsys):
    """--by keeps two readings of one method apart in a figure, as pipps table --by does in a table."""
    from pipps.cli import main

    folder = _two_estimator_choices(tiny_result, tmp_path)
    for figure in ("curves", "cells"):
        svg = tmp_path / f"{figure}.svg"
        argv = ["plot", str(folder), "--figure", figure, "--table", "4.1", "--custom", "--out", str(tmp_path / "x.rrd"),
                "--svg", str(svg), "--overwrite"]
        assert main(argv + ["--by", "estimator_choices"]) == 0
        text = svg.read_text()
        assert "estimator_choices = library" in text and "estimator_choices = thesis" in text, figure
        assert main(argv) == 0  # without --by the two files pool into one cell
        assert "estimator_choices =" not in svg.read_text(), figure
    assert "learning curves of 2 experiments" in capsys.readouterr().out
    assert main(["plot", str(folder), "--figure", "curves", "--by", "estimator", "--out", str(tmp_path / "y.rrd")]) == 2
    assert "--by estimator: not a setting" in capsys.readouterr().err
    assert main(["plot", str(folder), "--by", "estimator_choices", "--out", str(tmp_path / "z.rrd")]) == 2
    assert "--by draws the cells of --figure cells or curves" in capsys.readouterr().err


def test_plot_writes_a_recording_of_the_curves(tiny_result, tmp_path):
    from pipps.reporting.plot import curve, record

    result, _ = tiny_result
    mean, std = curve([result, result])
    np.testing.assert_allclose(mean, [t.eval_return for t in result.trials])
    np.testing.assert_allclose(std, 0.0)
    out = record([result], tmp_path / "r.rrd")
    assert out.read_bytes()[:4] == b"RRF2" and out.stat().st_size > 10_000


# -- learning ----------------------------------------------------------------------------------------


def test_quick_preset_learns():
    """A shortened quick run (2 learned trials): the learned policies beat the random trial.

    The random-action trial's evaluated return is ≈ 30 (the cost is ≈ 1 every step while the pole
    hangs); a sign error or a broken backward pass leaves the learned trials there or worse.
    """
    result = run_experiment(resolve_config("quick", "cartpole_swingup", num_learned=2, method="tp"))
    random_return = result.trials[0].eval_return
    assert random_return > 28.0
    assert min(t.eval_return for t in result.trials[1:]) < random_return - 3.0


@pytest.mark.slow
@pytest.mark.parametrize("method", ["tp", "pilco"])
def test_quick_preset_end_to_end(tmp_path, method):
    """`pipps run --preset quick` end to end: the schema, and learning improves the evaluated return."""
    out = tmp_path / "quick.h5"
    proc = subprocess.run([sys.executable, "-m", "pipps.cli", "run", "--preset", "quick", "--method", method,
                           "--out", str(out), "--quiet"], capture_output=True, text=True, timeout=1800)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert check_result(out) == "complete"
    r = read_result(out)
    assert len(r.trials) == r.config.num_trials == 6
    assert r.trials[-1].eval_return < r.trials[0].eval_return - 10.0


@pytest.mark.slow
def test_sweep_killed_with_sigkill_resumes(tmp_path):
    """A real kill: SIGKILL the sweep once its first result is complete, resume, compare."""
    args = ["--table", "4.1", "--k", "1", "--methods", "tp", "--seeds", "2", "--preset", "quick"]
    sets = [x for k, v in TINY.items() for x in ("--set", f"{k}={v}")]
    killed = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "pipps.cli", "sweep", *args, *sets, "--out", str(killed)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    first = killed / f"{experiment_name(tiny(method='tp', k=1.0, cost='angle', seed=0))}.h5"
    deadline = time.time() + 600
    while not is_complete(first) and time.time() < deadline and proc.poll() is None:
        time.sleep(0.2)
    proc.kill()
    proc.wait()
    subprocess.run([sys.executable, "-m", "pipps.cli", "sweep", *args, *sets, "--out", str(killed)], check=True,
                   capture_output=True)
    full = tmp_path / "full"
    subprocess.run([sys.executable, "-m", "pipps.cli", "sweep", *args, *sets, "--out", str(full)], check=True,
                   capture_output=True)
    assert sorted(p.name for p in full.glob("*.h5")) == sorted(p.name for p in killed.glob("*.h5"))
    assert first.name in os.listdir(full)
    for path in full.glob("*.h5"):  # the folder also holds its sweep manifest
        assert_same_results(read_result(path), read_result(killed / path.name))


def test_the_cli_keeps_compiled_programs_in_a_persistent_cache(monkeypatch, tmp_path):
    """`enable_compilation_cache` (called by every pipps command) stores compiled programs in the
    chosen folder, hands the folder to spawned workers through the environment, and can be switched off."""
    import jax
    from jax.experimental.compilation_cache import compilation_cache

    from pipps.cli import enable_compilation_cache

    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    monkeypatch.setenv("PIPPS_COMPILATION_CACHE", "off")
    assert enable_compilation_cache() is None and "JAX_COMPILATION_CACHE_DIR" not in os.environ
    monkeypatch.setenv("PIPPS_COMPILATION_CACHE", str(tmp_path / "cache"))
    before = jax.config.jax_compilation_cache_dir, jax.config.jax_persistent_cache_min_compile_time_secs
    try:
        assert enable_compilation_cache() == str(tmp_path / "cache") == os.environ["JAX_COMPILATION_CACHE_DIR"]
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)  # store even a fast compile
        compilation_cache.reset_cache()  # this test process compiled before: let it look at the setting again
        jax.jit(lambda x: jax.numpy.sin(x) * 3.0 + 0.25)(jax.numpy.arange(7.0)).block_until_ready()
        assert any((tmp_path / "cache").iterdir())
    finally:
        jax.config.update("jax_compilation_cache_dir", before[0])
        jax.config.update("jax_persistent_cache_min_compile_time_secs", before[1])
        compilation_cache.reset_cache()
