"""The shared linear-Gaussian reference system: exact dynamics, exact objective, exact gradient.

**This is the reference system of the project's exactness tests.** Its state distributions are
exactly Gaussian under a linear, *unsaturated* policy, so PILCO's moment matching must reproduce
it to rounding, and the particle gradient estimators (RP, LR, TP, …) are checked against the
exact gradient ``jax.grad(exact_objective)``.

* :class:`LinearGaussianModel` — the "dynamics model" (difference dynamics, as the GP):
  ``x_{t+1} = x_t + Δ``, ``Δ = F z + f0 + ε``, ``z = [x̃[I]; u]``, ``ε ~ N(0, diag(noise_var))``,
  zero epistemic variance. It offers the GP's two interfaces: per particle
  ``predict(z, variance) -> (mean, var or None)`` with ``noise_variance``, and for moment
  matching ``moments(mean_z, cov_z) -> GaussianMap`` (the exact linear map of the *latent*
  ``Fz + f0``; like PILCO's GP at a Gaussian input it adds no noise).
* :func:`make_linear_gaussian_task` — the :class:`~pipps.tasks.base.Problem` around it (no angles,
  every state component is a GP and a policy input; a planning problem only: there is no true
  system to simulate).
* :func:`exact_objective` / :func:`exact_trajectory` — the closed-form recursion
  ``μ' = Aμ + c``, ``Σ' = AΣAᵀ + s·diag(noise_var)`` with ``A = I + F_x + F_u W``,
  ``c = F_u b + f0`` for ``u = W x + b``, and ``J = Σ_{t=1..H} E[c(x_t)]``. The noise scale ``s``
  is 1 for the particle forward pass (which samples ``ε``) and 0 for PILCO's latent propagation.
* :func:`reference_system` — the fixed 3-state, 1-control instance the tests share.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax.tree_util import register_dataclass

from pipps.costs import SaturatingCost
from pipps.gaussian import GaussianMap, linear_map
from pipps.policies import LinearPolicy
from pipps.systems.quadratic_cost import QuadraticCost
from pipps.tasks.base import Cost, Problem


@register_dataclass
@dataclasses.dataclass(frozen=True)
class LinearGaussianModel:
    """Known linear-Gaussian difference dynamics ``Δ = F z + f0 + ε`` (a pytree).

    Attributes:
      F: (E, Dz) dynamics matrix acting on the model input ``z = [x̃[I]; u]``.
      f0: (E,) offset.
      noise_var: (E,) variance of ``ε`` (the analogue of the GP's σ_n²).
    """

    F: jax.Array
    f0: jax.Array
    noise_var: jax.Array

    @property
    def noise_variance(self) -> jax.Array:
        """(E,) per-output noise variance, as :attr:`pipps.gp.GPPosterior.noise_variance`."""
        return self.noise_var

    def predict(self, z: jax.Array, variance: bool = False):
        """Per-particle prediction: mean ``z Fᵀ + f0`` (P, E) and, if asked, the epistemic variance (zeros)."""
        mean = z @ self.F.T + self.f0
        return mean, (jnp.zeros_like(mean) if variance else None)

    def moments(self, mean_z: jax.Array, cov_z: jax.Array) -> GaussianMap:
        """Exact moments of the latent ``Δ = F z + f0`` for ``z ~ N(mean_z, cov_z)``: ``(Fμ + f0, FΣFᵀ, Fᵀ)``."""
        return linear_map(mean_z, cov_z, self.F, self.f0)


def frozen(a, shape, name) -> np.ndarray:
    """A read-only float64 copy of ``a``, checked to have ``shape`` and finite entries (the reference
    systems' fixed parameters; ``name`` names the parameter in the error)."""
    arr = np.array(a, dtype=np.float64)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    arr.setflags(write=False)
    return arr


def make_linear_gaussian_task(
    state_dim: int = 3,
    action_dim: int = 1,
    *,
    horizon: int = 10,
    init_mean=None,
    init_cov=None,
    cost: str | Cost = "quadratic",
    cost_weight=None,
    target=None,
    u_max=None,
    name: str = "linear_gaussian",
) -> Problem:
    """The :class:`Problem` of a linear-Gaussian system (no angles; all components are GP and policy inputs).

    Args:
      state_dim, action_dim: D and F.
      horizon: H.
      init_mean, init_cov: the planning start distribution (default 0 and 0.1²·I).
      cost: ``"quadratic"`` (:class:`QuadraticCost`, ``c = (x−z)ᵀQ(x−z)``, ``Q = cost_weight``),
        ``"saturating"`` (:class:`~pipps.costs.SaturatingCost`, ``W = cost_weight``), or a ready
        Cost object (then ``cost_weight`` and ``target`` must be None).
      cost_weight: (D, D) Q or W (default I).
      target: (D,) z (default 0).
      u_max: (F,) control limit, only used by saturated policies (default 10).

    A Problem only: its dynamics are :class:`LinearGaussianModel`, there is no true system to
    simulate (no :class:`~pipps.tasks.base.Simulator`, so no ``rollout``).
    """
    D, F = int(state_dim), int(action_dim)
    if D < 1 or F < 1 or int(horizon) < 1:
        raise ValueError(f"need state_dim, action_dim, horizon >= 1, got {D}, {F}, {horizon}")
    mean = frozen(np.zeros(D) if init_mean is None else init_mean, (D,), "init_mean")
    cov = frozen(0.01 * np.eye(D) if init_cov is None else init_cov, (D, D), "init_cov")
    if not np.allclose(cov, cov.T, rtol=0, atol=1e-12) or np.linalg.eigvalsh(cov).min() < -1e-12:
        raise ValueError("init_cov must be symmetric positive semi-definite")
    umax = frozen(10.0 * np.ones(F) if u_max is None else np.atleast_1d(u_max), (F,), "u_max")
    if np.any(umax <= 0):
        raise ValueError(f"u_max must be > 0, got {umax}")
    if isinstance(cost, str):
        weight = np.eye(D) if cost_weight is None else cost_weight
        z = np.zeros(D) if target is None else target
        if cost == "quadratic":
            cost_obj = QuadraticCost(weight, z)
        elif cost == "saturating":
            cost_obj = SaturatingCost(W=weight, target=z)
        else:
            raise ValueError(f"unknown cost {cost!r}; valid: 'quadratic', 'saturating' or a Cost object")
    else:
        if cost_weight is not None or target is not None:
            raise ValueError("cost_weight/target are only used with a cost name")
        cost_obj = cost
    return Problem(
        name=name,
        model_dim=D,
        action_dim=F,
        dt=1.0,
        horizon=int(horizon),
        u_max=umax,
        model_init_mean=mean,
        model_init_cov=cov,
        angle_idx=(),
        gp_input_idx=tuple(range(D)),
        policy_input_idx=tuple(range(D)),
        cost=cost_obj,
    )


def closed_loop(task: Problem, model: LinearGaussianModel, policy: LinearPolicy) -> tuple[jax.Array, jax.Array]:
    """``(A, c)`` of the closed loop ``x' = A x + c + ε`` under ``u = W x[P] + b`` (unsaturated)."""
    if task.angle_idx:
        raise ValueError("the closed-form recursion needs a task without angle augmentation")
    if not isinstance(policy, LinearPolicy) or policy.saturated:
        raise ValueError("the closed-form recursion needs an unsaturated LinearPolicy (saturated=False)")
    D = task.model_dim
    if model.F.shape != (D, task.gp_input_dim):
        raise ValueError(f"model.F must be ({D}, {task.gp_input_dim}) (all state components as outputs), got {model.F.shape}")
    n_i = len(task.gp_input_idx)
    f_x, f_u = model.F[:, :n_i], model.F[:, n_i:]
    gain = jnp.zeros((D, D), dtype=model.F.dtype)
    gain = gain.at[:, np.asarray(task.gp_input_idx)].add(f_x)
    gain = gain.at[:, np.asarray(task.policy_input_idx)].add(f_u @ policy.W)
    return jnp.eye(D, dtype=gain.dtype) + gain, f_u @ policy.b + model.f0


def exact_trajectory(
    task: Problem,
    model: LinearGaussianModel,
    policy: LinearPolicy,
    *,
    noise_scale=1.0,
    horizon: int | None = None,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Exact ``(means (H+1, D), covs (H+1, D, D), expected costs (H+1,))`` of the closed loop.

    ``noise_scale`` multiplies ``noise_var`` (1: the particle forward pass with noise; 0: PILCO's
    latent propagation; any other value: the ``+σ_n`` variants). Differentiable in everything.
    """
    A, c = closed_loop(task, model, policy)
    noise = noise_scale * jnp.diag(model.noise_var)
    H = task.horizon if horizon is None else int(horizon)

    def step(carry, _):
        mean, cov = carry
        mean = A @ mean + c
        cov = A @ cov @ A.T + noise
        cov = 0.5 * (cov + cov.T)
        return (mean, cov), (mean, cov, task.cost.expected(mean, cov)[0])

    m0, s0 = jnp.asarray(task.model_init_mean), jnp.asarray(task.model_init_cov)
    _, (means, covs, costs) = jax.lax.scan(step, (m0, s0), None, length=H)
    c0 = jnp.reshape(task.cost.expected(m0, s0)[0], (1,))
    return (jnp.concatenate([m0[None], means]), jnp.concatenate([s0[None], covs]), jnp.concatenate([c0, costs]))


def exact_objective(
    task: Problem,
    model: LinearGaussianModel,
    policy: LinearPolicy,
    *,
    noise_scale=1.0,
    horizon: int | None = None,
) -> jax.Array:
    """Exact ``J = Σ_{t=1..H} E[c(x_t)]`` of the linear-Gaussian closed loop; ``jax.grad`` it for the exact gradient.

    Exact whenever ``task.cost.expected`` is exact for Gaussians (:class:`QuadraticCost`, and a
    :class:`~pipps.costs.SaturatingCost` without angles).
    """
    _, _, costs = exact_trajectory(task, model, policy, noise_scale=noise_scale, horizon=horizon)
    return jnp.sum(costs[1:])


def reference_system(noise_std: float = 0.1, cost: str = "quadratic", horizon: int = 10):
    """The fixed reference instance ``(task, model, policy)``: 3 states, 1 control, H = 10.

    An open-loop slightly unstable, coupled system; a stabilising linear policy
    ``u = W x + b`` (unsaturated); start ``N([1, 0, −0.5], 0.1²I)``; cost ``"quadratic"``
    (``Q = diag(1, 0.5, 0.2)``) or ``"saturating"`` (``W = diag(1, 0.5, 0.2)``), target 0.
    """
    task = make_linear_gaussian_task(
        3, 1, horizon=horizon, init_mean=[1.0, 0.0, -0.5], init_cov=0.01 * np.eye(3),
        cost=cost, cost_weight=np.diag([1.0, 0.5, 0.2]),
    )
    F = jnp.array([
        [0.05, 0.10, 0.00, 0.00],
        [0.00, 0.02, 0.10, 0.10],
        [0.05, 0.00, -0.10, 0.20],
    ])
    model = LinearGaussianModel(F, jnp.array([0.01, 0.0, -0.01]), jnp.full((3,), noise_std**2))
    policy = LinearPolicy(jnp.array([[-0.5, -0.8, -0.2]]), jnp.array([0.05]), (10.0,), saturated=False)
    return task, model, policy


def two_action_reference_system(noise_std: float = 0.3, horizon: int = 10):
    """A reference instance with two controls of different effect, ``(task, model, policy)``: the
    states, start and saturating cost of :func:`reference_system`; the second control is weaker and
    acts on other states. For the estimators that weigh each action coordinate (``tpx``)."""
    task = make_linear_gaussian_task(
        3, 2, horizon=horizon, init_mean=[1.0, 0.0, -0.5], init_cov=0.01 * np.eye(3),
        cost="saturating", cost_weight=np.diag([1.0, 0.5, 0.2]),
    )
    F = jnp.array([
        [0.05, 0.10, 0.00, 0.00, 0.03],
        [0.00, 0.02, 0.10, 0.10, 0.00],
        [0.05, 0.00, -0.10, 0.20, 0.05],
    ])
    model = LinearGaussianModel(F, jnp.array([0.01, 0.0, -0.01]), jnp.full((3,), noise_std**2))
    W = jnp.array([[-0.5, -0.8, -0.2], [0.3, -0.2, -0.6]])
    policy = LinearPolicy(W, jnp.array([0.05, -0.02]), (10.0, 10.0), saturated=False)
    return task, model, policy
