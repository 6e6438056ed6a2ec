"""Full-GP dynamics model (docs/gp.md): prediction, objective, training, guards, errors.

Reference values come from dense NumPy/SciPy evaluations written independently of the library.
FITC has its own file (test_gp_fitc.py).
"""

import dataclasses
import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sla

from pipps.gp import (
    FitState,
    GPConfig,
    GPData,
    GPHyper,
    GPNumericsWarning,
    fit,
    fit_hyper,
    full_posterior,
    hyper_objective,
    hyper_to_rows,
    make_data,
    pad_to_capacity,
    predict,
)
from pipps.gp.fit import _train_full
from pipps.gp.lbfgs import lbfgs_minimize
from pipps.gp.linalg import adaptive_cholesky
from pipps.gp.train import input_log_std
from pipps.stats import z_bound

# ----------------------------------------------------------------------------- numpy references


def np_kernel(x1, x2, ell, sf):
    d = (x1[:, None, :] - x2[None, :, :]) / ell
    return sf**2 * np.exp(-0.5 * np.sum(d * d, -1))


def np_predict(x, y, z, ell, sf, sn):
    """Dense GP prediction of one output by scipy Cholesky: (mean, latent variance)."""
    c = sla.cho_factor(np_kernel(x, x, ell, sf) + sn**2 * np.eye(len(x)), lower=True)
    ks = np_kernel(z, x, ell, sf)
    return ks @ sla.cho_solve(c, y), sf**2 - np.sum(ks * sla.cho_solve(c, ks.T).T, 1)


def np_objective(psi, x, y, log_s, p=30, ls_curb=100.0, snr_curb=1000.0):
    """PILCO's penalised objective L_a (docs/gp.md) written out directly (slogdet + solve, not Cholesky)."""
    ell, sf, sn = np.exp(psi[:-2]), np.exp(psi[-2]), np.exp(psi[-1])
    ky = np_kernel(x, x, ell, sf) + sn**2 * np.eye(len(x))
    nll = 0.5 * y @ np.linalg.solve(ky, y) + 0.5 * np.linalg.slogdet(ky)[1] + 0.5 * len(x) * np.log(2 * np.pi)
    pen = np.sum(((psi[:-2] - log_s) / np.log(ls_curb)) ** p) + ((psi[-2] - psi[-1]) / np.log(snr_curb)) ** p
    return nll + pen


def random_hyper(rng, e, dz):
    return GPHyper(
        jnp.asarray(rng.uniform(-0.5, 0.7, (e, dz))),
        jnp.asarray(rng.uniform(-0.5, 0.5, e)),
        jnp.asarray(rng.uniform(-2.5, -1.5, e)),
    )


def sample_gp(rng, x, ell, sf, sn):
    """One draw y ~ N(0, K + σ_n² I)."""
    c = np_kernel(x, x, ell, sf) + sn**2 * np.eye(len(x))
    return np.linalg.cholesky(c) @ rng.standard_normal(len(x))


def with_garbage_padding(data: GPData, rng, n_pad: int) -> GPData:
    """Interleave n_pad masked rows holding large finite garbage at random positions."""
    n, dz = data.inputs.shape
    e = data.targets.shape[1]
    perm = rng.permutation(n + n_pad)
    x = np.concatenate([np.asarray(data.inputs), rng.normal(0, 50, (n_pad, dz))])[perm]
    y = np.concatenate([np.asarray(data.targets), rng.normal(0, 50, (n_pad, e))])[perm]
    m = np.concatenate([np.ones(n, bool), np.zeros(n_pad, bool)])[perm]
    return make_data(x, y, m)


SMALL = GPConfig(max_iters=100)
CAP = 64  # every fit() below pads to this capacity with E = 3, Dz = 2, so they share one program


@pytest.fixture(scope="module")
def toy():
    """E = 3 outputs, Dz = 2, N = 40, targets a smooth function plus noise 0.1."""
    rng = np.random.default_rng(0)
    x = rng.uniform(-2, 2, (40, 2))
    y = np.stack([np.sin(x[:, 0]), np.cos(x[:, 1]) * x[:, 0], 0.3 * x[:, 1] ** 2], 1)
    return make_data(x, y + 0.1 * rng.standard_normal(y.shape))


# ----------------------------------------------------------------------------- prediction


def test_predict_equals_dense_solve_with_and_without_padding(toy):
    rng = np.random.default_rng(1)
    hyper = random_hyper(rng, 3, 2)
    z = rng.uniform(-2.5, 2.5, (17, 2))
    padded = with_garbage_padding(toy, rng, 13)
    x, y = np.asarray(toy.inputs), np.asarray(toy.targets)
    for data in (toy, pad_to_capacity(toy, 64), padded):
        post, jitter, ok = full_posterior(hyper, data, SMALL)
        assert bool(ok.all()) and np.all(np.asarray(jitter) == 0.0)
        mean, var = predict(post, jnp.asarray(z), variance=True)
        mean_only = predict(post, jnp.asarray(z), variance=False)
        np.testing.assert_array_equal(mean_only, mean)
        for a in range(3):
            ell, sf, sn = (np.exp(np.asarray(hyper.log_lengthscale[a])), math.exp(hyper.log_signal[a]),
                           math.exp(hyper.log_noise[a]))
            m_ref, v_ref = np_predict(x, y[:, a], z, ell, sf, sn)
            np.testing.assert_allclose(mean[:, a], m_ref, rtol=1e-9, atol=1e-11)
            np.testing.assert_allclose(var[:, a], np.maximum(v_ref, 0), rtol=1e-7, atol=1e-11)
        # the stored inv is exactly zero on padded rows / columns, beta zero on padded rows
        pad = ~np.asarray(data.mask)
        assert np.all(np.asarray(post.beta)[:, pad] == 0) and np.all(np.asarray(post.inv)[:, pad, :] == 0)
    np.testing.assert_allclose(post.noise_variance, np.exp(2 * np.asarray(hyper.log_noise)), rtol=1e-15)


def test_variance_path_is_not_traced_when_not_requested(toy):
    """With variance=False the jaxpr must not read `inv` at all (nothing O(M²) is traced)."""
    post, _, _ = full_posterior(random_hyper(np.random.default_rng(2), 3, 2), toy, SMALL)
    z = jnp.zeros((5, 2))

    def uses_inv(variance):
        closed = jax.make_jaxpr(lambda inv: predict(post._replace(inv=inv), z, variance=variance))(post.inv)
        inv_var = closed.jaxpr.invars[0]
        return any(inv_var in eqn.invars for eqn in closed.jaxpr.eqns), len(closed.jaxpr.eqns)

    used_mean, n_mean = uses_inv(False)
    used_var, n_var = uses_inv(True)
    assert used_var and not used_mean  # the check can see the variance path when it is there
    assert n_mean < n_var
    with pytest.raises(ValueError, match="z must have shape"):
        predict(post, jnp.zeros((5, 3)))


# ----------------------------------------------------------------------------- objective


def test_objective_equals_direct_numpy_and_ignores_padding(toy):
    rng = np.random.default_rng(3)
    log_s, _ = input_log_std(toy, SMALL)
    x, y = np.asarray(toy.inputs), np.asarray(toy.targets[:, 0])
    padded = with_garbage_padding(toy, rng, 11)
    log_s_pad, _ = input_log_std(padded, SMALL)
    np.testing.assert_allclose(log_s_pad, log_s, rtol=1e-13)
    np.testing.assert_allclose(log_s, np.log(np.std(x, 0, ddof=1)), rtol=1e-13)
    # include a point where both penalties are large (ℓ_1 ≈ s_1/245, SNR ≈ 1.3·10⁴); short
    # length scales keep K_y well conditioned, so a tight rtol applies
    for psi in ([0.1, -0.3, 0.2, -2.0], [np.log(np.std(x[:, 0], ddof=1)) - 5.5, 0.0, 1.0, -8.5]):
        psi = np.asarray(psi)
        ref = np_objective(psi, x, y, np.asarray(log_s))
        got = hyper_objective(jnp.asarray(psi), toy.inputs, toy.targets[:, 0], toy.mask, log_s, 0.0, SMALL)
        got_pad = hyper_objective(jnp.asarray(psi), padded.inputs, padded.targets[:, 0], padded.mask, log_s, 0.0, SMALL)
        np.testing.assert_allclose(got, ref, rtol=1e-10)
        np.testing.assert_allclose(got_pad, got, rtol=1e-12)


def test_objective_gradient_matches_central_differences(toy):
    """PILCO's checkgrad.m: central differences, step 1e-4, d = ‖g_fd − g‖/‖g_fd + g‖."""
    log_s, _ = input_log_std(toy, SMALL)
    padded = with_garbage_padding(toy, np.random.default_rng(4), 9)
    for data in (toy, padded):
        f = jax.jit(lambda p: hyper_objective(p, data.inputs, data.targets[:, 1], data.mask, log_s, 0.0, SMALL))
        for psi in (jnp.array([0.1, -0.3, 0.2, -2.0]), jnp.array([-4.8, 0.5, 1.0, -8.0])):  # 2nd: penalty active
            g = np.asarray(jax.grad(f)(psi))
            h = 1e-4
            g_fd = np.array([(f(psi.at[i].add(h)) - f(psi.at[i].add(-h))) / (2 * h) for i in range(4)])
            d = np.linalg.norm(g_fd - g) / np.linalg.norm(g_fd + g)
            assert d < 1e-7, (d, g, g_fd)


# ----------------------------------------------------------------------------- training


def _fisher_information(x, ell, sf, sn):
    """Expected Fisher information of ψ = [log ℓ, log σ_f, log σ_n] for y ~ N(0, C):
    I_ij = ½ tr(C⁻¹ ∂_i C C⁻¹ ∂_j C)."""
    k = np_kernel(x, x, ell, sf)
    c = k + sn**2 * np.eye(len(x))
    dcs = [k * (x[:, None, d] - x[None, :, d]) ** 2 / ell[d] ** 2 for d in range(x.shape[1])]
    dcs += [2 * k, 2 * sn**2 * np.eye(len(x))]
    ci_dc = [np.linalg.solve(c, dc) for dc in dcs]
    return np.array([[0.5 * np.sum(a * b.T) for b in ci_dc] for a in ci_dc])


def test_training_recovers_known_hyperparameters():
    """Data drawn from 3 GPs with known ψ; the ML estimate must lie within a Bonferroni bound of
    z-scores computed from the exact expected Fisher information at the truth.

    Tolerance: asymptotically ψ̂ − ψ ~ N(0, I(ψ)⁻¹). With 12 estimated coordinates and a
    family-wise level of 0.001, |z| < Φ⁻¹(1 − 0.001/24) ≈ 3.94 per coordinate. The penalty is
    negligible at the truth (all length scales within a factor 2 of the input std, SNR 10),
    so it does not shift the estimate. Power: the same bound rejects an estimate whose length
    scales are off by a factor 2 (checked below), i.e. the standard errors are small enough for
    the test to catch e.g. a normalisation or factor-of-2 bug.
    """
    rng = np.random.default_rng(5)
    n, dz = 150, 2
    x = rng.uniform(-2, 2, (n, dz))
    truth = GPHyper(jnp.log(jnp.array([[0.8, 1.5], [1.2, 0.6], [1.0, 1.0]])),
                    jnp.log(jnp.array([1.0, 0.5, 2.0])), jnp.log(jnp.array([0.1, 0.05, 0.2])))
    ys = [sample_gp(rng, x, np.exp(np.asarray(truth.log_lengthscale[a])), math.exp(truth.log_signal[a]),
                    math.exp(truth.log_noise[a])) for a in range(3)]
    data = pad_to_capacity(make_data(x, np.stack(ys, 1)), 200)
    hyper, info = jax.jit(fit_hyper)(data, None, GPConfig())
    assert np.all(np.asarray(info.grad_norm) < 1e-3)
    z_crit = z_bound(12, 0.001)
    est, tru = np.asarray(hyper_to_rows(hyper)), np.asarray(hyper_to_rows(truth))
    for a in range(3):
        fisher = _fisher_information(x, np.exp(tru[a, :dz]), np.exp(tru[a, dz]), np.exp(tru[a, dz + 1]))
        se = np.sqrt(np.diag(np.linalg.inv(fisher)))
        z = (est[a] - tru[a]) / se
        assert np.all(np.abs(z) < z_crit), (a, z, se)
        biased = tru[a] + np.r_[np.log(2.0) * np.ones(dz), 0.0, 0.0]
        assert np.max(np.abs((biased - tru[a]) / se)) > z_crit  # power against a ×2 length-scale error


def test_training_ignores_padding_and_warm_start_stays_at_optimum(toy):
    rng = np.random.default_rng(6)
    padded = with_garbage_padding(toy, rng, CAP - 40)  # masked rows at random positions
    post, state, info = fit(None, pad_to_capacity(toy, CAP), config=SMALL)
    post_p, _, info_p = fit(None, padded, config=SMALL)
    np.testing.assert_allclose(info_p.hyper.objective, info.hyper.objective, rtol=1e-9)
    np.testing.assert_allclose(hyper_to_rows(post_p.hyper), hyper_to_rows(post.hyper), atol=1e-5)
    assert np.all(info.hyper.objective < info.hyper.objective_init)
    # warm start from the optimum: (nearly) unchanged, never worse
    post2, _, info2 = fit(None, padded, state, SMALL)
    np.testing.assert_allclose(info2.hyper.objective_init, info.hyper.objective, rtol=1e-9)
    assert np.all(info2.hyper.objective <= info2.hyper.objective_init)
    assert np.all(info.hyper.objective - info2.hyper.objective < 1e-6)
    np.testing.assert_allclose(hyper_to_rows(post2.hyper), hyper_to_rows(post.hyper), atol=1e-3)
    assert info.messages == () and info2.messages == ()


def test_no_recompilation_across_episodes(toy):
    """New data of the same capacity, first-time or warm-started, changed numeric settings:
    the training program is compiled once."""
    rng = np.random.default_rng(7)
    x2 = rng.uniform(-2, 2, (50, 2))
    b = pad_to_capacity(make_data(x2, np.stack([np.sin(x2[:, 0]), x2[:, 1], x2[:, 0] * x2[:, 1]], 1)), CAP)
    _, state, _ = fit(None, pad_to_capacity(toy, CAP), config=SMALL)
    size = _train_full._cache_size()
    fit(None, b, state, SMALL)
    fit(None, b, config=SMALL)
    fit(None, b, state, dataclasses.replace(SMALL, max_iters=7, noise_floor=1e-4, jitter=1e-12))
    assert _train_full._cache_size() == size


def test_lbfgs_never_returns_worse_than_start_or_nan():
    # NaN beyond x = 2.5 (a failed Cholesky looks like this); minimum of the smooth part at 3
    f = lambda x: jnp.sum((x - 3.0) ** 2) + jnp.where(jnp.all(x < 2.5), 0.0, jnp.nan)  # noqa: E731
    x, info = lbfgs_minimize(f, jnp.zeros(2), max_iters=50, memory_size=5, max_linesearch_steps=20, grad_tol=1e-10)
    assert np.all(np.isfinite(x)) and np.all(np.asarray(x) < 2.5) and float(info.value) < float(info.value_init)
    assert int(info.failures) >= 1  # trial points in the NaN region were rejected
    # a non-finite start is returned unchanged
    x0 = jnp.array([3.0, 3.0])
    x, info = lbfgs_minimize(f, x0, max_iters=50, memory_size=5, max_linesearch_steps=20, grad_tol=1e-10)
    np.testing.assert_array_equal(x, x0)
    assert int(info.iterations) == 0


# ----------------------------------------------------------------------------- degenerate data


def _penalty_ranges_ok(hyper, data, cfg):
    """log ℓ within 1.5·log 100 of log s_d and |log σ_f − log σ_n| within 1.5·log 1000.

    At 1.5× the curb the penalty term is 1.5^30 ≈ 2·10⁵ nats, far above any likelihood gain
    on these data sets, so an optimum cannot sit there."""
    log_s, _ = input_log_std(data, cfg)
    rows = np.asarray(hyper_to_rows(hyper))
    ls_ok = np.all(np.abs(rows[:, :-2] - np.asarray(log_s)) < 1.5 * math.log(cfg.ls_curb))
    snr_ok = np.all(np.abs(rows[:, -2] - rows[:, -1]) < 1.5 * math.log(cfg.snr_curb))
    return ls_ok and snr_ok and np.all(np.isfinite(rows))


def test_degenerate_data_stays_finite_and_in_range():
    rng = np.random.default_rng(8)
    x = np.stack([rng.uniform(-1, 1, 30), np.full(30, 0.7)], 1)  # column 1 constant
    x[15:] = x[:15]  # every input duplicated
    y = np.stack([np.full(30, 0.4), np.zeros(30), np.sin(3 * x[:, 0])], 1)  # constant, zero, noise-free
    data = pad_to_capacity(make_data(x, y), CAP)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        post, _, info = fit(None, data, config=SMALL)
    msgs = [str(m.message) for m in w if issubclass(m.category, GPNumericsWarning)]
    assert _penalty_ranges_ok(post.hyper, data, SMALL)
    assert np.all(np.isfinite(np.asarray(post.beta))) and np.all(np.isfinite(np.asarray(post.inv)))
    assert info.hyper.input_std_floored.tolist() == [False, True]
    assert info.hyper.target_std_floored.tolist() == [True, True, False]
    assert any("input std floor" in m and "[1]" in m for m in msgs)
    assert any("target std" in m for m in msgs)
    mean, var = predict(post, jnp.asarray(x), variance=True)
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(var))
    # How closely the mean meets the noise-free targets depends on where L-BFGS stops on this singular
    # objective, and that depends on the summation order (0.4118 at a point on AVX-512, < 0.41 on AVX2).
    # What holds at any hyperparameters: y − m = σ²Ay with A = (K + σ²I)⁻¹, σ² = σ_n² + jitter, and
    # λ_max(A) ≤ 1/σ², so |y_i − m_i| ≤ ‖σ²Ay‖₂ ≤ σ²·‖A^½‖·‖A^½y‖ = σ·sqrt(yᵀβ) (β = Ay, stored).
    sigma2 = np.exp(2 * np.asarray(post.hyper.log_noise)) + info.posterior_jitter
    for e in (0, 2):  # the constant and the noise-free sine
        bound = np.sqrt(sigma2[e] * float(y[:, e] @ np.asarray(post.beta)[e, :30]))
        assert np.max(np.abs(mean[:, e] - y[:, e])) <= bound * (1 + 1e-6) + 1e-12, (e, bound)
        assert bound < 0.1 * np.max(np.abs(y[:, e]))  # and the bound itself says the data are fitted
    assert np.exp(post.hyper.log_signal[0]) > 10 * np.sqrt(sigma2[0])  # the constant is carried by σ_f, not σ_n


def test_noise_floor_acts_and_is_reported():
    rng = np.random.default_rng(9)
    x = rng.uniform(-1, 1, (25, 2))
    data = pad_to_capacity(make_data(x, np.zeros((25, 3))), CAP)  # the likelihood wants σ_f, σ_n → 0
    cfg = dataclasses.replace(SMALL, noise_floor=1e-3)
    with pytest.warns(GPNumericsWarning, match="noise floor"):
        post, _, info = fit(None, data, config=cfg)
    assert info.hyper.noise_floored.tolist() == [True, True, True]
    np.testing.assert_allclose(post.hyper.log_noise, math.log(1e-3), atol=1e-12)
    assert _penalty_ranges_ok(post.hyper, data, cfg)
    # the same data with a lower floor ends lower: the floor really was binding
    with pytest.warns(GPNumericsWarning, match="noise floor"):
        post_lo, _, _ = fit(None, data, config=dataclasses.replace(SMALL, noise_floor=1e-4))
    assert np.all(np.asarray(post_lo.hyper.log_noise) < math.log(1e-3) - 1.0)


def test_adaptive_jitter_escalates_and_is_reported():
    x1 = np.repeat(np.linspace(-1, 1, 10)[:, None], 3, 0)  # each input three times
    a = np_kernel(x1, x1, np.array([0.5]), 1.0)  # rank 10 < 30: Cholesky fails without jitter
    chol, jitter, ok = adaptive_cholesky(jnp.asarray(a), base_jitter=0.0, jitter_min=1e-12, scale=1.0, max_tries=12)
    assert bool(ok) and 0 < float(jitter) <= 1e-6 and np.all(np.isfinite(chol))
    _, jitter_fail, ok_fail = adaptive_cholesky(jnp.asarray(a), base_jitter=0.0, jitter_min=1e-12, scale=1.0, max_tries=0)
    assert not bool(ok_fail) and float(jitter_fail) == 0.0
    # through fit(): a warm start whose noise is 1e-13 makes K_y singular at the start point
    x = np.concatenate([x1, x1**2], 1)  # still every row three times
    data = pad_to_capacity(make_data(x, np.stack([np.sin(3 * x[:, 0])] * 3, 1)), CAP)
    bad = FitState(GPHyper(jnp.log(jnp.full((3, 2), 0.5)), jnp.zeros(3), jnp.full(3, -30.0)))
    cfg = dataclasses.replace(SMALL, noise_floor=0.0)
    with pytest.warns(GPNumericsWarning, match="training jitter raised"):
        post, _, info = fit(None, data, bad, cfg)
    assert np.all(info.hyper.jitter > 0)
    assert np.all(np.isfinite(info.hyper.objective)) and np.all(info.hyper.objective < info.hyper.objective_init)


def test_repeated_inputs_are_counted_and_reported(toy):
    """No guard acts on repeated inputs (σ_n² keeps K + σ_n²I invertible), but repeated pairs pull σ_n
    down silently; fit counts real rows only (a masked copy of a real row is not a repeat)."""
    x, y = np.asarray(toy.inputs), np.asarray(toy.targets)
    x2 = np.concatenate([x, x[:5], x[5:8], x[9:10]])
    y2 = np.concatenate([y, y[:5], y[5:8] + 0.1, y[9:10]])
    m = np.concatenate([np.ones(48, bool), [False]])  # the copy of row 9 is padding
    data = pad_to_capacity(make_data(x2, y2, m), CAP)
    with pytest.warns(GPNumericsWarning, match=r"8 training inputs repeat an earlier input exactly \(5 with equal targets\)"):
        post, _, info = fit(None, data, config=SMALL)
    assert info.duplicate_inputs == (8, 5)
    assert np.all(np.isfinite(np.asarray(post.beta))) and np.all(np.isfinite(np.asarray(post.inv)))
    _, _, clean = fit(None, pad_to_capacity(toy, CAP), config=SMALL)
    assert clean.duplicate_inputs == (0, 0) and not any("repeat" in s for s in clean.messages)


# ----------------------------------------------------------------------------- errors


def test_bad_data_raises_value_error_naming_the_problem(toy):
    x, y = np.asarray(toy.inputs), np.asarray(toy.targets)
    x_nan = x.copy()
    x_nan[3, 1] = np.nan
    y_inf = y.copy()
    y_inf[7, 0] = np.inf
    cases = [
        (lambda: make_data(x_nan, y), r"inputs contain NaN .* rows \[3\]"),
        (lambda: make_data(x, y_inf), r"targets contain Inf .* rows \[7\]"),
        (lambda: make_data(x[:-1], y), "different lengths: 39 inputs vs 40 targets"),
        (lambda: make_data(x[:, 0], y), "inputs must be 2-D"),
        (lambda: make_data(x, y[:, :, None]), "targets must be 2-D"),
        (lambda: make_data(x, y, np.ones(39, bool)), r"mask must have shape \(40,\)"),
        (lambda: make_data(x, y, np.ones(40)), "mask must be boolean"),
        (lambda: make_data(x, y, np.arange(40) < 1), "at least 2 real"),
        (lambda: fit(None, GPData(jnp.asarray(x_nan), jnp.asarray(y), toy.mask)), "inputs contain NaN"),
        (lambda: fit(None, (x, y)), "data must be a GPData"),
        (lambda: fit(None, toy, FitState(GPHyper(jnp.zeros((2, 2)), jnp.zeros(2), jnp.zeros(2)))),
         r"log_lengthscale has shape \(2, 2\) but the data needs \(3, 2\)"),
        (lambda: fit(None, toy, FitState(GPHyper(jnp.full((3, 2), jnp.nan), jnp.zeros(3), jnp.zeros(3)))),
         "log_lengthscale contains NaN"),
        (lambda: fit(None, toy, config=GPConfig(fitc_threshold=30, num_inducing=10)), "key is required"),
        (lambda: GPConfig(num_inducing=400), "num_inducing=400 exceeds fitc_threshold"),
        (lambda: GPConfig(noise_floor=-1.0), "noise_floor must be ≥ 0"),
        (lambda: pad_to_capacity(toy, 10), "capacity 10 is smaller"),
    ]
    for call, match in cases:
        with pytest.raises(ValueError, match=match):
            call()


def test_map_and_vmap_over_outputs_agree(toy):
    """The CPU default maps over outputs (see linalg.map_outputs); vmap must give the same."""
    f = jax.jit(fit_hyper)
    h_map, i_map = f(toy, None, GPConfig(max_iters=20, output_batching="map"))
    h_vmap, i_vmap = f(toy, None, GPConfig(max_iters=20, output_batching="vmap"))
    # batched and unbatched LAPACK round differently; 20 L-BFGS steps amplify that to ~1e-7
    np.testing.assert_allclose(i_vmap.objective, i_map.objective, rtol=1e-10)
    np.testing.assert_allclose(hyper_to_rows(h_vmap), hyper_to_rows(h_map), atol=1e-5)
