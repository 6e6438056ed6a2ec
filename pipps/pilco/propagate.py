"""Moment-matching propagation and PILCO's objective (tasks.md §5, thesis Algorithm 2).

One step maps ``x_t ~ N(μ, Σ)`` to ``x_{t+1} ~ N(μ', Σ')`` by building the joint Gaussian of
``[x̃; u; Δ]`` block by block (§5.5), every cross-covariance filled by the §0 rule
``Cov[w, y] = Cov[w, v] C``:

1. ``x̃ = [x; sin x_a, cos x_a]`` (§5.1, :func:`pipps.gaussian.trig_augment`);
2. ``u = π(x̃[P])``: controller and saturation moments (§5.2–5.3), ``Cov[x̃, u] = Σ̃_{:,P} C_u``;
3. ``Δ = f(z)``, ``z = [x̃[I]; u]``: the model at a Gaussian input — §5.4 for a
   :class:`~pipps.gp.GPPosterior` (full or FITC), otherwise ``model.moments(mean_z, cov_z)``
   (e.g. the exact :class:`~pipps.systems.linear_gaussian.LinearGaussianModel`);
4. ``μ' = μ + M_Δ``, ``Σ' = Σ + S_Δ + Cov[x, Δ] + Cov[x, Δ]ᵀ`` with ``Cov[x, Δ] = Cov[x, z] C_Δ``,
   symmetrised.

:func:`step_moments` returns the step as a Gaussian map (with ``C = Σ⁻¹Cov[x_t, x_{t+1}]``
composed from the blocks' ``C``); :func:`propagate` returns ``(μ', Σ')``.

``J(θ) = Σ_{t=1..H} E[c(x_t)]`` from the task's planning start ``x_0 ~ N(μ_0^x, Σ_0^x)`` (the
cost of ``x_0`` is not included) is one ``lax.scan``; everything is pure, differentiable by
autodiff and vmappable (over policies, models or start distributions).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from pipps.gaussian import GaussianMap, append_map, trig_augment
from pipps.gp.types import GPPosterior
from pipps.pilco.controller import control_moments
from pipps.pilco.gp_moments import WeightedGP, gp_moments, weighted
from pipps.precision import require_float64
from pipps.tasks.base import Problem


class PilcoTrajectory(NamedTuple):
    """Predicted state distributions and expected costs over the horizon (for plots and tests).

    Index ``t = 0..H``; ``t = 0`` is the planning start. ``J = cost_mean[1:].sum()``.
    """

    means: jax.Array  # (H+1, D)
    covs: jax.Array  # (H+1, D, D)
    cost_mean: jax.Array  # (H+1,) E[c(x_t)]
    cost_var: jax.Array  # (H+1,) Var[c(x_t)] (reporting only, §5.6)


def dynamics_moments(model, mean: jax.Array, cov: jax.Array, *, model_uncertainty: bool = True) -> GaussianMap:
    """Moments of the state difference ``Δ = f(z)`` at ``z ~ N(mean, cov)``.

    A :class:`~pipps.gp.GPPosterior` goes through §5.4 (``model_uncertainty`` static); any other
    model must provide ``moments(mean, cov) -> GaussianMap`` (``model_uncertainty`` is then
    the model's own business and ignored here).
    """
    if isinstance(model, (GPPosterior, WeightedGP)):
        return gp_moments(model, mean, cov, model_uncertainty=model_uncertainty)
    moments = getattr(model, "moments", None)
    if not callable(moments):
        raise TypeError(
            f"model of type {type(model).__name__} is neither a GPPosterior nor has moments(mean, cov)"
        )
    return moments(mean, cov)


def _selection(rows: int, idx) -> np.ndarray:
    """(rows, len(idx)) 0/1 matrix with ``sel[idx[k], k] = 1``: ``C_full = sel @ C`` lifts a map of ``v[idx]``."""
    sel = np.zeros((rows, len(idx)))
    sel[np.asarray(idx, dtype=int), np.arange(len(idx))] = 1.0
    return sel


def state_control_joint(task: Problem, policy, mean: jax.Array, cov: jax.Array):
    """Joint Gaussian of ``[x̃; u]`` (§5.5 steps 1–2).

    Returns:
      ``(mean (D̃+F,), cov (D̃+F, D̃+F), C (D, D̃+F))`` with ``C = Σ⁻¹Cov[x, [x̃; u]]`` composed
      from the blocks' ``C`` (``[I, C_trig]`` for x̃, then ``C_x̃[:, P] C_u`` for u); Σ is never inverted.
    """
    m_aug, s_aug, c_trig = trig_augment(mean, cov, task.angle_idx)
    p_idx = np.asarray(task.policy_input_idx, dtype=int)
    ctrl = control_moments(policy, m_aug[p_idx], s_aug[np.ix_(p_idx, p_idx)])
    lifted = GaussianMap(ctrl.M, ctrl.S, jnp.asarray(_selection(m_aug.shape[0], p_idx)) @ ctrl.C)
    m_joint, s_joint = append_map(m_aug, s_aug, lifted)
    c_aug = jnp.concatenate([jnp.eye(mean.shape[0], dtype=cov.dtype), c_trig], axis=1)
    return m_joint, s_joint, jnp.concatenate([c_aug, c_aug[:, p_idx] @ ctrl.C], axis=1)


def step_moments(
    task: Problem,
    policy,
    model,
    mean: jax.Array,
    cov: jax.Array,
    *,
    model_uncertainty: bool = True,
) -> GaussianMap:
    """One moment-matching step as a Gaussian map (tasks.md §5.5).

    Returns ``GaussianMap(μ', Σ', C)`` with ``C = Σ⁻¹Cov[x_t, x_{t+1}] = I + C_xz C_Δ``.
    """
    n_x = task.model_dim
    m_joint, s_joint, c_joint = state_control_joint(task, policy, mean, cov)
    n_aug = task.augmented_dim
    z_idx = np.concatenate([np.asarray(task.gp_input_idx, dtype=int), n_aug + np.arange(task.action_dim)])
    delta = dynamics_moments(
        model, m_joint[z_idx], s_joint[np.ix_(z_idx, z_idx)], model_uncertainty=model_uncertainty
    )
    cross = s_joint[:n_x, z_idx] @ delta.C  # Cov[x, Δ] = Cov[x, z] C_Δ
    mean_next = mean + delta.M
    cov_next = cov + delta.S + cross + cross.T
    C = jnp.eye(n_x, dtype=cov.dtype) + c_joint[:, z_idx] @ delta.C
    return GaussianMap(mean_next, 0.5 * (cov_next + cov_next.T), C)


def propagate(
    task: Problem,
    policy,
    model,
    mean: jax.Array,
    cov: jax.Array,
    *,
    model_uncertainty: bool = True,
) -> tuple[jax.Array, jax.Array]:
    """One moment-matching step ``N(μ, Σ) → N(μ', Σ')`` of the model state (tasks.md §5.5)."""
    g = step_moments(task, policy, model, mean, cov, model_uncertainty=model_uncertainty)
    return g.M, g.S


def _start(task: Problem, init) -> tuple[jax.Array, jax.Array]:
    if init is None:
        return jnp.asarray(task.model_init_mean), jnp.asarray(task.model_init_cov)
    mean, cov = init
    return jnp.asarray(mean), jnp.asarray(cov)


def _scan_steps(task, policy, model, init, horizon, model_uncertainty, checkpoint, keep_states):
    H = task.horizon if horizon is None else int(horizon)
    if model_uncertainty and isinstance(model, GPPosterior):
        model = weighted(model)  # the pair weights once, not at every step (1.15x measured, docs/pilco.md)

    def step(carry, _):
        mean, cov = propagate(task, policy, model, *carry, model_uncertainty=model_uncertainty)
        c_mean, c_var = task.cost.expected(mean, cov)
        out = (mean, cov, c_mean, c_var) if keep_states else c_mean
        return (mean, cov), out

    if checkpoint:
        step = jax.checkpoint(step)
    return jax.lax.scan(step, _start(task, init), None, length=H)


def objective(
    task: Problem,
    policy,
    model,
    *,
    horizon: int | None = None,
    init: tuple[jax.Array, jax.Array] | None = None,
    model_uncertainty: bool = True,
    checkpoint: bool = False,
) -> jax.Array:
    """PILCO's ``J(θ) = Σ_{t=1..H} E[c(x_t)]`` by moment matching (tasks.md §1 step 2, §5).

    Args:
      task: the task (horizon, index sets, cost, planning start).
      policy: a policy pytree (differentiate with respect to it).
      model: a :class:`~pipps.gp.GPPosterior` (full or FITC) or a model with ``moments``.
      horizon: H (default ``task.horizon``); static.
      init: ``(mean, cov)`` of ``x_0`` (default the task's ``model_init_mean/cov``).
      model_uncertainty: static; False drops §5.4's ``E_z[var_f]`` term.
      checkpoint: static; recompute each step in the backward pass (``jax.checkpoint``) instead
        of storing its intermediates — H× less memory for about one extra forward pass.
    """
    require_float64("pipps.pilco.objective")
    _, costs = _scan_steps(task, policy, model, init, horizon, model_uncertainty, checkpoint, False)
    return jnp.sum(costs)


def trajectory(
    task: Problem,
    policy,
    model,
    *,
    horizon: int | None = None,
    init: tuple[jax.Array, jax.Array] | None = None,
    model_uncertainty: bool = True,
) -> PilcoTrajectory:
    """The predicted ``N(μ_t, Σ_t)`` and ``E[c(x_t)]``, ``Var[c(x_t)]`` for ``t = 0..H``."""
    require_float64("pipps.pilco.trajectory")
    mean0, cov0 = _start(task, init)
    _, (means, covs, c_mean, c_var) = _scan_steps(
        task, policy, model, (mean0, cov0), horizon, model_uncertainty, False, True
    )
    c0_mean, c0_var = task.cost.expected(mean0, cov0)
    return PilcoTrajectory(
        jnp.concatenate([mean0[None], means]),
        jnp.concatenate([cov0[None], covs]),
        jnp.concatenate([jnp.reshape(c0_mean, (1,)), c_mean]),
        jnp.concatenate([jnp.reshape(c0_var, (1,)), c_var]),
    )
