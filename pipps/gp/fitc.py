"""Sparse GP with FITC (Snelson & Ghahramani 2006) as PILCO uses it (docs/gp.md, "Sparse FITC").

With inducing inputs X_u (M, Dz) shared by all outputs, K_mm carrying ``fitc_jitter`` (PILCO's
ridge 1e-6), V = L⁻¹K_mn (L = chol K_mm), Q_nn = VᵀV and Λ_a = diag(K_nn − Q_nn) + σ_n,a² I:

    −log p_FITC(y_a) = ½ log|Q_nn + Λ_a| + ½ y_aᵀ(Q_nn + Λ_a)⁻¹y_a + (n/2) log 2π,

evaluated through A = I + V Λ⁻¹ Vᵀ (M×M) with the determinant lemma and Woodbury. The
posterior has the fields of the full GP (the moment-matching formulas with training inputs replaced by X_u):
β_a = B_a⁻¹ K_mn Λ_a⁻¹ y_a and inv_a = K_mm⁻¹ − B_a⁻¹, B_a = K_mm + K_mn Λ_a⁻¹ K_nm = L A Lᵀ.
Padded rows (mask False) get zero K_mn columns, zero targets and Λ = 1: no effect.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from pipps.gp.data import clean
from pipps.gp.kernel import se_ard
from pipps.gp.linalg import adaptive_cholesky, chol_inverse, map_outputs
from pipps.gp.objective import floored_log_noise, hyper_to_rows
from pipps.gp.posterior import with_noise_floor
from pipps.gp.types import GPConfig, GPData, GPHyper, GPPosterior

_tri = jax.scipy.linalg.solve_triangular


def kmm_scale(psi: jax.Array) -> jax.Array:
    return jnp.exp(2.0 * psi[-2])


def inducing_gram(psi: jax.Array, xu: jax.Array) -> jax.Array:
    """K_mm of one output without jitter: (M, M)."""
    return se_ard(xu, xu, psi[:-2], psi[-2])


def _fitc_factors(psi, xu, x, y, mask, chol_mm, noise_floor):
    """V Λ^{-1/2}, y Λ^{-1/2}, Λ and chol(A) for one output."""
    kmn = jnp.where(mask[None, :], se_ard(xu, x, psi[:-2], psi[-2]), 0.0)
    v = _tri(chol_mm, kmn, lower=True)  # (M, N)
    sf2 = jnp.exp(2.0 * psi[-2])
    sn2 = jnp.exp(2.0 * floored_log_noise(psi[-1], noise_floor))
    lam = jnp.where(mask, jnp.maximum(sf2 - jnp.sum(v * v, 0), 0.0) + sn2, 1.0)
    rs = jax.lax.rsqrt(lam)
    vs = v * rs[None, :]
    ys = jnp.where(mask, y, 0.0) * rs
    a = jnp.eye(xu.shape[0], dtype=x.dtype) + vs @ vs.T
    return vs, ys, lam, jnp.linalg.cholesky(a)


def fitc_neg_log_likelihood(psi, xu, x, y, mask, ridge, noise_floor) -> jax.Array:
    """−log p_FITC(y_a) of one output with K_mm + ridge·I; NaN if a Cholesky fails."""
    kmm = inducing_gram(psi, xu) + ridge * jnp.eye(xu.shape[0], dtype=xu.dtype)
    vs, ys, lam, chol_a = _fitc_factors(psi, xu, x, y, mask, jnp.linalg.cholesky(kmm), noise_floor)
    c = _tri(chol_a, vs @ ys, lower=True)
    n = jnp.sum(mask.astype(x.dtype))
    return (0.5 * jnp.sum(jnp.log(lam)) + jnp.sum(jnp.log(jnp.diagonal(chol_a)))
            + 0.5 * (jnp.dot(ys, ys) - jnp.dot(c, c)) + 0.5 * n * math.log(2.0 * math.pi))


def fitc_objective(xu: jax.Array, hyper: GPHyper, data: GPData, ridge: jax.Array, config: GPConfig) -> jax.Array:
    """Σ_a −log p_FITC(y_a) as a function of the shared inducing inputs X_u.

    ``ridge`` is the (E,) jitter on each K_mm (normally ``config.fitc_jitter``).
    """
    def one(args):
        psi, y, r = args
        return fitc_neg_log_likelihood(psi, xu, data.inputs, y, data.mask, r, config.noise_floor)

    return jnp.sum(map_outputs(one, (hyper_to_rows(hyper), data.targets.T, ridge), config.output_batching))


def fitc_ridge(hyper: GPHyper, xu: jax.Array, config: GPConfig) -> jax.Array:
    """(E,) jitter on K_mm: ``config.fitc_jitter``, escalated ×10 where the Cholesky fails."""
    def one(psi):
        _, jitter, _ = adaptive_cholesky(
            inducing_gram(psi, xu), base_jitter=config.fitc_jitter, jitter_min=config.jitter_min,
            scale=kmm_scale(psi), max_tries=config.max_jitter_tries)
        return jitter
    return map_outputs(one, hyper_to_rows(hyper), config.output_batching)


def fitc_posterior(hyper: GPHyper, data: GPData, xu: jax.Array, config: GPConfig) -> tuple[GPPosterior, jax.Array, jax.Array]:
    """FITC β_a and K_mm⁻¹ − B_a⁻¹ for all outputs, with adaptive K_mm jitter.

    Returns:
      (posterior, jitter (E,), ok (E,)) as :func:`pipps.gp.posterior.full_posterior`.
    """
    data = clean(data)
    hyper = with_noise_floor(hyper, config.noise_floor)
    m = xu.shape[0]
    eye = jnp.eye(m, dtype=xu.dtype)

    def one(args):
        psi, y = args
        chol_mm, jitter, ok_mm = adaptive_cholesky(
            inducing_gram(psi, xu), base_jitter=config.fitc_jitter, jitter_min=config.jitter_min,
            scale=kmm_scale(psi), max_tries=config.max_jitter_tries)
        vs, ys, _, chol_a = _fitc_factors(psi, xu, data.inputs, y, data.mask, chol_mm, config.noise_floor)
        c = _tri(chol_a, vs @ ys, lower=True)
        beta = _tri(chol_mm.T, _tri(chol_a.T, c, lower=False), lower=False)  # L⁻ᵀ A⁻¹ V Λ^{-1/2} y
        linv = _tri(chol_mm, eye, lower=True)
        inv = linv.T @ (eye - chol_inverse(chol_a)) @ linv  # K_mm⁻¹ − B⁻¹ = L⁻ᵀ (I − A⁻¹) L⁻¹
        ok = ok_mm & jnp.all(jnp.isfinite(chol_a))
        return beta, 0.5 * (inv + inv.T), jitter, ok

    beta, inv, jitter, ok = map_outputs(one, (hyper_to_rows(hyper), data.targets.T), config.output_batching)
    return GPPosterior(hyper, xu, beta, inv), jitter, ok


def initial_inducing(key: jax.Array, data: GPData, num_inducing: int) -> jax.Array:
    """A random subset, without replacement, of the real training inputs: (M, Dz) (PILCO's first FITC start).

    Requires at least ``num_inducing`` real rows (checked by the caller on the host).
    """
    p = data.mask.astype(data.inputs.dtype)
    idx = jax.random.choice(key, data.inputs.shape[0], (num_inducing,), replace=False, p=p / jnp.sum(p))
    return data.inputs[idx]
