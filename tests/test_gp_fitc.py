"""Sparse FITC GP (docs/gp.md, "Sparse FITC"): objective and posterior against dense formulas, the X_u = X
limit, training, warm start, and the switch at the threshold."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pipps.gp import (
    GPConfig,
    GPHyper,
    fit,
    fitc_objective,
    fitc_posterior,
    full_posterior,
    make_data,
    pad_to_capacity,
    predict,
)
from pipps.gp.fit import _train_sparse
from pipps.gp.fitc import fitc_neg_log_likelihood

EPS = 1e-6  # PILCO's K_mm ridge, GPConfig.fitc_jitter


def np_kernel(x1, x2, ell, sf):
    d = (x1[:, None, :] - x2[None, :, :]) / ell
    return sf**2 * np.exp(-0.5 * np.sum(d * d, -1))


def np_fitc(x, y, xu, ell, sf, sn, eps=EPS):
    """Dense FITC written from the definitions: (nll, beta, inv)."""
    kmm = np_kernel(xu, xu, ell, sf) + eps * np.eye(len(xu))
    kmn = np_kernel(xu, x, ell, sf)
    q = kmn.T @ np.linalg.solve(kmm, kmn)
    lam = np.diag(sf**2 - np.diag(q)) + sn**2 * np.eye(len(x))
    c = q + lam
    nll = 0.5 * np.linalg.slogdet(c)[1] + 0.5 * y @ np.linalg.solve(c, y) + 0.5 * len(x) * np.log(2 * np.pi)
    b = kmm + kmn @ np.linalg.solve(lam, kmn.T)
    beta = np.linalg.solve(b, kmn @ np.linalg.solve(lam, y))
    return nll, beta, np.linalg.inv(kmm) - np.linalg.inv(b)


@pytest.fixture(scope="module")
def smooth():
    rng = np.random.default_rng(10)
    x = rng.uniform(-3, 3, (60, 2))
    y = np.stack([np.sin(x[:, 0]) + 0.3 * x[:, 1], np.cos(0.7 * x[:, 1]) * x[:, 0]], 1)
    hyper = GPHyper(jnp.log(jnp.array([[1.3, 2.0], [1.8, 1.1]])), jnp.log(jnp.array([1.2, 1.5])),
                    jnp.log(jnp.array([0.1, 0.15])))
    return make_data(x, y + 0.1 * rng.standard_normal(y.shape)), hyper


def _unpack(hyper, a):
    return (np.exp(np.asarray(hyper.log_lengthscale[a])), math.exp(hyper.log_signal[a]),
            math.exp(hyper.log_noise[a]))


def test_fitc_objective_and_posterior_equal_dense_formulas(smooth):
    data, hyper = smooth
    rng = np.random.default_rng(11)
    xu = rng.uniform(-3, 3, (12, 2))
    padded = pad_to_capacity(data, 80)
    cfg = GPConfig(fitc_threshold=20, num_inducing=12)
    post, jitter, ok = fitc_posterior(hyper, padded, jnp.asarray(xu), cfg)
    assert bool(ok.all()) and np.all(np.asarray(jitter) == EPS)
    total = 0.0
    for a in range(2):
        nll, beta, inv = np_fitc(np.asarray(data.inputs), np.asarray(data.targets[:, a]), xu, *_unpack(hyper, a))
        total += nll
        for d in (data, padded):
            got = fitc_neg_log_likelihood(jnp.asarray(np.r_[np.asarray(hyper.log_lengthscale[a]), hyper.log_signal[a],
                                                            hyper.log_noise[a]]),
                                          jnp.asarray(xu), d.inputs, d.targets[:, a], d.mask, EPS, cfg.noise_floor)
            np.testing.assert_allclose(got, nll, rtol=1e-10)
        # κ(K_mm) ≈ 1e6 here, so dense inverses agree to ~1e-9 relative to their largest entry
        np.testing.assert_allclose(post.beta[a], beta, rtol=1e-7, atol=1e-8 * np.abs(beta).max())
        np.testing.assert_allclose(post.inv[a], inv, rtol=1e-7, atol=1e-8 * np.abs(inv).max())
    np.testing.assert_allclose(fitc_objective(jnp.asarray(xu), hyper, padded, jnp.full(2, EPS), cfg), total, rtol=1e-10)


def test_fitc_gradient_wrt_inducing_inputs_matches_central_differences(smooth):
    data, hyper = smooth
    xu = jnp.asarray(np.random.default_rng(12).uniform(-3, 3, (6, 2)))
    cfg = GPConfig(fitc_threshold=20, num_inducing=6)
    f = jax.jit(lambda u: fitc_objective(u, hyper, data, jnp.full(2, EPS), cfg))
    g = np.asarray(jax.grad(f)(xu)).ravel()
    h = 1e-4
    g_fd = np.array([(f(xu.ravel().at[i].add(h).reshape(xu.shape)) - f(xu.ravel().at[i].add(-h).reshape(xu.shape)))
                     / (2 * h) for i in range(xu.size)])
    assert np.linalg.norm(g_fd - g) / np.linalg.norm(g_fd + g) < 1e-6


def test_fitc_with_all_points_as_inducing_inputs_equals_full_gp(smooth):
    """X_u = X. With ridge ε on K_mm the FITC covariance is C_F = C + Δ with ‖Δ‖₂ < ε
    (Δ = −εK(K+εI)⁻¹ + diag(εK(K+εI)⁻¹); both parts have eigenvalues in [0, ε)), and the
    FITC cross-covariance is k*ᵀ(K+εI)⁻¹K = k*ᵀ − ε wᵀ with w = (K+εI)⁻¹k*. Hence, per test
    point and to first order in ε,
        |μ_F − μ| ≤ ε (‖w‖ ‖β‖ + ‖C⁻¹k*‖ ‖β‖),
        |v_F − v| ≤ ε (2 ‖w‖ ‖C⁻¹k*‖ + ‖C⁻¹k*‖²) + ε² ‖w‖²/σ_n²,
    with β = C⁻¹y. The test allows twice that bound (F-quantities replaced by full ones) plus
    1e-12 for rounding."""
    data, hyper = smooth
    x = np.asarray(data.inputs)
    z = np.random.default_rng(13).uniform(-3.5, 3.5, (40, 2))
    cfg = GPConfig(fitc_threshold=60, num_inducing=60)
    post_f, _, _ = fitc_posterior(hyper, data, data.inputs, cfg)
    post, _, _ = full_posterior(hyper, data, cfg)
    mf, vf = predict(post_f, jnp.asarray(z), variance=True)
    m, v = predict(post, jnp.asarray(z), variance=True)
    for a in range(2):
        ell, sf, sn = _unpack(hyper, a)
        k = np_kernel(x, x, ell, sf)
        c = k + sn**2 * np.eye(len(x))
        ks = np_kernel(x, z, ell, sf)  # (N, P)
        beta = np.linalg.solve(c, np.asarray(data.targets[:, a]))
        w = np.linalg.norm(np.linalg.solve(k + EPS * np.eye(len(x)), ks), axis=0)
        cks = np.linalg.norm(np.linalg.solve(c, ks), axis=0)
        tol_m = 2 * EPS * (w + cks) * np.linalg.norm(beta) + 1e-12
        tol_v = 2 * (EPS * (2 * w * cks + cks**2) + EPS**2 * w**2 / sn**2) + 1e-12
        err_m, err_v = np.abs(mf[:, a] - m[:, a]), np.abs(vf[:, a] - v[:, a])
        assert np.all(err_m <= tol_m), (err_m / tol_m).max()
        assert np.all(err_v <= tol_v), (err_v / tol_v).max()
        assert (err_m / tol_m).max() > 1e-4  # the bound is not vacuous: errors of its order occur


def test_fitc_switch_training_warm_start_and_closeness_to_full_gp():
    """An episode sequence: 250 points (= threshold: full GP), 260 (> threshold: FITC, first
    time, M = 30 inducing inputs from a random subset), 260 again (FITC warm-started).

    Closeness criterion: at test points inside the data domain the FITC mean differs from the
    full-GP mean by less than 0.2 of the full GP's predictive std sqrt(v + σ_n²) — the FITC
    error is small against what the model itself says it does not know. The criterion has
    teeth: 3 unoptimised inducing inputs violate it (checked below).
    """
    rng = np.random.default_rng(14)
    n, thr, m_ind = 260, 250, 30
    x = rng.uniform(-3, 3, (n, 2))
    y = np.stack([np.sin(x[:, 0]) + 0.3 * x[:, 1], np.cos(0.7 * x[:, 1]) * x[:, 0]], 1)
    y = y + 0.1 * rng.standard_normal(y.shape)
    cfg = GPConfig(max_iters=100, fitc_threshold=thr, num_inducing=m_ind, fitc_first_iters=100, fitc_iters=40)
    _, state, info = fit(None, pad_to_capacity(make_data(x[:thr], y[:thr]), 300), config=cfg)
    assert not info.sparse and info.fitc is None and state.inducing is None
    data = pad_to_capacity(make_data(x, y), 300)
    post, state, info = fit(jax.random.PRNGKey(0), data, state, cfg)
    programs = _train_sparse._cache_size()
    assert info.sparse and info.num_points == n and post.inputs.shape == state.inducing.shape == (m_ind, 2)
    f = info.fitc
    assert f.objective < f.objective_init - 1.0 and 0 < f.iterations <= cfg.fitc_first_iters
    full, _, _ = full_posterior(post.hyper, data, cfg)
    z = jnp.asarray(rng.uniform(-2.8, 2.8, (200, 2)))
    m, v = predict(full, z, variance=True)
    scale = np.sqrt(np.asarray(v) + np.asarray(post.noise_variance)[None, :])
    mf, vf = predict(post, z, variance=True)
    assert np.max(np.abs(mf - m) / scale) < 0.2
    assert np.all(np.asarray(vf) >= 0) and np.all(np.isfinite(vf))
    crude, _, _ = fitc_posterior(post.hyper, data, jnp.asarray(x[:3]), cfg)
    assert np.max(np.abs(predict(crude, z) - m) / scale) > 0.2
    # warm start: from the previous X_u (same objective up to the re-trained hyper), never worse
    _, _, info2 = fit(None, data, state, cfg)
    assert info2.fitc.objective_init == pytest.approx(f.objective, rel=1e-6)
    assert info2.fitc.objective <= info2.fitc.objective_init
    assert info2.fitc.iterations <= cfg.fitc_iters
    assert _train_sparse._cache_size() == programs  # first and warm-started FITC share a program
