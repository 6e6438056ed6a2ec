"""The known-simulator setting (noise on the actions, Suh et al.'s eq. 1) through the same estimator pieces.

On the linear simulator with noise on the actions and the state (:mod:`pipps.systems.linear_actions`)
the objective and its gradient are closed form. Checked here:

* **Identities.** RP through the custom sweep at the action node equals ``jax.grad`` of the
  reparameterised rollout (to rounding); total propagation with ``k_LR`` fixed at 0 or 1 equals RP
  or plain LR; the action-node combiner with every weight 0 equals RP.
* **Unbiasedness.** RP (FoBG), plain LR (ZoBG) with every baseline and both returns, total
  propagation with a "previous" or fixed weight, the action-node combiner and the robust combiner
  with a "previous" weight: every coordinate's ``|z|`` below the Bonferroni bound.
* **Power.** RP with the policy's state Jacobian cut fails the same test.
* **Refusals.** BIW-LR and DEL at the action node (their scores assume the sample is the whole next
  state), resampling with action noise, and a learned model with action noise each raise a
  ValueError that names the problem.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree
from jax.tree_util import register_dataclass

from pipps.particles.forward import RolloutConfig, reparameterized_objective, sample_noise
from pipps.propagation.estimate import estimate, init_estimator_state
from pipps.propagation.estimators import estimator
from pipps.stats import replicate_gradients, z_bound
from pipps.systems.linear_actions import exact_objective, reference_system

SIGMA_U, SIGMA_X = 0.3, 0.1
CFG = RolloutConfig(num_particles=30, action_noise=SIGMA_U, state_noise=SIGMA_X)
R = 600
N_THETA = 8  # W (2, 3) and b (2,)

UNBIASED = {
    "rp": estimator("rp"),
    "lr_plain": estimator("lr_plain"),
    "lr_plain_zero_noise": estimator("lr_plain", baseline="zero_noise"),
    "lr_plain_total": estimator("lr_plain", returns="total"),
    "zobg": estimator("lr_plain", returns="total", baseline="zero_noise"),  # Suh et al.'s Definition II.1 with §II.B's baseline
    "tp_plain_kprevious": estimator("tp_plain", k_lr="previous"),
    "tp_plain_kfixed": estimator("tp_plain", k_lr=0.4),
    "tpx_plain_kprevious": estimator("tpx", weighting="plain", k_lr="previous"),
    "aobg_kprevious": estimator("tp_plain", combiner="robust", robust_gamma=0.5, k_lr="previous"),
}
Z_BOUND = z_bound(len(UNBIASED) * N_THETA, 1e-3)


def _exact(problem, simulator, policy) -> np.ndarray:
    g = jax.grad(lambda p: exact_objective(problem, simulator, p, SIGMA_U, SIGMA_X))(policy)
    return np.asarray(ravel_pytree(g)[0])


def _one(name_or_est, policy=None, key=0, config=CFG):
    problem, simulator, ref = reference_system()
    est = UNBIASED[name_or_est] if isinstance(name_or_est, str) else name_or_est
    pol = ref if policy is None else policy
    state = init_estimator_state(jax.random.PRNGKey(99), pol, simulator, problem=problem, config=config, estimator=est)
    _, e = estimate(jax.random.PRNGKey(key), state, pol, simulator, problem=problem, config=config, estimator=est)
    return np.asarray(ravel_pytree(e.grad)[0]), e


def test_rp_through_the_action_node_equals_autodiff_of_the_rollout():
    problem, simulator, policy = reference_system()
    noise = sample_noise(jax.random.PRNGKey(0), problem, CFG)
    ref = jax.grad(lambda p: reparameterized_objective(problem, p, simulator, noise, CFG))(policy)
    g, e = _one("rp")
    assert np.allclose(g, ravel_pytree(ref)[0], rtol=1e-12, atol=1e-12)
    assert float(e.value) == pytest.approx(float(reparameterized_objective(problem, policy, simulator, noise, CFG)), rel=1e-13)


@pytest.mark.parametrize("k, same_as", [(0.0, "rp"), (1.0, "lr_plain")])
def test_total_propagation_at_its_ends_is_its_parts(k, same_as):
    g, _ = _one(estimator("tp_plain", k_lr=k))
    assert np.allclose(g, _one(same_as)[0], rtol=1e-11, atol=1e-12)


def test_action_node_combiner_with_every_weight_zero_is_rp():
    g, _ = _one(estimator("tpx", weighting="plain", k_lr=0.0))
    assert np.allclose(g, _one("rp")[0], rtol=1e-11, atol=1e-12)


@pytest.mark.parametrize("name", list(UNBIASED))
def test_mean_of_replicates_equals_the_exact_gradient(name):
    problem, simulator, policy = reference_system()
    exact = _exact(problem, simulator, policy)
    g = replicate_gradients(jax.random.fold_in(jax.random.PRNGKey(11), len(name)), problem, simulator, policy, CFG,
                            UNBIASED[name], R)
    z = (g.mean(0) - exact) / (g.std(0, ddof=1) / np.sqrt(R))
    assert np.linalg.norm(exact) > 1.0
    assert np.max(np.abs(z)) < Z_BOUND, f"{name}: z = {np.round(z, 2)} (bound {Z_BOUND:.2f})"


@register_dataclass
@dataclasses.dataclass(frozen=True)
class StateBlindPolicy:
    """The inner policy with ∂u/∂x cut (a deliberately biased pathwise gradient, same rollout)."""

    inner: object

    def __call__(self, v):
        return self.inner(jax.lax.stop_gradient(v))


def test_rp_without_the_policys_state_jacobian_fails_the_test():
    problem, simulator, policy = reference_system()
    exact = _exact(problem, simulator, policy)
    g = replicate_gradients(jax.random.PRNGKey(5), problem, simulator, StateBlindPolicy(policy), CFG, estimator("rp"), 300)
    z = (g.mean(0) - exact) / (g.std(0, ddof=1) / np.sqrt(300))
    assert np.max(np.abs(z)) > Z_BOUND, f"the bias was not detected: z = {np.round(z, 2)}"


@pytest.mark.parametrize("name", ["lr", "tp", "del"])
def test_scores_under_other_particles_are_refused_at_the_action_node(name):
    with pytest.raises(ValueError, match="plain LR"):
        _one(estimator(name))


def test_action_noise_settings_are_checked():
    with pytest.raises(ValueError, match="resampling"):
        RolloutConfig(action_noise=0.1, resampling="gaussian")
    with pytest.raises(ValueError, match="action_noise must be finite and > 0"):
        RolloutConfig(action_noise=0.0)
    with pytest.raises(ValueError, match="state_noise is the known simulator's"):
        RolloutConfig(state_noise=0.1)
    with pytest.raises(ValueError, match="action_noise has 3 entries"):
        _one("rp", config=RolloutConfig(num_particles=8, action_noise=(0.1, 0.2, 0.3)))


def test_a_learned_model_with_action_noise_is_refused():
    from pipps.systems import reference_system as gaussian_reference

    problem, model, policy = gaussian_reference(0.3, "saturating")
    cfg = RolloutConfig(num_particles=8, action_noise=0.1)
    state = init_estimator_state(jax.random.PRNGKey(0), policy, model, problem=problem, config=RolloutConfig(num_particles=8),
                                 estimator=estimator("rp"))
    with pytest.raises(ValueError, match="known simulator"):
        estimate(jax.random.PRNGKey(1), state, policy, model, problem=problem, config=cfg, estimator=estimator("rp"))
