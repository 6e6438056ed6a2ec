"""The custom backward pass: one reverse sweep over time (thesis Alg. 5; estimators.md §2–§6).

The sweep runs ``t = T, …, 1`` over the :class:`~pipps.particles.forward.ParticleRecord` and
carries, per particle, the returns ``G_{i,t}`` and — when the pathwise part is on — the
pathwise derivative of the return with respect to the particle, ``∂G_i/∂x_{i,t}``. At each step:

1. ``G_{i,t} = G_{i,t+1} + c_{i,t}`` (:mod:`~pipps.propagation.cost_terms`);
2. RP in ζ-space: ``γ^RP_{i,t} = a_i ∂x_{i,t}/∂ζ_{i,t}`` with ``a_i = ∂G_i/∂x_{i,t} + ∂c_i/∂x_{i,t}``;
   for ``x = μ + s ⊙ ε`` that is ``(a, a ⊙ ε)``, for GR the VJP of the resampling;
3. LR in ζ-space (:mod:`~pipps.propagation.lr`);
4. both to θ through the direct path ``∂ζ_{i,t}/∂u_{i,t−1} · ∂u_{i,t−1}/∂θ`` — per particle, with
   the model Jacobians recorded by the forward pass and a VJP of the (cheap) map
   ``x ↦ z = [x̃[I]; π(x̃[P]; θ)]``;
5. TP's weight ``k_LR`` from the per-particle gradient variances (:mod:`~pipps.propagation.combine`);
6. the estimate accumulates ``k·g^LR + (1−k)·g^RP`` per particle;
7. ``λ = k γ^LR + (1−k) γ^RP`` is passed back through ``dζ_{i,t}/dx_{i,t−1}``.

What is computed is fixed at trace time by the :class:`~pipps.propagation.config.Estimator`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from pipps.particles.forward import ParticleRecord, RolloutConfig
from pipps.propagation.combine import inverse_variance_k, robust_k, variance_trace
from pipps.propagation.config import Estimator
from pipps.propagation.lr import ZetaGrad, mix
from pipps.propagation.parts import StepInputs
from pipps.tasks.base import Task


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


def _z_map(task: Task):
    def z_of(x, policy):
        return task.gp_input(x, policy(task.policy_input(x)))

    return z_of


def _pull_back(task: Task, policy, x_prev, ct_z, *, with_x: bool):
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


def _choose_k(est: Estimator, var_rp, var_lr, mean_rp, mean_lr, k_prev, has_prev, P):
    if est.combiner == "robust":
        k_batch = robust_k(var_rp, var_lr, mean_rp, mean_lr, P, est.robust_gamma, est.robust_z)
    else:
        k_batch = inverse_variance_k(var_rp, var_lr)
    if isinstance(est.k_lr, str):
        k = k_batch if est.k_lr == "batch" else jnp.where(has_prev, k_prev, k_batch)
    else:
        k = jnp.asarray(float(est.k_lr), dtype=var_rp.dtype)
    # a part whose gradients are not finite gets no weight, whatever the source of k
    k = jnp.where(jnp.isfinite(var_rp), k, 1.0)
    k = jnp.where(jnp.isfinite(var_lr), k, jnp.where(jnp.isfinite(var_rp), 0.0, k))
    return k, k_batch


def mean_returns(task: Task, record: ParticleRecord, est: Estimator) -> jax.Array:
    """Per-step mean return-to-go of a forward record, (T,) — the "previous" baseline's source."""
    def step_cost(x_t, c):
        return est.costs.step(task.cost, x_t, c, None, None, gradient=False).cost

    c = jax.vmap(step_cost)(record.x_next, record.cost)  # (T, P)
    returns = jnp.cumsum(c[::-1], axis=0)[::-1]
    return jnp.mean(returns, axis=-1)


def backward_sweep(
    task: Task,
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

    def step(carry, xs):
        G, cot_x, contrib = carry
        x_prev, mean, std, eps, x_t, cost, jm, js, b_prev, k_prev = xs
        terms = est.costs.step(task.cost, x_t, cost, G, b_prev, gradient=est.pathwise)
        G = G + terms.cost

        inputs = StepInputs(x_t, mean, std, eps, G, b_prev, cot_x, terms.gradient)
        gammas = [part.zeta(inputs, config) for part in est.parts]
        ct_z = jnp.stack([_to_z(g, jm, js) for g in gammas])
        g_theta, cx = _pull_back(task, policy, x_prev, ct_z, with_x=est.pathwise)

        var_rp = var_lr = nan
        k = k_batch = jnp.asarray(0.0 if est.pathwise else 1.0, dtype)
        if est.total_propagation:
            g_rp, g_lr = g_theta[0], g_theta[1]
            var_rp, var_lr = variance_trace(g_rp), variance_trace(g_lr)
            k, k_batch = _choose_k(est, var_rp, var_lr, g_rp.mean(0), g_lr.mean(0), k_prev, previous.has_previous, P)
            g = mix(k, g_lr, g_rp)
            new_cot_x = mix(k, cx[1] + gammas[1].mean, cx[0] + gammas[0].mean)
        else:
            g = g_theta[0]
            var = variance_trace(g)
            var_rp, var_lr = (var, nan) if est.pathwise else (nan, var)
            new_cot_x = cx[0] + gammas[0].mean if est.pathwise else cot_x

        finite = jnp.all(jnp.isfinite(g))
        diag = StepDiagnostics(k, k_batch, var_rp, var_lr, jnp.mean(G), terms.objective, ~finite)
        return (G, new_cot_x, contrib + g), diag

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
