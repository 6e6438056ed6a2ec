"""A task of your own through the whole loop, and a gymnasium environment as the true system.

* A task defined in a module outside the package (written to a temporary folder, found from the
  current directory as ``MODULE:ATTRIBUTE``) runs through ``pipps run``, an interrupted run
  resumes to the uninterrupted one bit for bit, ``pipps table`` tabulates it in its own table,
  ``pipps plot`` draws every figure of it; without the module, resuming and tabulating fail with
  one line that names the task and where it was looked for, and ``--task`` says where it is now.
* :func:`pipps.tasks.from_gymnasium`: the rollout a task records is the environment's own stepping
  (replayed with ``reset(seed)`` and the recorded actions, equal to the last bit), a termination is
  a fall, a wrapped angle's GP targets are wrapped, and the learning loop runs on it.
"""

from __future__ import annotations

import sys

import gymnasium
import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pipps.tasks as T
from pipps import cli
from pipps.costs import SaturatingCost
from pipps.experiments import resolve_config, run_experiment
from pipps.experiments.records import ExperimentResult
from pipps.experiments.results import read_result, write_result
from pipps.rollout import Trajectory, rollout, training_pairs
from pipps.tasks import registry

MODULE = '''
"""A small pendulum: a task of your own (tests/test_user_tasks.py)."""
import jax.numpy as jnp
import numpy as np

from pipps.costs import SaturatingCost
from pipps.tasks import Problem, Simulator, Success, Task, TaskSpec


def ode(s, u):
    return jnp.stack([u[0] - 0.1 * s[0] - 9.81 * jnp.sin(s[1]), s[0]])


def upright(states, valid):
    return jnp.all(jnp.cos(states[..., -3:, 1]) <= -0.9, axis=-1)


cost = SaturatingCost(W=np.diag([0.0, 0.0, 4.0, 4.0]), target=[0.0, np.pi, 0.0, -1.0], angle_idx=(1,))
problem = Problem(name="tinypend", dt=0.1, horizon=8, u_max=[2.5], model_init_mean=[0.0, 0.0],
                  model_init_cov=np.eye(2) * 0.01, cost=cost, angle_idx=(1,), gp_input_idx=(0, 2, 3),
                  policy_input_idx=(0, 2, 3))
simulator = Simulator(name="tinypend", dt=0.1, ode=ode, init_mean=[0.0, 0.0], init_cov=np.eye(2) * 0.01,
                      obs_noise_std=0.01)
tinypend = TaskSpec(Task(problem, simulator), Success("upright", upright, fraction=0.5, reason="held up"))
'''
TINY = ["num_learned=2", "policy_evals=4", "progress_chunk=2", "eval_rollouts=3",
        "gp_max_iters=10", "store_particles=4"]


@pytest.fixture
def own_task(tmp_path, monkeypatch):
    """The module in a folder of its own, the current directory; the registry and sys.path restored after."""
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "tinypend_task.py").write_text(MODULE)
    monkeypatch.chdir(folder)
    monkeypatch.setattr(sys, "path", list(sys.path))  # pipps' main appends the current directory
    before = dict(registry._REGISTERED)
    yield folder
    registry._REGISTERED.clear()
    registry._REGISTERED.update(before)
    sys.modules.pop("tinypend_task", None)
    sys.modules.pop("tinypend_moved", None)


def _main(capsys, *argv) -> tuple[int, str, str]:
    code = cli.main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def _forget(monkeypatch, folder):
    """As in a new process without the module: not registered, not imported, not on the path."""
    registry.unregister("tinypend")
    sys.modules.pop("tinypend_task", None)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in (str(folder), "")])
    monkeypatch.chdir(folder.parent)


def test_a_task_of_your_own_runs_resumes_tabulates_and_plots(own_task, tmp_path, monkeypatch, capsys):
    runs, resumed = tmp_path / "runs", tmp_path / "resumed"
    sets = [a for s in TINY for a in ("--set", s)]
    code, out, err = _main(capsys, "run", "--task", "tinypend_task:tinypend", "--preset", "quick", "--particles", "8",
                           *sets, "--out", str(runs / "full.h5"), "--quiet")
    assert code == 0, err
    full = read_result(runs / "full.h5")
    assert (full.config.task, full.config.task_source) == ("tinypend", "tinypend_task:tinypend")
    assert len(full.trials) == 3 and full.trials[-1].eval_balanced is not None
    with h5py.File(runs / "full.h5") as f:
        assert f["config"].attrs["task_source"] == "tinypend_task:tinypend"
        assert "return_success" not in f.attrs  # the task has no return threshold

    # an interrupted run resumes to the uninterrupted one, bit for bit
    part = ExperimentResult(full.config, full.trials[:2], "interrupted", "KeyboardInterrupt: ", 1.0)
    write_result(resumed / "part.h5", part)
    code, out, err = _main(capsys, "run", "--resume", "--out", str(resumed / "part.h5"), "--quiet")
    assert code == 0, err
    again = read_result(resumed / "part.h5")
    assert again.resumed_at == [2]
    for a, b in zip(full.trials, again.trials, strict=True):
        for name in ("states", "observations", "actions", "eval_returns", "eval_balanced", "policy"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name

    # its own table: methods against k, the physical readings only (no return threshold)
    code, out, err = _main(capsys, "table", str(runs), "--preset", "quick", "--custom", "--per-seed")
    assert code == 0, err
    assert "**Task tinypend (quick preset) — success rate per method and noise multiplier (no thesis values)**" in out
    assert "| k = 1 | TP |" in out and "per trial, physical" in out and "per trial, return" not in out
    assert "1 complete results of the quick preset" in out

    for figure in ("overview", "curves", "cells", "diagnostics"):
        rrd = tmp_path / f"{figure}.rrd"
        code, out, err = _main(capsys, "plot", str(runs), "--figure", figure, "--preset", "quick", "--custom",
                               "--out", str(rrd))
        assert code == 0 and rrd.stat().st_size > 1000, (figure, err)

    # without the module: one line naming the task and its source; --task says where it is now
    _forget(monkeypatch, own_task)
    for argv in (["table", str(runs)], ["run", "--resume", "--out", str(resumed / "part.h5")]):
        code, out, err = _main(capsys, *argv)
        assert code == 2, argv
        assert len(err.strip().splitlines()) == 1, err
        assert "task 'tinypend': its source tinypend_task:tinypend cannot be loaded here" in err
    moved = tmp_path / "moved"
    moved.mkdir()
    (moved / "tinypend_moved.py").write_text(MODULE)
    monkeypatch.chdir(moved)
    code, out, err = _main(capsys, "table", str(runs), "--preset", "quick", "--custom", "--task",
                           "tinypend_moved:tinypend")
    assert code == 0 and "Task tinypend" in out, err


def test_run_experiment_takes_the_record_itself(own_task):
    sys.path.insert(0, str(own_task))
    import tinypend_task

    cfg = resolve_config("quick", tinypend_task.tinypend, num_learned=1, num_particles=8, policy_evals=2,
                         eval_rollouts=2, gp_max_iters=5, store_particles=2, progress_chunk=2)
    assert cfg.task == "tinypend" and cfg.protocol == "quick"
    result = run_experiment(cfg)
    assert result.status == "complete" and len(result.trials) == 2
    assert result.trials[-1].eval_balanced.shape == (2,)


# == gymnasium ==================================================================================


def _to_model(o):
    """Pendulum-v1's observation [cos θ, sin θ, θ̇] as the model state [θ, θ̇] (θ = 0 upright)."""
    return jnp.stack([jnp.arctan2(o[1], o[0]), o[2]])


def _upright(states, valid):
    return jnp.all(states[..., -3:, 0] >= jnp.cos(0.5), axis=-1)


def _gym_pendulum(**kw):
    cost = SaturatingCost(W=np.diag([0.0, 0.0, 4.0, 4.0]), target=[0.0, 0.0, 0.0, 1.0], angle_idx=(0,))
    args = dict(name="gym_pend_test", cost=cost, success=T.Success("upright", _upright, 0.5), horizon=12,
                to_model=_to_model, angle_idx=(0,), periodic=(0,), gp_input_idx=(1, 2, 3), policy_input_idx=(1, 2, 3),
                start_samples=200)
    args.update(kw)
    return T.from_gymnasium("Pendulum-v1", **args)


def _replay(key, traj, action_repeat: int):
    """The environment's own stepping: reset with the seed the rollout drew, then the recorded actions."""
    seed = int(jax.random.randint(jax.random.split(key, 3)[0], (), 0, 2**31 - 1))
    env = gymnasium.make("Pendulum-v1")
    obs, _ = env.reset(seed=seed)
    states = [obs]
    for u in np.asarray(traj.actions):
        for _ in range(action_repeat):
            obs, *_ = env.step(u.astype(np.float32))
        states.append(obs)
    return np.asarray(states, dtype=np.float64)


@pytest.mark.parametrize("action_repeat", [1, 2])
def test_a_gymnasium_rollout_is_the_environments_own_stepping(action_repeat):
    spec = _gym_pendulum(action_repeat=action_repeat)
    task = spec.make()
    assert task.host_stepped and task.problem.dt == pytest.approx(0.05 * action_repeat)
    assert np.allclose(task.problem.model_init_mean, 0.0, atol=0.3)  # θ ~ U[−π, π], θ̇ ~ U[−1, 1]
    assert np.allclose(np.diag(task.problem.model_init_cov), [np.pi**2 / 3, 1 / 3], rtol=0.25)
    key = jax.random.PRNGKey(3)
    traj = rollout(key, task, None)  # random actions, drawn from the key as a simulated rollout draws them
    assert np.array_equal(np.asarray(traj.states), _replay(key, traj, action_repeat))
    assert np.asarray(traj.valid).all()
    x = jax.vmap(_to_model)(traj.states[1:])
    assert np.allclose(traj.costs, jax.vmap(task.problem.cost)(x), rtol=0, atol=0)
    from pipps.policies import init_linear_policy

    policy = init_linear_policy(jax.random.PRNGKey(1), task.problem.policy_input_dim, task.problem.u_max)
    traj = rollout(key, task, policy)
    want = jax.vmap(lambda o: policy(task.problem.policy_input(_to_model(o))))(traj.observations[:-1])
    assert np.allclose(traj.actions, want, rtol=0, atol=1e-12)
    assert np.array_equal(np.asarray(traj.states), _replay(key, traj, action_repeat))
    with pytest.raises(TypeError, match="cannot be traced"):
        jax.jit(lambda k: rollout(k, task, None).costs)(key)


def test_wrapped_angles_give_small_targets():
    task = _gym_pendulum().make()
    theta = np.array([3.1, -3.1, -3.0])  # across ±π
    obs = np.stack([np.cos(theta), np.sin(theta), np.zeros(3)], axis=1)
    traj = Trajectory(jnp.asarray(obs), jnp.asarray(obs), jnp.zeros((2, 1)), jnp.zeros(2), jnp.ones(2, bool))
    _, targets = training_pairs(task, traj)
    assert np.allclose(targets[:, 0], [2 * np.pi - 6.2, 0.1], atol=1e-12)


class _Drops(gymnasium.Env):
    """Falls (terminates) at its third step."""

    observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (2,), np.float64)
    action_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)
    dt = 0.1

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t, self.s = 0, self.np_random.normal(size=2)
        return self.s.copy(), {}

    def step(self, action):
        self.t += 1
        self.s = self.s + np.array([float(action[0]), 0.1])
        return self.s.copy(), 0.0, self.t >= 3, False, {}


def test_a_termination_is_a_fall():
    cost = lambda x: jnp.sum(x**2)  # noqa: E731  (no Gaussian expectation: PILCO cannot plan on it)
    spec = T.from_gymnasium(_Drops, name="drops_test", cost=cost, horizon=6, start_samples=50,
                            success=T.Success("upright", T.never_fell, 0.5))
    traj = rollout(jax.random.PRNGKey(0), spec.make(), None)
    assert np.asarray(traj.valid).tolist() == [True, True, False, False, False, False]
    states = np.asarray(traj.states)
    assert np.array_equal(states[3:], np.repeat(states[2:3], 4, axis=0))  # frozen after the fall
    assert np.array_equal(np.asarray(traj.costs)[2:], np.zeros(4))
    from pipps.experiments.preflight import check_experiment

    with pytest.raises(ValueError, match="has no Gaussian expectation"):
        check_experiment(resolve_config("quick", spec, method="pilco"))


def test_the_learning_loop_runs_on_a_gymnasium_environment():
    spec = _gym_pendulum(name="gym_pend_loop", horizon=8, action_repeat=2)
    cfg = resolve_config("quick", spec, num_learned=1, num_particles=8, policy_evals=2, progress_chunk=2,
                         eval_rollouts=2, gp_max_iters=5, store_particles=2)
    from pipps.experiments.batched import check_batchable

    with pytest.raises(ValueError, match="stepped from Python"):
        check_batchable([cfg, cfg.replace(seed=1)])
    result = run_experiment(cfg)
    assert result.status == "complete" and len(result.trials) == 2
    trial = result.trials[-1]
    key = __import__("pipps.experiments.state", fromlist=["trial_keys"]).trial_keys(cfg, 1).trial
    assert np.array_equal(trial.states, _replay(key, trial, 2))  # the trial the learner saw is the env's own
    flags = _upright(jnp.asarray(trial.states)[None], jnp.asarray(trial.valid)[None])
    assert trial.eval_balanced.shape == (2,) and flags.shape == (1,)
