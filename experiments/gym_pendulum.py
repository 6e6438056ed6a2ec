"""Pendulum-v1 swing-up learned by pipps, with the gymnasium environment itself as the true system.

The environment is stepped with its own ``reset(seed=…)`` and ``step`` (``pipps.tasks.from_gymnasium``);
pipps adds a cost, a success criterion and the map from its observation into the model state the
GP learns. Results and the commands in docs/experiments.md ("Your own task, and gymnasium
environments as the true system")::

    pipps sweep --task experiments.gym_pendulum:pendulum --preset quick --seeds 5 --jobs 1 --out runs/gym-pendulum
    pipps table runs/gym-pendulum --preset quick --per-seed

(run from the repository's root, whose ``experiments`` folder then imports as a namespace package).

* **Observation and model state.** Pendulum-v1 observes ``[cos θ, sin θ, θ̇]`` with θ = 0 upright;
  the model state is ``[θ, θ̇]``, θ read back with ``arctan2`` (so it wraps at ±π: ``periodic``
  wraps its one-step differences too) and fed to the GP and the policy as ``sin θ, cos θ``.
* **Control.** The environment's 0.05 s step held for two steps: a control interval of 0.1 s,
  30 of them (3 s) per episode, within its 200-step time limit. The torque is the action
  space's ±2 N m, too weak to lift the pendulum from below without swinging it.
* **Start.** The environment's own: θ ~ U[−π, π], θ̇ ~ U[−1, 1]; the planning start distribution
  is its moments (``start_samples`` seeded resets).
* **Cost.** ``1 − exp(−(1 − cos θ)/2)`` (a saturating quadratic in ``sin θ, cos θ``), 0 upright;
  its Gaussian expectation is closed-form, so PILCO can plan on it too.
* **Success.** An evaluation rollout succeeds when ``cos θ ≥ cos 0.5`` (within 0.5 rad of upright)
  in each observation of its last second (10 intervals); an experiment, when half of its final
  trial's evaluation rollouts do. Swinging up from the bottom takes most of the 3 s at this
  torque, so the rule asks for the pendulum to be up and held at the end, from any start.
"""

import jax.numpy as jnp
import numpy as np

from pipps.costs import SaturatingCost
from pipps.tasks import Success, from_gymnasium


def to_model(observation):
    """``[cos θ, sin θ, θ̇]`` -> ``[θ, θ̇]``, θ in (−π, π]."""
    return jnp.stack([jnp.arctan2(observation[1], observation[0]), observation[2]])


def upright(states, valid):
    """Per rollout: within 0.5 rad of upright in each of the last 10 observations (1 s)."""
    del valid
    return jnp.all(states[..., -10:, 0] >= jnp.cos(0.5), axis=-1)


#: on the features [θ, θ̇, sin θ, cos θ]: ½·0.5·(sin² θ + (cos θ − 1)²) = (1 − cos θ)/2
cost = SaturatingCost(W=np.diag([0.0, 0.0, 0.5, 0.5]), target=[0.0, 0.0, 0.0, 1.0], angle_idx=(0,))

pendulum = from_gymnasium(
    "Pendulum-v1", name="gym_pendulum", cost=cost, horizon=30, action_repeat=2,
    to_model=to_model, angle_idx=(0,), periodic=(0,), gp_input_idx=(1, 2, 3), policy_input_idx=(1, 2, 3),
    success=Success("upright", upright, fraction=0.5,
                    reason="Pendulum-v1 is a swing-up: up, and held there, at the end of the episode"),
)
