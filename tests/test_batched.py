"""Many seeds at once (issue 7): the batched path equals the unbatched one, seed for seed.

The configuration is the tiny quick-preset experiment of test_experiments.py with a FITC
threshold of 40 points, so the batch trains a full GP (30 points) and then FITC (60 points,
first inducing inputs drawn from the seed's key): both training programs and both model shapes
go through the seed axis. Equality is to a tolerance, not bit for bit: the batched programs
are compiled as a whole and XLA may reassociate sums in them.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipps.experiments import resolve_config, run_experiment
from pipps.experiments.batched import check_batchable, run_batched
from pipps.experiments.methods import METHODS
from pipps.experiments.results import read_result
from pipps.experiments.sweep import experiment_name, run_sweep

SMALL = dict(num_learned=2, num_particles=8, policy_evals=6, eval_rollouts=3, gp_max_iters=10, progress_chunk=3,
             store_particles=4, fitc_threshold=40, num_inducing=20, fitc_iters=5, fitc_first_iters=5)
SEEDS = (0, 3)


def small(seed, **kw):
    unused = METHODS[kw.get("method", "tp")].unused  # PILCO takes no particle settings
    return resolve_config("quick", "cartpole_swingup",
                          **{**{k: v for k, v in SMALL.items() if k not in unused}, "seed": seed, **kw})


@pytest.fixture(scope="module")
def unbatched():
    return [run_experiment(small(s)) for s in SEEDS]


def assert_close_results(a, b, rtol=1e-7, atol=1e-9):
    assert a.config == b.config and a.status == b.status == "complete"
    assert len(a.trials) == len(b.trials)
    for ta, tb in zip(a.trials, b.trials):
        for name in ("states", "observations", "actions", "eval_returns", "policy"):
            np.testing.assert_allclose(getattr(ta, name), getattr(tb, name), rtol=rtol, atol=atol,
                                       err_msg=f"trial {ta.index}: {name}")
        if ta.kind == "learned":
            np.testing.assert_allclose(ta.gp.log_noise, tb.gp.log_noise, rtol=rtol, atol=atol)
            np.testing.assert_allclose(ta.opt_trace.value, tb.opt_trace.value, rtol=rtol, atol=atol)
            assert ta.gp.sparse == tb.gp.sparse
            if ta.gp.sparse:  # L-BFGS on the FITC objective amplifies reassociation: measured
                # 1.2e-7 absolute (5.7e-7 relative) between vmapped and separate runs, while the
                # trajectories and policies that follow agree to 1e-7 relative
                np.testing.assert_allclose(ta.gp.inducing, tb.gp.inducing, rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_batched_seeds_equal_separate_runs(unbatched):
    """The CPU default (seeds mapped inside one program per phase), with its own checks; the
    sweep test below covers the same path in the default run."""
    batched = run_batched([small(s) for s in SEEDS], batching="map")
    assert [t.gp.sparse for t in batched[0].trials[1:]] == [False, True]
    for a, b in zip(unbatched, batched):
        assert_close_results(a, b)
        assert all(t.timings.batched_seeds == len(SEEDS) for t in b.trials)
    # the seeds really differ: equality above is not two copies of one run
    assert not np.allclose(batched[0].trials[-1].policy, batched[1].trials[-1].policy)


@pytest.mark.slow  # ~2.5 min of CI; the GPU path. The mapped path stays in the default run (sweep and resume tests)
def test_vmapped_seeds_equal_separate_runs(unbatched):
    """The accelerator path: vmapped trials, rollouts and optimiser steps. On CPU (here) the GP
    training's seed axis stays mapped (batched CPU LAPACK deadlocks with two XLA threads; a
    vmapped GP training is exercised only on an accelerator).

    Vectorized programs reassociate sums, and the optimisation amplifies that; with the GP
    vmapped too (one pinned core) the largest gap measured was 5.8e-7 relative in a policy weight
    after the FITC trial. A batching bug (a wrong key, seed slot or model) moves these by O(1)."""
    batched = run_batched([small(s) for s in SEEDS], batching="vmap")
    for a, b in zip(unbatched, batched):
        assert_close_results(a, b, rtol=1e-6, atol=1e-8)


def test_fit_many_refuses_vmap_on_cpu():
    import jax

    from pipps.gp import GPConfig, fit_many

    if jax.default_backend() != "cpu":
        pytest.skip("the refusal is CPU-only")
    with pytest.raises(ValueError, match="deadlock"):
        fit_many([None], [None], [None], GPConfig(), batching="vmap")


@pytest.mark.parametrize(
    "cfgs, match",
    [
        ([small(0), small(1, policy_evals=9)], r"differ only in the seed \(policy_evals: 6 stored, 9 asked\)"),
        ([small(0), small(0)], "seeds repeat"),
        ([small(0, method="pilco"), small(1, method="pilco")], "'pilco' optimises with per-seed quasi-Newton"),
        ([small(0, method="rp_fs"), small(1, method="rp_fs")], "'rp_fs'"),
        ([], "no configurations"),
    ],
)
def test_what_cannot_be_batched_is_refused_by_name(cfgs, match):
    with pytest.raises(ValueError, match=match):
        check_batchable(cfgs)


def test_a_batched_phase_that_fails_fails_every_seed_and_keeps_their_trials():
    seen = []

    def progress(event):
        if event["phase"] == "gp" and event["trial"] == 2:
            raise RuntimeError("simulated crash in trial 2")

    with pytest.raises(RuntimeError, match="simulated"):
        run_batched([small(s) for s in SEEDS], progress=progress, batching="map",
                    on_trial=lambda rs: seen.append([(r.status, len(r.trials)) for r in rs]))
    assert seen[-1] == [("failed", 2), ("failed", 2)]


def test_sweep_batched_writes_each_seed_like_the_unbatched_sweep(unbatched, tmp_path):
    cfgs = [small(s) for s in SEEDS]
    report = run_sweep(cfgs, tmp_path, batched=True)
    assert not report.failed and len(report.ran) == 2
    for cfg, ref in zip(cfgs, unbatched):
        assert_close_results(ref, read_result(tmp_path / f"{experiment_name(cfg)}.h5"))
    again = run_sweep(cfgs, tmp_path, batched=True)
    assert again.ran == [] and len(again.skipped) == 2


def test_a_batched_sweep_cut_part_way_resumes_as_a_batch(unbatched, tmp_path):
    """A GPU job cut off after trial 1 (issue 18): the files hold trials 0-1; the rerun sweep resumes
    both seeds as one batch from trial 2 and ends where uninterrupted runs end."""
    from pipps.experiments.results import write_result

    cfgs = [small(s) for s in SEEDS]
    paths = [tmp_path / f"{experiment_name(c)}.h5" for c in cfgs]

    def cut(event):
        if event["phase"] == "gp" and event["trial"] == 2:
            raise KeyboardInterrupt  # the job's time limit

    with pytest.raises(KeyboardInterrupt):
        run_batched(cfgs, progress=cut, batching="map",
                    on_trial=lambda rs: [write_result(p, r) for r, p in zip(rs, paths)])
    assert [len(read_result(p, verify=False).trials) for p in paths] == [2, 2]
    seen = []
    import pipps.experiments.batched as batched_module

    real = batched_module.run_batched

    def spy(cfgs, **kw):
        seen.append([len(r.trials) for r in kw["resumes"]] if kw.get("resumes") else None)
        return real(cfgs, **kw)

    batched_module.run_batched = spy
    try:
        report = run_sweep(cfgs, tmp_path, batched=True)
    finally:
        batched_module.run_batched = real
    assert seen == [[2, 2]] and not report.failed and len(report.ran) == 2
    for path, ref in zip(paths, unbatched):
        got = read_result(path)
        assert_close_results(ref, got)
        assert got.resumed_at == [2]
    with pytest.raises(ValueError, match="same trial"):
        run_batched(cfgs, resumes=[read_result(paths[0]).__class__(cfgs[0], unbatched[0].trials[:1]),
                                   read_result(paths[1]).__class__(cfgs[1], unbatched[1].trials[:2])])
