"""GP training (docs/gp.md): pure, vmappable pieces.

* :func:`initial_hyper` — PILCO's first-time initialisation.
* :func:`fit_hyper` — per-output penalised marginal-likelihood training with L-BFGS, mapped
  over outputs (:func:`pipps.gp.linalg.map_outputs`).
* :func:`fit_inducing` — FITC inducing-input optimisation with the hyperparameters fixed.

The host-level entry point that validates data, jits these, builds the posterior and emits
warnings is :func:`pipps.gp.fit.fit`.
"""

from __future__ import annotations

import math
from typing import Optional

import jax
import jax.numpy as jnp

from pipps.gp.data import clean, masked_rms, masked_std
from pipps.gp.fitc import fitc_objective, fitc_ridge
from pipps.gp.lbfgs import lbfgs_minimize
from pipps.gp.linalg import adaptive_cholesky, map_outputs
from pipps.gp.objective import floored_log_noise, hyper_objective, hyper_to_rows, noisy_gram, rows_to_hyper
from pipps.gp.types import FitcFitInfo, GPConfig, GPData, GPHyper, HyperFitInfo


def input_log_std(data: GPData, config: GPConfig) -> tuple[jax.Array, jax.Array]:
    """log s_d, the floored sample std of each input column, and where the floor acted: (Dz,), (Dz,)."""
    s = masked_std(data.inputs, data.mask)
    floored = s < config.input_std_floor
    return jnp.log(jnp.maximum(s, config.input_std_floor)), floored


def initial_hyper(data: GPData, config: GPConfig) -> tuple[GPHyper, jax.Array]:
    """First-time initialisation (PILCO's): log ℓ = log s_d, σ_f = std(y_a), σ_n = std(y_a)/10.

    Degenerate targets: where std(y_a) < ``target_std_floor`` the root mean square of y_a is
    used instead (a zero-mean GP must explain a constant offset with σ_f), floored at
    ``target_std_floor``. Returns (hyper, target_std_floored (E,)).
    """
    data = clean(data)
    log_s, _ = input_log_std(data, config)
    sy = masked_std(data.targets, data.mask)
    floored = sy < config.target_std_floor
    sy = jnp.where(floored, jnp.maximum(masked_rms(data.targets, data.mask), config.target_std_floor), sy)
    e = data.targets.shape[1]
    hyper = GPHyper(jnp.tile(log_s, (e, 1)), jnp.log(sy), jnp.log(sy) - math.log(10.0))
    return hyper, floored


def start_jitter(rows: jax.Array, data: GPData, config: GPConfig) -> jax.Array:
    """(E,) jitter for training: ``config.jitter``, escalated ×10 where chol(K_y) fails at the start."""
    def one(psi):
        ky = noisy_gram(psi, data.inputs, data.mask, 0.0, config.noise_floor)
        scale = jnp.exp(2.0 * psi[-2]) + jnp.exp(2.0 * floored_log_noise(psi[-1], config.noise_floor))
        _, jitter, _ = adaptive_cholesky(
            ky, base_jitter=config.jitter, jitter_min=config.jitter_min, scale=scale,
            max_tries=config.max_jitter_tries, diag_mask=data.mask)
        return jitter
    return map_outputs(one, rows, config.output_batching)


def fit_hyper(data: GPData, init: Optional[GPHyper], config: GPConfig) -> tuple[GPHyper, HyperFitInfo]:
    """Train the hyperparameters of all outputs (docs/gp.md, "Optimiser and budgets").

    Pure; vmappable over data sets on accelerators (on CPU with jaxlib 0.10 batched LAPACK calls
    can deadlock, see :func:`pipps.gp.linalg.map_outputs`; use ``lax.map`` there).

    Args:
      data: training set (padded rows are ignored).
      init: warm start (the previous training's hyperparameters), or None for the first-time
        initialisation of :func:`initial_hyper`.
      config: settings (its numbers may be traced).

    Returns:
      (hyper, info). The returned ``log_noise`` is at least log(noise_floor).
    """
    data = clean(data)
    if init is None:
        init, target_floored = initial_hyper(data, config)
    else:
        target_floored = jnp.zeros(data.targets.shape[1], bool)
    log_s, input_floored = input_log_std(data, config)
    rows0 = hyper_to_rows(init)
    jitter = start_jitter(rows0, data, config)

    def one(args):
        psi0, y, jit = args

        def fun(psi):
            return hyper_objective(psi, data.inputs, y, data.mask, log_s, jit, config)
        return lbfgs_minimize(fun, psi0, max_iters=config.max_iters, memory_size=config.memory_size,
                              max_linesearch_steps=config.max_linesearch_steps, grad_tol=config.grad_tol)

    rows, info = map_outputs(one, (rows0, data.targets.T, jitter), config.output_batching)
    noise_floored = rows[:, -1] < jnp.log(config.noise_floor)
    rows = rows.at[:, -1].set(floored_log_noise(rows[:, -1], config.noise_floor))
    return rows_to_hyper(rows), HyperFitInfo(
        objective_init=info.value_init, objective=info.value, iterations=info.iterations,
        failed_linesearches=info.failures, grad_norm=info.grad_norm, jitter=jitter,
        noise_floored=noise_floored, input_std_floored=input_floored, target_std_floored=target_floored)


def fit_inducing(data: GPData, hyper: GPHyper, xu0: jax.Array, config: GPConfig, max_iters) -> tuple[jax.Array, FitcFitInfo]:
    """Optimise the shared inducing inputs X_u with fixed hyperparameters (docs/gp.md, "Sparse FITC").

    Minimises Σ_a −log p_FITC(y_a) with L-BFGS (memory ``fitc_memory_size``) for at most
    ``max_iters`` line searches (may be traced): ``config.fitc_first_iters`` the first time,
    ``config.fitc_iters`` when warm-started.
    """
    data = clean(data)
    ridge = fitc_ridge(hyper, xu0, config)

    def fun(xu):
        return fitc_objective(xu, hyper, data, ridge, config)

    xu, info = lbfgs_minimize(fun, xu0, max_iters=max_iters, memory_size=config.fitc_memory_size,
                              max_linesearch_steps=config.max_linesearch_steps, grad_tol=config.fitc_grad_tol)
    return xu, FitcFitInfo(info.value_init, info.value, info.iterations, info.failures, ridge)
