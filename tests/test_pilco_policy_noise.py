"""PILCO's policy-input noise term (``pilco_policy_noise``; docs/pilco.md, "Policy input noise").

With the setting on, the policy is evaluated at the trig augmentation of ``N(μ, Σ + diag(σ_n²/2))``
and ``Cov[x̃, u] = Σ̃_{:,P} C_u`` with the un-inflated Σ̃ (PILCO release V0.9, ``propagate.m``). Where
the policy's inputs are model-state components (the thesis cart-pole) that is the exact joint of
``x`` and ``u = π(x_P + ε)``, ``ε ~ N(0, diag(σ_n²/2))`` independent of x, so a Monte Carlo sample
of that pair checks every moment; with sin/cos inputs (the PILCO cart-pole) the control's own mean
and variance are exact for an unsaturated linear policy and are checked there. Tolerances: z-scores
below :func:`pipps.stats.z_bound` (Bonferroni over the entries compared) and finite differences
whose tolerance is measured in the same call; each check is shown to reject the setting-off
moments or gradient. The default (off) runs the code from before the option existed, and the
setting belongs to PILCO alone and leaves the committed results' identities as they were.
"""

from __future__ import annotations

import functools
import importlib
import json
import re
from pathlib import Path

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from pipps import gp
from pipps.experiments.config import (
    ConfigError,
    config_hash,
    departures,
    experiment_name,
    from_dict,
    resolve_config,
    same_experiment,
)
from pipps.experiments.methods import METHODS
from pipps.gaussian import GaussianMap, append_map, trig_augment
from pipps.gp.types import GPConfig, GPHyper
from pipps.pilco import control_moments, objective, policy_input_noise, state_control_joint, step_moments
from pipps.pilco.propagate import _selection
from pipps.policies import LinearPolicy, init_rbf_policy
from pipps.stats import cov_z, mean_z, z_bound
from pipps.systems import reference_system
from pipps.tasks.presets import make_task

from moment_checks import FAMILY_ALPHA, N_MC, normal_samples  # tests/moment_checks.py

# the module (the package's attribute of that name is the function propagate)
propagate_module = importlib.import_module("pipps.pilco.propagate")
RESULTS = Path(__file__).resolve().parents[1] / "results/thesis"

joint_jit = jax.jit(state_control_joint, static_argnums=0)


@functools.lru_cache(maxsize=None)
def problem(preset: str):
    return make_task("cartpole_swingup", preset=preset, k=9).problem


def random_cov(rng, dim, scale):
    B = rng.normal(size=(dim, dim)) * scale / np.sqrt(dim)
    return B @ B.T + 0.05 * scale**2 * np.eye(dim)


def noisy_pairs(seed, mean, cov, noise):
    """x ~ N(mean, cov) and the policy's measurement o = x + ε, ε ~ N(0, diag(noise)) independent."""
    eps = normal_samples(seed, N_MC, 2 * len(mean))
    x = mean + eps[:, : len(mean)] @ np.linalg.cholesky(cov).T
    return x, x + eps[:, len(mean):] * np.sqrt(noise)


def max_z_and_bound(samples, m, S):
    z = np.concatenate([mean_z(samples, np.asarray(m)), cov_z(samples, np.asarray(S))])
    return float(np.max(z)), z_bound(z.size, FAMILY_ALPHA)


# ================================================================================================
# (a) the controller's moments at the inflated covariance, against Monte Carlo
# ================================================================================================
def test_joint_of_state_and_noisy_control_against_monte_carlo():
    """Thesis cart-pole (raw state inputs), saturated linear policy (ũ Gaussian, saturation exact):
    the joint of ``[x; u]`` — mean, Cov[u], Cov[x, u] and Cov[x] — is that of ``u = π(x + ε)``."""
    task = problem("thesis")
    rng = np.random.default_rng(1)
    mean, cov = 0.3 * rng.normal(size=4), random_cov(rng, 4, 0.6)
    noise = np.array([0.2, 0.5, 0.3, 0.4])
    policy = LinearPolicy(jnp.array([[0.9, -0.6, 0.5, 1.1]]), jnp.array([0.2]), tuple(task.u_max), saturated=True)
    x, o = noisy_pairs(11, mean, cov, noise)
    u = np.asarray(jax.jit(jax.vmap(lambda v: policy(task.policy_input(v))))(jnp.asarray(o)))
    samples = np.concatenate([x, u], axis=1)

    args = (task, policy, jnp.asarray(mean), jnp.asarray(cov))
    m_on, s_on, c_on = joint_jit(*args, jnp.asarray(noise))
    z, bound = max_z_and_bound(samples, m_on, s_on)
    print(f"MC joint [x; u], noise on: max z = {z:.2f} (bound {bound:.2f})")
    assert z < bound, (z, bound)
    # the composed C is Σ⁻¹ of the same cross-covariance
    np.testing.assert_allclose(cov @ np.asarray(c_on), np.asarray(s_on)[:4], rtol=1e-12, atol=1e-14)

    # power: the latent-state moments (setting off) are rejected by the same samples
    m_off, s_off, _ = joint_jit(*args, None)
    z_off, _ = max_z_and_bound(samples, m_off, s_off)
    print(f"MC joint [x; u], noise off against the noisy samples: max z = {z_off:.1f}")
    assert z_off > 10 * bound, z_off


def test_control_moments_with_trig_inputs_against_monte_carlo():
    """PILCO cart-pole (inputs x, v, ω, sin θ, cos θ), unsaturated linear policy: E[u] and Var[u] of
    ``u = W x̃(x + ε)[P] + b`` are exact, so the controller must see the augmentation of the inflated
    covariance (the noisy angle's sin/cos, damped by the extra variance) — not noise added after it."""
    task = problem("pilco")
    rng = np.random.default_rng(2)
    mean, cov = np.array([0.1, -0.2, 0.4, 2.5]), random_cov(rng, 4, 0.5)
    noise = np.array([0.1, 0.2, 0.3, 0.6])
    policy = LinearPolicy(jnp.array([[0.7, -0.4, 0.6, 1.5, -1.2]]), jnp.array([0.1]), tuple(task.u_max),
                          saturated=False)
    _, o = noisy_pairs(12, mean, cov, noise)
    u = np.asarray(jax.jit(jax.vmap(lambda v: policy(task.policy_input(v))))(jnp.asarray(o)))
    n_aug = task.augmented_dim

    def control_block(noise_or_none):
        m, s, _ = joint_jit(task, policy, jnp.asarray(mean), jnp.asarray(cov), noise_or_none)
        return np.asarray(m)[n_aug:], np.asarray(s)[n_aug:, n_aug:]

    z, bound = max_z_and_bound(u, *control_block(jnp.asarray(noise)))
    print(f"MC u with trig inputs, noise on: max z = {z:.2f} (bound {bound:.2f})")
    assert z < bound, (z, bound)
    z_off, _ = max_z_and_bound(u, *control_block(None))
    assert z_off > 10 * bound, z_off
    # noise added to the augmented covariance instead (sin/cos means undamped) is rejected too
    m_aug, s_aug, _ = trig_augment(jnp.asarray(mean), jnp.asarray(cov), task.angle_idx)
    p = np.asarray(task.policy_input_idx)
    wrong = np.asarray(s_aug) + np.diag(np.concatenate([noise, np.zeros(2)]))
    g = control_moments(policy, m_aug[p], jnp.asarray(wrong[np.ix_(p, p)]))
    z_wrong, _ = max_z_and_bound(u, g.M, g.S)
    print(f"MC u with trig inputs, noise on the augmented state: max z = {z_wrong:.1f}")
    assert z_wrong > bound, z_wrong


def test_policy_input_noise_is_the_models_noise_halved():
    """σ²_{n,a}/2 per model-state component, from the GP's (or a WeightedGP's, or any model's) noise."""
    task, model, _ = gp_case()
    expected = 0.5 * np.exp(2 * np.asarray(model.hyper.log_noise))
    np.testing.assert_allclose(np.asarray(policy_input_noise(task, model)), expected, rtol=1e-15)
    from pipps.pilco.gp_moments import weighted

    np.testing.assert_array_equal(np.asarray(policy_input_noise(task, weighted(model))),
                                  np.asarray(policy_input_noise(task, model)))
    ref_task, ref_model, _ = reference_system()
    np.testing.assert_allclose(np.asarray(policy_input_noise(ref_task, ref_model)),
                               0.5 * np.asarray(ref_model.noise_var))
    with pytest.raises(ValueError, match="one GP output per model-state component"):
        policy_input_noise(problem("thesis"), ref_model)  # 3 outputs for a 4-component state
    with pytest.raises(TypeError, match="no noise_variance"):
        policy_input_noise(task, object())


# ================================================================================================
# (b) the objective's gradient with the setting on, against central differences
# ================================================================================================
@functools.lru_cache(maxsize=None)
def gp_case():
    """Thesis cart-pole, a GP on random data (5 inputs, 4 outputs, σ_n ~ 0.3: the term is not small
    against the planning start's covariance) and a spread 10-centre RBF policy."""
    task = problem("thesis")
    rng = np.random.default_rng(3)
    X = rng.normal(size=(40, 5))
    Y = np.sin(X @ rng.normal(size=(5, 4))) + 0.1 * rng.normal(size=(40, 4))
    hyper = GPHyper(jnp.asarray(np.log(rng.uniform(0.8, 2.0, (4, 5)))), jnp.asarray(np.log(rng.uniform(0.6, 1.2, 4))),
                    jnp.asarray(np.log(rng.uniform(0.2, 0.4, 4))))
    post, _, ok = jax.jit(gp.full_posterior, static_argnames=("config",))(hyper, gp.make_data(X, Y), GPConfig())
    assert bool(np.all(ok))
    policy = init_rbf_policy(jax.random.key(4), 10, np.zeros(4), np.eye(4), task.u_max, weight_scale=1.0)
    return task, post, policy


H = 5


@functools.partial(jax.jit, static_argnames=("on",))
def line_values(theta, d, ts, model, on):
    """J(θ + t·d) for each t, and J's derivative along d at θ (autodiff), with or without the term."""
    task, _, policy = gp_case()
    unravel = ravel_pytree(policy)[1]
    J = lambda th: objective(task, unravel(th), model, horizon=H, checkpoint=True, policy_noise=on)  # noqa: E731
    return jax.vmap(lambda t: J(theta + t * d))(ts), jax.jvp(J, (theta,), (d,))[1]


@pytest.mark.parametrize("direction", [0, 1])
def test_objective_gradient_with_policy_noise_matches_finite_differences(direction):
    """dJ/dθ along a random unit direction d against central differences; the tolerance is the
    difference quotient's own error, measured in the same call (as tests/test_studies.py's J_MM check):
    truncation from steps h and 2h (fd(2h) − fd(h) is three times fd(h)'s h² term), rounding from
    J's scatter about its tangent over steps far below h. The check has power: the derivative of
    the setting-off objective misses it by far more than the tolerance."""
    _, model, policy = gp_case()
    theta = ravel_pytree(policy)[0]
    d = jax.random.normal(jax.random.key(10 + direction), theta.shape, theta.dtype)
    d = d / jnp.linalg.norm(d)
    h, tiny = 1e-3, 1e-9
    probes = [k * tiny for k in (-2, -1, 1, 2)]
    ts = jnp.asarray([0.0, -h, h, -2 * h, 2 * h, *probes])
    J, g = (np.asarray(a) for a in line_values(theta, d, ts, model, True))
    g = float(g)
    fd_h, fd_2h = (J[2] - J[1]) / (2 * h), (J[4] - J[3]) / (4 * h)
    noise = max(abs(J[5 + i] - J[0] - g * t) for i, t in enumerate(probes))
    truncation = abs(fd_2h - fd_h) / 3
    rounding = noise / h
    bound = 2 * (truncation + rounding) + 8 * np.finfo(float).eps * abs(g)
    print(f"FD J with policy noise, direction {direction}: g = {g:.6e}, fd = {fd_h:.6e}, bound {bound:.1e}")
    assert abs(g - fd_h) <= bound, (g, fd_h, truncation, rounding)

    J_off, g_off = (np.asarray(a) for a in line_values(theta, d, ts[:1], model, False))
    print(f"  setting off: J {float(J_off[0]):.6f} vs {J[0]:.6f}, g {float(g_off):.6e}")
    assert abs(float(g_off) - fd_h) > 100 * bound, (float(g_off), fd_h, bound)
    assert abs(float(J_off[0]) - J[0]) > 1e4 * max(noise, np.finfo(float).eps * abs(J[0])), (J_off, J[0])


# ================================================================================================
# (c) the setting off is the code from before the option existed
# ================================================================================================
def _state_control_joint_before(task, policy, mean, cov):
    """``state_control_joint`` as it was before the option existed (commit 12ca6d6), verbatim."""
    m_aug, s_aug, c_trig = trig_augment(mean, cov, task.angle_idx)
    p_idx = np.asarray(task.policy_input_idx, dtype=int)
    ctrl = control_moments(policy, m_aug[p_idx], s_aug[np.ix_(p_idx, p_idx)])
    lifted = GaussianMap(ctrl.M, ctrl.S, jnp.asarray(_selection(m_aug.shape[0], p_idx)) @ ctrl.C)
    m_joint, s_joint = append_map(m_aug, s_aug, lifted)
    c_aug = jnp.concatenate([jnp.eye(mean.shape[0], dtype=cov.dtype), c_trig], axis=1)
    return m_joint, s_joint, jnp.concatenate([c_aug, c_aug[:, p_idx] @ ctrl.C], axis=1)


def _program(fn, *args):
    """The lowered StableHLO of ``fn(*args)`` without source locations (the same text: the same program)."""
    text = jax.jit(fn).lower(*args).as_text(debug_info=False)
    return "\n".join(ln for ln in text.splitlines() if not ln.lstrip().startswith("#loc"))


@pytest.mark.parametrize("preset", ["thesis", "pilco"])
def test_setting_off_is_the_program_from_before(preset, monkeypatch):
    task = problem(preset)
    policy = init_rbf_policy(jax.random.key(5), 6, np.zeros(task.policy_input_dim), np.eye(task.policy_input_dim),
                             task.u_max, weight_scale=1.0)
    rng = np.random.default_rng(6)
    mean, cov = jnp.asarray(0.3 * rng.normal(size=4)), jnp.asarray(random_cov(rng, 4, 0.5))
    now = lambda p, m, c: state_control_joint(task, p, m, c)  # noqa: E731
    before = lambda p, m, c: _state_control_joint_before(task, p, m, c)  # noqa: E731
    assert _program(now, policy, mean, cov) == _program(before, policy, mean, cov)
    for a, b in zip(jax.jit(now)(policy, mean, cov), jax.jit(before)(policy, mean, cov)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))  # bit for bit
    noisy = lambda p, m, c: state_control_joint(task, p, m, c, jnp.full((4,), 0.1))  # noqa: E731
    assert _program(noisy, policy, mean, cov) != _program(before, policy, mean, cov)

    # the objective: policy_noise=False is the call without it, and never reaches the noise term
    _, model, _ = gp_case()
    if preset == "thesis":
        default = lambda p, m: objective(task, p, m, horizon=3)  # noqa: E731
        off = lambda p, m: objective(task, p, m, horizon=3, policy_noise=False)  # noqa: E731
        assert _program(default, policy, model) == _program(off, policy, model)

        def refuse(*_):
            raise AssertionError("the noise term was computed with the setting off")

        monkeypatch.setattr(propagate_module, "policy_input_noise", refuse)
        np.testing.assert_array_equal(np.asarray(jax.jit(off)(policy, model)),
                                      np.asarray(jax.jit(default)(policy, model)))
        with pytest.raises(AssertionError, match="setting off"):
            objective(task, policy, model, horizon=3, policy_noise=True)


def test_step_with_input_noise_leaves_the_state_block_alone():
    """The term reaches the control only: the joint's x̃ block is the state's, and Cov[x̃, u] = Σ̃_{:,P} C_u."""
    task, model, policy = gp_case()
    rng = np.random.default_rng(7)
    mean, cov = jnp.asarray(0.3 * rng.normal(size=4)), jnp.asarray(random_cov(rng, 4, 0.4))
    noise = policy_input_noise(task, model)
    m_on, s_on, _ = joint_jit(task, policy, mean, cov, noise)
    m_off, s_off, _ = joint_jit(task, policy, mean, cov, None)
    np.testing.assert_array_equal(np.asarray(m_on)[:4], np.asarray(m_off)[:4])
    np.testing.assert_array_equal(np.asarray(s_on)[:4, :4], np.asarray(s_off)[:4, :4])
    ctrl = control_moments(policy, mean, cov + jnp.diag(noise))
    np.testing.assert_allclose(np.asarray(s_on)[:4, 4:], np.asarray(cov @ ctrl.C), rtol=1e-12, atol=1e-15)
    g_on = jax.jit(step_moments, static_argnums=0)(task, policy, model, mean, cov, input_noise=noise)
    g_off = jax.jit(step_moments, static_argnums=0)(task, policy, model, mean, cov)
    assert np.max(np.abs(np.asarray(g_on.M) - np.asarray(g_off.M))) > 1e-6


# ================================================================================================
# (d), (e) the setting in the experiment configuration
# ================================================================================================
def test_only_pilco_takes_the_setting():
    assert "pilco_policy_noise" in METHODS["pilco"].settings
    for name in METHODS:
        if name != "pilco":
            assert "pilco_policy_noise" in METHODS[name].unused, name
            with pytest.raises(ConfigError, match=rf"^pilco_policy_noise: {re.escape(name)} does not use it"):
                resolve_config("thesis", "cartpole_swingup", method=name, pilco_policy_noise=True)
    cfg = resolve_config("thesis", "cartpole_swingup", method="pilco", k=9, pilco_policy_noise="true")
    assert cfg.pilco_policy_noise is True and departures(cfg) == {"pilco_policy_noise": (True, False)}
    with pytest.raises(ConfigError, match="^pilco_policy_noise: must be true or false"):
        cfg.replace(pilco_policy_noise=2)


@pytest.mark.parametrize("name", ["cartpole_swingup_angle_k9_pilco_thesis_s10",
                                  "cartpole_swingup_angle_k9_tp_thesis_s10"])
def test_committed_results_keep_their_identity(name):
    """A committed result written before the setting existed keeps its stored ``config_hash``, its file
    name and its experiment (resume and pooling accept it); for PILCO the setting on is another
    experiment with another name, and a particle method cannot be given it."""
    path = RESULTS / f"{name}.h5"
    with h5py.File(path, "r") as f:  # read only
        stored_json, stored_hash = f.attrs["config_json"], f.attrs["config_hash"]
    assert "pilco_policy_noise" not in json.loads(stored_json)
    cfg = from_dict(json.loads(stored_json))
    assert cfg.pilco_policy_noise is False
    assert config_hash(cfg) == stored_hash
    assert experiment_name(cfg) == path.stem and not departures(cfg)
    asked = resolve_config("thesis", "cartpole_swingup", method=cfg.method, k=9, seed=10)
    assert same_experiment(cfg, asked) and config_hash(asked) == stored_hash
    if cfg.method == "pilco":
        on = asked.replace(pilco_policy_noise=True)
        assert not same_experiment(cfg, on) and config_hash(on) != stored_hash
        assert experiment_name(on) == f"{path.stem}_c{config_hash(on)[:8]}"


def test_the_loop_hands_the_setting_to_the_policy_search(monkeypatch):
    """Programs builds PILCO's search with the configuration's setting (and the default without it)."""
    import pipps.pilco
    from pipps.experiments.programs import Programs
    from pipps.experiments.state import make_experiment_task

    seen = []

    class Stop(Exception):
        pass

    def capture(problem, model, policy, config):
        seen.append(config.policy_noise)
        raise Stop  # before any search runs

    monkeypatch.setattr(pipps.pilco, "optimize_policy", capture)
    for on in (True, False):
        cfg = resolve_config("thesis", "cartpole_swingup", method="pilco", pilco_policy_noise=on)
        programs = Programs(cfg, make_experiment_task(cfg))
        with pytest.raises(Stop):
            programs.optimize([None], [None], [None], lambda info: None)
    assert seen == [True, False]
