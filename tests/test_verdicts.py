"""The physical success criterion, the verdict and its statistics (pipps.reporting.verdicts, docs/results.md)."""

from __future__ import annotations

import math
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import binom

from pipps.experiments.resimulate import Resimulator, program_key
from pipps.experiments.results import read_result, read_summary
from pipps.reporting.tables import difference_interval, fisher_exact, judge, wilson_interval
from pipps.reporting.verdicts import flip_probability_fraction, flip_probability_return
from pipps.tasks.cartpole import balanced

RESULTS = Path(__file__).resolve().parents[1] / "results/thesis"


def _states(theta, x, n=31):
    s = np.zeros((n, 4))
    s[:, 3], s[:, 0] = theta, x
    return s


def test_balanced_reads_the_last_states_and_wraps_the_angle():
    up = _states(math.pi, 0.0)
    assert balanced(up)
    assert balanced(_states(3 * math.pi + 0.29, 0.0))  # upright after swinging over once: still upright
    assert balanced(_states(-math.pi, 0.49))  # the other swing direction
    assert not balanced(_states(math.pi + 0.31, 0.0)) and not balanced(_states(math.pi, 0.51))
    early = _states(math.pi, 0.0)
    early[:21, 3] = 0.0  # hanging until state 20, then upright for the last 10 states
    assert balanced(early, steps=10) and not balanced(early, steps=11)
    late = _states(math.pi, 0.0)
    late[-1, 0] = 0.8  # runs away in the very last state
    assert not balanced(late)
    batch = np.stack([up, late, early])
    assert balanced(batch).tolist() == [True, False, True]
    assert np.asarray(balanced(jnp.asarray(batch))).tolist() == [True, False, True]  # the JAX path agrees


def test_fraction_flip_probability_is_the_beta_binomial_predictive():
    """Against a Monte Carlo of the same model: p ~ Beta(b + ½, n − b + ½), fresh count ~ Bin(n, p)."""
    rng = np.random.default_rng(0)
    n, need = 30, 0.5
    for b in (3, 14, 15, 16, 29, 30):
        p = rng.beta(b + 0.5, n - b + 0.5, 400_000)
        fresh = rng.binomial(n, p)
        passed = b >= 15
        mc = float(np.mean((fresh >= 15) != passed))
        got = flip_probability_fraction(b, n, need)
        se = math.sqrt(mc * (1 - mc) / p.size) + 1e-6
        assert abs(got - mc) < 5 * se, (b, got, mc)
    assert flip_probability_fraction(30, 30, 0.5) < 1e-6 and flip_probability_fraction(15, 30, 0.5) > 0.3


def test_return_flip_probability_matches_its_normal_model():
    rng = np.random.default_rng(1)
    r = rng.normal(14.0, 3.0, 30)
    se = np.std(r, ddof=1) / math.sqrt(30)
    # fresh − observed ~ N(0, 2 SE²): P(cross 15) = Φ(−|m − 15| / (√2 SE))
    from scipy.stats import norm

    assert flip_probability_return(r, 15.0) == pytest.approx(norm.cdf(-abs(r.mean() - 15) / (math.sqrt(2) * se)), 1e-12)
    assert flip_probability_return(np.full(30, 8.0), 15.0) == 0.0


def test_fisher_and_newcombe_against_known_values():
    # Fisher's exact test, two-sided, by direct enumeration of the hypergeometric table
    from scipy.stats import hypergeom

    a, n1, b, n2 = 17, 20, 8, 20
    total = hypergeom(n1 + n2, a + b, n1)
    p_obs = total.pmf(a)
    ks = np.arange(max(0, a + b - n2), min(a + b, n1) + 1)
    brute = float(sum(total.pmf(k) for k in ks if total.pmf(k) <= p_obs * (1 + 1e-7)))
    assert fisher_exact(a, n1, b, n2) == pytest.approx(brute, rel=1e-9)
    # Newcombe (1998) Table II, example (a): 56/70 vs 48/80 → difference 0.2, 95 % CI (0.0524, 0.3339)
    lo, hi = difference_interval(56, 70, 48, 80)
    assert lo == pytest.approx(0.0524, abs=5e-4) and hi == pytest.approx(0.3339, abs=5e-4)
    # and its coverage is not below nominal by much on a grid (a property the hybrid method has)
    cover = []
    for p1, p2 in ((0.8, 0.4), (0.95, 0.5), (0.5, 0.5)):
        k1, k2 = np.arange(21), np.arange(21)
        w = binom.pmf(k1, 20, p1)[:, None] * binom.pmf(k2, 20, p2)[None, :]
        hit = np.array([[lo <= p1 - p2 <= hi for lo, hi in (difference_interval(i, 20, j, 20),)][0]
                        for i in k1 for j in k2]).reshape(21, 21)
        cover.append(float(np.sum(w * hit)))
    assert min(cover) > 0.92, cover
    assert wilson_interval(4, 5) == pytest.approx((0.376, 0.964), abs=1e-3)


def test_resimulation_reproduces_a_stored_evaluation_exactly_and_judges_it():
    """A committed file's final evaluation, rerun with its stored policy and keys, gives its stored
    returns (the true system is deterministic given the keys); the table's verdict comes from it."""
    path = RESULTS / "cartpole_swingup_angle_k1_tp_thesis_s4.h5"
    result = read_result(path)
    ret, upright, flags = Resimulator().trial(result, len(result.trials) - 1)
    np.testing.assert_allclose(ret, result.trials[-1].eval_returns, rtol=1e-9, atol=1e-9)
    assert upright.all()
    (s,) = judge([read_summary(path)])
    assert s["resimulated"] and s["resim_error"] < 1e-9
    # swings up (return 13.9 < 15) but never ends balanced: the verdicts differ, the physical one decides
    assert s["return_success"] and not s["success"] and s["final_balanced"] == float(np.mean(flags)) == 0.0
    with pytest.raises(ValueError, match="random trial"):
        Resimulator().trial(result, 0)


def test_resimulation_programs_are_shared_only_across_learning_settings():
    """Files that differ only in how they learned (method, seed, particles, estimator rule) share one
    compiled program; any setting the true system, the policy's structure or the success rule may
    read (here the return threshold, the balance bounds, the noise, the task's source) gets its own,
    and a file naming its preset's default cost shares the program of one naming none."""
    cfg = read_result(RESULTS / "cartpole_swingup_angle_k1_tp_thesis_s4.h5").config
    same = [cfg.replace(seed=7), cfg.replace(method="pilco"), cfg.replace(num_particles=100),
            cfg.replace(estimator_choices="library"), cfg.replace(cost=None), cfg.replace(cost=cfg.cost_name)]
    assert all(program_key(c) == program_key(cfg) for c in same)
    other = [cfg.replace(success_threshold=14.0), cfg.replace(balance_angle=0.5), cfg.replace(k=9.0),
             cfg.replace(task_source="my_tasks.py"), cfg.replace(cost="tip")]
    keys = {program_key(c) for c in other}
    assert len(keys) == len(other) and program_key(cfg) not in keys
    sim = Resimulator()
    for c in [cfg, *same[:2], other[0]]:
        sim._program(c)
    assert len(sim._programs) == 2


def test_resimulation_at_another_noise_level_changes_only_the_noise_scale(tmp_path, capsys):
    """``k`` observes the same true system at another noise multiplier with the same keys: the
    experiment's own k reproduces the default fresh rollouts exactly, a vanishing k approaches k = 0
    continuously, and k = 1 differs from both (so ``k`` reaches the program)."""
    import importlib.util

    path = RESULTS / "cartpole_swingup_angle_k1_tp_thesis_s4.h5"
    result, resim = read_result(path), Resimulator()
    last = len(result.trials) - 1
    own = resim.trial(result, last, fresh=4, seed=3)
    np.testing.assert_array_equal(resim.trial(result, last, fresh=4, seed=3, k=result.config.k)[0], own[0])
    zero = resim.trial(result, last, fresh=4, seed=3, k=0.0)[0]
    tiny = resim.trial(result, last, fresh=4, seed=3, k=1e-16)[0]
    np.testing.assert_allclose(tiny, zero, rtol=0, atol=1e-5)  # noise scale 1e-8 of the base: a perturbation
    assert np.max(np.abs(own[0] - zero)) > 1e-3
    spec = importlib.util.spec_from_file_location("observation_noise_eval",
                                                  RESULTS.parents[1] / "experiments/observation_noise_eval.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    out = tmp_path / "noise.json"
    script.main([str(path), "--rollouts", "4", "--key-seed", "3", "--out", str(out)])
    import json

    row = json.loads(out.read_text())["rows"][0]
    assert row["at"]["1"]["mean_return"] == pytest.approx(float(np.mean(own[0])), abs=1e-12)
    assert row["at"]["0"]["mean_return"] == pytest.approx(float(np.mean(zero)), abs=1e-12)
    assert "k=0: <15" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        script.main([str(path), "--out", str(out)])  # an existing file is refused


def _calibration_script():
    """experiments/calibrate_cartpole.py as a module (a script, not part of the package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("calibrate_cartpole",
                                                  RESULTS.parents[1] / "experiments/calibrate_cartpole.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    return script


def test_the_calibration_script_lists_the_policies_the_two_rules_disagree_on(capsys):
    script = _calibration_script()
    script.main([str(RESULTS / "cartpole_swingup_angle_k1_tp_thesis_s4.h5"), "--bounds", "0.3:0.5,3.2:1000"])
    out = capsys.readouterr().out
    assert "15 learned policies from 1 files (re-simulated returns differ from the stored ones by at most 0.0e+00)" in out
    assert "| TP | 4 | 15 | 13.90 | 0.00 | no | yes |" in out  # swings up, never balanced, passes the return rule
    assert "| 1 | TP | 1 | 0/1 | 0/1 | 1/1 |" in out
    # bounds nothing can fail (the wrapped angle is within π): the seed passes there, and is named
    assert "| 1 | TP | 1 | 0/1 | 1/1 |" in out
    assert "k = 1, TP, at 3.2 : 1000: the verdict differs from the criterion's on seed(s) 4 (passes)" in out


def test_the_calibration_script_refuses_files_of_two_costs():
    """Its cells are keyed by k and method: files of two costs would pool into one cell."""
    script = _calibration_script()
    angle, tip = (RESULTS / f"cartpole_swingup_{c}_k1_tp_thesis_s4.h5" for c in ("angle", "tip"))
    with pytest.raises(SystemExit, match="one task and cost at a time"):
        script.main([str(angle), str(tip)])


def test_the_calibration_script_reads_an_unnamed_cost_as_the_presets(capsys):
    """Older files store no cost (None: they ran the preset's, the Angle Cost); with files that name
    it, they are one cost, not two."""
    script = _calibration_script()
    unnamed, named = RESULTS / "cartpole_swingup_angle_k1_tp_thesis_s0.h5", RESULTS / "cartpole_swingup_angle_k1_glr_thesis_s0.h5"
    assert read_result(unnamed).config.cost is None and read_result(named).config.cost == "angle"
    script.main([str(named), str(unnamed), "--bounds", "0.3:0.5"])
    assert "30 learned policies from 2 files" in capsys.readouterr().out


def test_pipps_resimulate_reproduces_each_files_own_rollouts_and_judges_fresh_ones(capsys):
    """``pipps resimulate`` on a cart-pole and a unicycle file: with the trial's own keys the returns
    equal the stored ones to rounding (the true system is deterministic given them, float64) and the
    criterion's flags equal the stored ones; the fresh rollouts are judged by the same verdict as
    the stored ones, and the cell row pools them."""
    import re

    from pipps.cli import main
    from pipps.reporting.verdicts import criterion, verdict

    files = [RESULTS / "cartpole_swingup_angle_k1_tp_thesis_s4.h5", RESULTS / "unicycle_default_k1_tp_thesis_s3.h5"]
    assert main(["resimulate", *map(str, files), "--fresh", "8", "--seed", "3"]) == 0
    out = capsys.readouterr().out
    worst = float(re.search(r"the largest return difference from the stored returns is (\S+);", out).group(1))
    # a return is a sum of H ≤ 100 costs in [0, 1]: rounding alone stays far below 1e-9
    assert worst < 1e-9 and "every stored set of criterion flags is reproduced" in out
    assert "1 file(s) store no flags" in out  # the cart-pole file predates them: its returns alone are checked
    sim = Resimulator()
    for f in files:
        result = read_result(f)
        ret, _, flags = sim.trial(result, len(result.trials) - 1, fresh=8, seed=3)
        fresh = verdict(result.config, ret, flags)
        row = next(line for line in out.splitlines() if line.startswith(f"| {f.name} |"))
        assert f"| {fresh.fraction:.2f} [" in row and f"{np.mean(ret):.2f} ± " in row
        assert row.split("|")[5].strip().endswith("pass" if fresh.success else "fail")
    result = read_result(files[0])
    below = np.mean(np.asarray(result.trials[-1].eval_returns) < criterion(result.config).threshold)
    cells = out.split("Per cell")[1]
    assert "| cartpole_swingup | thesis | angle | 1 | TP | thesis | – | 1 | " in cells and f"| {below:.2f} |" in cells
    ret, _, _ = sim.trial(result, len(result.trials) - 1, fresh=8, seed=3)
    fresh_below = np.mean(ret < criterion(result.config).threshold)
    threshold = criterion(result.config).threshold
    holds = "yes" if (np.mean(ret) < threshold) == (np.mean(result.trials[-1].eval_returns) < threshold) else "NO"
    assert f"| {below:.2f}, {fresh_below:.2f}; {holds} |" in out.split("Per cell")[0]
    assert next(line for line in out.splitlines() if line.startswith(f"| {files[1].name} |")).endswith("| – |")
    assert "| unicycle | thesis | unicycle | 1 | TP | thesis | – | 1 | 1.00 [" in cells
    assert f"| {files[0].name} | 4 | " in out and ", not stored |" in out


def test_pipps_resimulate_fails_a_file_whose_stored_flags_its_policy_does_not_earn(monkeypatch, capsys):
    """A stored verdict its policy does not reproduce is reported by name and makes the command exit 1
    (one final rollout's stored flag flipped in memory: the checksum would refuse a tampered file)."""
    import dataclasses

    import pipps.experiments.results as results
    from pipps.cli import main

    path = RESULTS / "unicycle_default_k1_tp_thesis_s3.h5"
    result = read_result(path)
    final = result.trials[-1]
    flipped = np.asarray(final.eval_upright, bool).copy()
    flipped[0] = not flipped[0]
    tampered = dataclasses.replace(result, trials=[*result.trials[:-1], dataclasses.replace(final, eval_upright=flipped)])
    monkeypatch.setattr(results, "read_result", lambda p, **kw: tampered)
    assert main(["resimulate", str(path), "--fresh", "2"]) == 1
    out = capsys.readouterr().out
    assert "| unicycle_default_k1_tp_thesis_s3.h5 | 3 | " in out and ", NO |" in out
    assert "differ from the stored ones in unicycle_default_k1_tp_thesis_s3.h5" in out


def test_pipps_resimulate_fails_a_file_whose_stored_returns_its_policy_does_not_give(monkeypatch, capsys):
    """One stored return moved by 1e-3 (far beyond rounding, far below what would move a verdict): the
    command names the file and exits 1."""
    import dataclasses

    import pipps.experiments.results as results
    from pipps.cli import main

    path = RESULTS / "unicycle_default_k1_tp_thesis_s3.h5"
    result = read_result(path)
    final = result.trials[-1]
    moved = np.asarray(final.eval_returns, float).copy()
    moved[3] += 1e-3
    tampered = dataclasses.replace(result, trials=[*result.trials[:-1], dataclasses.replace(final, eval_returns=moved)])
    monkeypatch.setattr(results, "read_result", lambda p, **kw: tampered)
    assert main(["resimulate", str(path), "--fresh", "2"]) == 1
    out = capsys.readouterr().out
    assert "1.0e-03 (NOT rounding), yes |" in out and "beyond rounding in unicycle_default_k1_tp_thesis_s3.h5" in out


def test_pipps_resimulate_pools_a_cells_seeds_with_their_intervals_and_counts_each_once(capsys):
    """Two seeds of one cell: its row is the mean of the seeds' fractions with the clustered interval of
    their counts (stored: the files' upright flags; fresh: the simulator's), computed here apart from
    the command; the same file given twice is refused."""
    from pipps.cli import main
    from pipps.reporting.readings import clustered_interval

    files = [RESULTS / f"unicycle_default_k1_pilco_thesis_s{s}.h5" for s in (2, 3)]
    assert main(["resimulate", *map(str, files), "--fresh", "5"]) == 0
    row = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("| unicycle | thesis |"))
    sim, stored, fresh = Resimulator(), [], []
    for f in files:
        result = read_result(f)
        stored.append(int(np.sum(result.trials[-1].eval_upright)))
        fresh.append(int(np.sum(sim.trial(result, len(result.trials) - 1, fresh=5, seed=0)[2])))
    expect = []
    for counts, n in ((stored, 30), (fresh, 5)):
        lo, hi = clustered_interval(counts, [n, n])
        expect.append(f"{np.mean(counts) / n:.2f} [{lo:.2f}, {hi:.2f}]")
    assert f"| PILCO | thesis | – | 2 | {expect[0]} | {expect[1]} | – | – |" in row, (row, expect)
    assert main(["resimulate", str(files[0]), str(files[0]), "--fresh", "2"]) == 2
    assert "seed 2 of one cell twice" in capsys.readouterr().err


def test_pipps_resimulate_skips_incomplete_files_and_refuses_bad_input(tmp_path, capsys):
    from pipps.cli import main

    assert main(["resimulate", str(RESULTS / "unicycle_default_k1_tp_thesis_s3.h5"), "--fresh", "1"]) == 2
    assert "--fresh 1: a fresh verdict needs at least 2 rollouts" in capsys.readouterr().err
    (tmp_path / "broken.h5").write_bytes(b"not HDF5")
    assert main(["resimulate", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "skipped: " in err and "broken.h5" in err and "no complete result to re-simulate" in err
    assert main(["resimulate", str(tmp_path / "absent")]) == 2
    assert "no such result file or folder" in capsys.readouterr().err
