"""True-system rollouts: exact agreement with step-by-step simulation, data pairs, falls, CLI."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pipps.cli import main
from pipps.policies import init_linear_policy, init_rbf_policy
from pipps.rollout import rollout, training_pairs
from pipps.tasks.presets import make_task


def test_noise_free_rollout_equals_stepping_the_ode():
    task = make_task("cartpole_swingup", k=0.0)
    traj = jax.jit(lambda key: rollout(key, task))(jax.random.PRNGKey(0))
    s = traj.states[0]
    for t in range(task.horizon):
        s = task.step(s, traj.actions[t])
        np.testing.assert_allclose(np.asarray(traj.states[t + 1]), np.asarray(s), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(traj.observations), np.asarray(traj.states))  # k = 0
    u = np.asarray(traj.actions)
    assert np.all(np.abs(u) <= 10.0) and u.std() > 3.0  # U[-10, 10] random actions, unsquashed
    cost = np.asarray(jax.vmap(task.cost)(jax.vmap(task.sim_to_model)(traj.states[1:])))
    np.testing.assert_allclose(np.asarray(traj.costs), cost, rtol=1e-14)  # cost of the next, true state


def test_policy_sees_the_noisy_observation_and_training_pairs_are_differences():
    task = make_task("cartpole_swingup", preset="pilco", k=4.0)
    pol = init_rbf_policy(jax.random.PRNGKey(1), 10, np.zeros(5), np.eye(5), task.u_max)
    traj = rollout(jax.random.PRNGKey(2), task, pol)
    x_obs = jax.vmap(task.sim_to_model)(traj.observations)
    expected_u = jax.vmap(lambda x: pol(task.policy_input(x)))(x_obs[:-1])
    np.testing.assert_allclose(np.asarray(traj.actions), np.asarray(expected_u), rtol=1e-13)
    noise = np.asarray(traj.observations - traj.states)
    assert np.all(noise.std(axis=0) > 0)  # observations are noisy (k = 4)
    inputs, targets = training_pairs(task, traj)
    assert inputs.shape == (task.horizon, 6) and targets.shape == (task.horizon, 4)
    np.testing.assert_allclose(targets, np.diff(np.asarray(x_obs), axis=0), rtol=1e-14)
    theta = np.asarray(x_obs[:-1, 3])  # pilco preset: GP sees [x, v, ω, sin θ, cos θ, u] of the noisy state
    np.testing.assert_allclose(inputs[:, 3:5], np.stack([np.sin(theta), np.cos(theta)], 1), rtol=1e-14)
    np.testing.assert_allclose(inputs[:, 5], np.asarray(traj.actions[:, 0]))


def test_unicycle_fall_stops_the_trajectory():
    task = make_task("unicycle", k=1.0)
    pol = init_linear_policy(jax.random.PRNGKey(3), 10, task.u_max)
    traj = rollout(jax.random.PRNGKey(4), task, pol)
    valid = np.asarray(traj.valid)
    n = int(valid.sum())
    assert 0 < n < task.horizon  # an untrained policy falls within 2 s
    assert valid[:n].all() and not valid[n:].any()  # once fallen, never valid again
    model_next = jax.vmap(task.sim_to_model)(traj.states[1 : n + 1])
    assert np.all(np.abs(np.asarray(model_next[:, [7, 9]])) <= np.pi / 2)  # valid states are upright
    s_fall = task.step(traj.states[n], traj.actions[n])
    assert bool(task.fallen(s_fall))  # the discarded transition is the one that falls
    assert np.all(np.asarray(traj.costs[n:]) == 0.0)
    inputs, targets = training_pairs(task, traj)
    assert inputs.shape == (n, 11) and targets.shape == (n, 10)  # fallen transition discarded (as PILCO's rollout.m)


def test_cli_rollout_prints_the_library_returns(capsys):
    assert main(["rollout", "--episodes", "2", "--seed", "5"]) == 0
    out = capsys.readouterr().out
    from pipps.demo import random_policy_rollouts

    rep = random_policy_rollouts(episodes=2, seed=5)
    for r in rep.returns:
        assert f"{r:.4f}" in out


@pytest.mark.parametrize(
    "argv, option",
    [(["rollout", "--k", "-1"], "--k"), (["rollout", "--episodes", "0"], "--episodes"), (["rollout", "--preset", "bad"], "--preset")],
)
def test_cli_rejects_bad_values_naming_the_option(argv, option, capsys):
    # argparse rejects a bad number while parsing (SystemExit); a task preset is checked once the
    # task's record is found (a task of your own has its own presets), and main returns the usage code
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    assert code == 2
    assert option in capsys.readouterr().err
