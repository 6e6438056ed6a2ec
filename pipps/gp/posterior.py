"""Full-GP posterior, built once per training, and batched prediction (docs/gp.md).

:func:`full_posterior` stores β_a = (K_a + σ_n²I)⁻¹ y_a and (K_a + σ_n²I)⁻¹ for every output
(padded rows and columns zeroed). :func:`predict` evaluates the mean k*ᵀβ and, only when asked
(``variance=True``, a static Python bool), the latent epistemic variance σ_f² − k*ᵀ inv k*.
The FITC posterior (:mod:`pipps.gp.fitc`) has the same fields, so every consumer treats both
alike.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from pipps.gp.data import clean
from pipps.gp.kernel import se_ard_batched
from pipps.gp.linalg import adaptive_cholesky, chol_inverse, map_outputs
from pipps.gp.objective import floored_log_noise, hyper_to_rows, noisy_gram
from pipps.gp.types import GPConfig, GPData, GPHyper, GPPosterior


def with_noise_floor(hyper: GPHyper, noise_floor: float) -> GPHyper:
    """The hyperparameters with σ_n raised to the noise floor (what the model actually uses)."""
    return hyper._replace(log_noise=floored_log_noise(hyper.log_noise, noise_floor))


def full_posterior(hyper: GPHyper, data: GPData, config: GPConfig) -> tuple[GPPosterior, jax.Array, jax.Array]:
    """β and (K + σ_n²I)⁻¹ of the full GP for all outputs.

    The Cholesky factor uses the adaptive jitter of :func:`pipps.gp.linalg.adaptive_cholesky`
    starting from ``config.jitter``.

    Returns:
      (posterior, jitter (E,), ok (E,)): the jitter added to each K_y and whether its Cholesky
      succeeded (if not, that output's β and inv are NaN).
    """
    data = clean(data)
    hyper = with_noise_floor(hyper, config.noise_floor)
    rows = hyper_to_rows(hyper)

    def one(args):
        psi, y = args
        ky = noisy_gram(psi, data.inputs, data.mask, 0.0, config.noise_floor)
        scale = jnp.exp(2.0 * psi[-2]) + jnp.exp(2.0 * psi[-1])
        chol, jitter, ok = adaptive_cholesky(
            ky, base_jitter=config.jitter, jitter_min=config.jitter_min, scale=scale,
            max_tries=config.max_jitter_tries, diag_mask=data.mask)
        beta = jax.scipy.linalg.cho_solve((chol, True), y)
        pair = data.mask[:, None] & data.mask[None, :]
        inv = jnp.where(pair, chol_inverse(chol), 0.0)
        return jnp.where(data.mask, beta, 0.0), inv, jitter, ok

    beta, inv, jitter, ok = map_outputs(one, (rows, data.targets.T), config.output_batching)
    return GPPosterior(hyper, data.inputs, beta, inv), jitter, ok


def predict(post: GPPosterior, z: jax.Array, *, variance: bool = False):
    """GP predictions at a batch of deterministic inputs (the particles).

    Args:
      post: full or FITC posterior.
      z: (P, Dz) inputs.
      variance: static. If False, only the means are computed and nothing of the O(M²)
        variance path is traced.

    Returns:
      mean (P, E) if ``variance`` is False, else (mean (P, E), latent variance (P, E)) with
      variance σ_f² − k*ᵀ inv k* ≥ 0 (epistemic; the noise σ_n² is not added).
    """
    if z.ndim != 2 or z.shape[1] != post.inputs.shape[1]:
        raise ValueError(f"predict: z must have shape (P, {post.inputs.shape[1]}), got {z.shape}")
    ks = se_ard_batched(post.hyper, z, post.inputs)  # (E, P, M)
    mean = jnp.einsum("epm,em->pe", ks, post.beta)
    if not variance:
        return mean
    quad = jnp.einsum("epm,emn,epn->pe", ks, post.inv, ks)
    var = jnp.maximum(post.hyper.signal_variance[None, :] - quad, 0.0)
    return mean, var
