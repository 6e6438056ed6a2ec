"""Nothing a user types loses or mislabels a result (docs/reliability.md).

Most tests replace the learning loop by a fake that writes small, valid results in milliseconds
(``fake_loop``): what is under test is the bookkeeping around it (names, presets, locks, overwrite
rules, option parsing, output checks), which does not depend on what a trial computes.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import pipps.experiments.loop as loop
from pipps.cli import main
from pipps.cli_report import RunProgress
from pipps.experiments import budget
from pipps.experiments.config import (
    config_hash,
    departures,
    experiment_name,
    from_dict,
    resolve_config,
    same_experiment,
)
from pipps.experiments.records import (
    ExperimentResult,
    GPRecord,
    MomentPrediction,
    ParticlePrediction,
    SearchTrace,
    StepTrace,
    Timings,
    TrialResult,
)
from pipps.experiments.results import read_result, read_summary, verify_result, write_result
from pipps.experiments.storage import (
    MANIFEST,
    OutputError,
    ResultBusy,
    ResultLock,
    check_output_file,
    check_output_folder,
    claim_sweep_folder,
)
from pipps.experiments.sweep import _run_one, run_sweep

REPO = Path(__file__).resolve().parents[1]


def fake_trial(cfg, i):
    rng = np.random.default_rng([cfg.seed, i, int(cfg.k * 100)])
    return TrialResult(
        i, "random" if i < cfg.num_random else "learned", states=rng.normal(size=(4, 4)),
        observations=rng.normal(size=(4, 4)), actions=rng.normal(size=(3, 1)), costs=rng.uniform(size=3),
        valid=np.ones(3, bool), eval_returns=rng.uniform(0, 30, size=3), eval_upright=np.ones(3, bool),
        policy=rng.normal(size=5), timings=Timings(total=0.0), eval_balanced=rng.uniform(size=3) < 0.5,
        gp=None if i < cfg.num_random else GPRecord(np.zeros((4, 5)), np.zeros(4), np.zeros(4), sparse=False,
                                                     num_points=10 * i, objective=np.zeros(4), messages=""))


def fake_run_experiment(cfg, *, progress=None, on_trial=None, resume=None, stop_after=None):
    trials = list(resume.trials) if resume is not None else []
    result = ExperimentResult(cfg, trials, "running", resumed_at=[len(trials)] if trials else [])
    for i in range(len(trials), cfg.num_trials):
        if stop_after is not None and i >= stop_after:
            raise KeyboardInterrupt  # a kill between trials: the file keeps what finished
        trials.append(fake_trial(cfg, i))
        if i == cfg.num_trials - 1:
            result.status = "complete"
        if on_trial:
            on_trial(result)
    return result


@pytest.fixture
def fake_loop(monkeypatch):
    monkeypatch.setattr(loop, "run_experiment", fake_run_experiment)
    return fake_run_experiment


def cli(*args, capsys=None):
    code = main([str(a) for a in args])
    out = capsys.readouterr() if capsys else None
    return code, out


# -- 1. silent overwrite ------------------------------------------------------------------------------


def test_run_never_replaces_an_existing_result_without_overwrite(fake_loop, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli("run", "--quiet", capsys=capsys)[0] == 0
    thesis = tmp_path / "runs/cartpole_swingup_angle_k1_tp_thesis_s0.h5"
    stamp = thesis.read_bytes()
    code, out = cli("run", "--quiet", capsys=capsys)
    assert code == 2 and "already holds a complete result" in out.err and "--overwrite" in out.err
    assert thesis.read_bytes() == stamp
    # a quick run goes to its own name, the thesis file is untouched
    assert cli("run", "--quiet", "--preset", "quick", capsys=capsys)[0] == 0
    assert (tmp_path / "runs/cartpole_swingup_angle_k1_tp_quick_s0.h5").exists() and thesis.read_bytes() == stamp
    # --set changes the name: a different configuration never reuses one
    assert cli("run", "--quiet", "--set", "policy_evals=7", capsys=capsys)[0] == 0
    custom = resolve_config("thesis", "cartpole_swingup", policy_evals=7)
    assert (tmp_path / f"runs/{experiment_name(custom)}.h5").exists() and thesis.read_bytes() == stamp
    # an explicit --out onto another experiment is refused, naming the difference
    code, out = cli("run", "--quiet", "--seed", "3", "--out", thesis, capsys=capsys)
    assert code == 2 and "another experiment (seed: 0 stored, 3 asked)" in out.err and thesis.read_bytes() == stamp
    # ... and replaced only when asked
    assert cli("run", "--quiet", "--seed", "3", "--out", thesis, "--overwrite", capsys=capsys)[0] == 0
    assert read_result(thesis).config.seed == 3


def test_run_refuses_an_unfinished_or_damaged_file_and_resume_continues(fake_loop, tmp_path, capsys, monkeypatch):
    cfg = resolve_config("quick", "cartpole_swingup")
    out = tmp_path / "x.h5"
    with pytest.raises(KeyboardInterrupt):
        fake_run_experiment(cfg, on_trial=lambda r: write_result(out, r), stop_after=2)
    code, o = cli("run", "--quiet", "--preset", "quick", "--out", out, capsys=capsys)
    assert code == 2 and "unfinished run of this experiment (2 of 6 trials); --resume" in o.err
    assert cli("run", "--quiet", "--preset", "quick", "--out", out, "--resume", capsys=capsys)[0] == 0
    assert verify_result(out)[0] == "complete"
    code, o = cli("run", "--quiet", "--preset", "quick", "--out", out, "--resume", capsys=capsys)
    assert code == 2 and "already complete" in o.err
    out.write_bytes(b"not hdf5")
    code, o = cli("run", "--quiet", "--preset", "quick", "--out", out, capsys=capsys)
    assert code == 2 and "not an intact pipps result" in o.err and out.read_bytes() == b"not hdf5"
    code, o = cli("run", "--quiet", "--resume", "--overwrite", "--out", out, capsys=capsys)
    assert code == 2 and "contradict" in o.err


# -- 2. presets are stored and tabulated honestly ------------------------------------------------------


def test_quick_runs_are_stored_as_quick_and_not_counted_in_thesis_tables(fake_loop, tmp_path, capsys):
    assert cli("run", "--quiet", "--preset", "quick", "--out", tmp_path / "q.h5", capsys=capsys)[0] == 0
    with h5py.File(tmp_path / "q.h5") as f:
        assert json.loads(f.attrs["config_json"])["protocol"] == "quick"
        assert f["config"].attrs["protocol"] == "quick"
        assert f.attrs["config_hash"] == config_hash(read_result(tmp_path / "q.h5").config)
    code, out = cli("table", tmp_path, "--preset", "thesis", capsys=capsys)
    assert code == 1 and "no complete result of the thesis preset" in out.err and "--preset quick counts" in out.err
    assert "run with --preset quick" in out.out
    code, out = cli("table", tmp_path, "--preset", "quick", capsys=capsys)
    assert code == 0 and "(1) / 0.99" in out.out and "quick preset, not the thesis protocol" in out.out
    # without --preset, a folder of quick results alone is counted as quick, and says it is not the thesis'
    code, out = cli("table", tmp_path, capsys=capsys)
    assert code == 0 and "(1) / 0.99" in out.out and "not the thesis protocol" in out.out
    assert "no complete result of the thesis preset" in out.err
    with pytest.raises(SystemExit) as exc:
        main(["table", str(tmp_path), "--preset", "bogus"])
    assert exc.value.code == 2 and "invalid choice: 'bogus'" in capsys.readouterr().err


def test_a_legacy_quick_file_is_recognised_as_quick():
    """Files written before ``protocol`` existed stored a quick run as ``preset: thesis``."""
    quick = resolve_config("quick", "cartpole_swingup", seed=4).to_dict()
    legacy = {k: v for k, v in quick.items() if k != "protocol"}
    assert legacy["preset"] == "thesis"
    assert from_dict(legacy).protocol == "quick"
    thesis = {k: v for k, v in resolve_config("thesis", "unicycle").to_dict().items() if k != "protocol"}
    assert from_dict(thesis).protocol == "thesis" and not departures(from_dict(thesis))
    custom = dict(thesis, policy_evals=11)
    assert from_dict(custom).protocol == "thesis" and departures(from_dict(custom)) == {"policy_evals": (11, 600)}


def test_committed_results_read_keep_their_names_and_retabulate(capsys, tmp_path):
    files = sorted((REPO / "results/thesis").glob("*.h5"))
    assert files
    for p in files:
        cfg = read_summary(p)["config"]
        assert f"{experiment_name(cfg)}.h5" == p.name and cfg.protocol == "thesis" and not departures(cfg)
    # the k = 1 cell's first five seeds of TP and PILCO (the folder grows as sweeps add seeds and methods)
    for p in files:
        if (p.name.startswith(("cartpole_swingup_angle_k1_tp_", "cartpole_swingup_angle_k1_pilco_"))
                and p.stem[-2:] in ("s0", "s1", "s2", "s3", "s4")):
            (tmp_path / p.name).symlink_to(p)
    code, out = cli("table", tmp_path, "--table", "4.1", capsys=capsys)
    # every reading (docs/results.md): 5/5 by the per-seed mean return each; TP seed 4 and PILCO seed 4
    # swing up but do not stay balanced (4/5 physically per seed), and PILCO's seed 4 system trial fails
    assert code == 0 and "| k = 1 | 0.83 [0.63, 0.92] (5) / 0.79 | 0.95 [0.61, 1.00] (5) / 0.99 |" in out.out
    assert ("| k = 1 | PILCO | 5 | 0.79 | 0.83 [0.63, 0.92] | 5/5 = 1.00 [0.57, 1.00] | 4/5 = 0.80 [0.38, 0.96] | "
            "0.73 [0.48, 0.87] | 4/5 = 0.80 [0.38, 0.96] | 4/5 = 0.80 [0.38, 0.96] |") in out.out
    assert ("| k = 1 | TP | 5 | 0.99 | 0.95 [0.61, 1.00] | 5/5 = 1.00 [0.57, 1.00] | 5/5 = 1.00 [0.57, 1.00] | "
            "0.79 [0.38, 0.98] | 4/5 = 0.80 [0.38, 0.96] | 4/5 = 0.80 [0.38, 0.96] |") in out.out


def test_the_default_cost_and_its_name_are_one_experiment():
    a = resolve_config("thesis", "cartpole_swingup")
    b = resolve_config("thesis", "cartpole_swingup", cost="angle")
    assert a != b and same_experiment(a, b) and experiment_name(a) == experiment_name(b)
    assert config_hash(a) == config_hash(b)
    assert not same_experiment(a, resolve_config("thesis", "cartpole_swingup", cost="tip"))
    assert a.cost_name == b.cost_name == "angle"  # the one name tables, plots and re-simulation print
    assert resolve_config("pilco", "cartpole_swingup").cost_name == "tip"


# -- 3. one writer per file, one protocol per sweep folder -------------------------------------------------


def _hold_lock(path, ready, release):
    with ResultLock(path):
        ready.set()
        release.wait(30)


def test_a_result_lock_excludes_other_processes_and_dies_with_its_holder(tmp_path):
    path = tmp_path / "a.h5"
    ctx = mp.get_context("spawn")
    ready, release = ctx.Event(), ctx.Event()
    holder = ctx.Process(target=_hold_lock, args=(str(path), ready, release))
    holder.start()
    try:
        assert ready.wait(60)
        with pytest.raises(ResultBusy, match=f"pid {holder.pid}"):
            ResultLock(path).acquire()
        cfg = resolve_config("quick", "cartpole_swingup")
        assert _run_one(cfg, str(path))[1:] == ("skipped", _run_one(cfg, str(path))[2])
        assert "running in another process" in _run_one(cfg, str(path))[2] and not path.exists()
    finally:
        release.set()
        holder.join(30)
    with ResultLock(path):  # released with its holder
        pass
    holder = ctx.Process(target=_hold_lock, args=(str(path), ctx.Event(), ctx.Event()))
    holder.start()
    time.sleep(0.5)
    holder.kill()
    holder.join(30)
    with ResultLock(path):  # a killed holder's lock is released by the kernel
        pass
    assert not (tmp_path / ".a.h5.lock").exists()


def test_a_sweep_skips_what_another_process_finished_and_never_reruns_it(fake_loop, tmp_path):
    cfgs = [resolve_config("quick", "cartpole_swingup", seed=s) for s in range(2)]
    path = tmp_path / f"{experiment_name(cfgs[0])}.h5"
    fake_run_experiment(cfgs[0], on_trial=lambda r: write_result(path, r))
    stamp = path.read_bytes()
    # planned as to-run when the other process had not finished: decided again under the lock
    assert _run_one(cfgs[0], str(path)) == (str(path), "skipped", "complete (finished by another process)")
    assert path.read_bytes() == stamp
    report = run_sweep(cfgs, tmp_path)
    assert report.ran == [str(tmp_path / f"{experiment_name(cfgs[1])}.h5")] and str(path) in report.skipped


def test_a_sweep_releases_each_experiments_compiled_programs(fake_loop, tmp_path, monkeypatch):
    """A long in-process sweep must not keep every experiment's compiled programs: their memory
    mappings accumulate until the kernel refuses more (a thesis sweep died after seven experiments).
    Released after every experiment, a failed one included."""
    import jax

    calls = []
    monkeypatch.setattr(jax, "clear_caches", lambda: calls.append(1))
    cfgs = [resolve_config("quick", "cartpole_swingup", seed=s) for s in range(3)]
    report = run_sweep(cfgs, tmp_path, jobs=1)
    assert len(report.ran) == 3 and len(calls) == 3

    def broken(cfg, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(loop, "run_experiment", broken)
    cfg = resolve_config("quick", "cartpole_swingup", seed=7)
    assert _run_one(cfg, str(tmp_path / "x.h5"))[1] == "failed" and len(calls) == 4


def test_sweeps_with_other_settings_refuse_the_folder(fake_loop, tmp_path, capsys):
    args = ["sweep", "--table", "4.1", "--k", "1", "--methods", "tp", "--seeds", "1", "--preset", "quick",
            "--out", tmp_path]
    assert cli(*args, capsys=capsys)[0] == 0
    manifest = json.loads((tmp_path / MANIFEST).read_text())
    assert manifest == {"protocol": "quick", "settings": {}}
    code, out = cli(*args, "--set", "policy_evals=7", capsys=capsys)
    assert code == 2 and "holds a sweep run with --preset quick" in out.err and "policy_evals=7" in out.err
    code, out = cli(*args[:-4], "--preset", "thesis", "--out", tmp_path, "--dry-run", capsys=capsys)
    assert code == 2 and "use another --out" in out.err
    assert len(list(tmp_path.glob("*.h5"))) == 1


def test_a_damaged_file_in_a_sweep_is_set_aside_not_overwritten(fake_loop, tmp_path):
    cfg = resolve_config("quick", "cartpole_swingup")
    path = tmp_path / f"{experiment_name(cfg)}.h5"
    path.write_bytes(b"damaged")
    report = run_sweep([cfg], tmp_path)
    assert report.ran == [str(path)] and "set aside" in report.notes[str(path)]
    (aside,) = tmp_path.glob("*.damaged-*")
    assert aside.read_bytes() == b"damaged" and verify_result(path)[0] == "complete"


# -- 4. one option, one meaning ---------------------------------------------------------------------------


@pytest.mark.parametrize("args, message", [
    (["run", "--set", "task=unicycle"], "use --task"),
    (["run", "--set", "preset=quick"], "use --preset"),
    (["run", "--method", "tp", "--set", "method=lr"], "use --method"),
    (["run", "--set", "num_particles=7"], "use --particles"),
    (["run", "--set", "policy_evals=7", "--set", "policy_evals=8"], "given twice"),
    (["sweep", "--table", "4.1", "--set", "method=lr"], "use --methods"),
    (["sweep", "--table", "4.1", "--set", "task=unicycle"], "use --table"),
    (["sweep", "--table", "4.1", "--set", "seed=3"], "use --seeds/--seed-start"),
    (["sweep", "--table", "4.1", "--set", "k=3"], "use --k"),
    (["sweep", "--table", "4.3", "--set", "cost=tip"], "the table's cells fix cost"),
    (["run", "--set", "bogus=1"], "bogus: unknown setting"),
])
def test_options_given_twice_or_unknown_are_named(args, message, capsys, tmp_path):
    code, out = cli(*args, "--out", tmp_path / ("x.h5" if args[0] == "run" else "d"), capsys=capsys)
    assert code == 2 and message in out.err and len(out.err.strip().splitlines()) == 1
    assert "Traceback" not in out.err and not list(tmp_path.rglob("*.h5"))


# -- 5. output paths are checked before any work ------------------------------------------------------------


def test_bad_outputs_are_refused_before_any_trial(fake_loop, tmp_path, capsys, monkeypatch):
    calls = []
    monkeypatch.setattr(loop, "run_experiment", lambda *a, **k: calls.append(1))
    afile = tmp_path / "afile"
    afile.write_text("x")
    for out, message in ((afile / "r.h5", "is a file, not a folder"), (tmp_path, "is a folder"),
                         ("/proc/pipps/r.h5", "cannot create folder"), (tmp_path / "r.txt", "must end in .h5")):
        code, o = cli("run", "--quiet", "--out", out, capsys=capsys)
        assert code == 2 and message in o.err, (out, o.err)
    for extra in ((), ("--dry-run",)):
        code, o = cli("sweep", "--table", "4.1", "--out", afile, *extra, capsys=capsys)
        assert code == 2 and "is a file, not a folder" in o.err
    assert not calls


def test_check_output_helpers(tmp_path):
    assert check_output_folder(tmp_path / "a/b", create=False) == tmp_path / "a/b" and not (tmp_path / "a").exists()
    assert check_output_file(tmp_path / "a/b/c.h5") and (tmp_path / "a/b").is_dir()
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        with pytest.raises(OutputError, match="cannot write"):
            check_output_file(ro / "x.h5")


def test_plot_png_without_its_viewer_is_one_line(monkeypatch, capsys):
    monkeypatch.setenv("PATH", "/nonexistent")
    code, out = cli("plot", REPO / "results/thesis/cartpole_swingup_angle_k1_tp_thesis_s0.h5", "--out",
                    "/tmp/pipps-test-never.rrd", "--png", "/tmp/x.png", capsys=capsys)
    assert code == 2 and "--png needs xvfb-run and the rerun viewer" in out.err
    assert len(out.err.strip().splitlines()) == 1 and not Path("/tmp/pipps-test-never.rrd").exists()


def test_an_unexpected_error_is_one_line_and_debug_shows_the_traceback(monkeypatch, tmp_path, capsys):
    def boom(*a, **k):
        raise RuntimeError("something broke\nsecond line")

    monkeypatch.setattr(loop, "run_experiment", boom)
    code, out = cli("run", "--quiet", "--out", tmp_path / "x.h5", capsys=capsys)
    assert code == 1 and out.err.strip() == ("pipps run: error: RuntimeError: something broke (pipps --debug run … "
                                             "or PIPPS_DEBUG=1 shows the traceback)")
    with pytest.raises(RuntimeError):
        main(["--debug", "run", "--quiet", "--out", str(tmp_path / "y.h5")])


# -- 6. the schema does not drift on resume -------------------------------------------------------------------


def test_scalars_stay_attributes_through_a_resume(fake_loop, tmp_path):
    cfg = resolve_config("quick", "cartpole_swingup")
    path = tmp_path / "r.h5"
    with pytest.raises(KeyboardInterrupt):
        fake_run_experiment(cfg, on_trial=lambda r: write_result(path, r), stop_after=3)
    fake_run_experiment(cfg, on_trial=lambda r: write_result(path, r), resume=read_result(path, verify=False))
    with h5py.File(path) as f:
        for name in ("001", "002", "003", "005"):
            gp = f["trials"][name]["gp"]
            assert "num_points" in gp.attrs and "num_points" not in gp and "sparse" in gp.attrs, name


def test_older_layouts_read_into_typed_records_and_are_written_back_as_fresh_ones(tmp_path):
    """Files resumed by older versions stored some scalars as datasets (gp/num_points) or attributes
    (opt_trace/stop_reason), and a file from another version may hold entries no record knows: all
    read, the known ones into their typed fields, and a rewrite stores the fresh layout and keeps the
    unknown entries as they were."""
    cfg = resolve_config("quick", "cartpole_swingup")
    path = tmp_path / "r.h5"
    result = fake_run_experiment(cfg)
    result.trials[1].opt_trace = SearchTrace(np.arange(3.0), np.array([4, 5, 6]), np.zeros(3, bool), np.asarray(2))
    write_result(path, result)
    with h5py.File(path, "r+") as f:
        gp, trace, timings = f["trials/001/gp"], f["trials/001/opt_trace"], f["trials/001/timings"]
        n = int(gp.attrs["num_points"])
        del gp.attrs["num_points"]
        gp.create_dataset("num_points", data=np.int64(n))
        del trace["stop_reason"]
        trace.attrs["stop_reason"] = np.int64(2)
        gp.create_dataset("from_the_future", data=np.arange(4))
        timings.attrs["warmup"] = 0.5
    back = read_result(path)
    t = back.trials[1]
    assert isinstance(t.gp, GPRecord) and t.gp.num_points == n and type(t.gp.num_points) is int
    assert isinstance(t.opt_trace, SearchTrace) and int(t.opt_trace.stop_reason) == 2
    np.testing.assert_array_equal(t.gp.extra["from_the_future"], np.arange(4))
    assert t.timings.extra == {"warmup": 0.5} and t.timings.total == 0.0
    again = tmp_path / "again.h5"
    write_result(again, back)
    with h5py.File(again) as f:
        gp, trace = f["trials/001/gp"], f["trials/001/opt_trace"]
        assert "num_points" in gp.attrs and "num_points" not in gp
        assert "stop_reason" in trace and "stop_reason" not in trace.attrs
        np.testing.assert_array_equal(gp["from_the_future"][()], np.arange(4))
        assert f["trials/001/timings"].attrs["warmup"] == 0.5


def _trial_entries(path) -> dict:
    """Every entry under /trials, attributes and datasets in one namespace per group (so a scalar an
    older version stored as the other kind compares equal)."""
    out = {}

    def visit(name, obj):
        for k, v in obj.attrs.items():
            out[f"{name}/{k}"] = v
        if isinstance(obj, h5py.Dataset):
            out[name] = obj[()]

    with h5py.File(path, "r") as f:
        f["trials"].visititems(visit)
    return out


def _one_file_per_writer(files) -> list:
    """The committed files that differ in what wrote them: the first file of each (recorded code
    commit, task, method, resumed or not), and every file whose writer is not one known commit (none
    recorded, ``unknown``, or a ``+dirty`` tree). More files from the same sweep add nothing, so the
    default run grows by at most one file per (commit, task, method, resumed), not per result; the
    slow run checks every file."""
    chosen, seen = [], set()
    for p in files:
        with h5py.File(p, "r") as f:
            code = f["versions"].attrs.get("code") if "versions" in f else None
            config = json.loads(f.attrs["config_json"])
            resumed = len(f.attrs.get("resumed_at", [])) > 0
        key = (code, config["task"], config["method"], resumed)
        if code is None or code == "unknown" or str(code).endswith("+dirty") or key not in seen:
            seen.add(key)
            chosen.append(p)
    return chosen


@pytest.mark.parametrize("every_file", [pytest.param(True, marks=pytest.mark.slow), False])
def test_committed_results_restore_the_loops_state_and_write_back_unchanged(tmp_path, every_file):
    """Old files still read (after the loop's refactors): committed results read into typed records, and restore()
    rebuilds the loop's state after its trials: the last trial's policy and GP, and data of one
    training pair per valid transition, the count each learned trial's GP records it was trained on
    (so the data restore rebuilds at a trial is the data that trial used). Written back by this
    writer, every trial entry is what the file holds. The default run checks one file per writer
    (:func:`_one_file_per_writer`), the slow run every file."""
    from jax.flatten_util import ravel_pytree

    from pipps.experiments.state import make_experiment_task, rebuildable_trials, restore

    files = sorted((REPO / "results/thesis").glob("*.h5"))
    assert files
    if not every_file:
        files = _one_file_per_writer(files)
    for p in files:
        r = read_result(p)
        transitions = np.cumsum([0] + [int(t.valid.sum()) for t in r.trials])  # before each trial, and after all
        for t in r.trials:
            assert isinstance(t.timings, Timings) and t.timings.total > 0, p.name
            if t.kind == "learned":
                assert t.gp.num_points == transitions[t.index], (p.name, t.index)
                # the quasi-Newton searches (PILCO, the fixed-seed methods) store their line searches
                searched = r.config.is_pilco or r.config.fixed_seed
                assert isinstance(t.opt_trace, SearchTrace if searched else StepTrace), (p.name, t.index)
                assert isinstance(t.predicted, MomentPrediction if r.config.is_pilco else ParticlePrediction)
        restored = restore(r, task=make_experiment_task(r.config))
        assert restored.trial == len(r.trials) and restored.num_points == transitions[-1]
        np.testing.assert_array_equal(np.asarray(ravel_pytree(restored.policy)[0]), r.trials[-1].policy)
        last = [t.gp for t in r.trials if t.gp is not None][-1]
        np.testing.assert_array_equal(np.asarray(restored.warm_start.hyper.log_lengthscale), last.log_lengthscale)
        assert rebuildable_trials(r) == [t.index for t in r.trials if t.kind == "learned"
                                         and (not t.gp.sparse or t.gp.inducing is not None)]
        write_result(tmp_path / p.name, r)
        a, b = _trial_entries(p), _trial_entries(tmp_path / p.name)
        assert a.keys() == b.keys(), (p.name, sorted(a.keys() ^ b.keys())[:5])
        for k in a:
            assert np.array_equal(np.asarray(a[k]), np.asarray(b[k]), equal_nan=np.asarray(a[k]).dtype.kind == "f"), k


# -- 7. numbering -------------------------------------------------------------------------------------------------


def test_progress_counts_trials_from_zero_like_trial_and_resume():
    import io

    out = io.StringIO()
    cfg = resolve_config("quick", "cartpole_swingup", num_learned=5)
    show = RunProgress(budget.estimate(cfg, budget.REFERENCE_GFLOPS), cfg.num_random, out)
    show(dict(phase="trial", trial=0, trials=6))
    show(dict(phase="evaluated", trial=0, trials=6, eval_return=1.0, upright=1.0, seconds=1.0))
    assert "trial 0 of 0-5" in out.getvalue()


def test_the_help_lists_every_command(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    for command in ("run", "sweep", "table", "plot", "study", "bench", "rollout"):
        assert f"``{command}``" in text


# -- the property: no sequence of commands leaves a file that claims another configuration ------------------

COMMANDS = st.lists(st.tuples(
    st.sampled_from(["run", "run-overwrite", "run-resume", "sweep", "kill-run"]),
    st.sampled_from(["thesis", "quick"]),
    st.sampled_from([(), ("policy_evals=7",), ("num_basis=3",)]),
    st.integers(0, 1)), min_size=1, max_size=6)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(COMMANDS)
def test_no_command_sequence_leaves_a_file_that_claims_another_configuration(fake_loop, tmp_path_factory, monkeypatch,
                                                                              commands):
    folder = tmp_path_factory.mktemp("prop")
    for command, preset, sets, seed in commands:
        set_args = [a for s in sets for a in ("--set", s)]
        if command == "sweep":
            main(["sweep", "--table", "4.1", "--k", "1", "--methods", "tp", "--seeds", "1", "--seed-start",
                  str(seed), "--preset", preset, *set_args, "--out", str(folder)])
            continue
        extra = {"run": [], "run-overwrite": ["--overwrite"], "run-resume": ["--resume"], "kill-run": []}[command]
        if command == "kill-run":
            monkeypatch.setattr(loop, "run_experiment",
                                lambda cfg, **kw: fake_run_experiment(cfg, stop_after=2, **kw))
        name = experiment_name(resolve_config(preset, "cartpole_swingup", seed=seed, **dict(
            s.split("=") for s in sets)))
        main(["run", "--quiet", "--preset", preset, "--seed", str(seed), *set_args, *extra,
              "--out", str(folder / f"{name}.h5")])
        monkeypatch.setattr(loop, "run_experiment", fake_run_experiment)
    for path in folder.glob("*.h5"):
        status, cfg, n = verify_result(path)
        assert path.name == f"{experiment_name(cfg)}.h5"  # the name claims exactly the stored configuration
        with h5py.File(path) as f:
            assert f.attrs["config_hash"] == config_hash(cfg)
    assert not list(folder.glob(".*.lock"))


# -- 8. extreme data ----------------------------------------------------------------------------------------------


def test_gp_data_whose_squares_overflow_are_refused():
    from pipps.gp import make_data

    x = np.random.default_rng(0).uniform(-1, 1, (20, 3))
    with pytest.raises(ValueError, match="inputs reach .* overflow float64 .* rescale the inputs"):
        make_data(x * 1e160, np.zeros(20))
    with pytest.raises(ValueError, match="targets reach"):
        make_data(x, x[:, 0] * 1e160)
    make_data(x * 1e150, x[:, 0] * 1e150)  # within range: accepted (and the fit is scale-invariant there)


# -- 10. the cluster path ------------------------------------------------------------------------------------------


def test_the_ray_extra_installs_the_client():
    text = (REPO / "pyproject.toml").read_text()
    assert 'ray = ["ray[client]' in text


def test_review_mends(fake_loop, tmp_path, capsys):
    """Found in review: an int and a float setting are one experiment and one name; a legacy quick file
    with a --set reads as quick; a run stopped in trial 0 is simply run again; a file another
    configuration holds stops a sweep as bad input (exit 2)."""
    a = resolve_config("thesis", "cartpole_swingup", k=1, policy_evals=7)
    b = resolve_config("thesis", "cartpole_swingup", k=1.0, policy_evals=7)
    assert same_experiment(a, b) and experiment_name(a) == experiment_name(b) and config_hash(a) == config_hash(b)
    c = resolve_config("thesis", "cartpole_swingup", k=1.0000001)
    assert experiment_name(c) != experiment_name(resolve_config("thesis", "cartpole_swingup"))
    quick = {k: v for k, v in resolve_config("quick", "cartpole_swingup", policy_evals=7).to_dict().items()
             if k != "protocol"}
    assert from_dict(quick).protocol == "quick"
    out = tmp_path / "x.h5"
    cfg = resolve_config("thesis", "cartpole_swingup")
    write_result(out, ExperimentResult(cfg, [], "failed", "KeyboardInterrupt"))
    assert cli("run", "--quiet", "--out", out, capsys=capsys)[0] == 0 and verify_result(out)[0] == "complete"
    folder = tmp_path / "sweep"
    other = resolve_config("thesis", "cartpole_swingup", method="tp", k=1.0, seed=0, cost="angle")
    fake_run_experiment(other.replace(seed=5), on_trial=lambda r: write_result(folder / f"{experiment_name(other)}.h5", r))
    code, o = cli("sweep", "--table", "4.1", "--k", "1", "--methods", "tp", "--seeds", "1", "--out", folder,
                  capsys=capsys)
    assert code == 2 and "holds another configuration" in o.err
