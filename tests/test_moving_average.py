"""The moving-average k_LR (pipps.propagation.moving_average): a weight source with its own memory.

* registered by name: ``estimator("tp", k_lr="moving_average")`` is TP with it, and ``β`` is a traced
  number (a new value does not recompile);
* its memory is what the module says, over four iterations: the weight it uses is the average of the
  earlier batches' weights, ``m ← β m + (1 − β) k_batch``, the first iteration's own batch weight;
  with ``β = 0`` it is "previous" bit for bit, gradient and state, iteration after iteration;
* the estimator with it stays total propagation: an average of 0 is RP and of 1 is BIW-LR (up to
  rounding), at one weight per step and at the action nodes;
* unbiased, as every weight from earlier batches is (docs/estimators.md, "Choosing k_LR"): on the
  linear-Gaussian reference system with its exact gradient, after three earlier iterations, every
  coordinate's z-score is below the Bonferroni bound; the same test at the same R detects the bias
  of the weight from this batch (power).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from pipps.particles.forward import RolloutConfig
from pipps.propagation.combine import action_nodes, inverse_variance
from pipps.propagation.cost_terms import plain_costs
from pipps.propagation.estimate import estimate, init_estimator_state
from pipps.propagation.estimators import compose, estimator, thesis_estimator
from pipps.propagation.moving_average import MovingAverage, moving_average
from pipps.propagation.parts import biw_lr, pathwise
from pipps.stats import z_bound
from pipps.systems.linear_gaussian import exact_objective, reference_system, two_action_reference_system

CFG = RolloutConfig(num_particles=16)


def flat(tree):
    return np.asarray(ravel_pytree(tree)[0])


def iterations(system, est, n, cfg=CFG):
    """n estimates in a row, as an optimizer at a fixed policy makes them: (states before each, estimates)."""
    task, model, policy = system
    state = init_estimator_state(jax.random.PRNGKey(9), policy, model, problem=task, config=cfg, estimator=est)
    states, estimates = [], []
    for i in range(n):
        states.append(state)
        state, e = estimate(jax.random.PRNGKey(100 + i), state, policy, model, problem=task, config=cfg, estimator=est)
        estimates.append(e)
    return states + [state], estimates


@pytest.fixture(scope="module")
def system():
    return reference_system(noise_std=0.3, cost="saturating")


def test_it_is_registered_and_its_beta_is_traced(system):
    assert estimator("tp", k_lr="moving_average") == compose(
        plain_costs(), pathwise(), biw_lr(), combiner=inverse_variance(moving_average()))
    assert estimator("tp", k_lr="moving_average").cold_start and estimator("tp", k_lr=moving_average(0.5)).combiner.k_lr == "moving_average"
    with pytest.raises(ValueError, match="beta must lie in"):
        moving_average(1.5)
    task, model, policy = system
    est = estimator("tp", k_lr=moving_average(0.5))
    st = init_estimator_state(jax.random.PRNGKey(9), policy, model, problem=task, config=CFG, estimator=est)
    st, _ = estimate(jax.random.PRNGKey(1), st, policy, model, problem=task, config=CFG, estimator=est)

    @jax.jit
    def grad(e):
        return ravel_pytree(estimate(jax.random.PRNGKey(2), st, policy, model, problem=task, config=CFG, estimator=e)[1].grad)[0]

    a, b = np.asarray(grad(est)), np.asarray(grad(estimator("tp", k_lr=moving_average(0.8))))
    assert grad._cache_size() == 1 and np.all(np.isfinite(a))
    assert np.array_equal(a, b)  # the average after one estimate is that estimate's weight, for any β


def test_beta_zero_is_previous_bit_for_bit(system):
    states_p, est_p = iterations(system, estimator("tp", k_lr="previous"), 4)
    states_m, est_m = iterations(system, estimator("tp", k_lr=moving_average(0.0)), 4)
    for ep, em in zip(est_p, est_m):
        np.testing.assert_array_equal(flat(ep.grad), flat(em.grad))
        np.testing.assert_array_equal(np.asarray(ep.diagnostics.k_lr), np.asarray(em.diagnostics.k_lr))
    for sp, sm in zip(states_p, states_m):
        np.testing.assert_array_equal(np.asarray(sp.combiner.k_batch), np.asarray(sm.combiner.k))
        np.testing.assert_array_equal(np.asarray(sp.combiner.has_previous), np.asarray(sm.combiner.has_previous))


@pytest.mark.parametrize("beta", [0.5, 0.9])
def test_the_weight_is_the_average_of_the_earlier_batches(system, beta):
    states, estimates = iterations(system, estimator("tp", k_lr=moving_average(beta)), 4)
    batch = [np.asarray(e.diagnostics.k_lr_batch) for e in estimates]
    used = [np.asarray(e.diagnostics.k_lr) for e in estimates]
    assert not np.any(np.asarray(states[0].combiner.has_previous))
    np.testing.assert_array_equal(used[0], batch[0])  # the first iteration: its own batch's weight
    m = batch[0]
    for n in range(1, 4):
        np.testing.assert_allclose(used[n], m, rtol=1e-14)  # earlier batches only
        np.testing.assert_allclose(np.asarray(states[n].combiner.k), m, rtol=1e-14)
        m = beta * m + (1 - beta) * batch[n]
    np.testing.assert_allclose(np.asarray(states[4].combiner.k), m, rtol=1e-14)
    assert np.all(np.asarray(states[4].combiner.has_previous))
    assert np.max(np.abs(batch[1] - batch[2])) > 1e-3  # the batches' weights differ: the average matters
    assert np.max(np.abs(used[3] - batch[2])) > 1e-4  # and it is not "previous"


@pytest.mark.parametrize("combiner, system_of", [
    (inverse_variance, lambda: reference_system(noise_std=0.3, cost="saturating")),
    (action_nodes, two_action_reference_system),
])
def test_an_average_of_zero_is_rp_and_of_one_is_lr(combiner, system_of):
    system = system_of()
    task, model, policy = system
    est = compose(plain_costs(), pathwise(), biw_lr(), combiner=combiner(moving_average(0.7)))
    state = init_estimator_state(jax.random.PRNGKey(9), policy, model, problem=task, config=CFG, estimator=est)
    ref = {n: flat(estimate(jax.random.PRNGKey(3), init_estimator_state(jax.random.PRNGKey(9), policy, model, problem=task,
                                                                       config=CFG, estimator=estimator(n)),
                            policy, model, problem=task, config=CFG, estimator=estimator(n))[1].grad) for n in ("rp", "lr")}
    assert np.linalg.norm(ref["rp"] - ref["lr"]) > 1e-2 * np.linalg.norm(ref["rp"])  # the limits differ
    for k, want in ((0.0, ref["rp"]), (1.0, ref["lr"])):
        average = jnp.full_like(state.combiner.k, k)
        fixed = state._replace(combiner=MovingAverage(average, jnp.ones(average.shape, bool)))
        _, e = estimate(jax.random.PRNGKey(3), fixed, policy, model, problem=task, config=CFG, estimator=est)
        np.testing.assert_allclose(flat(e.grad), want, rtol=1e-10, atol=1e-12 * np.abs(want).max())


R, P, WARM_UP = 2000, 30, 3
Z = z_bound(2 * 4, 1e-3)  # two estimators × the reference policy's four parameters, family-wise 10⁻³


def _z_after_warm_up(est, seed):
    """z-scores of the mean of R estimates, each after WARM_UP earlier iterations at independent keys."""
    task, model, policy = reference_system(noise_std=0.3, cost="saturating")
    cfg = RolloutConfig(num_particles=P)
    exact = flat(jax.grad(exact_objective, argnums=2)(task, model, policy))

    def one(key):
        keys = jax.random.split(key, WARM_UP + 2)
        state = init_estimator_state(keys[0], policy, model, problem=task, config=cfg, estimator=est)
        for k in keys[1:-1]:
            state, _ = estimate(k, state, policy, model, problem=task, config=cfg, estimator=est)
        return ravel_pytree(estimate(keys[-1], state, policy, model, problem=task, config=cfg, estimator=est)[1].grad)[0]

    run = jax.jit(jax.vmap(one))
    keys = jax.random.split(jax.random.PRNGKey(seed), R)
    g = np.concatenate([np.asarray(run(keys[i:i + 250])) for i in range(0, R, 250)])
    se = g.std(0, ddof=1) / np.sqrt(R)
    assert np.linalg.norm(exact) > 1e-2 and np.all(se > 0)
    return (g.mean(0) - exact) / se


def test_tp_with_the_moving_average_is_unbiased():
    z = _z_after_warm_up(estimator("tp", k_lr=moving_average(0.5)), seed=101)
    print(f"moving average, P = {P}, R = {R}: z = {np.round(z, 2)}, bound {Z:.2f}")
    assert np.max(np.abs(z)) < Z


def test_the_same_test_detects_a_weight_from_this_batch():
    """Power: the thesis' TP (eq. 4.3 baseline, batch k_LR) fails the same test at the same R."""
    z = _z_after_warm_up(thesis_estimator("tp"), seed=101)
    assert np.max(np.abs(z)) > Z, f"z = {z}"
