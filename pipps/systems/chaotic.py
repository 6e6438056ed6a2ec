"""A known chaotic system for the gradient-variance studies: the controlled kicked rotor (standard map).

The Chirikov standard map with an additive control kick and small Gaussian process noise,
written as a difference model (like the GP: ``x_{t+1} = x_t + Δ``) on the model state
``x = [θ, p]`` (angle, momentum; the angle raw, not wrapped):

``Δp = K sin θ + b·u``, ``Δθ = p + Δp`` (so ``p' = p + K sin θ + b u``, ``θ' = θ + p'``),
plus ``ε ~ N(0, diag(σ_θ², σ_p²))``.

For ``K ≳ 0.97`` the uncontrolled map has no rotational invariant circles and a connected
chaotic sea; at ``K = 2`` (the chaotic setting) its maximal Lyapunov exponent is about 0.4 per
step. Under the study's weak saturated policy (``|u| ≤ 0.2``) the closed noisy loop has a
finite-time exponent (T = 30) of median ≈ 0.08 with a long upper tail (max ≈ 0.6), and the
products of Jacobians that RP differentiates through are heavy-tailed: RP's gradient variance is
10¹⁰–10¹¹, ten orders of magnitude above LR's (the curse of chaos, thesis §4.2). At ``K = 0.1`` (the
smooth setting) the map is near-integrable (KAM circles; median λ ≈ 0.007) and RP has the lowest
variance. :func:`finite_time_lyapunov` estimates λ per particle.

* :class:`KickedRotorModel` — the model with the particle interface
  (``predict(z, variance) -> (mean, var or None)``, ``noise_variance``; zero epistemic variance).
* :func:`make_kicked_rotor_task` — the :class:`~pipps.tasks.base.Problem` around it (a planning
  problem only, no true system to simulate), the angle fed to the policy as ``(sin θ, cos θ)``, a saturating cost towards the
  unstable fixed point ``θ = 0 (mod 2π), p = 0``.
* :func:`kicked_rotor_system` — the fixed ``(task, model, policy)`` instances of the variance
  study: ``"chaotic"`` and ``"smooth"`` (see :data:`SETTINGS`; docs/estimator-variance.md).

The study's protocol (R independent estimates per estimator on common random numbers) and its
statistics are in :mod:`pipps.stats` (:func:`~pipps.stats.paired_replicate_gradients`).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax.tree_util import register_dataclass

from pipps.costs import SaturatingCost
from pipps.particles.forward import RolloutConfig, sample_noise
from pipps.policies import LinearPolicy
from pipps.systems.linear_gaussian import frozen
from pipps.tasks.base import Problem


@register_dataclass
@dataclasses.dataclass(frozen=True)
class KickedRotorModel:
    """Controlled standard map in difference form (a pytree).

    The model input is ``z = [θ, p, u]`` (the task's ``gp_input``).

    Attributes:
      kick: K, the kick strength (scalar).
      control_gain: b, the control's share of the kick (scalar).
      noise_var: (2,) variances of the process noise on (θ, p) (the analogue of the GP's σ_n²).
    """

    kick: jax.Array
    control_gain: jax.Array
    noise_var: jax.Array

    @property
    def noise_variance(self) -> jax.Array:
        """(2,) per-output noise variance, as :attr:`pipps.gp.GPPosterior.noise_variance`."""
        return self.noise_var

    def predict(self, z: jax.Array, variance: bool = False):
        """Difference mean ``[p + Δp, Δp]`` with ``Δp = K sin θ + b u`` (P, 2); zero epistemic variance."""
        theta, p, u = z[:, 0], z[:, 1], z[:, 2]
        dp = self.kick * jnp.sin(theta) + self.control_gain * u
        mean = jnp.stack([p + dp, dp], axis=-1)
        return mean, (jnp.zeros_like(mean) if variance else None)


def make_kicked_rotor_task(
    *,
    horizon: int = 30,
    init_mean=(0.5, 0.0),
    init_std=(0.05, 0.05),
    cost_width: float = 1.0,
    u_max: float = 0.2,
    name: str = "kicked_rotor",
) -> Problem:
    """The :class:`Problem` of the kicked rotor on the model state ``x = [θ, p]``.

    * ``angle_idx = (0,)``: ``x̃ = [θ, p, sin θ, cos θ]``; the model gets the raw ``[θ, p]``
      (:class:`KickedRotorModel` takes the sine itself), the policy ``[p, sin θ, cos θ]``.
    * cost ``1 − exp(−½ (φ − z)ᵀ W (φ − z))`` on ``φ = [θ, p, sin θ, cos θ]`` with
      ``W = diag(0, 1, 1, 1)/cost_width²`` and target ``[0, 0, 0, 1]``, i.e.
      ``1 − exp(−(p²/2 + 1 − cos θ)/cost_width²)``: saturating, periodic in θ, lowest at the
      hyperbolic fixed point ``θ = 0, p = 0``.
    * start ``N(init_mean, diag(init_std²))``; ``u_max`` the control limit of saturated policies.
    """
    if int(horizon) < 1:
        raise ValueError(f"horizon must be >= 1, got {horizon}")
    if not cost_width > 0 or not u_max > 0:
        raise ValueError(f"cost_width and u_max must be > 0, got {cost_width}, {u_max}")
    mean = frozen(init_mean, (2,), "init_mean")
    std = frozen(init_std, (2,), "init_std")
    cov = frozen(np.diag(std**2), (2, 2), "init_cov")
    umax = frozen([u_max], (1,), "u_max")
    cost = SaturatingCost(
        W=np.diag([0.0, 1.0, 1.0, 1.0]) / cost_width**2, target=np.array([0.0, 0.0, 0.0, 1.0]), angle_idx=(0,)
    )
    return Problem(
        name=name,
        model_dim=2,
        action_dim=1,
        dt=1.0,
        horizon=int(horizon),
        u_max=umax,
        model_init_mean=mean,
        model_init_cov=cov,
        angle_idx=(0,),
        gp_input_idx=(0, 1),
        policy_input_idx=(1, 2, 3),
        cost=cost,
    )



# The two settings of the variance study (docs/estimator-variance.md): the same task, policy and
# noise; only the kick strength K differs.
SETTINGS = {
    "chaotic": dict(kick=2.0, horizon=30),
    "smooth": dict(kick=0.1, horizon=30),
}
NOISE_STD = 0.05  # process-noise standard deviation on θ and p


def kicked_rotor_system(setting: str = "chaotic", *, horizon: int | None = None):
    """The fixed ``(task, model, policy)`` of the variance study for a named setting of :data:`SETTINGS`.

    Start ``N([0.5, 0], 0.05²I)``, noise std :data:`NOISE_STD` on both components, control gain 1,
    ``u_max = 0.2``, and the saturated :class:`~pipps.policies.LinearPolicy`
    ``u = u_max·sat(W [p, sin θ, cos θ] + b)`` with fixed ``W = [−0.3, −0.4, 0.1]``, ``b = 0.05``
    (4 parameters, all with a nonzero gradient). ``horizon`` overrides the setting's T.
    """
    if setting not in SETTINGS:
        raise ValueError(f"unknown setting {setting!r}; choose one of {tuple(SETTINGS)}")
    s = SETTINGS[setting]
    task = make_kicked_rotor_task(horizon=s["horizon"] if horizon is None else horizon, name=f"kicked_rotor_{setting}")
    model = KickedRotorModel(jnp.asarray(s["kick"]), jnp.asarray(1.0), jnp.full((2,), NOISE_STD**2))
    policy = LinearPolicy(jnp.array([[-0.3, -0.4, 0.1]]), jnp.array([0.05]), (float(task.u_max[0]),), saturated=True)
    return task, model, policy


def finite_time_lyapunov(key: jax.Array, task: Problem, model, policy, *, num_particles: int = 256, horizon: int | None = None) -> jax.Array:
    """(P,) finite-time maximal Lyapunov exponents (per step) of the closed, noisy loop.

    For each particle a tangent vector is pushed through the total Jacobian ``dx_{t+1}/dx_t``
    (model and policy, the noise ``ε`` held fixed — the Jacobian chain RP differentiates through)
    and renormalised every step: ``λ_i = (1/T) Σ_t log ‖J_{i,t} v_{i,t}‖``.
    """
    T = task.horizon if horizon is None else int(horizon)
    noise = sample_noise(key, task, RolloutConfig(num_particles=num_particles, horizon=T))
    std = jnp.sqrt(model.noise_variance)

    def f(x, eps):
        u = policy(task.policy_input(x))
        mean, _ = model.predict(task.gp_input(x, u)[None], variance=False)
        return x + mean[0] + std * eps

    def one(x0, eps_seq):
        def body(carry, eps):
            x, v = carry
            x_next, jv = jax.jvp(lambda y: f(y, eps), (x,), (v,))
            n = jnp.linalg.norm(jv)
            return (x_next, jv / n), jnp.log(n)

        v0 = jnp.ones_like(x0) / jnp.sqrt(x0.shape[0])
        _, logs = jax.lax.scan(body, (x0, v0), eps_seq)
        return jnp.mean(logs)

    return jax.vmap(one, in_axes=(0, 1))(noise.x0, noise.eps)
