"""Rollouts on the true (simulated) system, as pure JAX, as PILCO's ``base/rollout.m`` does them.

One ``lax.scan`` over the horizon; vmap :func:`rollout` over keys for the evaluation
rollouts. The gymnasium environments in :mod:`pipps.tasks.envs` expose the same
system step by step for external use; the learning code uses this function because
it runs a whole trajectory in one compiled call.

A rollout takes a :class:`~pipps.tasks.base.Task`: its simulator integrates, observes and maps
into the model state; its problem gives the horizon, the cost and the policy input.

A true system JAX cannot trace (a :class:`~pipps.tasks.base.HostSimulator`: a gymnasium
environment, a robot) is stepped from Python by :func:`host_rollout`, with the same keys, noise,
random actions and records as :func:`rollout`; only the policy and the cost are compiled.
:func:`rollout` hands such a task to it (outside ``jit``), and :func:`rollouts` runs one episode
per key either way.
"""

from __future__ import annotations

import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from pipps.policies import check_policy
from pipps.precision import require_float64
from pipps.tasks.base import Simulator, Task


class Trajectory(NamedTuple):
    """One rollout. Transition ``t`` goes from ``states[t]`` to ``states[t+1]`` under ``actions[t]``."""

    states: jax.Array  # (H+1, sim_dim) true simulator states s_0..s_H
    observations: jax.Array  # (H+1, sim_dim) noisy observations o_t = s_t + ε_t
    actions: jax.Array  # (H, F)
    costs: jax.Array  # (H,) c(x(s_{t+1})) on the noise-free next state, 0 where not valid
    valid: jax.Array  # (H,) bool: the transition happened (unicycle: before the fall)

    @property
    def total_cost(self) -> jax.Array:
        """The return reported in the thesis' tables: the summed cost of the valid transitions."""
        return jnp.sum(jnp.where(self.valid, self.costs, 0.0), axis=-1)


def sample_initial_state(key: jax.Array, simulator: Simulator) -> jax.Array:
    """s_0 ~ N(μ0, Σ0) in simulator coordinates."""
    return jax.random.multivariate_normal(
        key, jnp.asarray(simulator.init_mean), jnp.asarray(simulator.init_cov), method="svd"
    )


def rollout(
    key: jax.Array,
    task: Task,
    policy: Callable[[jax.Array], jax.Array] | None = None,
    *,
    horizon: int | None = None,
) -> Trajectory:
    """Run one episode on the true system: observe with noise, act, integrate one interval, repeat.

    ``policy`` maps the policy input ``x̃^o[P]`` (built from the *noisy* observation) to the
    control; ``None`` draws i.i.d. random actions ``U[-u_rand, u_rand]`` (no squashing).
    After the unicycle falls, the remaining transitions are marked invalid and their
    costs are 0; the state is frozen so that nothing downstream sees a blown-up value. For a
    task with a fall condition, a non-finite next state counts as a fall as well.
    """
    require_float64("pipps.rollout.rollout")
    if task.host_stepped:
        if isinstance(key, jax.core.Tracer):
            raise TypeError(f"{task.simulator.name}: a host-stepped true system cannot be traced (jit, vmap); "
                            "call rollout() or host_rollout() outside them")
        return host_rollout(key, task, policy, horizon=horizon)  # it checks the policy itself
    if policy is not None:
        check_policy(policy, task.problem.policy_input_dim, task.problem.action_dim)
    sim, problem = task.simulator, task.problem
    H = problem.horizon if horizon is None else int(horizon)
    k0, k_obs, k_act = jax.random.split(key, 3)
    s0 = sample_initial_state(k0, sim)
    noise_std = jnp.asarray(sim.obs_noise_std)
    obs_noise = noise_std * jax.random.normal(k_obs, (H + 1, sim.sim_dim))
    u_rand = jnp.asarray(sim.u_rand)
    rand_u = jax.random.uniform(k_act, (H, problem.action_dim), minval=-u_rand, maxval=u_rand)

    def step(carry, inp):
        s, alive = carry
        eps, u_random = inp
        o = s + eps
        if policy is None:
            u = u_random
        else:
            u = policy(problem.policy_input(sim.sim_to_model(o)))
        s_next = sim.step(s, u)
        if sim.fallen is not None:
            # a state the integrator could not carry (non-finite, deep in a fall) ends the episode too
            fell = sim.fallen(s_next) | ~jnp.all(jnp.isfinite(s_next))
        else:
            fell = jnp.asarray(False)
        valid = alive & ~fell
        c = jnp.where(valid, problem.cost(sim.sim_to_model(s_next)), 0.0)
        s_keep = jnp.where(valid, s_next, s)
        return (s_keep, valid), (s_keep, o, u, c, valid)

    (s_last, _), (states, obs, actions, costs, valid) = jax.lax.scan(
        step, (s0, jnp.asarray(True)), (obs_noise[:H], rand_u)
    )
    states = jnp.concatenate([s0[None], states], axis=0)
    obs = jnp.concatenate([obs, (s_last + obs_noise[H])[None]], axis=0)
    return Trajectory(states, obs, actions, costs, valid)


def training_pairs(task: Task, traj: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """GP training data of one trajectory: inputs ``[x̃^o_t[I]; u_t]``, targets ``x^o_{t+1} − x^o_t``.

    Only valid transitions are returned (host-side arrays; the data set grows on the host). The
    simulator's ``periodic`` components (angles ``sim_to_model`` returns wrapped) have their
    differences wrapped into [−π, π), so crossing ±π is a small step, not a jump of 2π.
    """
    x_obs = jax.vmap(task.simulator.sim_to_model)(traj.observations)
    inputs = jax.vmap(task.problem.gp_input)(x_obs[:-1], traj.actions)
    targets = x_obs[1:] - x_obs[:-1]
    if task.simulator.periodic:
        idx = jnp.asarray(task.simulator.periodic)
        targets = targets.at[:, idx].set(jnp.mod(targets[:, idx] + jnp.pi, 2 * jnp.pi) - jnp.pi)
    keep = np.asarray(traj.valid)
    return np.asarray(inputs)[keep], np.asarray(targets)[keep]


# -- a true system stepped from Python ------------------------------------------------------------------


@functools.partial(jax.jit, static_argnums=(0, 1))
def _act(problem, sim_to_model, policy, observation):
    """The control the policy applies to one observation (compiled once per problem and policy shape)."""
    return policy(problem.policy_input(sim_to_model(observation)))


@functools.partial(jax.jit, static_argnums=(0, 1))
def _costs(problem, sim_to_model, states, valid):
    """c(x(s_{t+1})) of every transition, 0 where not valid."""
    return jnp.where(valid, jax.vmap(lambda s: problem.cost(sim_to_model(s)))(states[1:]), 0.0)


@functools.partial(jax.jit, static_argnums=(1, 2, 3))
def _draws(key, horizon: int, sim_dim: int, action_dim: int, noise_std, u_rand):
    """What :func:`rollout` draws from ``key``: the reset seed (in place of s_0), observation noise, random actions."""
    k0, k_obs, k_act = jax.random.split(key, 3)
    seed = jax.random.randint(k0, (), 0, 2**31 - 1)
    obs_noise = noise_std * jax.random.normal(k_obs, (horizon + 1, sim_dim))
    rand_u = jax.random.uniform(k_act, (horizon, action_dim), minval=-u_rand, maxval=u_rand)
    return seed, obs_noise, rand_u


def host_rollout(key: jax.Array, task: Task, policy: Callable[[jax.Array], jax.Array] | None = None, *,
                 horizon: int | None = None) -> Trajectory:
    """One episode of a host-stepped true system (a :class:`~pipps.tasks.base.HostSimulator`), as
    :func:`rollout` runs one of a simulated system: the same splits of ``key`` (the first seeds the
    system's own ``reset`` instead of drawing s_0), the same observation noise and random actions,
    the same record. After the system ends an episode (a fall) it is not stepped again: the rest
    of the transitions are invalid, their costs 0 and the state frozen. Not jittable (it calls
    Python); the policy and the cost are compiled once per task and policy shape.
    """
    require_float64("pipps.rollout.host_rollout")
    sim, problem = task.simulator, task.problem
    if policy is not None:
        check_policy(policy, problem.policy_input_dim, problem.action_dim)
    H = problem.horizon if horizon is None else int(horizon)
    seed, obs_noise, rand_u = jax.device_get(_draws(key, H, sim.sim_dim, problem.action_dim,
                                                    jnp.asarray(sim.obs_noise_std), jnp.asarray(sim.u_rand)))
    system = sim.system()
    s = np.asarray(system.reset(int(seed)), dtype=np.float64)
    states, obs, actions, valid = [s], [], [], []
    alive = True
    for t in range(H):
        o = s + obs_noise[t]
        u = rand_u[t] if policy is None else np.asarray(_act(problem, sim.sim_to_model, policy, jnp.asarray(o)))
        ok = False
        if alive:
            s_next, ended = system.step(u)
            s_next = np.asarray(s_next, dtype=np.float64)
            ok = not ended and bool(np.all(np.isfinite(s_next)))
            alive = not ended
            if ok:
                s = s_next
        obs.append(o)
        actions.append(np.asarray(u, dtype=np.float64))
        valid.append(ok)
        states.append(s)
    obs.append(s + obs_noise[H])
    states, valid = np.stack(states), np.asarray(valid)
    costs = _costs(problem, sim.sim_to_model, jnp.asarray(states), jnp.asarray(valid))
    return Trajectory(jnp.asarray(states), jnp.asarray(np.stack(obs)), jnp.asarray(np.stack(actions)), costs,
                      jnp.asarray(valid))


def rollouts(keys: jax.Array, task: Task, policy: Callable[[jax.Array], jax.Array] | None = None) -> Trajectory:
    """One rollout per key, stacked on a leading axis: ``vmap`` of :func:`rollout` (pure, jittable),
    or, for a host-stepped system, :func:`host_rollout` key by key."""
    if not task.host_stepped:
        return jax.vmap(lambda k: rollout(k, task, policy))(keys)
    trajs = [host_rollout(k, task, policy) for k in keys]
    return Trajectory(*(jnp.stack(parts) for parts in zip(*trajs)))
