"""The custom backward pass: one reverse sweep over time (thesis Alg. 5; estimators.md §2–§6).

The sweep runs ``t = T, …, 1`` over the :class:`~pipps.particles.forward.ParticleRecord` and
carries, per particle, the returns ``G_{i,t}`` and — when the estimator has a pathwise part — the
pathwise derivative of the return with respect to the particle, ``∂G_i/∂x_{i,t}``. The estimator
(:class:`~pipps.propagation.config.Estimator`) is the strategy; at each step the sweep

1. asks its cost terms for ``c_{i,t}`` and ``∂c_i/∂x_{i,t}`` and sets ``G_{i,t} = G_{i,t+1} + c_{i,t}``
   (:mod:`~pipps.propagation.cost_terms`);
2. asks each of its parts for a ζ-cotangent ``γ_{i,t}`` (:mod:`~pipps.propagation.parts`);
3. turns every γ into a cotangent on the GP input ``z = [x̃[I]; π(x̃[P]; θ)]`` with the model
   Jacobians the forward pass recorded, and hands these (:class:`~pipps.propagation.parts.PartCotangents`)
   with the pull-back — one per-particle VJP of the (cheap) map ``x ↦ z`` for a stack of
   cotangents, giving θ-gradients and, when a pathwise part reads them, messages ``∂G/∂x_{i,t−1}`` —
   to its combiner;
4. the combiner chooses ``k_LR`` and returns the step's contribution and the message ``λ`` passed
   back (:mod:`~pipps.propagation.combine`): total propagation pulls every part back at once and
   mixes the θ-gradients; a combiner at the action nodes mixes the z-cotangents first.

The sweep itself does not depend on which estimator it runs.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from pipps.particles.forward import ParticleRecord, RolloutConfig
from pipps.propagation.config import Estimator
from pipps.propagation.lr import ZetaGrad
from pipps.propagation.parts import LIKELIHOOD_RATIO, PATHWISE, PartCotangents, StepInputs
from pipps.tasks.base import Problem


class StepDiagnostics(NamedTuple):
    """Per-step diagnostics of one estimate, each (T,), step t = 1..T in order."""

    k_lr: jax.Array  # the weight used on the LR part (0 for RP, 1 for LR)
    k_lr_batch: jax.Array  # the weight this batch's variances give (what "previous" uses next time)
    var_rp: jax.Array  # σ²_RP = trace Var_i[g^RP_{i,t}] (NaN if the RP part is off)
    var_lr: jax.Array  # σ²_LR (NaN if the LR part is off)
    mean_return: jax.Array  # mean_i G_{i,t}, the next iteration's "previous" baseline
    objective: jax.Array  # the step's objective term: mean_i c_{i,t}, or Ē_t under shaping
    nonfinite: jax.Array  # bool: a per-particle gradient at this step was not finite


class SweepOutput(NamedTuple):
    contributions: jax.Array  # (P, n_θ) each particle's total contribution Σ_t g_{i,t}
    diagnostics: StepDiagnostics


class PreviousIteration(NamedTuple):
    """What the sweep reads from the previous optimizer iteration, each (T,)."""

    baseline: jax.Array  # mean return-to-go per step
    k_lr: jax.Array  # per-step batch weight
    has_previous: jax.Array  # bool scalar: False on an optimizer's first iteration


def _z_map(task: Problem):
    def z_of(x, policy):
        return task.gp_input(x, policy(task.policy_input(x)))

    return z_of


def _pull_back(task: Problem, policy, x_prev, ct_z, *, with_x: bool):
    """Per-particle VJP of x ↦ z(x, θ) for K stacked cotangents ct_z (K, P, Dz).

    Returns (θ-cotangents (K, P, n_θ), x-cotangents (K, P, D) or None).
    """
    z_of = _z_map(task)
    flat = lambda tree: ravel_pytree(tree)[0]  # noqa: E731

    if with_x:
        def one(x, cts):
            _, vjp = jax.vjp(z_of, x, policy)
            cx, cpol = jax.vmap(vjp)(cts)
            return jax.vmap(flat)(cpol), cx

        g, cx = jax.vmap(one, in_axes=(0, 1), out_axes=1)(x_prev, ct_z)
        return g, cx

    def one_theta(x, cts):
        _, vjp = jax.vjp(lambda pol: z_of(x, pol), policy)
        (cpol,) = jax.vmap(vjp)(cts)
        return jax.vmap(flat)(cpol)

    return jax.vmap(one_theta, in_axes=(0, 1), out_axes=1)(x_prev, ct_z), None


def _to_z(gam: ZetaGrad, jac_mean, jac_std) -> jax.Array:
    """ζ-cotangent → z-cotangent: Jμᵀ γμ + Jsᵀ γs (s is constant in z under −σ_f)."""
    ct = jnp.einsum("pd,pdz->pz", gam.mean, jac_mean)
    if jac_std is not None:
        ct = ct + jnp.einsum("pd,pdz->pz", gam.std, jac_std)
    return ct


def mean_returns(task: Problem, record: ParticleRecord, est: Estimator) -> jax.Array:
    """Per-step mean return-to-go of a forward record, (T,) — the "previous" baseline's source."""
    def step_cost(x_t, c):
        return est.costs.step(task.cost, x_t, c, None, None, gradient=False).cost

    c = jax.vmap(step_cost)(record.x_next, record.cost)  # (T, P)
    returns = jnp.cumsum(c[::-1], axis=0)[::-1]
    return jnp.mean(returns, axis=-1)


def backward_sweep(
    task: Problem,
    policy,
    record: ParticleRecord,
    config: RolloutConfig,
    est: Estimator,
    previous: PreviousIteration,
) -> SweepOutput:
    """Run the reverse sweep; returns per-particle contributions and per-step diagnostics."""
    T, P, D = record.x.shape
    n_theta = ravel_pytree(policy)[0].size
    dtype = record.x.dtype
    nan = jnp.asarray(jnp.nan, dtype)
    kinds = est.kinds

    def step(carry, xs):
        G, cot_x, contrib = carry
        x_prev, mean, std, eps, x_t, cost, jm, js, b_prev, k_prev = xs
        terms = est.costs.step(task.cost, x_t, cost, G, b_prev, gradient=est.pathwise)
        G = G + terms.cost

        inputs = StepInputs(x_t, mean, std, eps, G, b_prev, cot_x, terms.gradient)
        gammas = tuple(part.zeta(inputs, config) for part in est.parts)
        ct_z = jnp.stack([_to_z(g, jm, js) for g in gammas])
        pull_back = partial(_pull_back, task, policy, x_prev, with_x=est.pathwise)
        step_parts = PartCotangents(gammas, ct_z, task.action_dim, pull_back)
        out = est.combiner.combine(kinds, step_parts, k_prev, previous.has_previous)
        variance = dict(zip(kinds, out.variances))
        new_cot_x = cot_x if out.message is None else out.message

        finite = jnp.all(jnp.isfinite(out.gradient))
        diag = StepDiagnostics(
            out.k, out.k_batch, variance.get(PATHWISE, nan), variance.get(LIKELIHOOD_RATIO, nan),
            jnp.mean(G), terms.objective, ~finite,
        )
        return (G, new_cot_x, contrib + out.gradient), diag

    xs = (
        record.x,
        record.mean,
        record.std,
        record.eps,
        record.x_next,
        record.cost,
        record.jac_mean,
        record.jac_std,
        previous.baseline,
        previous.k_lr,
    )
    init = (jnp.zeros(P, dtype), jnp.zeros((P, D), dtype), jnp.zeros((P, n_theta), dtype))
    (_, _, contrib), diag = jax.lax.scan(step, init, xs, reverse=True)
    return SweepOutput(contrib, diag)
