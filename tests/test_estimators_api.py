"""The public entry point: purity (vmap over seeds), no recompilation, fixed seed, the optimizer."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jax.flatten_util import ravel_pytree

from pipps.optimizers.normalized import normalized_momentum
from pipps.particles.forward import RolloutConfig
from pipps.propagation.estimators import estimator
from pipps.propagation.estimate import estimate, init_estimator_state
from pipps.propagation.update import init_policy_opt_state, make_policy_optimizer, make_policy_update
from pipps.systems.linear_gaussian import reference_system

CFG = RolloutConfig(num_particles=32)


def flat(tree):
    return np.asarray(ravel_pytree(tree)[0])


@pytest.fixture(scope="module")
def system():
    return reference_system(noise_std=0.1, cost="saturating")


def test_vmap_over_seeds_equals_a_loop(system):
    task, model, policy = system
    est = estimator("tp")
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    # a leading axis of independent experiments: keys, estimator states and policies
    policies = jax.tree.map(lambda p: jnp.stack([p, 1.1 * p, 0.9 * p]), policy)
    init = lambda k, p: init_estimator_state(k, p, model, problem=task, config=CFG, estimator=est)  # noqa: E731
    states = jax.vmap(init)(keys, policies)
    run = lambda k, s, p: estimate(k, s, p, model, problem=task, config=CFG, estimator=est)[1].grad  # noqa: E731
    batched = jax.jit(jax.vmap(run))(keys, states, policies)
    for i in range(3):
        pol_i = jax.tree.map(lambda a: a[i], policies)
        st_i = jax.tree.map(lambda a: a[i], states)
        np.testing.assert_allclose(flat(jax.tree.map(lambda a: a[i], batched)), flat(run(keys[i], st_i, pol_i)), rtol=1e-10, atol=1e-14)


def test_update_step_does_not_recompile(system):
    task, model, policy = system
    est, opt = estimator("tp"), normalized_momentum()
    step = make_policy_update(task, CFG, est, opt)
    st = init_policy_opt_state(jax.random.PRNGKey(0), policy, model, problem=task, config=CFG, estimator=est, optimizer=opt)
    st, _ = step(jax.random.PRNGKey(1), st, model)
    st, _ = step(jax.random.PRNGKey(2), st, model)
    model2 = jax.tree.map(lambda a: 1.01 * a, model)  # a retrained model of the same shapes
    st, _ = step(jax.random.PRNGKey(3), st, model2)
    assert step._cache_size() == 1


def test_fixed_seed_is_deterministic_and_fresh_keys_are_not(system):
    task, model, policy = system
    est, opt = estimator("rp"), normalized_momentum(1e-2)
    st = init_policy_opt_state(jax.random.PRNGKey(0), policy, model, problem=task, config=CFG, estimator=est, optimizer=opt)
    fixed = make_policy_optimizer(task, CFG, est, opt, fixed_seed=True)
    fresh = make_policy_optimizer(task, CFG, est, opt, fixed_seed=False)
    _, info_f = fixed(jax.random.PRNGKey(5), st, model, num_steps=3)
    _, info_r = fresh(jax.random.PRNGKey(5), st, model, num_steps=3)
    # fixed seed: the same noise, so the objective changes only through θ and is smooth in it
    e = lambda k, p: estimate(k, st.estimator_state, p, model, problem=task, config=CFG, estimator=est)[1].value  # noqa: E731
    assert float(info_f.value[0]) == pytest.approx(float(e(jax.random.PRNGKey(5), policy)), rel=1e-14)
    assert float(info_r.value[1]) != float(info_f.value[1])


def test_normalized_momentum_formula_and_step_bound():
    opt = normalized_momentum(learning_rate=0.1, momentum=0.5)
    params = {"a": jnp.array([1.0, 2.0, 3.0])}
    state = opt.init(params)
    g = {"a": jnp.array([1.0, -2.0, 0.0])}
    v = {"a": jnp.array([3.0, 0.0, 0.0])}
    upd, state = opt.update(g, state, params, grad_variance=v)
    np.testing.assert_allclose(np.asarray(upd["a"]), -0.1 * np.array([0.5, -1.0, 0.0]))
    upd, state = opt.update(g, state, params, grad_variance=v)
    np.testing.assert_allclose(np.asarray(upd["a"]), -0.1 * np.array([0.5 * 0.5 + 0.5, -(0.5 + 1.0), 0.0]))
    # however large the gradient, a parameter moves at most α/(1−γ) per step
    for _ in range(50):
        upd, state = opt.update({"a": jnp.array([1e30, -1e30, 1e-30])}, state, params, grad_variance=v)
    assert np.all(np.abs(np.asarray(upd["a"])) <= 0.1 / (1 - 0.5) + 1e-12)
    with pytest.raises(ValueError, match="grad_variance"):
        opt.update(g, state, params)
    assert isinstance(optax.apply_updates(params, upd), dict)


def test_optimizing_on_the_model_lowers_the_exact_objective(system):
    """A few hundred TP steps on the reference system lower its exact J (a check that the sign is right)."""
    from pipps.systems.linear_gaussian import exact_objective

    task, model, policy = system
    est, opt = estimator("tp"), normalized_momentum(5e-3, 0.9)
    st = init_policy_opt_state(jax.random.PRNGKey(0), policy, model, problem=task, config=CFG, estimator=est, optimizer=opt)
    run = make_policy_optimizer(task, CFG, est, opt)
    new, info = run(jax.random.PRNGKey(1), st, model, num_steps=200)
    assert not np.any(np.asarray(info.skipped))
    before = float(exact_objective(task, model, policy))
    after = float(exact_objective(task, model, new.policy))
    assert after < before - 0.05 * before


@pytest.mark.parametrize("resampling", ["none", "gaussian"])
def test_fixed_seed_quasi_newton_minimises_the_fixed_objective(system, resampling):
    """RP_FS / GR_FS: quasi-Newton on the deterministic objective reaches a stationary point of it."""
    from pipps.optimizers.quasi_newton import QuasiNewtonConfig
    from pipps.particles.forward import reparameterized_objective, sample_noise
    from pipps.propagation.fixed_seed import optimize_fixed_seed

    task, model, policy = system
    cfg = RolloutConfig(num_particles=32, resampling=resampling)
    key = jax.random.PRNGKey(11)
    qn = QuasiNewtonConfig(length=40, max_evals_per_linesearch=20)
    run = jax.jit(lambda p: optimize_fixed_seed(key, p, model, problem=task, config=cfg, qn_config=qn))
    new, trace = run(policy)
    noise = sample_noise(key, task, cfg)
    J = lambda p: reparameterized_objective(task, p, model, noise, cfg)  # noqa: E731
    assert float(J(new)) == pytest.approx(float(trace.value), rel=1e-12)
    assert float(trace.value) < float(J(policy)) - 1e-3
    g0 = np.linalg.norm(flat(jax.grad(J)(policy)))
    assert np.linalg.norm(flat(jax.grad(J)(new))) < 1e-2 * g0  # (near-)stationary for the fixed noise
