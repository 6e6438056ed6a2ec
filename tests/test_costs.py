"""Costs and Gaussian moments: PILCO reference values, Monte Carlo, limits, autodiff vs finite differences.

Monte Carlo checks use a fixed key, 10⁶ samples and a tolerance of ``b`` standard errors,
each standard error estimated from the same samples and ``b`` the two-sided normal
quantile at a family-wise level of 1e-3, Bonferroni-corrected over the comparisons a test
makes. Nothing is hand-tuned; ``test_trig_monte_carlo_has_power`` shows the check rejects a
plausible mistake.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from pipps.costs import (
    SaturatingCost,
    cartpole_angle_cost,
    cartpole_tip_cost,
    unicycle_cost,
)
from pipps.gaussian import expected_saturating_cost, linear_map, trig_augment, trig_moments
from pipps.stats import cov_z, cross_z, mean_z, z_bound

from moment_checks import (  # tests/moment_checks.py, shared with test_pilco.py
    FAMILY_ALPHA,
    FD_TOL,
    N_MC,
    assert_fd,
    checkgrad,
    moments_of_variance_z,
    normal_samples,
    sym_from_tril,
    tril_of,
)

COSTS = {
    "angle": cartpole_angle_cost,
    "angle_0.01": lambda: cartpole_angle_cost(scale=0.01),
    "tip": cartpole_tip_cost,
    "unicycle": unicycle_cost,
}
TASK_COSTS = ["angle", "tip", "unicycle"]


# -- helpers ---------------------------------------------------------------------------------
def random_gaussian(rng, dim, mean_scale, cov_scale, rank=None):
    """Mean ~ N(0, mean_scale²), covariance B Bᵀ with B (dim, rank) ~ N(0, cov_scale²/rank)."""
    rank = dim if rank is None else rank
    B = rng.normal(size=(dim, rank)) * cov_scale / np.sqrt(rank)
    return rng.normal(size=dim) * mean_scale, B @ B.T, B


def cost_point(name, rng):
    """A model-state Gaussian where the cost is far from saturated (E[c] well inside (0, 1))."""
    if name.startswith("angle"):
        spread = 1.0 if name == "angle" else 10.0  # scale 0.01 needs 10× the distance
        offset = np.array([0.2, 0.5, -1.0, -0.5]) + 0.1 * rng.normal(size=4)
        mean = np.array([0.0, 0.0, 0.0, np.pi]) + spread * offset
        return mean, random_gaussian(rng, 4, 0.0, 0.4 * spread)[1]
    if name == "tip":
        mean = np.array([0.1, 0.3, -0.2, np.pi - 0.4]) + 0.1 * rng.normal(size=4)
        return mean, random_gaussian(rng, 4, 0.0, 0.3)[1]
    mean = 0.3 * rng.normal(size=10)
    return mean, random_gaussian(rng, 10, 0.0, 0.3)[1]


# -- reference values (transcribed from PILCO's code) ----------------------------------------------
@pytest.mark.parametrize(
    "x, value",
    [([0.2, 0.0, 0.0, 2.5], 0.874189814022), ([0.0, 0.0, 0.0, 0.0], 0.999664537372),
     ([0.0, 0.0, 0.0, np.pi], 0.0)],
)
def test_tip_cost_reference_values(x, value):
    assert float(cartpole_tip_cost()(jnp.asarray(x))) == pytest.approx(value, abs=1e-9)


def test_tip_cost_moment_matched_reference():
    mu = jnp.array([0.1, 0.3, -0.2, np.pi - 0.2])
    cov = jnp.diag(jnp.array([0.03, 0.04, 0.06, 0.05])).at[0, 3].set(-0.01).at[3, 0].set(-0.01)
    e, v = cartpole_tip_cost().expected(mu, cov)
    assert float(e) == pytest.approx(0.379042594224, abs=1e-9)
    assert float(v) == pytest.approx(0.095031140975, abs=1e-9)


def test_tip_cost_reference_monte_carlo_gap():
    """Reference values: the exact E[c], Var[c] at the same Gaussian are about 0.3789 and 0.0959.

    The 4-digit values allow ±5e-5 rounding on top of b standard errors.
    """
    mu = np.array([0.1, 0.3, -0.2, np.pi - 0.2])
    cov = np.diag([0.03, 0.04, 0.06, 0.05])
    cov[0, 3] = cov[3, 0] = -0.01
    x = mu + normal_samples(11, N_MC, 4) @ np.linalg.cholesky(cov).T
    c = np.asarray(cartpole_tip_cost()(jnp.asarray(x)))
    n = len(c)
    se_mean = c.std(ddof=1) / np.sqrt(n)
    se_var = np.sqrt((np.mean((c - c.mean()) ** 4) - c.var(ddof=1) ** 2) / n)
    b = z_bound(2, FAMILY_ALPHA)
    assert abs(c.mean() - 0.3789) <= b * se_mean + 5e-5
    assert abs(c.var(ddof=1) - 0.0959) <= b * se_var + 5e-5


def test_unicycle_cost_reference_value():
    x = jnp.array([0, 0, 0, 0, 0, 0.1, -0.05, 0.05, 0.3, -0.08])
    assert float(unicycle_cost()(x)) == pytest.approx(0.009656629969, abs=1e-9)


# -- pointwise formulas -----------------------------------------------------------------------
@pytest.mark.parametrize("scale", [1.0, 0.01])
def test_angle_cost_is_thesis_formula(scale):
    rng = np.random.default_rng(0)
    x = rng.normal(size=(200, 4)) * np.array([1.0, 3.0, 8.0, 4.0])
    got = np.asarray(cartpole_angle_cost(scale)(jnp.asarray(x)))
    thesis = 1 - np.exp(-scale * (x[:, 0] ** 2 + (x[:, 3] - np.pi) ** 2))
    np.testing.assert_allclose(got, thesis, rtol=0, atol=1e-15)
    # Raw angle: the −π upright is not a target.
    assert float(cartpole_angle_cost(scale)(jnp.array([0.0, 0, 0, np.pi]))) == 0.0
    assert float(cartpole_angle_cost(scale)(jnp.array([0.0, 0, 0, -np.pi]))) == pytest.approx(
        1 - np.exp(-scale * 4 * np.pi**2), abs=1e-15
    )


def test_tip_cost_is_tip_distance_formula():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(200, 4)) * np.array([0.5, 2.0, 5.0, 3.0])
    l, sc = 0.5, 0.25
    d2 = (x[:, 0] + l * np.sin(x[:, 3])) ** 2 + l**2 * (1 + np.cos(x[:, 3])) ** 2
    got = np.asarray(cartpole_tip_cost()(jnp.asarray(x)))
    np.testing.assert_allclose(got, 1 - np.exp(-d2 / (2 * sc**2)), rtol=0, atol=1e-14)


def test_unicycle_cost_is_section_3_6_formula():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(200, 10)) * 0.4
    r_w, r = 0.22, 0.81
    th, yaw, pf = x[:, 7], x[:, 8], x[:, 9]
    dx = x[:, 5] - r * np.sin(pf)
    dy = x[:, 6] - (r + r_w) * np.sin(th)
    dz = r_w * np.cos(th) + r * np.cos(th) * np.cos(pf) - (r_w + r)
    want = 1 - np.exp(-0.5 * (8 * dz**2 + 0.5 * dx**2 + 0.5 * dy**2 + yaw**2 / (16 * np.pi**2)))
    got = np.asarray(unicycle_cost()(jnp.asarray(x)))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-14)


@pytest.mark.parametrize("name", list(COSTS))
def test_cost_vmaps_and_broadcasts(name):
    cost = COSTS[name]()
    x = jnp.asarray(np.random.default_rng(3).normal(size=(7, cost.model_dim)))
    batched = cost(x)
    assert batched.shape == (7,)
    np.testing.assert_array_equal(np.asarray(jax.vmap(cost)(x)), np.asarray(batched))
    np.testing.assert_allclose(
        np.asarray(batched), [float(cost(xi)) for xi in x], rtol=0, atol=1e-15
    )


def test_cost_rejects_inconsistent_shapes():
    with pytest.raises(ValueError):
        SaturatingCost(W=np.eye(5), target=np.zeros(5), angle_idx=(3,))  # 5 − 2 = 3, idx 3 ∉ [0, 3)
    with pytest.raises(ValueError):
        SaturatingCost(W=np.eye(4), target=np.zeros(3))
    with pytest.raises(ValueError):
        SaturatingCost(W=np.triu(np.ones((3, 3))), target=np.zeros(3))


# -- trig augmentation (PILCO's gTrig.m) -----------------------------------------------------------
TRIG_CASES = [(1, (0,)), (3, (0, 2)), (4, (3, 1, 0)), (6, (1, 2, 4, 5))]


@functools.lru_cache(maxsize=None)
def trig_case(case: int):
    """Random Gaussian for a TRIG_CASES entry, its closed-form moments and the MC samples."""
    dim, idx = TRIG_CASES[case]
    rng = np.random.default_rng(100 + case)
    mean = rng.uniform(-np.pi, np.pi, size=dim)
    _, cov, _ = random_gaussian(rng, dim, 0.0, 1.0)
    cov += 0.05 * np.eye(dim)
    chol = np.linalg.cholesky(cov)
    eps = normal_samples(200 + case, N_MC, dim)
    x = mean + eps @ chol.T
    u = scipy.linalg.solve_triangular(chol, eps.T, lower=True, trans="T").T  # Σ⁻¹(x − μ)
    trig = np.stack([np.sin(x[:, idx]), np.cos(x[:, idx])], axis=-1).reshape(N_MC, -1)
    aug = np.concatenate([x, trig], axis=1)
    m, S, C = (np.asarray(a) for a in trig_augment(jnp.asarray(mean), jnp.asarray(cov), idx))
    return dict(mean=mean, cov=cov, idx=idx, aug=aug, u=u, trig=trig, m=m, S=S, C=C)


@pytest.mark.parametrize("case", range(len(TRIG_CASES)))
def test_trig_augment_against_monte_carlo(case):
    t = trig_case(case)
    dim, n_ang = len(t["mean"]), len(t["idx"])
    assert t["m"].shape == (dim + 2 * n_ang,) and t["S"].shape == (dim + 2 * n_ang,) * 2
    assert t["C"].shape == (dim, 2 * n_ang)
    np.testing.assert_array_equal(t["m"][:dim], t["mean"])  # the x block is exact
    np.testing.assert_array_equal(t["S"][:dim, :dim], t["cov"])
    np.testing.assert_allclose(t["S"], t["S"].T, rtol=0, atol=0)
    np.testing.assert_allclose(t["S"][:dim, dim:], t["cov"] @ t["C"], rtol=0, atol=1e-15)
    z = np.concatenate(
        [mean_z(t["aug"], t["m"]), cov_z(t["aug"], t["S"]), cross_z(t["u"], t["trig"], t["C"])]
    )
    assert np.max(z) < z_bound(z.size, FAMILY_ALPHA), (np.max(z), z_bound(z.size, FAMILY_ALPHA))


def test_trig_monte_carlo_has_power():
    """Dropping the cross terms between different angles must fail the same MC check."""
    t = trig_case(3)
    dim, n_ang = len(t["mean"]), len(t["idx"])
    wrong = t["S"].copy()
    block = wrong[dim:, dim:].reshape(n_ang, 2, n_ang, 2)
    for i in range(n_ang):
        for j in range(n_ang):
            if i != j:
                block[i, :, j, :] = 0.0
    wrong[dim:, dim:] = block.reshape(2 * n_ang, 2 * n_ang)
    z = cov_z(t["aug"], wrong)
    assert np.max(z) > z_bound(z.size, FAMILY_ALPHA)


def test_trig_moments_zero_covariance_is_pointwise():
    mean = jnp.array([0.3, -1.2, 2.0])
    g = trig_moments(mean, jnp.zeros((3, 3)), (0, 2))
    a = np.asarray(mean)[[0, 2]]
    np.testing.assert_allclose(
        np.asarray(g.M), np.stack([np.sin(a), np.cos(a)], -1).ravel(), rtol=0, atol=1e-16
    )
    np.testing.assert_array_equal(np.asarray(g.S), np.zeros((4, 4)))
    # C = E[∂f/∂v]ᵀ: the Jacobian of (sin, cos) at the mean.
    ang = np.array([0, 2])
    jac = jax.jacfwd(lambda v: jnp.stack([jnp.sin(v[ang]), jnp.cos(v[ang])], -1).ravel())
    np.testing.assert_allclose(np.asarray(g.C), np.asarray(jac(mean)).T, rtol=0, atol=1e-16)


def test_trig_augment_no_angles_and_vmap():
    mean, cov, _ = random_gaussian(np.random.default_rng(4), 3, 1.0, 1.0)
    m, S, C = trig_augment(jnp.asarray(mean), jnp.asarray(cov), ())
    np.testing.assert_array_equal(np.asarray(m), mean)
    np.testing.assert_array_equal(np.asarray(S), cov)
    assert C.shape == (3, 0)
    rng = np.random.default_rng(5)
    means = jnp.asarray(rng.normal(size=(5, 3)))
    covs = jnp.asarray(np.stack([random_gaussian(rng, 3, 0, 1)[1] for _ in range(5)]))
    batched = jax.vmap(lambda m_, c_: trig_augment(m_, c_, (2, 0)))(means, covs)
    for k in range(5):
        single = trig_augment(means[k], covs[k], (2, 0))
        for a, b in zip(batched, single):
            np.testing.assert_allclose(np.asarray(a[k]), np.asarray(b), rtol=0, atol=1e-15)


def test_linear_map_is_exact():
    rng = np.random.default_rng(6)
    mean, cov, _ = random_gaussian(rng, 4, 1.0, 1.0)
    L, b = rng.normal(size=(3, 4)), rng.normal(size=3)
    g = linear_map(jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(L), jnp.asarray(b))
    np.testing.assert_allclose(np.asarray(g.M), L @ mean + b, rtol=1e-14)
    np.testing.assert_allclose(np.asarray(g.S), L @ cov @ L.T, rtol=1e-13, atol=1e-14)
    np.testing.assert_array_equal(np.asarray(g.C), L.T)


@pytest.mark.parametrize("case", [1, 3])
def test_trig_augment_gradients_match_finite_differences(case):
    dim, idx = TRIG_CASES[case]
    rng = np.random.default_rng(300 + case)
    mean, cov, _ = random_gaussian(rng, dim, 1.5, 0.8)
    n_tril = dim * (dim + 1) // 2

    def f(p):
        m, S, C = trig_augment(p[:dim], sym_from_tril(p[dim:], dim), idx)
        return jnp.concatenate([m, S.ravel(), C.ravel()])

    d, _ = checkgrad(f, jnp.concatenate([jnp.asarray(mean), tril_of(cov)]))
    assert n_tril > 0
    assert_fd(d, f"trig_augment case {case}")


# -- expected saturating cost (PILCO's lossSat.m) --------------------------------------------------
def feature_gaussian(name, rng, rank=None):
    """A random Gaussian over the cost's feature space φ, centred near the target."""
    cost = COSTS[name]()
    dim = cost.feature_dim
    offset, cov, B = random_gaussian(rng, dim, 0.3, 0.6, rank)
    return cost, cost.target + offset, cov, B


@pytest.mark.parametrize("rank", [None, 2], ids=["full", "rank2"])
@pytest.mark.parametrize("name", TASK_COSTS)
def test_expected_saturating_cost_against_monte_carlo(name, rank):
    rng = np.random.default_rng(400 + TASK_COSTS.index(name) + (0 if rank is None else 10))
    cost, mean, cov, B = feature_gaussian(name, rng, rank)
    e, v = expected_saturating_cost(jnp.asarray(mean), jnp.asarray(cov), cost.W, cost.target)
    assert 0.05 < float(e) < 0.95 and float(v) > 1e-3  # an informative point
    y = mean + normal_samples(500 + TASK_COSTS.index(name), N_MC, B.shape[1]) @ B.T
    d = y - cost.target
    c = 1 - np.exp(-0.5 * np.einsum("ni,ij,nj->n", d, cost.W, d))
    z_e, z_v = moments_of_variance_z(c, float(e), float(v))
    assert max(z_e, z_v) < z_bound(2, FAMILY_ALPHA), (z_e, z_v)


@pytest.mark.parametrize("name", ["angle", "angle_0.01"])
def test_angle_cost_expected_is_exact_against_monte_carlo(name):
    """No trig features: `.expected` is exact, so it must match MC of c(x) itself."""
    cost = COSTS[name]()
    mean, cov = cost_point(name, np.random.default_rng(7))
    e, v = cost.expected(jnp.asarray(mean), jnp.asarray(cov))
    x = mean + normal_samples(8, N_MC, 4) @ np.linalg.cholesky(cov).T
    c = np.asarray(cost(jnp.asarray(x)))
    z_e, z_v = moments_of_variance_z(c, float(e), float(v))
    assert max(z_e, z_v) < z_bound(2, FAMILY_ALPHA), (z_e, z_v)


@pytest.mark.parametrize("name", list(COSTS))
def test_expected_reduces_to_pointwise_cost_at_zero_covariance(name):
    cost = COSTS[name]()
    rng = np.random.default_rng(9)
    mean, cov = cost_point(name, rng)
    mean = jnp.asarray(mean)
    e, v = cost.expected(mean, jnp.zeros((cost.model_dim,) * 2))
    assert float(e) == pytest.approx(float(cost(mean)), abs=1e-14)
    assert float(v) == 0.0
    # Small covariance εΣ: E[c] = c(μ) + ε ½ tr(∇²c(μ) Σ) + O(ε²) (moment matching is exact
    # to first order), so the rescaled difference must converge to the Hessian term. With
    # ε = 1e-6 the remainder is ε·O(1) relative and the rounding 1e-16/ε = 1e-10: rel 1e-5.
    eps = 1e-6
    e_small, _ = cost.expected(mean, eps * jnp.asarray(cov))
    slope = (float(e_small) - float(cost(mean))) / eps
    hess = 0.5 * float(jnp.sum(jax.hessian(cost)(mean) * cov))
    assert slope == pytest.approx(hess, rel=1e-5)


@pytest.mark.parametrize("name", list(COSTS))
def test_expected_gradients_match_finite_differences(name):
    cost = COSTS[name]()
    mean, cov = cost_point(name, np.random.default_rng(10 + list(COSTS).index(name)))
    dim = cost.model_dim

    def f(p):
        return jnp.stack(cost.expected(p[:dim], sym_from_tril(p[dim:], dim)))

    p = jnp.concatenate([jnp.asarray(mean), tril_of(cov)])
    e, v = f(p)
    assert 0.02 < float(e) < 0.98 and float(v) > 1e-4
    d, g = checkgrad(f, p)
    assert np.all(np.isfinite(d)), d  # both outputs testable
    assert np.max(d) < FD_TOL, d
    assert np.all(np.linalg.norm(g, axis=1) > 1e-3)  # not a vacuous 0 = 0


@pytest.mark.parametrize("name", TASK_COSTS)
def test_near_singular_covariance_is_finite_and_continuous(name):
    cost = COSTS[name]()
    dim = cost.model_dim
    rng = np.random.default_rng(20 + TASK_COSTS.index(name))
    mean, _ = cost_point(name, rng)
    v = rng.normal(size=dim) * 0.3
    cov = np.outer(v, v) + 1e-14 * np.eye(dim)  # rank one up to 1e-14
    e, var = cost.expected(jnp.asarray(mean), jnp.asarray(cov))
    e_reg, var_reg = cost.expected(jnp.asarray(mean), jnp.asarray(cov + 1e-8 * np.eye(dim)))
    assert np.isfinite(float(e)) and np.isfinite(float(var))
    # E[c] is Lipschitz in Σ (|∂E/∂Σ| ≤ ‖W‖-scale), so δ = 1e-8 moves it by O(1e-8).
    assert abs(float(e) - float(e_reg)) < 1e-6 and abs(float(var) - float(var_reg)) < 1e-6

    def f(p):
        return jnp.stack(cost.expected(p[:dim], sym_from_tril(p[dim:], dim)))

    d, g = checkgrad(f, jnp.concatenate([jnp.asarray(mean), tril_of(cov)]))
    assert np.all(np.isfinite(g))
    assert np.nanmax(d) < FD_TOL, d


def test_expected_vmaps():
    cost = unicycle_cost()
    rng = np.random.default_rng(30)
    pts = [cost_point("unicycle", rng) for _ in range(4)]
    means = jnp.asarray(np.stack([m for m, _ in pts]))
    covs = jnp.asarray(np.stack([c for _, c in pts]))
    e, v = jax.vmap(cost.expected)(means, covs)
    for k in range(4):
        e_k, v_k = cost.expected(means[k], covs[k])
        assert float(e[k]) == pytest.approx(float(e_k), abs=1e-15)
        assert float(v[k]) == pytest.approx(float(v_k), abs=1e-15)
