"""The small default job until the learning loop exists: a few true-system rollouts with a random policy."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from pipps.policies import init_linear_policy, init_rbf_policy
from pipps.rollout import rollout
from pipps.tasks.presets import make_task


@dataclasses.dataclass(frozen=True)
class RolloutReport:
    task: str
    preset: str
    k: float
    policy: str
    returns: np.ndarray  # (episodes,)
    lengths: np.ndarray  # (episodes,) number of valid transitions


def random_policy_rollouts(
    task_name: str = "cartpole_swingup",
    preset: str = "thesis",
    k: float = 1.0,
    policy: str = "random-actions",
    episodes: int = 3,
    seed: int = 0,
) -> RolloutReport:
    """Roll out ``episodes`` episodes with random actions or a freshly initialised policy."""
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if policy not in ("random-actions", "random-policy"):
        raise ValueError(f"policy must be 'random-actions' or 'random-policy', got {policy!r}")
    task = make_task(task_name, preset=preset, k=k)
    key_pol, key_roll = jax.random.split(jax.random.PRNGKey(seed))
    pol = None
    if policy == "random-policy":
        d = task.problem.policy_input_dim
        if task_name == "unicycle":
            pol = init_linear_policy(key_pol, d, task.problem.u_max)
        else:
            pol = init_rbf_policy(key_pol, 50, np.zeros(d), np.eye(d), task.problem.u_max)
    run = jax.jit(jax.vmap(lambda key: rollout(key, task, pol)))
    trajs = run(jax.random.split(key_roll, episodes))
    return RolloutReport(
        task_name,
        preset,
        k,
        policy,
        np.asarray(trajs.total_cost),
        np.asarray(trajs.valid.sum(axis=-1)),
    )
