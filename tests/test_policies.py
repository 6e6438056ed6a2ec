"""Policies: pointwise formulas against naive NumPy, parameter counts, the moment-matching form, gradients."""

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree
import numpy as np
import pytest

from pipps.policies import (
    LinearPolicy,
    PilcoRBFPolicy,
    RBFPolicy,
    init_linear_policy,
    init_pilco_rbf_policy,
    init_rbf_policy,
    init_rbf_policy_uniform,
    num_parameters,
    saturate,
)


def _rbf_form_eval(form, v):
    """Evaluate the PILCO-convention RBF network of `as_rbf()` naively."""
    out = []
    for a in range(form.beta.shape[1]):
        d = v[None, :] - np.asarray(form.centres)
        k = np.exp(-0.5 * np.sum(d**2 / np.asarray(form.lengthscale_sq[a]), axis=1))
        out.append(k @ np.asarray(form.beta[:, a]))
    return np.array(out)


def test_saturation_formula_range_and_extrema():
    w = np.linspace(-10, 10, 2001)
    s = np.asarray(saturate(jnp.asarray(w)))
    np.testing.assert_allclose(s, (9 * np.sin(w) + np.sin(3 * w)) / 8, rtol=0, atol=1e-15)
    assert s.max() <= 1.0 + 1e-15 and s.min() >= -1.0 - 1e-15
    assert float(saturate(jnp.pi / 2)) == pytest.approx(1.0, abs=1e-15)
    # sat'(π/2) = (9 cos(π/2) + 3 cos(3π/2))/8 = 0: the maximum is flat.
    assert float(jax.grad(saturate)(jnp.pi / 2)) == pytest.approx(0.0, abs=1e-14)


def test_thesis_rbf_matches_naive_formula_and_count():
    key = jax.random.PRNGKey(0)
    pol = init_rbf_policy(key, 50, np.zeros(4), 0.1**2 * np.eye(4), 10.0)
    assert num_parameters(pol) == 50 * 4 + 50 + 4 == 254
    pol = RBFPolicy(pol.centres, pol.weights, jnp.array([0.3, -0.2, 0.5, 0.1]), pol.u_max)
    rng = np.random.default_rng(1)
    for v in rng.normal(size=(5, 4)) * 0.3:
        lam = np.exp(np.asarray(pol.log_lambda))
        d = v[None, :] - np.asarray(pol.centres)
        pre = np.exp(-np.sum(d**2 / lam, axis=1)) @ np.asarray(pol.weights[:, 0])  # thesis: no ½
        expected = 10.0 * (9 * np.sin(pre) + np.sin(3 * pre)) / 8
        np.testing.assert_allclose(np.asarray(pol(jnp.asarray(v))), [expected], rtol=1e-13)
        np.testing.assert_allclose(_rbf_form_eval(pol.as_rbf(), v), [pre], rtol=1e-12)


def test_pilco_rbf_beta_is_regularised_solve_and_count():
    key = jax.random.PRNGKey(2)
    mean = np.array([0, 0, 0, 0, np.exp(-0.005)])
    cov = np.diag([0.01, 0.01, 0.01, 0.0099007, 4.9503e-5])
    pol = init_pilco_rbf_policy(key, 10, mean, cov, 10.0)
    # PILCO's settings_cp.m: 10·5 centres + 10 pseudo-targets + 5 log ℓ (σ_f, σ_π fixed, not parameters)
    assert num_parameters(pol) == 65
    np.testing.assert_allclose(np.exp(np.asarray(pol.log_lengthscale[0])), [1, 1, 1, 0.7, 0.7])
    C = np.asarray(pol.centres)
    ell2 = np.exp(2 * np.asarray(pol.log_lengthscale[0]))
    K = np.exp(-0.5 * np.sum((C[:, None] - C[None]) ** 2 / ell2, axis=-1))
    beta = np.linalg.solve(K + 0.01**2 * np.eye(10), np.asarray(pol.pseudo_targets[:, 0]))
    np.testing.assert_allclose(np.asarray(pol.beta()[:, 0]), beta, rtol=1e-9)
    v = np.array([0.05, -0.1, 0.2, 0.01, 0.99])
    np.testing.assert_allclose(np.asarray(pol.unsquashed(jnp.asarray(v))), _rbf_form_eval(pol.as_rbf(), v), rtol=1e-11)


def test_linear_policy_formula_and_count():
    pol = init_linear_policy(jax.random.PRNGKey(3), 10, [10.0, 50.0])
    assert num_parameters(pol) == 22
    np.testing.assert_array_equal(np.asarray(pol.b), 0.0)
    W = np.arange(20.0).reshape(2, 10) * 1e-2
    pol = LinearPolicy(jnp.asarray(W), jnp.array([0.1, -0.2]), pol.u_max)
    v = np.linspace(-1, 1, 10)
    pre = W @ v + np.array([0.1, -0.2])
    np.testing.assert_allclose(np.asarray(pol(jnp.asarray(v))), np.array([10, 50]) * (9 * np.sin(pre) + np.sin(3 * pre)) / 8, rtol=1e-14)
    plain = LinearPolicy(pol.W, pol.b, pol.u_max, saturated=False)
    np.testing.assert_allclose(np.asarray(plain(jnp.asarray(v))), pre, rtol=1e-14)


def test_u_max_is_static_and_vmap_matches_loop():
    pol = init_rbf_policy(jax.random.PRNGKey(4), 7, np.zeros(3), np.eye(3), [2.0, 5.0])
    assert len(jax.tree.leaves(pol)) == 3  # centres, weights, log_lambda: u_max carries no gradient
    V = jax.random.normal(jax.random.PRNGKey(5), (11, 3))
    batched = jax.jit(jax.vmap(lambda v: pol(v)))(V)
    looped = np.stack([np.asarray(pol(v)) for v in V])
    np.testing.assert_allclose(np.asarray(batched), looped, rtol=1e-13)


@pytest.mark.parametrize("which", ["thesis", "pilco", "linear"])
def test_a_float32_policy_gives_float32_controls(which):
    """pipps/__init__.py: code that wants float32 casts explicitly. The static ``u_max`` (Python
    floats) and PILCO's σ_π² I must not promote a cast policy back to float64 — a float32 particle
    rollout's scan carry would change dtype and fail (found by the stress suite)."""
    key = jax.random.PRNGKey(9)
    if which == "thesis":
        pol = init_rbf_policy(key, 6, np.zeros(4), 0.5 * np.eye(4), [10.0])
    elif which == "pilco":
        pol = init_pilco_rbf_policy(key, 6, np.zeros(4), 0.5 * np.eye(4), [10.0])
    else:
        pol = init_linear_policy(key, 4, [10.0], scale=0.5)
    v = jnp.array([0.1, -0.3, 0.2, 0.4])
    pol32 = jax.tree.map(lambda a: a.astype(jnp.float32), pol)
    u32 = pol32(v.astype(jnp.float32))
    assert u32.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(u32), np.asarray(pol(v)), rtol=1e-4)
    assert pol(v).dtype == jnp.float64  # the float64 path is unchanged


@pytest.mark.parametrize("which", ["thesis", "pilco"])
def test_parameter_gradient_matches_central_differences(which):
    key = jax.random.PRNGKey(6)
    if which == "thesis":
        pol = init_rbf_policy(key, 6, np.zeros(4), 0.5 * np.eye(4), 10.0, log_lambda=0.3)
        v = jnp.array([0.1, -0.3, 0.2, 0.4])
    else:
        pol = init_pilco_rbf_policy(key, 6, np.zeros(5), 0.5 * np.eye(5), 10.0)
        v = jnp.array([0.1, -0.3, 0.2, 0.4, 0.9])
    flat, unravel = ravel_pytree(pol)
    f = lambda p: unravel(p)(v)[0]  # noqa: E731
    g = np.asarray(jax.grad(f)(flat))
    h = 1e-4
    fd = np.array([(f(flat.at[i].add(h)) - f(flat.at[i].add(-h))) / (2 * h) for i in range(flat.size)])
    d = np.linalg.norm(fd - g) / np.linalg.norm(fd + g)  # PILCO's checkgrad.m metric
    assert d < 1e-6


def test_initialisation_statistics():
    mean = np.array([0.5, -1.0, 2.0])
    cov = np.diag([0.04, 0.25, 1.0])
    pol = init_rbf_policy(jax.random.PRNGKey(7), 20000, mean, cov, 10.0)
    C = np.asarray(pol.centres)
    # sample mean within 4 standard errors of the requested mean
    assert np.all(np.abs(C.mean(0) - mean) < 4 * np.sqrt(np.diag(cov) / C.shape[0]))
    W = np.asarray(pol.weights)
    assert abs(W.std() - 0.1) < 4 * 0.1 / np.sqrt(2 * W.size)
    U = init_rbf_policy_uniform(jax.random.PRNGKey(8), 5000, [-1, -3], [1, 3], 10.0, log_lambda=[0.0, 2.0])
    Cu = np.asarray(U.centres)
    assert Cu.min(0)[0] >= -1 and Cu.max(0)[1] <= 3 and np.allclose(np.asarray(U.log_lambda), [0, 2])


def test_bad_arguments_are_named():
    key = jax.random.PRNGKey(0)
    with pytest.raises(ValueError, match="u_max"):
        init_linear_policy(key, 3, [-1.0])
    with pytest.raises(ValueError, match="cov"):
        init_rbf_policy(key, 3, np.zeros(2), np.eye(3), 1.0)
    with pytest.raises(ValueError, match="finite"):
        init_rbf_policy(key, 3, np.array([np.nan, 0.0]), np.eye(2), 1.0)
    with pytest.raises(ValueError, match="low < high"):
        init_rbf_policy_uniform(key, 3, [1.0], [0.0], 1.0)
    assert isinstance(init_pilco_rbf_policy(key, 2, np.zeros(2), np.eye(2), 1.0), PilcoRBFPolicy)
