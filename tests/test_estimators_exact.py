"""Exact identities of the custom backward pass (thesis Alg. 3–6; exact identities are tested first).

* RP through the sweep equals ``jax.grad`` of the reparameterized objective for the same noise,
  for the plain, −σ_f, +σ_n and GR rollouts, full GP and FITC-shaped posteriors alike;
* TP with k_LR forced to 0 / 1 equals RP / LR; GTP likewise equals shaped RP / GLR;
* the BIW pieces equal a direct (looped, NumPy) evaluation of eq. 4.2–4.3;
* the −σ_f rollout contains no GP-variance computation at all.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from pipps.gp import fit, make_data
from pipps.particles.forward import RolloutConfig, particle_rollout, particle_step, reparameterized_objective, sample_noise
from pipps.policies import init_rbf_policy
from pipps.propagation import cost_terms, lr
from pipps.propagation.cost_terms import density_estimation_costs
from pipps.propagation.estimators import compose, estimator, thesis_estimator
from pipps.propagation.parts import pathwise
from pipps.propagation.estimate import estimate, init_estimator_state
from pipps.rollout import rollout, training_pairs
from pipps.tasks.presets import make_task

P = 16


@pytest.fixture(scope="module")
def setup():
    task = make_task("cartpole_swingup", horizon=8)
    X, Y = [], []
    for s in range(2):
        tr = rollout(jax.random.PRNGKey(s), task)
        i, t = training_pairs(task, tr)
        X.append(i)
        Y.append(t)
    post = fit(jax.random.PRNGKey(0), make_data(np.concatenate(X), np.concatenate(Y)))[0]
    # centres spread over the visited states so that the policy matters (nonzero gradients)
    pol = init_rbf_policy(jax.random.PRNGKey(1), 8, np.zeros(4), np.diag([0.1, 1.0, 4.0, 1.0]), task.u_max)
    return task, post, pol


def flat(tree):
    return np.asarray(ravel_pytree(tree)[0])


def run(setup, est, cfg, key=3, state_key=9):
    task, post, pol = setup
    st = init_estimator_state(jax.random.PRNGKey(state_key), pol, post, problem=task, config=cfg, estimator=est)
    _, e = estimate(jax.random.PRNGKey(key), st, pol, post, problem=task, config=cfg, estimator=est)
    return e


@pytest.mark.parametrize(
    "cfg",
    [
        RolloutConfig(num_particles=P),
        RolloutConfig(num_particles=P, model_variance=False),
        RolloutConfig(num_particles=P, noise_multiplier=100.0),
        RolloutConfig(num_particles=P, resampling="gaussian"),
    ],
    ids=["plain", "minus_sigma_f", "plus_sigma_n", "gaussian_resampling"],
)
def test_rp_sweep_equals_autodiff_of_the_reparameterized_objective(setup, cfg):
    task, post, pol = setup
    key = jax.random.PRNGKey(3)
    e = run(setup, estimator("rp"), cfg)
    noise = sample_noise(key, task, cfg)
    ref = jax.grad(lambda p: reparameterized_objective(task, p, post, noise, cfg))(pol)
    g, r = flat(e.grad), flat(ref)
    assert np.linalg.norm(r) > 1e-6  # a real gradient, not a vacuous comparison
    np.testing.assert_allclose(g, r, rtol=1e-9, atol=1e-12 * np.abs(r).max())
    assert float(e.value) == pytest.approx(float(reparameterized_objective(task, pol, post, noise, cfg)), rel=1e-14)


@pytest.mark.parametrize("weighting", ["biw", "plain"])
def test_tp_with_k_fixed_reduces_to_its_parts(setup, weighting):
    cfg = RolloutConfig(num_particles=P)
    rp = run(setup, estimator("rp"), cfg)
    lr_name = "lr" if weighting == "biw" else "lr_plain"
    lr_e = run(setup, estimator(lr_name), cfg)
    tp0 = run(setup, estimator("tp", weighting=weighting, k_lr=0.0), cfg)
    tp1 = run(setup, estimator("tp", weighting=weighting, k_lr=1.0), cfg)
    np.testing.assert_allclose(flat(tp0.grad), flat(rp.grad), rtol=1e-11, atol=1e-15)
    np.testing.assert_allclose(flat(tp1.grad), flat(lr_e.grad), rtol=1e-11, atol=1e-15)
    np.testing.assert_allclose(flat(tp0.grad_variance), flat(rp.grad_variance), rtol=1e-9, atol=1e-20)
    assert np.linalg.norm(flat(rp.grad) - flat(lr_e.grad)) > 1e-3 * np.linalg.norm(flat(rp.grad))


def test_gtp_with_k_fixed_reduces_to_shaped_rp_and_glr(setup):
    task, post, pol = setup
    cfg = RolloutConfig(num_particles=P)
    g0 = run(setup, estimator("gtp", k_lr=0.0), cfg)
    g1 = run(setup, estimator("gtp", k_lr=1.0), cfg)
    glr = run(setup, estimator("glr"), cfg)
    np.testing.assert_allclose(flat(g1.grad), flat(glr.grad), rtol=1e-11, atol=1e-15)
    # shaped RP is the pathwise gradient of J_GS = Σ_t Ē_t(μ̂_t, Σ̂_t) for the same noise
    noise = sample_noise(jax.random.PRNGKey(3), task, cfg)

    def j_gs(p):
        rec = particle_rollout(task, p, post, noise, cfg, jacobian=False)
        return jnp.sum(jax.vmap(lambda x: cost_terms.shaping_terms(task.cost, x, lr_costs=False, gradient=False)[2])(rec.x_next))

    ref = jax.grad(j_gs)(pol)
    np.testing.assert_allclose(flat(g0.grad), flat(ref), rtol=1e-9, atol=1e-12 * np.abs(flat(ref)).max())
    assert float(g0.value) == pytest.approx(float(j_gs(pol)), rel=1e-13)


def _del_surrogate(setup, cfg, key, one_step, own_cost=False):
    """Σ_t (1/P) Σ_i G_{i,t} log q_t(x_{i,t}) as a function of θ, the samples and G held at their
    values: ``q_t`` fitted to the particles of a rollout under θ (``one_step=False``: every step
    under θ, the thesis' DEL) or of one model step under θ from the recorded ``x_{t−1}`` (the
    library's DEL); ``own_cost``: each step's own cost ``c_{i,t}`` in place of ``G_{i,t}``."""
    task, post, pol = setup
    noise = sample_noise(jax.random.PRNGKey(key), task, cfg)
    rec = particle_rollout(task, pol, post, noise, cfg, jacobian=False)
    returns = rec.cost if own_cost else jnp.cumsum(rec.cost[::-1], axis=0)[::-1]  # (T, P)

    def fitted(p):
        if not one_step:
            return particle_rollout(task, p, post, noise, cfg, jacobian=False).x_next
        return jnp.stack([particle_step(task, p, post, cfg, rec.x[t], rec.eps[t], jacobian=False).x_next
                          for t in range(rec.x.shape[0])])

    def surrogate(p):
        total = 0.0
        for t, xt in enumerate(fitted(p)):
            mu = xt.mean(0)
            cov = (xt - mu).T @ (xt - mu) / (P - 1) + 1e-12 * jnp.eye(4)
            total = total + jnp.mean(returns[t] * cost_terms.gaussian_logpdf(rec.x_next[t], mu, cov))
        return total

    return surrogate


@pytest.mark.parametrize("choices", ["library", "thesis"])
def test_del_gradient_equals_autodiff_of_its_surrogate(setup, choices):
    """DEL = ∇θ Σ_t (1/P) Σ_i (G_i − b_t) log q_t(x_i) with x_i and G held fixed (thesis §3.3.1): the
    library's through one model step from x_{t−1}, the thesis' through the whole rollout."""
    cfg = RolloutConfig(num_particles=P)
    build = estimator if choices == "library" else thesis_estimator
    e = run(setup, build("del", baseline="none"), cfg)
    one_step, chain = (flat(jax.grad(_del_surrogate(setup, cfg, 3, s))(setup[2])) for s in (True, False))
    ref, other = (one_step, chain) if choices == "library" else (chain, one_step)
    np.testing.assert_allclose(flat(e.grad), ref, rtol=1e-8, atol=1e-10 * np.abs(ref).max())
    assert np.linalg.norm(one_step - chain) > 0.1 * np.linalg.norm(ref)  # the two readings differ here


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_del_refuses_a_degenerate_fit_in_either_precision(dtype):
    """P ≤ D particles have a covariance of rank P − 1 < D: float64's jitter turned it into a finite
    number with no meaning and float32's Cholesky into NaN; both now raise, naming P and D."""
    x = jax.random.normal(jax.random.PRNGKey(0), (4, 4)).astype(dtype)
    with pytest.raises(ValueError, match=r"P = 4 particles of dimension D = 4 \(need P > D\)"):
        cost_terms.del_gradient(x, jnp.arange(4.0, dtype=dtype), jnp.zeros((), dtype))
    five = jnp.concatenate([x, x[:1] + 1.0])
    assert jnp.all(jnp.isfinite(cost_terms.del_gradient(five, jnp.arange(5.0, dtype=dtype), jnp.zeros((), dtype))))


def test_whole_chain_del_weighted_by_each_steps_cost_equals_autodiff_of_its_surrogate(setup):
    """The third reading: the whole chain, each particle's fitted score weighted by its own cost
    c_{i,t} instead of its return-to-go."""
    cfg = RolloutConfig(num_particles=P)
    e = run(setup, compose(density_estimation_costs("none", weights="cost"), pathwise()), cfg)
    ref, returns = (flat(jax.grad(_del_surrogate(setup, cfg, 3, False, own))(setup[2])) for own in (True, False))
    np.testing.assert_allclose(flat(e.grad), ref, rtol=1e-8, atol=1e-10 * np.abs(ref).max())
    assert np.linalg.norm(ref - returns) > 0.1 * np.linalg.norm(ref)  # the weights matter here
    with pytest.raises(ValueError, match="weights must be one of"):
        density_estimation_costs(weights="return")


def _direct_biw(x, mean, std, G, baseline):
    """Eq. 4.2–4.3 evaluated with explicit loops and raw densities (small P only)."""
    Pn, D = x.shape
    dens = np.array([[np.prod(np.exp(-0.5 * ((x[j] - mean[i]) / std[i]) ** 2) / (np.sqrt(2 * np.pi) * std[i])) for j in range(Pn)] for i in range(Pn)])
    w = dens / dens.sum(axis=0, keepdims=True)
    gm = np.zeros((Pn, D))
    gs = np.zeros((Pn, D))
    for i in range(Pn):
        if baseline == "thesis":
            others = [j for j in range(Pn) if j != i]
            b = sum(w[i, j] * G[j] for j in others) / sum(w[i, j] for j in others)
        else:
            b = baseline
        for j in range(Pn):
            d = x[j] - mean[i]
            gm[i] += w[i, j] * (G[j] - b) * d / std[i] ** 2
            gs[i] += w[i, j] * (G[j] - b) * (d**2 - std[i] ** 2) / std[i] ** 3
    return w, gm, gs


@pytest.mark.parametrize("baseline", ["thesis", "previous", "none"])
def test_biw_lr_matches_a_direct_evaluation(baseline):
    rng = np.random.default_rng(0)
    Pn, D = 7, 3
    mean = rng.normal(size=(Pn, D))
    std = rng.uniform(0.3, 1.5, size=(Pn, D))
    x = mean + std * rng.normal(size=(Pn, D))
    G = rng.normal(size=Pn) + 2.0
    b = {"thesis": "thesis", "previous": 1.7, "none": 0.0}[baseline]
    w_ref, gm_ref, gs_ref = _direct_biw(x, mean, std, G, b)
    np.testing.assert_allclose(np.asarray(lr.biw_weights(jnp.asarray(x), jnp.asarray(mean), jnp.asarray(std))), w_ref, rtol=1e-12)
    got = lr.biw_lr(jnp.asarray(x), jnp.asarray(mean), jnp.asarray(std), jnp.asarray(G), baseline, jnp.asarray(1.7))
    np.testing.assert_allclose(np.asarray(got.mean), gm_ref, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(np.asarray(got.std), gs_ref, rtol=1e-10, atol=1e-13)


def test_biw_weights_stay_finite_where_raw_densities_underflow():
    x = jnp.array([[0.0], [50.0]])
    mean = jnp.array([[0.0], [50.0]])
    std = jnp.full((2, 1), 1e-3)  # exp(-0.5·(5e4)²) underflows to 0 in float64
    w = lr.biw_weights(x, mean, std)
    np.testing.assert_allclose(np.asarray(w), np.eye(2), atol=1e-300)
    b = lr.thesis_baseline(w, jnp.array([1.0, 3.0]))  # denominators underflow: leave-one-out fallback
    np.testing.assert_allclose(np.asarray(b), [3.0, 1.0])


def test_plain_lr_matches_direct_formula():
    rng = np.random.default_rng(1)
    mean = rng.normal(size=(5, 2))
    std = rng.uniform(0.5, 2.0, size=(5, 2))
    eps = rng.normal(size=(5, 2))
    x = mean + std * eps
    G = rng.normal(size=5)
    got = lr.plain_lr(jnp.asarray(x), jnp.asarray(mean), jnp.asarray(std), jnp.asarray(G))
    b = np.array([(G.sum() - G[i]) / 4 for i in range(5)])
    np.testing.assert_allclose(np.asarray(got.mean), (G - b)[:, None] * (x - mean) / std**2, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(got.std), (G - b)[:, None] * ((x - mean) ** 2 - std**2) / std**3, rtol=1e-12)


def test_minus_sigma_f_computes_no_gp_variance(setup):
    """−σ_f must skip the variance path, not multiply it by 0: a NaN `inv` may not reach anything."""
    task, post, pol = setup
    poisoned = post._replace(inv=jnp.full_like(post.inv, jnp.nan))
    for cfg, finite in ((RolloutConfig(num_particles=P, model_variance=False), True), (RolloutConfig(num_particles=P), False)):
        e = run((task, poisoned, pol), estimator("tp"), cfg)
        assert bool(np.all(np.isfinite(flat(e.grad)))) == finite
        assert bool(np.isfinite(float(e.value))) == finite


def test_estimator_configuration_errors_name_the_problem():
    with pytest.raises(ValueError, match="unknown estimator"):
        estimator("bogus")
    with pytest.raises(ValueError, match="k_lr"):
        estimator("tp", k_lr=1.5)
    with pytest.raises(ValueError, match="baseline"):
        estimator("lr", baseline="loo")
    with pytest.raises(ValueError, match="num_particles"):
        RolloutConfig(num_particles=0)
    with pytest.raises(ValueError, match="noise_multiplier"):
        RolloutConfig(noise_multiplier=-1.0)
    assert thesis_estimator("tp").parts[1].baseline == "thesis" and thesis_estimator("tp").combiner.k_lr == "batch"


def test_float32_variance_product_stays_within_its_rounding_bound(setup):
    """The float32 option rounds only the A·k product: mean and Jacobian of the mean are untouched,
    and |v32 − v64| obeys the GEMM bound M·ε₃₂·|k|ᵀ|A||k| (docs/performance.md measures what that
    bound means on trained models: too much at the thesis' noise levels, hence off by default)."""
    from pipps.gp.kernel import se_ard_batched
    from pipps.particles.models import model_output

    task, post, _ = setup
    rng = np.random.default_rng(0)
    rows = rng.integers(0, int(np.sum(np.asarray(post.inputs[:, 0]) != 0)), 64)
    z = jnp.asarray(np.asarray(post.inputs)[rows] + 0.3 * rng.normal(size=(64, post.inputs.shape[1])))
    o64 = model_output(post, z, variance=True, jacobian=True)
    o32 = model_output(post, z, variance=True, jacobian=True, precision="float32")
    np.testing.assert_array_equal(np.asarray(o32.mean), np.asarray(o64.mean))
    np.testing.assert_array_equal(np.asarray(o32.jac_mean), np.asarray(o64.jac_mean))
    ks = np.abs(np.asarray(se_ard_batched(post.hyper, z, post.inputs)))  # (E, P, M)
    bound = post.inputs.shape[0] * np.finfo(np.float32).eps * np.einsum("epm,emn,epn->pe", ks, np.abs(np.asarray(post.inv)), ks)
    err = np.abs(np.asarray(o32.var) - np.asarray(o64.var))
    assert np.all(err <= bound + 1e-300)
    assert err.max() > 0.0  # the product really ran in single precision
    with pytest.raises(ValueError, match="variance_precision"):
        RolloutConfig(num_particles=P, variance_precision="float16")
