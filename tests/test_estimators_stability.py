"""Numerical stability of the estimators and the update step (the requirement: "no NaN or Inf reaches θ").

Each case builds a model that provokes one failure mode and checks (a) what the estimator
does is the documented guard, not an accident, and (b) the policy and the optimizer state stay
finite after a jitted update step, with ``info.skipped`` reporting a refused step.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree
from jax.tree_util import register_dataclass

from pipps.optimizers.normalized import normalized_momentum, normalized_term
from pipps.particles.forward import RolloutConfig
from pipps.policies import LinearPolicy
from pipps.propagation.combine import inverse_variance_k
from pipps.propagation.estimators import estimator
from pipps.propagation.estimate import estimate, init_estimator_state
from pipps.propagation.update import init_policy_opt_state, make_policy_update
from pipps.systems.linear_gaussian import make_linear_gaussian_task


@register_dataclass
@dataclasses.dataclass(frozen=True)
class SineModel:
    """Δx = a·sin(k·x) + b·u with noise variance `noise` (1 state, 1 control)."""

    a: jax.Array
    k: jax.Array
    b: jax.Array
    noise: jax.Array

    @property
    def noise_variance(self):
        return jnp.atleast_1d(self.noise)

    def predict(self, z, variance=False):
        mean = self.a * jnp.sin(self.k * z[:, :1]) + self.b * z[:, 1:2]
        return mean, (jnp.zeros_like(mean) if variance else None)


def flat(tree):
    return np.asarray(ravel_pytree(tree)[0])


def setup(model, horizon, init_cov=0.01, target=0.0, P=64):
    task = make_linear_gaussian_task(
        1, 1, horizon=horizon, init_mean=[0.3], init_cov=[[init_cov]], cost="saturating", cost_weight=[[1.0]], target=[target]
    )
    policy = LinearPolicy(jnp.array([[-0.3]]), jnp.array([0.1]), (10.0,), saturated=True)
    return task, policy, RolloutConfig(num_particles=P)


def one_estimate(task, policy, model, cfg, name, **kw):
    est = estimator(name, **kw)
    st = init_estimator_state(jax.random.PRNGKey(1), policy, model, problem=task, config=cfg, estimator=est)
    _, e = estimate(jax.random.PRNGKey(2), st, policy, model, problem=task, config=cfg, estimator=est)
    return e


def one_update(task, policy, model, cfg, name, **kw):
    est = estimator(name, **kw)
    opt = normalized_momentum(1e-2, 0.9)
    st = init_policy_opt_state(jax.random.PRNGKey(1), policy, model, problem=task, config=cfg, estimator=est, optimizer=opt)
    step = make_policy_update(task, cfg, est, opt)
    new, info = step(jax.random.PRNGKey(2), st, model)
    for leaf in jax.tree.leaves(new):
        assert np.all(np.isfinite(np.asarray(leaf))), "a non-finite value reached the policy/optimizer state"
    return st, new, info


# -- RP's gradient overflows: k_LR → 1 in TP, the RP step is refused ---------------------------

OVERFLOW = SineModel(jnp.array(1.0), jnp.array(1e3), jnp.array(0.01), jnp.array(1e-2))


def test_rp_overflow_is_refused_not_applied():
    task, policy, cfg = setup(OVERFLOW, horizon=120)
    e = one_estimate(task, policy, OVERFLOW, cfg, "rp")
    assert not np.all(np.isfinite(flat(e.grad)))  # the case really overflows (|∂x_T/∂x_0| ~ 10^360)
    assert np.isfinite(float(e.value))  # the states and the objective stay finite
    st, new, info = one_update(task, policy, OVERFLOW, cfg, "rp")
    assert bool(info.skipped)
    np.testing.assert_array_equal(flat(new.policy), flat(st.policy))  # last good parameters kept


def test_tp_falls_back_to_lr_where_rp_overflows():
    task, policy, cfg = setup(OVERFLOW, horizon=120)
    tp = one_estimate(task, policy, OVERFLOW, cfg, "tp", k_lr="batch")
    lr_e = one_estimate(task, policy, OVERFLOW, cfg, "lr")
    k = np.asarray(tp.diagnostics.k_lr)
    assert np.all(np.isfinite(flat(tp.grad))) and np.all(np.isfinite(flat(tp.grad_variance)))
    # TP passes the mixed message back, so RP's chain restarts at every step and its per-step
    # variance stays finite — but it is ~10^5× LR's, so nearly all weight goes to LR ...
    assert np.all(np.isfinite(np.asarray(tp.diagnostics.var_rp)))
    assert np.all(k[:100] > 0.999)  # (near the end RP is little more than ∇c and gets weight again)
    # ... and the estimate is the LR estimate up to that tiny RP share
    np.testing.assert_allclose(flat(tp.grad), flat(lr_e.grad), rtol=0.05)
    _, new, info = one_update(task, policy, OVERFLOW, cfg, "tp", k_lr="batch")
    assert not bool(info.skipped)
    assert np.any(flat(new.policy) != flat(policy))


# -- σ → 0: tiny model noise (k = 1e-2 observation noise leads to σ_n ~ 1e-4 and below) ---------


@pytest.mark.parametrize("name", ["lr", "tp", "lr_plain"])
def test_tiny_noise_keeps_lr_and_tp_finite(name):
    model = SineModel(jnp.array(0.5), jnp.array(1.0), jnp.array(0.05), jnp.array(1e-12))  # σ = 1e-6
    task, policy, cfg = setup(model, horizon=10)
    e = one_estimate(task, policy, model, cfg, name)
    assert np.all(np.isfinite(flat(e.grad))) and np.all(np.isfinite(flat(e.grad_variance)))
    if name != "lr_plain":
        # BIW weights are one-hot at this noise level: BIW-LR reduces to LR without batch weighting
        assert np.isfinite(float(e.diagnostics.var_lr[0]))
    _, _, info = one_update(task, policy, model, cfg, name)
    assert not bool(info.skipped)


# -- all particles coincide ----------------------------------------------------------------------


def test_coinciding_start_particles():
    model = SineModel(jnp.array(0.5), jnp.array(1.0), jnp.array(0.05), jnp.array(1e-4))
    task, policy, cfg = setup(model, horizon=10, init_cov=0.0)
    for name in ("rp", "lr", "tp", "gtp", "del"):
        e = one_estimate(task, policy, model, cfg, name)
        assert np.all(np.isfinite(flat(e.grad))), name
        _, _, info = one_update(task, policy, model, cfg, name)
        assert not bool(info.skipped), name


def test_zero_noise_model_lr_is_undefined_and_tp_uses_rp():
    """With s = 0 the score (x−μ)/s² is 0/0: LR's variance is not finite, TP puts all weight on RP."""
    model = SineModel(jnp.array(0.5), jnp.array(1.0), jnp.array(0.05), jnp.array(0.0))
    task, policy, cfg = setup(model, horizon=10)
    tp = one_estimate(task, policy, model, cfg, "tp", k_lr="batch")
    rp = one_estimate(task, policy, model, cfg, "rp")
    np.testing.assert_array_equal(np.asarray(tp.diagnostics.k_lr), 0.0)
    np.testing.assert_allclose(flat(tp.grad), flat(rp.grad), rtol=1e-12)
    st, new, info = one_update(task, policy, model, cfg, "lr")
    assert bool(info.skipped)  # an LR step from NaN scores is refused, the policy unchanged
    np.testing.assert_array_equal(flat(new.policy), flat(st.policy))


# -- saturated costs: zero gradient, zero variance ------------------------------------------------


@pytest.mark.parametrize("name", ["rp", "lr", "tp", "gtp"])
def test_saturated_cost_gives_a_zero_step_not_nan(name):
    model = SineModel(jnp.array(0.1), jnp.array(1.0), jnp.array(0.05), jnp.array(1e-4))
    task, policy, cfg = setup(model, horizon=5, target=100.0)  # exp(−½·100²) underflows: c ≡ 1
    e = one_estimate(task, policy, model, cfg, name)
    np.testing.assert_array_equal(flat(e.grad), 0.0)
    st, new, info = one_update(task, policy, model, cfg, name)
    assert not bool(info.skipped)
    np.testing.assert_array_equal(flat(new.policy), flat(st.policy))  # 0/sqrt(0+0) := 0, no step


def test_guards_of_the_combiner_and_the_normalized_step():
    assert float(inverse_variance_k(jnp.inf, 1.0)) == 1.0
    assert float(inverse_variance_k(jnp.nan, 1.0)) == 1.0
    assert float(inverse_variance_k(1.0, jnp.nan)) == 0.0
    assert float(inverse_variance_k(0.0, 0.0)) == 0.5
    assert float(inverse_variance_k(3.0, 1.0)) == 0.75
    assert float(normalized_term(jnp.array(0.0), jnp.array(0.0))) == 0.0
    assert float(normalized_term(jnp.array(3.0), jnp.array(16.0))) == pytest.approx(0.6)
