"""experiments/balance_reference.py: the linear reference controllers behind docs/results.md's
"Can the criterion be met at high noise?" (linearisation, gains, the static/filtered runner)."""

import importlib.util
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pipps
from pipps.tasks.presets import make_task

pipps.enable_float64()

_PATH = pathlib.Path(__file__).parents[1] / "experiments/balance_reference.py"
_spec = importlib.util.spec_from_file_location("balance_reference", _PATH)
br = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(br)


@pytest.fixture(scope="module")
def system():
    task = make_task("cartpole_swingup", preset="thesis", k=9.0)
    A, B = br.linearise(task.simulator)
    return task, A, B


def test_linearisation_matches_central_differences(system):
    task, A, B = system
    step = jax.jit(task.simulator.step)
    s0, h = np.asarray(br.UPRIGHT), 1e-5
    fd_A = np.stack([(np.asarray(step(jnp.asarray(s0 + h * e), jnp.zeros(1)))
                      - np.asarray(step(jnp.asarray(s0 - h * e), jnp.zeros(1)))) / (2 * h) for e in np.eye(4)], axis=1)
    fd_B = ((np.asarray(step(jnp.asarray(s0), jnp.full(1, h))) - np.asarray(step(jnp.asarray(s0), jnp.full(1, -h))))
            / (2 * h))[:, None]
    # central differences: truncation O(h²·|third derivative|) and rounding O(eps·|s|/h) ≈ 1e-10 here
    np.testing.assert_allclose(A, fd_A, atol=1e-7 * np.abs(A).max())
    np.testing.assert_allclose(B, fd_B, atol=1e-7 * np.abs(B).max())
    assert np.max(np.abs(np.linalg.eigvals(A))) > 1.5  # the upright pole is unstable at dt = 0.1 s


def test_lqr_gain_stabilises_the_linearisation(system):
    _, A, B = system
    for q, r in [((1, 0, 0, 1), 1e-3), ((10, 1, 0.1, 1), 1.0)]:
        K = br.lqr_gain(A, B, q, r)
        assert np.max(np.abs(np.linalg.eigvals(A - B @ K))) < 1.0


def test_kalman_gain_limits(system):
    task, A, _ = system
    var = np.asarray(task.simulator.obs_noise_std) ** 2
    small, large = br.kalman_gain(A, var, 1e-10), br.kalman_gain(A, var, 1e6)
    # without process noise the filter still corrects the unstable mode λ_u: its gain tends to
    # 1 − 1/λ_u² (the error variance it can hold steady), every other mode's to 0 (the marginal
    # cart-position mode slowest, as √w)
    lam_u = np.max(np.abs(np.linalg.eigvals(A)))
    gains = np.sort(np.abs(np.linalg.eigvals(small)))[::-1]
    assert gains[0] == pytest.approx(1 - 1 / lam_u**2, abs=1e-4)
    assert gains[1] < 1e-2
    np.testing.assert_allclose(large, np.eye(4), atol=1e-3)  # trusts the observation
    np.testing.assert_array_equal(br.kalman_gain(A, np.zeros(4), 1.0), np.eye(4))


@pytest.fixture(scope="module")
def k1_runner():
    task = make_task("cartpole_swingup", preset="thesis", k=1.0)
    A, B = br.linearise(task.simulator)
    K = br.lqr_gain(A, B, (1, 0.1, 0, 1), 1e-2)
    var = np.asarray(task.simulator.obs_noise_std) ** 2
    run, _ = br.make_runner(task, task.problem.horizon, 0)
    keys = jax.random.split(jax.random.PRNGKey(1), 64)

    def rate(L):
        flags = run(keys, jnp.asarray(K), jnp.asarray(L), jnp.asarray(A), jnp.asarray(B))
        return float(np.mean(np.asarray(flags)))

    return rate, A, var


def test_feedback_on_the_observation_or_the_estimate_balances_and_the_model_alone_does_not(k1_runner):
    """At k = 1 (noise std 1°, 10°/s) the static controller (estimate = observation, L = I) and the
    Kalman-filtered one both hold the pole from upright; L = 0 ignores every observation after the
    first, and with an unstable pole it must lose balance (guards the estimate update's sign and form)."""
    rate, A, var = k1_runner
    assert rate(np.eye(4)) > 0.9
    assert rate(br.kalman_gain(A, var, 1e-2)) > 0.9
    assert rate(np.zeros((4, 4))) < 0.5
