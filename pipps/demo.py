"""The small default job until the learning loop exists: a few true-system rollouts with a random policy."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from pipps.policies import init_linear_policy, init_rbf_policy
from pipps.rollout import rollout, rollouts
from pipps.tasks.registry import get_task


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
    """Roll out ``episodes`` episodes with random actions or a freshly initialised policy: a linear
    one where the task's thesis-preset experiments learn one (the unicycle), else an RBF policy.
    ``task_name``: a task's name or ``module:attribute`` (:func:`pipps.tasks.get_task`)."""
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if policy not in ("random-actions", "random-policy"):
        raise ValueError(f"policy must be 'random-actions' or 'random-policy', got {policy!r}")
    spec = get_task(task_name)
    task = spec.make(preset, k)
    key_pol, key_roll = jax.random.split(jax.random.PRNGKey(seed))
    pol = None
    if policy == "random-policy":
        d = task.problem.policy_input_dim
        if spec.experiment_settings("thesis").get("policy") == "linear":
            pol = init_linear_policy(key_pol, d, task.problem.u_max)
        else:
            pol = init_rbf_policy(key_pol, 50, np.zeros(d), np.eye(d), task.problem.u_max)
    keys = jax.random.split(key_roll, episodes)
    if task.host_stepped:
        trajs = rollouts(keys, task, pol)
    else:
        trajs = jax.jit(jax.vmap(lambda key: rollout(key, task, pol)))(keys)
    return RolloutReport(
        spec.name,
        preset,
        k,
        policy,
        np.asarray(trajs.total_cost),
        np.asarray(trajs.valid.sum(axis=-1)),
    )
