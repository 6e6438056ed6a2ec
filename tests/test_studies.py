"""Gradient studies (docs/gradients.md): the snapshot rebuilds exactly what a trial optimised on,
the studies evaluate the estimators where they say, and the CLI writes what it documents.

The snapshot comes from a committed thesis-preset result (results/thesis, TP seed 0), trial 2
(60 GP points), so these tests need no training run.
"""

from pathlib import Path

import h5py
import jax
import numpy as np
import pytest

from pipps.cli import main
from pipps.experiments.programs import predict_particles
from pipps.experiments.methods import particle_method
from pipps.studies import load_snapshot
from pipps.studies.gradients import interval, landscape, variance_study


def _particle_prediction(task, rcfg, store):
    """The loop's stored particle prediction, as a function of (key, policy, model)."""
    predict = jax.jit(lambda key, policy, model: predict_particles(key, task, rcfg, store, policy, model))
    return lambda key, policy, model: {"particles": np.asarray(predict(key, policy, model)[0])}


RESULT = Path(__file__).resolve().parents[1] / "results/thesis/cartpole_swingup_angle_k1_tp_thesis_s0.h5"
TRIAL = 2


@pytest.fixture(scope="module")
def snap():
    return load_snapshot(RESULT, TRIAL)


def _reversed_model(snap):
    """The snapshot's full-GP posterior rebuilt from its real training pairs in reverse order."""
    import jax.numpy as jnp

    from pipps.experiments.loop import gp_config, make_experiment_task
    from pipps.experiments.results import read_result
    from pipps.gp import full_posterior, make_data, pad_to_capacity
    from pipps.rollout import Trajectory, training_pairs

    result = read_result(RESULT)
    task = make_experiment_task(result.config)
    pairs = [training_pairs(task, Trajectory(*(jnp.asarray(getattr(t, n)) for n in Trajectory._fields)))
             for t in result.trials[:TRIAL]]
    x = np.concatenate([a for a, _ in pairs])[::-1]
    y = np.concatenate([b for _, b in pairs])[::-1]
    data = pad_to_capacity(make_data(x, y), chunk=result.config.gp_chunk)
    model, _, ok = full_posterior(snap.model.hyper, data, gp_config(result.config))
    assert bool(np.all(np.asarray(ok)))
    return model


def test_snapshot_reproduces_the_trials_stored_particle_prediction(snap):
    """The loop stored, after optimising trial 2, a particle prediction with the trial's final policy on
    the trial's model. The rebuilt model with the same key must give the same particles: this pins the
    data (trials 0-1, padded), the hyperparameters and the posterior, to rounding."""
    cfg = snap.config
    k_trials = jax.random.split(jax.random.PRNGKey(cfg.seed))[1]
    k_opt = jax.random.split(jax.random.fold_in(k_trials, TRIAL), 4)[2]  # loop.run_experiment's key order
    k_pred = jax.random.split(k_opt, 3)[2]  # the stochastic optimizer's key order
    from pipps.experiments.results import read_result

    stored = read_result(RESULT).trials[TRIAL]
    rcfg, _ = particle_method(cfg)
    predict = _particle_prediction(snap.task, rcfg, cfg.store_particles)
    pred = predict(k_pred, snap.unravel(stored.policy), snap.model)["particles"]
    # The file was written on another machine; its CPU summed in another order, and 30 steps of
    # a particle rollout amplify rounding. The tolerance is that amplification measured here: the
    # same model rebuilt from the training pairs in reverse order (equal in exact arithmetic, other
    # rounding) moves the prediction by `spread`; the stored one may differ by 100x that, while a
    # wrong model, policy or key moves it by O(1) (checked below).
    permuted = predict(k_pred, snap.unravel(stored.policy), _reversed_model(snap))["particles"]
    spread = float(np.max(np.abs(np.asarray(permuted) - np.asarray(pred))))
    assert 0.0 < spread < 1e-6, spread  # rounding, amplified, but rounding
    np.testing.assert_allclose(pred, stored.predicted.particles, rtol=0, atol=100 * spread)
    other = predict(jax.random.fold_in(k_pred, 1), snap.unravel(stored.policy), snap.model)["particles"]
    assert float(np.max(np.abs(np.asarray(other) - stored.predicted.particles))) > 1e4 * spread
    assert snap.num_points == 60
    # and the snapshot's policy is the one trial 2 started from: what trial 1 ran
    np.testing.assert_array_equal(np.asarray(snap.theta), read_result(RESULT).trials[1].policy)


def test_snapshot_refuses_trials_it_cannot_rebuild():
    with pytest.raises(ValueError, match="not a learned trial"):
        load_snapshot(RESULT, 0)
    with pytest.raises(ValueError, match="FITC"):
        load_snapshot(RESULT, 12)


def test_landscape_moment_matching_derivative_matches_finite_differences(snap):
    """J_MM along the line and its autodiff derivative along d agree (central differences): the points
    θ + Δ·d and the direction are what the study reports.

    The tolerance is the central difference's own error, measured in the same call: truncation from
    two step sizes (the h² term: fd(2h) − fd(h) is three times fd(h)'s), rounding from J_MM's
    scatter at steps far below h (J_MM carries ~1e-10 of rounding through its GP solves, which a
    step of 1e-4 turns into 1e-6 of derivative, 3e-5 relative: a fixed rtol of 1e-5 failed in CI)."""
    h, tiny = 1e-3, 1e-10
    probes = [0.3 + k * tiny for k in (-2, -1, 1, 2)]
    r = landscape(snap, deltas=[0.3, 0.3 - h, 0.3 + h, 0.3 - 2 * h, 0.3 + 2 * h, *probes], particles=4,
                  repeats=2, estimators=["rp"], direction="random")
    J, g = np.asarray(r.objective_mm), float(r.directional_mm[0])
    fd_h, fd_2h = (J[2] - J[1]) / (2 * h), (J[4] - J[3]) / (4 * h)
    # rounding scatter of J_MM: its departure from the tangent line over steps of 1e-10 (the curvature
    # there is ~1e-20, the slope's share g·k·tiny is removed)
    noise = max(abs(J[5 + i] - J[0] - g * (p - 0.3)) for i, p in enumerate(probes))
    truncation = abs(fd_2h - fd_h) / 3
    rounding = noise / h  # (e₊ − e₋)/2h with |e±| ≤ noise
    bound = 2 * (truncation + rounding) + 8 * np.finfo(float).eps * abs(g)
    assert abs(g - fd_h) <= bound, (g, fd_h, truncation, rounding)
    assert bound < 1e-4 * abs(g), bound  # else the check would have no power: a wrong term moves g by far more
    assert np.isclose(np.linalg.norm(r.direction), 1.0)


def test_unbiased_estimators_agree_along_the_direction(snap):
    """RP, BIW-LR and TP estimate the same ∇J·d: their means over independent repeats agree within
    their combined 99.9 % intervals at a smooth point (fixed seeds: deterministic)."""
    r = landscape(snap, deltas=[0.0], particles=100, repeats=8, estimators=["rp", "lr", "tp"], direction="random", seed=3)
    stats = {n: interval(r.samples[n][0].directional) for n in r.samples}
    for a in stats:
        for b in stats:
            (ma, ha), (mb, hb) = stats[a], stats[b]
            assert abs(ma - mb) <= 3.29 / 1.96 * np.hypot(ha, hb), (a, b, stats)
    assert all(s[0].nonfinite == 0 for s in r.samples.values())


def test_variance_falls_with_the_number_of_particles(snap):
    """For a smooth point the covariance trace of an average over P independent particles falls as 1/P:
    from P = 20 to 80 the ratio is near 4 (a study that ignored P would give ~1)."""
    r = variance_study(snap, deltas=[0.0], particles=[20, 80], repeats=12, estimators=["rp"], direction="random")
    ratio = r.samples["rp"][0][0].trace_variance / r.samples["rp"][0][1].trace_variance
    assert 2.0 < ratio < 8.0, ratio


def test_cli_landscape_quick_writes_the_documented_file(tmp_path, capsys):
    out = tmp_path / "l.h5"
    assert main(["study", "landscape", str(RESULT), "--trial", str(TRIAL), "--quick", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| Δ | J (fixed seed)" in text and "RP ĝ·d" in text
    with h5py.File(out, "r") as f:
        assert f.attrs["study"] == "landscape" and f.attrs["trial"] == TRIAL and f.attrs["particles"] == 30
        assert f["deltas"].shape == (3,) and f["objective_mm"].shape == (3,)
        assert set(f["estimators"]) == {"rp", "tp"}
        assert f["estimators/tp/delta_002/directional"].shape == (3,)
    assert (tmp_path / "l.rrd").stat().st_size > 0


@pytest.mark.slow  # the landscape's CLI test above runs by default; this is the same path for the variance study
def test_cli_variance_quick_writes_the_documented_file(tmp_path, capsys):
    out = tmp_path / "v.h5"
    assert main(["study", "variance", str(RESULT), "--trial", str(TRIAL), "--quick", "--out", str(out)]) == 0
    assert "TP/BIW-LR" not in capsys.readouterr().out  # quick mode has no BIW-LR column to compare with
    with h5py.File(out, "r") as f:
        assert f.attrs["study"] == "variance" and list(f["particles"][()]) == [10, 30]
        assert f["estimators/tp/delta_001/P_30/directional"].shape == (3,)
    assert (tmp_path / "v.rrd").stat().st_size > 0


@pytest.mark.parametrize("argv, needle", [
    (["--trial", "12"], "FITC"),
    (["--estimators", "rp,xx"], "estimators"),
])
def test_cli_study_errors_name_the_problem(argv, needle, capsys, tmp_path):
    assert main(["study", "landscape", str(RESULT), "--quick", "--out", str(tmp_path / "s.h5"), *argv]) == 2
    assert needle in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:  # a malformed grid is refused by argparse, before the file is read
        main(["study", "landscape", str(RESULT), "--quick", "--deltas", "0:1.5"])
    assert exc.value.code == 2 and "--deltas" in capsys.readouterr().err


def test_bench_pareto_front_and_errors():
    from pipps.studies.bench import BenchEntry, pareto

    es = [BenchEntry("rp", 10, 0.01, 5.0, 0, 0), BenchEntry("rp", 30, 0.02, 1.0, 0, 0),
          BenchEntry("tp", 10, 0.015, 6.0, 0, 0), BenchEntry("tp", 30, 0.03, 0.5, 0, 0),
          BenchEntry("lr", 30, 0.03, 2.0, 0, 0), BenchEntry("del", 30, 0.01, float("nan"), 0, 3)]
    assert [(e.estimator, e.particles) for e in pareto(es)] == [("rp", 10), ("rp", 30), ("tp", 30)]


def test_bench_mse_is_measured_against_the_reference(snap):
    """With the reference estimator itself at the reference P, the MSE of one estimate is its covariance
    trace plus the reference's own error: E‖ĝ − ḡ‖² = tr C (1 + 1/n) for independent draws. (Plain LR:
    its gradients are light-tailed; RP's are heavy-tailed on this model even at Δ = 0, where one
    outlier among the reference draws dominates both sides.)"""
    from pipps.studies.bench import bench

    r = bench(snap, deltas=[0.0], particles=[40], estimators=["lr_plain"], repeats=24, reference="lr_plain",
              reference_repeats=24, time_repeats=1, direction="random")
    e, ref_err = r.entries[0][0], r.reference_error[0]
    expected = ref_err * 24 * (1 + 1 / 24)  # tr C = n · tr Cov[g_ref]
    assert abs(e.mse - expected) < 3 * e.mse_se + 0.5 * expected, (e.mse, expected, e.mse_se)
    assert e.seconds > 0 and r.mm_seconds > 0


def test_bench_variance_tolerance_axis(snap, tmp_path):
    """Each tolerance adds a series on the low-rank model; its estimates are paired with the exact
    variance's (same keys): at a tolerance far below rounding they equal them to rounding, at a loose
    one they move, by far less than their own Monte Carlo spread; the file keeps ranks and bounds."""
    from pipps.studies.bench import bench, bench_table, read_bench, write_bench

    r = bench(snap, deltas=[0.0], particles=[30], estimators=["tp"], repeats=4, reference_repeats=2, time_repeats=1,
              direction="random", variance_tols=[1e-300, 1e-1])
    es = {e.variance_tol: e for e in r.entries[0]}
    assert sorted(es) == [0.0, 1e-300, 1e-1]
    exact, tight, loose = es[0.0], es[1e-300], es[1e-1]
    assert exact.exact_change == 0.0 and exact.exact_spread > 0
    # full rank is the exact variance computed in another order (to ~1e-9 σ_f², test_lowrank.py); the
    # rollout's 30 steps and the LR weights amplify that rounding, but far less than a 1e-1 truncation
    assert tight.exact_change <= 1e-4 * tight.exact_spread, (tight.exact_change, tight.exact_spread)
    assert 10 * tight.exact_change < loose.exact_change < 0.1 * loose.exact_spread, (loose.exact_change, loose.exact_spread)
    assert np.all(r.variance_bounds[1e-1] <= 1e-1) and np.all(r.variance_ranks[1e-1] < snap.num_points)
    assert "variance tol 0.1" in bench_table(r)
    back = read_bench(write_bench(tmp_path / "b.h5", r))
    assert [(e.series, e.exact_change) for e in back.entries[0]] == [(e.series, e.exact_change) for e in r.entries[0]]
    np.testing.assert_array_equal(back.variance_ranks[1e-1], r.variance_ranks[1e-1])


@pytest.mark.slow  # end to end through the CLI; the library path runs by default (test above)
def test_cli_bench_quick(tmp_path, capsys):
    out = tmp_path / "b.h5"
    assert main(["bench", str(RESULT), "--trial", str(TRIAL), "--quick", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| error target (MSE ≤) | fastest |" in text and "PILCO (exact MM gradient)" in text
    with h5py.File(out, "r") as f:
        assert f.attrs["study"] == "bench" and f["reference"].shape[0] == 2
        assert list(f["entries/delta_000/particles"][()]) == [20, 20]
    assert (tmp_path / "b.rrd").stat().st_size > 0


def test_snapshot_of_a_fitc_trial_reproduces_its_stored_prediction(tmp_path):
    """A run whose last trial trains FITC (threshold lowered) stores the inducing inputs; the snapshot
    rebuilds that FITC model exactly (the stored particle prediction is reproduced)."""
    from pipps.experiments import resolve_config, run_experiment
    from pipps.experiments.results import read_result, write_result

    cfg = resolve_config("quick", "cartpole_swingup", num_learned=2, num_particles=8, policy_evals=6, eval_rollouts=3,
                         gp_max_iters=10, progress_chunk=3, store_particles=4, fitc_threshold=50, num_inducing=20,
                         fitc_first_iters=5)
    path = tmp_path / "fitc.h5"
    run_experiment(cfg, on_trial=lambda r: write_result(path, r))
    stored = read_result(path).trials[-1]
    assert stored.gp.sparse and stored.gp.inducing.shape == (20, 5)
    snap = load_snapshot(path, stored.index)
    assert snap.model.inputs.shape == (20, 5)
    k_trials = jax.random.split(jax.random.PRNGKey(cfg.seed))[1]
    k_pred = jax.random.split(jax.random.split(jax.random.fold_in(k_trials, stored.index), 4)[2], 3)[2]
    rcfg, _ = particle_method(cfg)
    pred = _particle_prediction(snap.task, rcfg, cfg.store_particles)(k_pred, snap.unravel(stored.policy), snap.model)
    np.testing.assert_allclose(pred["particles"], stored.predicted.particles, rtol=1e-9, atol=1e-9)


def _experiment_script(name: str):
    """experiments/NAME.py as a module (a script, not part of the package)."""
    import importlib.util

    path = Path(__file__).resolve().parents[1] / f"experiments/{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    return script


def test_the_del_alignment_script_measures_each_reading_against_the_reference(capsys):
    """docs/results.md's "Where the failing runs stuck" table, small: at trial 1 of a committed DEL run
    (balancing; every estimator points down the gradient there), the library's TP, the reference's own
    estimator at fewer particles, must point along the reference, and each row must count its
    finite estimates. A wrong reference, sign or projection would break the first row's numbers."""
    script = _experiment_script("del_gradient_alignment")
    run = Path(__file__).resolve().parents[1] / "results/thesis/cartpole_balance_angle_k1_del_thesis_s0.h5"
    with pytest.raises(SystemExit):
        script.main([str(run), "--trial", "1", "--readings", "del:nonsense"])
    assert "--readings: unknown del:nonsense" in capsys.readouterr().err
    script.main([str(run), "--trial", "1", "--particles", "10", "--repeats", "3", "--reference-particles", "20",
                 "--reference-repeats", "4", "--readings", "tp:library,del:library"])
    out = capsys.readouterr().out
    assert "P = 10, 3 estimates each; reference: library TP at P = 20, 4 estimates" in out
    rows = [line.split(" | ") for line in out.splitlines() if line.startswith("| ") and "/3 |" in line]
    assert [r[0] for r in rows] == ["| DEL, library (returns-to-go, one step)", "| TP, library"]  # READINGS' order
    tp = rows[1]
    assert tp[1] == "3/3" and float(tp[2]) > 0.9  # cos(E ĝ, g_ref): the same estimator as the reference
    projection, half_width = (float(v) for v in tp[3].split(" ± "))
    assert abs(projection - 1) < max(3 * half_width, 0.3)


def test_mardias_statistics_tell_a_gaussian_from_a_uniform_and_a_skewed_marginal():
    """experiments/del_marginal_shape.py's statistics: kurtosis over D(D+2) is 1 for a Gaussian and
    (1.8·D + D(D−1)) / (D(D+2)) = 0.8 for independent standardised uniforms in D = 4 (E z⁴ = 1.8);
    skewness b₁ is about D(D+1)(D+2)/P for a Gaussian and far above it for exponentials.
    Tolerances: five standard errors of b₂/(D(D+2)), √(8 / (D(D+2)P)) for a Gaussian."""
    script = _experiment_script("del_marginal_shape")
    from pipps.precision import enable_float64

    enable_float64()
    P, D = 4_000, 4  # b₁ takes a P × P matrix
    tol = 5 * np.sqrt(8 / (D * (D + 2) * P))
    k = jax.random.split(jax.random.PRNGKey(0), 3)
    kurt, skew = script.mardia(jax.random.normal(k[0], (P, D)))
    assert abs(float(kurt) - 1) < tol and float(skew) < 3 * D * (D + 1) * (D + 2) / P
    kurt, _ = script.mardia(jax.random.uniform(k[1], (P, D)))
    assert abs(float(kurt) - 0.8) < tol
    _, skew = script.mardia(jax.random.exponential(k[2], (P, D)))
    assert float(skew) > 100 * D * (D + 1) * (D + 2) / P


def test_trial_traces_reads_quasi_newton_files_and_prices_the_return_the_tables_count(capsys):
    """experiments/trial_traces.py on a PILCO file (a line-search trace, no gradient steps): it must not
    fail, and its "model" column must be PILCO's predicted return over steps 1..T, the steps the true
    return counts — the stored moment prediction's cost_mean[1:].sum(), not its sum over 0..T, which
    adds the start's cost (1 on the cart-pole's Tip Cost) and made docs quote 8.0 for a 7.0."""
    from pipps.experiments.results import read_result

    script = _experiment_script("trial_traces")
    run = Path(__file__).resolve().parents[1] / "results/thesis/cartpole_swingup_tip_k1_pilco_thesis_s0.h5"
    script.main([str(run)])
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("  trial 015:")]
    assert len(lines) == 1 and "line searches" in lines[0]
    model = float(lines[0].split("model ")[1].split()[0])
    final = read_result(run, verify=False).trials[-1]
    cost = np.asarray(final.predicted.cost_mean)
    assert abs(model - cost[1:].sum()) < 0.005  # printed to 2 decimals
    assert abs(cost[0] - 1.0) < 0.01 and abs(model - cost.sum()) > 0.9
