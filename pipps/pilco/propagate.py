"""Moment-matching propagation and PILCO's objective (thesis Algorithm 2; docs/pilco.md).

One step maps ``x_t ~ N(μ, Σ)`` to ``x_{t+1} ~ N(μ', Σ')`` by building the joint Gaussian of
``[x̃; u; Δ]`` block by block (PILCO's ``propagated.m``), every cross-covariance filled by the rule
``Cov[w, y] = Cov[w, v] C``:

1. ``x̃ = [x; sin x_a, cos x_a]`` (:func:`pipps.gaussian.trig_augment`);
2. ``u = π(x̃[P])``: controller and saturation moments, ``Cov[x̃, u] = Σ̃_{:,P} C_u``;
3. ``Δ = f(z)``, ``z = [x̃[I]; u]``: the model at a Gaussian input — :func:`gp_moments` for a
   :class:`~pipps.gp.GPPosterior` (full or FITC), otherwise ``model.moments(mean_z, cov_z)``
   (e.g. the exact :class:`~pipps.systems.linear_gaussian.LinearGaussianModel`);
4. ``μ' = μ + M_Δ``, ``Σ' = Σ + S_Δ + Cov[x, Δ] + Cov[x, Δ]ᵀ`` with ``Cov[x, Δ] = Cov[x, z] C_Δ``,
   symmetrised.

:func:`step_moments` returns the step as a Gaussian map (with ``C = Σ⁻¹Cov[x_t, x_{t+1}]``
composed from the blocks' ``C``); :func:`propagate` returns ``(μ', Σ')``.

``J(θ) = Σ_{t=1..H} E[c(x_t)]`` from the task's planning start ``x_0 ~ N(μ_0^x, Σ_0^x)`` (the
cost of ``x_0`` is not included) is one ``lax.scan``; everything is pure, differentiable by
autodiff and vmappable (over policies, models or start distributions).

**Policy input noise** (``policy_noise=True`` of :func:`objective` and :func:`trajectory`; an
``input_noise`` array of the step functions). The PILCO code's release V0.9 (``a65d266``) let the
policy see a noisy measurement of the state: in ``propagate.m``/``propagated.m`` it forms
``ss = S + diag(sn2)`` with ``sn2 = exp(2·hyp(end, :))`` (the GP outputs' noise variances σ²_{n,a}),
halved for the difference targets (``sn2(difi)/2``; every model-state component here is one),
trig-augments ``N(m, ss)`` and evaluates the controller there (``policy.fcn(policy, mm(poli),
ss(poli, poli))``). The state's own distribution is untouched, and ``Cov[x̃, u]`` is filled with the
*un-inflated* joint, ``q = S(j, poli)·C`` — ``Σ̃_{:,P} C_u`` with ``C_u = ss_PP⁻¹ Cov_ss[x̃_P, u]``
computed at the inflated input. For policy inputs that are model-state components (no sin/cos)
this is the exact joint of ``x`` and ``u = π(x_P + ε)``, ``ε ~ N(0, diag(sn2))`` independent of x,
since ``Cov[x, x_P + ε] = Σ_{:,P}``; for sin/cos inputs it keeps the latent trig
cross-covariances, as the code does. Commit ``a0b48b7`` removed the term; the default (off,
``input_noise=None``) follows it and runs exactly the program it ran before the option existed.
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
from pipps.policies import check_policy
from pipps.precision import require_float64
from pipps.tasks.base import Problem


class PilcoTrajectory(NamedTuple):
    """Predicted state distributions and expected costs over the horizon (for plots and tests).

    Index ``t = 0..H``; ``t = 0`` is the planning start. ``J = cost_mean[1:].sum()``.
    """

    means: jax.Array  # (H+1, D)
    covs: jax.Array  # (H+1, D, D)
    cost_mean: jax.Array  # (H+1,) E[c(x_t)]
    cost_var: jax.Array  # (H+1,) Var[c(x_t)] (reporting only)


def dynamics_moments(model, mean: jax.Array, cov: jax.Array, *, model_uncertainty: bool = True) -> GaussianMap:
    """Moments of the state difference ``Δ = f(z)`` at ``z ~ N(mean, cov)``.

    A :class:`~pipps.gp.GPPosterior` goes through :func:`gp_moments` (``model_uncertainty`` static); any other
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


def policy_input_noise(task: Problem, model) -> jax.Array:
    """(D,) the variances PILCO V0.9 adds to the state covariance given to the policy (module doc):
    ``σ²_{n,a}/2`` for each model-state component ``a``, from GP output ``a``'s noise variance
    (halved: every component is a difference target). ``model``: a
    :class:`~pipps.gp.GPPosterior` (or its :class:`WeightedGP`) or any model with ``noise_variance``."""
    post = model.post if isinstance(model, WeightedGP) else model
    noise = getattr(post, "noise_variance", None)
    if noise is None:
        raise TypeError(f"model of type {type(post).__name__} has no noise_variance for the policy input noise")
    noise = jnp.asarray(noise)
    if noise.shape != (task.model_dim,):
        raise ValueError(f"policy input noise needs one GP output per model-state component "
                         f"({task.model_dim}), the model has noise variances of shape {noise.shape}")
    return 0.5 * noise


def state_control_joint(task: Problem, policy, mean: jax.Array, cov: jax.Array, input_noise=None):
    """Joint Gaussian of ``[x̃; u]`` (steps 1–2 of the module docstring).

    ``input_noise``: None (default), or (D,) variances added to Σ for the policy's input only
    (PILCO V0.9, module doc): the controller is evaluated at the trig augmentation of
    ``N(μ, Σ + diag(input_noise))``, and ``Cov[x̃, u] = Σ̃_{:,P} C_u`` with the un-inflated Σ̃.

    Returns:
      ``(mean (D̃+F,), cov (D̃+F, D̃+F), C (D, D̃+F))`` with ``C = Σ⁻¹Cov[x, [x̃; u]]`` composed
      from the blocks' ``C`` (``[I, C_trig]`` for x̃, then ``C_x̃[:, P] C_u`` for u); Σ is never inverted.
    """
    m_aug, s_aug, c_trig = trig_augment(mean, cov, task.angle_idx)
    p_idx = np.asarray(task.policy_input_idx, dtype=int)
    if input_noise is None:
        m_in, s_in = m_aug, s_aug
    else:  # the noisy measurement's distribution, augmented as the state's is (PILCO's mm, ss)
        m_in, s_in, _ = trig_augment(mean, cov + jnp.diag(input_noise), task.angle_idx)
    ctrl = control_moments(policy, m_in[p_idx], s_in[np.ix_(p_idx, p_idx)])
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
    input_noise: jax.Array | None = None,
) -> GaussianMap:
    """One moment-matching step as a Gaussian map (steps 1–4 of the module docstring).

    ``input_noise``: see :func:`state_control_joint` (None: the policy sees the state's distribution).

    Returns ``GaussianMap(μ', Σ', C)`` with ``C = Σ⁻¹Cov[x_t, x_{t+1}] = I + C_xz C_Δ``.
    """
    n_x = task.model_dim
    m_joint, s_joint, c_joint = state_control_joint(task, policy, mean, cov, input_noise)
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
    input_noise: jax.Array | None = None,
) -> tuple[jax.Array, jax.Array]:
    """One moment-matching step ``N(μ, Σ) → N(μ', Σ')`` of the model state (the module docstring's steps)."""
    g = step_moments(task, policy, model, mean, cov, model_uncertainty=model_uncertainty, input_noise=input_noise)
    return g.M, g.S


def _start(task: Problem, init) -> tuple[jax.Array, jax.Array]:
    if init is None:
        return jnp.asarray(task.model_init_mean), jnp.asarray(task.model_init_cov)
    mean, cov = init
    return jnp.asarray(mean), jnp.asarray(cov)


def _scan_steps(task, policy, model, init, horizon, model_uncertainty, checkpoint, keep_states, policy_noise=False):
    check_policy(policy, task.policy_input_dim, task.action_dim)
    H = task.horizon if horizon is None else int(horizon)
    input_noise = policy_input_noise(task, model) if policy_noise else None  # once, not at every step
    if model_uncertainty and isinstance(model, GPPosterior):
        model = weighted(model)  # the pair weights once, not at every step (1.15x measured, docs/pilco.md)

    def step(carry, _):
        mean, cov = propagate(task, policy, model, *carry, model_uncertainty=model_uncertainty,
                              input_noise=input_noise)
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
    policy_noise: bool = False,
) -> jax.Array:
    """PILCO's ``J(θ) = Σ_{t=1..H} E[c(x_t)]`` by moment matching (thesis Algorithm 2).

    Args:
      task: the task (horizon, index sets, cost, planning start).
      policy: a policy pytree (differentiate with respect to it).
      model: a :class:`~pipps.gp.GPPosterior` (full or FITC) or a model with ``moments``.
      horizon: H (default ``task.horizon``); static.
      init: ``(mean, cov)`` of ``x_0`` (default the task's ``model_init_mean/cov``).
      model_uncertainty: static; False drops the GP's ``E_z[var_f]`` term.
      checkpoint: static; recompute each step in the backward pass (``jax.checkpoint``) instead
        of storing its intermediates — H× less memory for about one extra forward pass.
      policy_noise: static; True evaluates the policy at the state distribution plus the model's
        noise variances halved, as PILCO V0.9 did (module doc, :func:`policy_input_noise`); False
        (default) follows the later code (``a0b48b7``): the policy sees the latent state.
    """
    require_float64("pipps.pilco.objective")
    _, costs = _scan_steps(task, policy, model, init, horizon, model_uncertainty, checkpoint, False, policy_noise)
    return jnp.sum(costs)


def trajectory(
    task: Problem,
    policy,
    model,
    *,
    horizon: int | None = None,
    init: tuple[jax.Array, jax.Array] | None = None,
    model_uncertainty: bool = True,
    policy_noise: bool = False,
) -> PilcoTrajectory:
    """The predicted ``N(μ_t, Σ_t)`` and ``E[c(x_t)]``, ``Var[c(x_t)]`` for ``t = 0..H``
    (``policy_noise`` as in :func:`objective`)."""
    require_float64("pipps.pilco.trajectory")
    mean0, cov0 = _start(task, init)
    _, (means, covs, c_mean, c_var) = _scan_steps(
        task, policy, model, (mean0, cov0), horizon, model_uncertainty, False, True, policy_noise
    )
    c0_mean, c0_var = task.cost.expected(mean0, cov0)
    return PilcoTrajectory(
        jnp.concatenate([mean0[None], means]),
        jnp.concatenate([cov0[None], covs]),
        jnp.concatenate([jnp.reshape(c0_mean, (1,)), c_mean]),
        jnp.concatenate([jnp.reshape(c0_var, (1,)), c_var]),
    )
