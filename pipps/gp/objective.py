"""The penalised negative log marginal likelihood of one output (PILCO's hypCurb; docs/gp.md).

    L_a(ψ_a) = ½ yᵀK_y⁻¹y + ½ log|K_y| + (n/2) log 2π
               + Σ_d ((log ℓ_{a,d} − log s_d) / log ls_curb)^p
               + ((log σ_f,a − log σ_n,a) / log snr_curb)^p,     K_y = K_a + σ_n,a² I,

with p = 30, ls_curb = 100, snr_curb = 1000 and s_d the sample std of input column d.
ψ_a = [log ℓ_{a,1..Dz}, log σ_f,a, log σ_n,a] is one row of :func:`hyper_to_rows`.

σ_n enters everywhere as max(σ_n, noise_floor) (the noise floor; see docs/gp.md). Padded rows
(mask False) are replaced by identity rows of K_y and zero targets, so they contribute exactly
nothing (log 1 = 0, n counts real rows only).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from pipps.gp.kernel import se_ard
from pipps.gp.types import GPConfig, GPHyper


def hyper_to_rows(hyper: GPHyper) -> jax.Array:
    """GPHyper → (E, Dz+2) rows ψ_a = [log ℓ_a, log σ_f,a, log σ_n,a] (PILCO's layout, transposed)."""
    return jnp.concatenate([hyper.log_lengthscale, hyper.log_signal[:, None], hyper.log_noise[:, None]], 1)


def rows_to_hyper(rows: jax.Array) -> GPHyper:
    """(E, Dz+2) rows → GPHyper (inverse of :func:`hyper_to_rows`)."""
    return GPHyper(rows[:, :-2], rows[:, -2], rows[:, -1])


def floored_log_noise(log_noise: jax.Array, noise_floor) -> jax.Array:
    """log max(σ_n, noise_floor): the noise actually used (gradient 0 below the floor).

    ``noise_floor`` may be traced; a floor of 0 gives log 0 = −∞, i.e. no floor."""
    return jnp.maximum(log_noise, jnp.log(noise_floor))


def noisy_gram(psi: jax.Array, x: jax.Array, mask: jax.Array, jitter: jax.Array, noise_floor) -> jax.Array:
    """K_y = K + (σ_n² + jitter) I on real rows; identity on padded rows/columns: (N, N)."""
    log_ell, log_sf, log_sn = psi[:-2], psi[-2], floored_log_noise(psi[-1], noise_floor)
    k = se_ard(x, x, log_ell, log_sf)
    pair = mask[:, None] & mask[None, :]
    diag = jnp.where(mask, jnp.exp(2.0 * log_sn) + jitter, 1.0)
    return jnp.where(pair, k, 0.0) + jnp.diag(diag)


def neg_log_marginal(psi, x, y, mask, jitter, noise_floor) -> jax.Array:
    """½ yᵀK_y⁻¹y + ½ log|K_y| + (n/2) log 2π of one output (unpenalised), masked.

    Non-finite (NaN) when the Cholesky of K_y fails; the optimiser treats that as a failed
    trial point.
    """
    ky = noisy_gram(psi, x, mask, jitter, noise_floor)
    chol = jnp.linalg.cholesky(ky)
    y = jnp.where(mask, y, 0.0)
    w = jax.scipy.linalg.solve_triangular(chol, y, lower=True)
    n = jnp.sum(mask.astype(y.dtype))
    return 0.5 * jnp.dot(w, w) + jnp.sum(jnp.log(jnp.diagonal(chol))) + 0.5 * n * math.log(2.0 * math.pi)


def penalty(psi: jax.Array, log_input_std: jax.Array, config: GPConfig) -> jax.Array:
    """PILCO's hyperparameter curb (hypCurb): length scales near the input spread, bounded SNR."""
    p = config.penalty_power
    log_ell, log_sf = psi[:-2], psi[-2]
    log_sn = floored_log_noise(psi[-1], config.noise_floor)
    ls = jnp.sum(((log_ell - log_input_std) / jnp.log(config.ls_curb)) ** p)
    snr = ((log_sf - log_sn) / jnp.log(config.snr_curb)) ** p
    return ls + snr


def hyper_objective(psi, x, y, mask, log_input_std, jitter, config: GPConfig) -> jax.Array:
    """The training objective L_a(ψ_a) of one output, to be minimised."""
    return neg_log_marginal(psi, x, y, mask, jitter, config.noise_floor) + penalty(psi, log_input_std, config)
