"""Particle predictions through the learned model (thesis Algorithm 3; GR, thesis §4.3.1), and
through a known simulator with noise on the actions (:mod:`pipps.particles.simulator`).

Where the noise enters is a setting of :class:`RolloutConfig`: on the state (the thesis: the model's
Gaussian over the next state, below) or, with ``action_noise``, on the actions
(``u = π(x̃[P]) + σ_u w``, Suh et al.'s setting; the model is then a known simulator
``x' = step(x, u)``). :func:`particle_rollout` and :func:`sample_noise` serve both.

P particles through T steps of policy → model → sample, as one ``lax.scan`` over time with
the particles vectorised. Step ``t`` (0-based, ``t = 0..T−1``) maps ``x_t`` to

* the control ``u_t = π(x̃_t[P])`` and the model input ``z_t = [x̃_t[I]; u_t]``,
* the distribution parameters ``ζ_{t+1} = (μ_{t+1}, s_{t+1})`` with
  ``μ = x_t + m_Δ(z_t)`` and ``s² = v_f(z_t)·[model_variance] + σ_n²·noise_multiplier``,
* the next particles ``x_{t+1} = μ + s ⊙ ε_{t+1}`` — or, with Gaussian resampling (GR),
  ``x_{t+1} = μ̂ + L ε_{t+1}`` with ``(μ̂, LLᵀ)`` the moments of the Gaussian mixture —
* and the cost ``c(x_{t+1})``. The objective is ``J = Σ_{t=1..T} (1/P) Σ_i c(x_{i,t})``.

The record keeps what the backward sweep needs, indexed by the step that produced it:
``x[t] = x_t``, ``mean[t], std[t] = ζ_{t+1}``, ``eps[t] = ε_{t+1}``, ``x_next[t] = x_{t+1}``,
``cost[t] = c(x_{t+1})`` and the model Jacobians ``∂μ/∂z, ∂s/∂z`` at ``z_t``.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from pipps.particles.models import PRECISIONS, model_output, noise_variance
from pipps.policies import check_policy
from pipps.tasks.base import Problem

RESAMPLING = ("none", "gaussian")


@dataclasses.dataclass(frozen=True)
class RolloutConfig:
    """Static settings of the particle rollout (a jit static argument).

    Attributes:
      num_particles: P.
      horizon: T; None uses the task's horizon.
      model_variance: include the GP's epistemic variance v_f; False is the ``−σ_f``
        variant and then no GP variance is computed at all.
      noise_multiplier: factor on σ_n² (the ``+σ_n`` variant: 100 for TP, 25 for GTP).
      resampling: "none" or "gaussian" (GR, thesis §4.3.1).
      resample_jitter: added to the diagonal of the GR covariance before its Cholesky.
      variance_precision: "float64" or "float32", the precision of the GP variance's
        O(P·E·M²) product (:func:`pipps.particles.models.model_output`).
      action_noise: None (the thesis: the noise is the model's, on the state), or σ_u > 0, one
        number or one per action component: the actions are ``u = π(x̃[P]) + σ_u ⊙ w``,
        ``w ~ N(0, I)``, and the model is a known simulator (:mod:`pipps.particles.simulator`).
      state_noise: with ``action_noise``, the standard deviation of Gaussian noise added to the
        simulator's next state (0: none; one number or one per state component). A GP model's
        state noise is its own σ_n (scaled by ``noise_multiplier``), so it takes no state_noise.
    """

    num_particles: int = 300
    horizon: int | None = None
    model_variance: bool = True
    noise_multiplier: float = 1.0
    resampling: str = "none"
    resample_jitter: float = 1e-10
    variance_precision: str = "float64"
    action_noise: float | tuple[float, ...] | None = None
    state_noise: float | tuple[float, ...] = 0.0

    def __post_init__(self):
        if int(self.num_particles) < 2:
            raise ValueError(f"num_particles must be >= 2, got {self.num_particles}")
        if self.horizon is not None and int(self.horizon) < 1:
            raise ValueError(f"horizon must be >= 1, got {self.horizon}")
        if not (self.noise_multiplier > 0 and jnp.isfinite(self.noise_multiplier)):
            raise ValueError(f"noise_multiplier must be positive and finite, got {self.noise_multiplier}")
        if self.resampling not in RESAMPLING:
            raise ValueError(f"resampling must be one of {RESAMPLING}, got {self.resampling!r}")
        if self.variance_precision not in PRECISIONS:
            raise ValueError(f"variance_precision must be one of {PRECISIONS}, got {self.variance_precision!r}")
        if self.action_noise is not None:
            object.__setattr__(self, "action_noise", _stds("action_noise", self.action_noise, positive=True))
            if self.resampling != "none":
                raise ValueError("resampling refits the state particles of a model's Gaussian; with action_noise the "
                                 "state is the simulator's, so resampling must be 'none'")
        object.__setattr__(self, "state_noise", _stds("state_noise", self.state_noise, positive=False))
        if self.action_noise is None and any(self.state_noise):
            raise ValueError("state_noise is the known simulator's (with action_noise); a model's state noise is its "
                             "own sigma_n, scaled by noise_multiplier")

    @property
    def noise_on_actions(self) -> bool:
        """The noise enters at the actions (a known simulator), not at the model's next state."""
        return self.action_noise is not None

    def steps(self, task: Problem) -> int:
        return task.horizon if self.horizon is None else int(self.horizon)


def _stds(name: str, value, *, positive: bool) -> tuple[float, ...]:
    """Standard deviations as a tuple of floats (hashable: the configuration is a jit static argument)."""
    values = tuple(float(v) for v in (value if isinstance(value, (tuple, list)) else (value,)))
    low = (lambda v: v > 0) if positive else (lambda v: v >= 0)
    if not values or not all(low(v) and v < float("inf") for v in values):
        bound = "> 0" if positive else ">= 0"
        raise ValueError(f"{name} must be finite and {bound} (one number or one per component), got {value!r}")
    return values


class ParticleRecord(NamedTuple):
    """Everything the backward sweep needs, stacked over steps t = 0..T−1 (see module doc)."""

    x: jax.Array  # (T, P, D) x_t
    u: jax.Array  # (T, P, F) u_t
    mean: jax.Array  # (T, P, D) μ_{t+1}
    std: jax.Array  # (T, P, D) s_{t+1}
    eps: jax.Array  # (T, P, D) ε_{t+1}
    x_next: jax.Array  # (T, P, D) x_{t+1}
    cost: jax.Array  # (T, P) c(x_{t+1})
    jac_mean: jax.Array | None  # (T, P, D, Dz) ∂μ_{t+1}/∂z_t (the x_t in μ = x_t + m is not included)
    jac_std: jax.Array | None  # (T, P, D, Dz) ∂s_{t+1}/∂z_t; None under −σ_f (s does not depend on z)
    nominal_cost: jax.Array | None = None  # (T, P) c of each particle's zero-noise rollout, where a baseline reads it

    @property
    def objective(self) -> jax.Array:
        """J = Σ_t mean_i c(x_{i,t})."""
        return jnp.sum(jnp.mean(self.cost, axis=-1))


class Noise(NamedTuple):
    """The random numbers of one rollout: the start particles and the per-step ε.

    With noise on the actions, ``eps`` is the actions' standardised noise ``w`` (T, P, F) and
    ``state_eps`` the simulator state's (T, P, D), or None without state noise."""

    x0: jax.Array  # (P, D)
    eps: jax.Array  # (T, P, D), or (T, P, F) with noise on the actions
    state_eps: jax.Array | None = None  # (T, P, D) with noise on the actions and the state

    def without_noise(self) -> Noise:
        """The same start particles with every later noise zero: the zero-noise rollouts."""
        return Noise(self.x0, jnp.zeros_like(self.eps), None if self.state_eps is None else jnp.zeros_like(self.state_eps))


def sample_noise(key: jax.Array, task: Problem, config: RolloutConfig) -> Noise:
    """Draw x_0 ~ N(μ0^x, Σ0^x) and ε ~ N(0, I). Reusing the key gives the fixed-seed variant."""
    if config.noise_on_actions:
        from pipps.particles.simulator import sample_action_noise

        return sample_action_noise(key, task, config)
    k0, ke = jax.random.split(key)
    P, T, D = config.num_particles, config.steps(task), task.model_dim
    x0 = jax.random.multivariate_normal(
        k0, jnp.asarray(task.model_init_mean), jnp.asarray(task.model_init_cov), (P,), method="svd"
    )
    return Noise(x0, jax.random.normal(ke, (T, P, D)))


def controls(task: Problem, policy, x: jax.Array) -> jax.Array:
    """u_i = π(x̃_i[P]) for every particle."""
    return jax.vmap(lambda xi: policy(task.policy_input(xi)))(x)


def model_input(task: Problem, policy, x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(u, z) for every particle: the control and the GP input [x̃[I]; u]."""
    u = controls(task, policy, x)
    return u, jax.vmap(task.gp_input)(x, u)


def gaussian_resample(mean: jax.Array, std: jax.Array, eps: jax.Array, jitter: float) -> jax.Array:
    """GR (thesis §4.3.1): a fresh sample from one Gaussian fitted to the mixture Σ_i N(μ_i, s_i²)/P.

    μ̂ = mean_i μ_i, Σ̂ = cov_i(μ_i) + mean_i diag(s_i²) (the mixture's exact moments, so the
    covariance over i uses 1/P), z_i = μ̂ + L ε_i with L = chol(Σ̂ + jitter·I).
    """
    mu_hat = jnp.mean(mean, axis=0)
    centred = mean - mu_hat
    cov = centred.T @ centred / mean.shape[0] + jnp.diag(jnp.mean(std**2, axis=0))
    chol = jnp.linalg.cholesky(cov + jitter * jnp.eye(cov.shape[0]))
    return mu_hat + eps @ chol.T


def particle_step(task: Problem, policy, model, config: RolloutConfig, x, eps, *, jacobian: bool):
    """One step of Algorithm 3 for all particles. Returns the record entries of this step."""
    u, z = model_input(task, policy, x)
    out = model_output(model, z, variance=config.model_variance, jacobian=jacobian, precision=config.variance_precision)
    mean = x + out.mean
    noise_var = config.noise_multiplier * noise_variance(model)
    var = noise_var[None, :] + (out.var if config.model_variance else 0.0)
    std = jnp.sqrt(jnp.broadcast_to(var, mean.shape))
    jac_std = None
    if jacobian and config.model_variance:
        # ∂s/∂z = ∂v/∂z / 2s; where s = 0 the variance sits at its clamp (a minimum): slope 0
        positive = (std > 0.0)[..., None]
        jac_std = jnp.where(positive, out.jac_var / (2.0 * jnp.where(positive, std[..., None], 1.0)), 0.0)
    if config.resampling == "gaussian":
        x_next = gaussian_resample(mean, std, eps, config.resample_jitter)
    else:
        x_next = mean + std * eps
    cost = jax.vmap(task.cost)(x_next)
    return ParticleRecord(x, u, mean, std, eps, x_next, cost, out.jac_mean, jac_std)


def particle_rollout(task: Problem, policy, model, noise: Noise, config: RolloutConfig, *, jacobian: bool = True) -> ParticleRecord:
    """Algorithm 3: all particles through all steps, one scan over time.

    ``jacobian`` (static) records the model's input Jacobians for the custom backward pass;
    a forward-only evaluation sets it False. With ``config.action_noise`` the model is a known
    simulator and the record an :class:`~pipps.particles.simulator.ActionRecord`
    (:func:`pipps.particles.simulator.action_rollout`).
    """
    if config.noise_on_actions:
        from pipps.particles.simulator import action_rollout

        return action_rollout(task, policy, model, noise, config, jacobian=jacobian)
    if task.model_dim != noise.x0.shape[-1]:
        raise ValueError(f"noise has state dimension {noise.x0.shape[-1]}, task has {task.model_dim}")
    check_policy(policy, task.policy_input_dim, task.action_dim)

    def body(x, eps):
        rec = particle_step(task, policy, model, config, x, eps, jacobian=jacobian)
        return rec.x_next, rec

    _, record = jax.lax.scan(body, noise.x0, noise.eps)
    return record


def reparameterized_objective(task: Problem, policy, model, noise: Noise, config: RolloutConfig) -> jax.Array:
    """J(θ) for fixed noise, written plainly so ``jax.grad`` of it is the RP gradient.

    The reference the custom backward pass is tested against, and the objective of the
    fixed-seed (``_FS``) variants.
    """
    return particle_rollout(task, policy, model, noise, config, jacobian=False).objective
