"""The certified low-rank GP variance (pipps.gp.lowrank): the bound holds at every input,
the form is exact at full rank, and the default (variance_tol = 0) leaves the exact path alone."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jax
import jax.numpy as jnp

from pipps.experiments import resolve_config
from pipps.experiments.loop import planning_model
from pipps.gp import GPHyper, full_posterior, make_data, pad_to_capacity
from pipps.gp.fitc import fitc_posterior
from pipps.gp.lowrank import low_rank_fitc_posterior, low_rank_posterior
from pipps.gp.types import GPConfig
from pipps.particles.models import model_output


def _data_and_hyper(rng, n, dz, e, log_sn):
    """Random smooth data (padded to multiples of 16) and SE-ARD hyperparameters."""
    x = rng.uniform(-2, 2, (n, dz))
    y = np.sin(x @ rng.normal(size=(dz, e))) + 0.01 * rng.normal(size=(n, e))
    data = pad_to_capacity(make_data(x, y), chunk=16)
    hyper = GPHyper(jnp.asarray(rng.uniform(-1.0, 0.7, (e, dz))), jnp.asarray(rng.uniform(-0.5, 0.5, e)),
                    jnp.full(e, log_sn))
    return x, data, hyper


def _problem(seed, n, dz, e, log_sn):
    rng = np.random.default_rng(seed)
    x, data, hyper = _data_and_hyper(rng, n, dz, e, log_sn)
    post, jitter, ok = full_posterior(hyper, data, GPConfig())
    assert bool(np.all(np.asarray(ok)))
    z = jnp.asarray(np.concatenate([x[: n // 2] + 0.1 * rng.normal(size=(n // 2, dz)), rng.uniform(-3, 3, (20, dz))]))
    return post, data, np.asarray(jitter), z


@settings(max_examples=8, deadline=None)  # each example compiles new shapes
@given(seed=st.integers(0, 10_000), n=st.integers(4, 40), dz=st.integers(1, 3), e=st.integers(1, 3),
       log_sn=st.floats(-4.0, -1.0), tol=st.sampled_from([1e-1, 1e-3, 1e-6]))
def test_the_certified_bound_holds_at_every_input(seed, n, dz, e, log_sn, tol):
    post, data, jitter, z = _problem(seed, n, dz, e, log_sn)
    lr, ranks = low_rank_posterior(post, data, tol, jitter=jitter, bucket=4)
    exact = model_output(post, z, variance=True, jacobian=False)
    approx = model_output(lr, z, variance=True, jacobian=False)
    s2 = np.exp(2 * log_sn) + jitter
    sf2 = np.exp(2 * np.asarray(post.hyper.log_signal))
    # exact − low-rank = e ∈ [0, bound·σ²]; slack: the exact path's own rounding, ~eps·cond(K + σ²I)·σ_f²
    slack = 1e-12 * sf2 * (1 + n * sf2 / s2)
    err = np.asarray(exact.var) - np.asarray(approx.var)
    assert np.all(err >= -slack), (err.min(), slack)
    assert np.all(err <= np.asarray(lr.bound) * s2 + slack), (err.max(), np.asarray(lr.bound) * s2)
    assert np.all(np.asarray(lr.bound) <= tol) and np.all(ranks <= n)
    np.testing.assert_array_equal(np.asarray(approx.mean), np.asarray(exact.mean))  # the mean is untouched


def test_at_full_rank_the_form_is_the_exact_variance_and_its_jacobian():
    post, data, jitter, z = _problem(3, 30, 3, 2, -2.0)
    lr, ranks = low_rank_posterior(post, data, 1e-300, jitter=jitter)
    assert ranks.tolist() == [30, 30]
    exact = model_output(post, z, variance=True, jacobian=True)
    approx = model_output(lr, z, variance=True, jacobian=True)
    scale = float(np.max(np.exp(2 * np.asarray(post.hyper.log_signal))))
    np.testing.assert_allclose(approx.var, exact.var, rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(approx.jac_var, exact.jac_var, rtol=1e-6, atol=1e-9 * scale)


def _fitc_problem(seed, n, m, dz, e, log_sn):
    rng = np.random.default_rng(seed)
    x, data, hyper = _data_and_hyper(rng, n, dz, e, log_sn)
    xu = x[rng.choice(n, m, replace=False)] + 0.05 * rng.normal(size=(m, dz))
    post, jitter, ok = fitc_posterior(hyper, data, jnp.asarray(xu), GPConfig(fitc_threshold=m, num_inducing=m))
    assert bool(np.all(np.asarray(ok)))
    z = jnp.asarray(np.concatenate([x[: n // 2] + 0.1 * rng.normal(size=(n // 2, dz)), rng.uniform(-3, 3, (20, dz))]))
    return post, np.asarray(jitter), z


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(20, 60), m=st.integers(4, 20), dz=st.integers(1, 3),
       e=st.integers(1, 3), log_sn=st.floats(-4.0, -1.0), tol=st.sampled_from([1e-1, 1e-3, 1e-6]))
def test_the_fitc_bound_holds_at_every_input(seed, n, m, dz, e, log_sn, tol):
    post, jitter, z = _fitc_problem(seed, n, m, dz, e, log_sn)
    lr, ranks = low_rank_fitc_posterior(post, tol, jitter=jitter, bucket=4)
    exact = model_output(post, z, variance=True, jacobian=False)
    approx = model_output(lr, z, variance=True, jacobian=False)
    sn2 = np.exp(2 * log_sn)
    sf2 = np.exp(2 * np.asarray(post.hyper.log_signal))
    # slack: the exact path's rounding of kᵀ inv k, ~eps·‖inv‖·M·σ_f², with ‖inv‖ ≤ ‖(K_mm + ρI)⁻¹‖ ≤ 1/ρ
    slack = 1e-15 * m * sf2 / np.maximum(jitter, 1e-12) * sf2
    err = np.abs(np.asarray(exact.var) - np.asarray(approx.var))
    assert np.all(err <= np.asarray(lr.bound) * sn2 + slack), (err.max(), np.asarray(lr.bound) * sn2, slack)
    assert np.all(np.asarray(lr.bound) <= tol) and np.all(ranks <= m)
    np.testing.assert_array_equal(np.asarray(approx.mean), np.asarray(exact.mean))


def test_the_fitc_bound_is_not_vacuous_and_full_rank_is_exact():
    """On a problem whose spectrum falls, a loose tolerance keeps few directions and the error it
    makes is real (so the bound test can fail); at full rank the form is the exact variance and Jacobian."""
    post, jitter, z = _fitc_problem(5, 80, 40, 1, 2, -1.0)  # 40 inducing inputs on a line
    lr, ranks = low_rank_fitc_posterior(post, 1e-1, jitter=jitter)
    assert np.all(ranks <= 12)
    err = np.abs(np.asarray(model_output(post, z, variance=True, jacobian=False).var)
                 - np.asarray(model_output(lr, z, variance=True, jacobian=False).var))
    assert np.all(err.max(axis=0) > 1e-3 * np.asarray(lr.bound) * np.exp(-2.0))  # a real error, within the bound
    full, ranks = low_rank_fitc_posterior(post, 1e-300, jitter=jitter)
    exact = model_output(post, z, variance=True, jacobian=True)
    approx = model_output(full, z, variance=True, jacobian=True)
    scale = float(np.max(np.exp(2 * np.asarray(post.hyper.log_signal))))
    np.testing.assert_allclose(approx.var, exact.var, rtol=0, atol=1e-8 * scale)
    np.testing.assert_allclose(approx.jac_var, exact.jac_var, rtol=1e-6, atol=1e-8 * scale)


def test_the_default_plans_on_the_exact_posterior_and_refusals():
    post, data, jitter, _ = _problem(1, 20, 2, 2, -2.0)

    class Info:
        sparse, posterior_jitter = False, jitter

    cfg = resolve_config("thesis", "cartpole_swingup")
    assert cfg.variance_tol == 0.0
    model, ranks = planning_model(cfg, post, data, Info)
    assert model is post and ranks is None  # the exact path, untouched
    model, ranks = planning_model(cfg.replace(variance_tol=1e-2), post, data, Info)
    assert ranks is not None and type(model).__name__ == "LowRankPosterior"
    assert planning_model(cfg.replace(variance_tol=1e-2, method="tp-sf"), post, data, Info)[0] is post
    Info.sparse = True
    fpost, fjitter, _ = _fitc_problem(1, 40, 12, 2, 2, -2.0)[:3]
    Info.posterior_jitter = fjitter
    model, ranks = planning_model(cfg.replace(variance_tol=1e-2), fpost, None, Info)  # FITC: its own form
    assert ranks is not None and type(model).__name__ == "LowRankPosterior" and np.all(np.asarray(model.bound) <= 1e-2)
    assert planning_model(cfg, fpost, None, Info)[0] is fpost
    with pytest.raises(ValueError, match="tol must be > 0"):
        low_rank_posterior(post, data, 0.0)
    with pytest.raises(ValueError, match="variance_tol"):
        cfg.replace(variance_tol=-1.0)


def test_an_experiment_runs_on_the_low_rank_variance_and_records_its_ranks():
    from pipps.experiments import run_experiment

    cfg = resolve_config("quick", "cartpole_swingup", num_learned=1, num_particles=8, policy_evals=6,
                         eval_rollouts=3, gp_max_iters=10, progress_chunk=3, store_particles=4, variance_tol=1e-3)
    r = run_experiment(cfg)
    gp = r.trials[1].gp
    assert r.status == "complete" and len(gp.variance_ranks) == 4
    assert np.all(np.asarray(gp.variance_bound) <= 1e-3)
    assert jax.numpy.isfinite(r.trials[1].policy).all()
