"""MuJoCo's InvertedDoublePendulum-v5 balanced by pipps, with the gymnasium environment itself as the true system.

Needs ``pip install "mujoco>=3" imageio`` (gymnasium's MuJoCo environments). Run from the
repository's root (its ``experiments`` folder imports as a namespace package)::

    pipps sweep --task experiments.gym_double_pendulum:double_pendulum --preset quick --methods tp,pilco \
        --seeds 5 --jobs 1 --out runs/gym-double-pendulum
    pipps table runs/gym-double-pendulum --preset quick --per-seed

* **Observation and model state.** The environment observes ``[x, sin θ₁, sin θ₂, cos θ₁, cos θ₂,
  ẋ, θ̇₁, θ̇₂, f]`` (cart position, the two poles' angles from upright, θ₂ relative to the first pole,
  velocities, a constraint force that is always 0 in v5). The model state is ``[x, θ₁, θ₂, ẋ, θ̇₁,
  θ̇₂]``, the angles read back with ``arctan2``. Balancing keeps the angles small (the environment
  ends an episode when the tip drops below y = 1, about 0.5 rad of summed tilt), so they are fed to
  the GP and the policy as they are, without sin/cos features.
* **Control.** The environment's own 0.05 s step, one per control interval; 40 intervals (2 s),
  within its 1000-step limit. The action is the cart force's ±1 (scaled by the model's gear).
* **Start.** The environment's own: the upright pose plus U(−0.1, 0.1) on the positions and
  N(0, 0.1²) on the velocities; the planning start distribution is its moments.
* **Cost.** ``1 − exp(−½ (s − 0)ᵀ W (s − 0))`` with W penalising the cart's offset and both tilts
  (``W = diag(0.5, 20, 20, 0.05, 0.05, 0.05)``); its Gaussian expectation is closed-form, so PILCO
  plans on it too.
* **Success.** A rollout succeeds when the environment never ended it (every transition valid:
  the tip stayed up for the 2 s), an experiment when half its final evaluation rollouts do.
  Random actions fall within about 0.2–0.35 s (4–7 steps).
* **Policy.** Linear (balancing near an equilibrium), as the thesis' unicycle uses.
"""

import jax.numpy as jnp
import numpy as np

from pipps.costs import SaturatingCost
from pipps.tasks import PlotInfo, Success, from_gymnasium, never_fell


def to_model(observation):
    """The 9 observations -> ``[x, θ₁, θ₂, ẋ, θ̇₁, θ̇₂]``."""
    o = observation
    return jnp.stack([o[0], jnp.arctan2(o[1], o[3]), jnp.arctan2(o[2], o[4]), o[5], o[6], o[7]])


cost = SaturatingCost(W=np.diag([0.5, 20.0, 20.0, 0.05, 0.05, 0.05]), target=np.zeros(6))

double_pendulum = from_gymnasium(
    "InvertedDoublePendulum-v5", name="gym_double_pendulum", cost=cost, horizon=40, to_model=to_model,
    success=Success("balanced", never_fell, fraction=0.5,
                    reason="the environment never ended the episode: both poles stayed up for the 2 s"),
    plot=PlotInfo(state_labels=("x (m)", "θ1 (rad)", "θ2 (rad)", "ẋ (m/s)", "θ̇1 (rad/s)", "θ̇2 (rad/s)"), panel=1),
    settings={"quick": {"policy": "linear"}, "thesis": {"policy": "linear"}},
)
