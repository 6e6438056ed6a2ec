"""An SE-kernel regression at a Gaussian input: the GP dynamics model and the RBF controller (PILCO's gp*d.m).

Both are ``f_a(z) = Σ_i β_{a,i} k_a(z, z_i)`` with ``k_a(z, z') = σ_{f,a}² exp(−½ (z−z')ᵀ Λ_a⁻¹ (z−z'))``
(``Λ_a = diag(ℓ_a²)``), evaluated at ``z ~ N(μ, Σ)``. With ``ν_i = z_i − μ``:

* mean: ``q_{a,i} = σ_{f,a}² |ΣΛ_a⁻¹ + I|^{−½} exp(−½ ν_iᵀ(Σ + Λ_a)⁻¹ν_i)``, ``M_a = β_aᵀ q_a``;
* input–output: ``C_{:,a} = Σ⁻¹Cov[z, f_a] = Σ_i β_{a,i} q_{a,i} (Σ + Λ_a)⁻¹ν_i``;
* second moments: ``Q^{ab}_{ij} = k_a(z_i, μ) k_b(z_j, μ) |R_ab|^{−½} exp(½ ζ_ijᵀ R_ab⁻¹ Σ ζ_ij)``,
  ``R_ab = Σ(Λ_a⁻¹ + Λ_b⁻¹) + I``, ``ζ_ij = Λ_a⁻¹ν_i + Λ_b⁻¹ν_j``, and
  ``E[f_a f_b] = β_aᵀ Q^{ab} β_b + δ_ab (σ_{f,a}² − tr[inv_a Q^{aa}])`` — the δ_ab term is the
  model uncertainty ``E_z[var_f f_a(z)]`` (GP only; the controller has none).

Every matrix that is factorised is a symmetric "identity plus PSD" matrix, so the routine stays
well conditioned however singular Σ is: ``Λ_a^{−½} Σ Λ_a^{−½} + I`` for the mean and
``P^{½} Σ P^{½} + I`` (``P = Λ_a⁻¹ + Λ_b⁻¹``, which has the determinant of ``R_ab``) for the
second moments, where ``R_ab⁻¹Σ = P^{−½} [(P^{½}ΣP^{½} + I)⁻¹ P^{½}ΣP^{½}] P^{−½}``. Only the
pairs a ≤ b are computed (static index arrays; einsum over pairs and data points).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from pipps.gaussian import GaussianMap
from pipps.gp.types import GPPosterior


def _chol_logdet(chol: jax.Array) -> jax.Array:
    return 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol, axis1=-2, axis2=-1)), axis=-1)


def _mean_and_cross(inputs, beta, lengthscale, signal_var, mean, cov):
    """M (E,), C (D, E) and the scaled residuals ν_i/ℓ_a (E, n, D)."""
    dim = mean.shape[0]
    eye = jnp.eye(dim, dtype=mean.dtype)
    nu_s = (inputs - mean)[None, :, :] / lengthscale[:, None, :]  # (E, n, D) Λ_a^{-½} ν_i
    B = cov[None] / (lengthscale[:, :, None] * lengthscale[:, None, :]) + eye  # Λ^{-½}ΣΛ^{-½} + I
    chol = jnp.linalg.cholesky(B)
    # B⁻¹ is D×D: form it once per output and apply it with einsum (a batched triangular solve
    # against the n right-hand sides is ~20× slower on CPU).
    B_inv = jax.vmap(lambda L: jax.scipy.linalg.cho_solve((L, True), eye))(chol)
    B_inv = 0.5 * (B_inv + jnp.swapaxes(B_inv, -1, -2))
    t = jnp.einsum("edf,enf->end", B_inv, nu_s)  # B⁻¹ ν̃
    log_q = -0.5 * _chol_logdet(chol)[:, None] - 0.5 * jnp.sum(nu_s * t, axis=-1)
    bq = beta * signal_var[:, None] * jnp.exp(log_q)  # (E, n) β_{a,i} q_{a,i}
    M = jnp.sum(bq, axis=-1)
    C = jnp.einsum("en,end->de", bq, t / lengthscale[:, None, :])  # (Σ+Λ_a)⁻¹ν_i = Λ^{-½}B⁻¹ν̃_i
    return M, C, nu_s


def pair_weights(beta: jax.Array, inv: jax.Array) -> jax.Array:
    """``W^{ab} = β_a β_bᵀ − δ_ab inv_a`` for the pairs a ≤ b (``np.triu_indices`` order): (pairs, n, n).

    ``Σ_ij W^{ab}_ij Q^{ab}_ij = E[f_a f_b] − δ_ab σ_{f,a}²`` in one pass over each ``Q^{ab}``. W
    depends on the model only, so a propagation computes it once, not at every step (see
    :class:`WeightedGP`)."""
    ia, ib = np.triu_indices(beta.shape[0])
    w = beta[ia][:, :, None] * beta[ib][:, None, :]
    return w.at[np.nonzero(ia == ib)[0]].add(-inv)


class WeightedGP(NamedTuple):
    """A GP posterior with its :func:`pair_weights`, for propagations that keep the model uncertainty
    (:func:`pipps.pilco.propagate.objective` builds it once per call; 10 × n² numbers for E = 4)."""

    post: GPPosterior
    weights: jax.Array


def weighted(post: GPPosterior) -> WeightedGP:
    return WeightedGP(post, pair_weights(post.beta, post.inv))


def _pair_second_moments(inputs, beta, lengthscale, signal_var, mean, cov, nu_s, inv, weights=None):
    """E[f_a f_b] − δ_ab-term for the pairs a ≤ b, and tr[inv_a Q^{aa}] if ``inv`` is given; with
    ``weights`` (:func:`pair_weights`) the trace is inside the first result and the second is None."""
    n_out, dim = lengthscale.shape
    ia, ib = np.triu_indices(n_out)
    eye = jnp.eye(dim, dtype=mean.dtype)
    inv_lsq = lengthscale ** -2  # (E, D) diag Λ_a⁻¹
    sqrt_p = jnp.sqrt(inv_lsq[ia] + inv_lsq[ib])  # (P, D) P^{½}
    T = cov[None] * sqrt_p[:, :, None] * sqrt_p[:, None, :]  # P^{½} Σ P^{½}
    chol = jnp.linalg.cholesky(T + eye)
    A = jax.vmap(lambda L, t: jax.scipy.linalg.cho_solve((L, True), t))(chol, T)  # (T+I)⁻¹T
    A = 0.5 * (A + jnp.swapaxes(A, -1, -2))
    # ζ_ij scaled by P^{-½}: u_i + w_j with u_i = Λ_a⁻¹ν_i P^{-½}, w_j = Λ_b⁻¹ν_j P^{-½}
    nu = inputs - mean
    u = nu[None] * (inv_lsq[ia] / sqrt_p)[:, None, :]  # (P, n, D)
    w = nu[None] * (inv_lsq[ib] / sqrt_p)[:, None, :]
    Au = jnp.einsum("pde,pie->pid", A, u)
    Aw = jnp.einsum("pde,pje->pjd", A, w)
    log_k = jnp.log(signal_var)[:, None] - 0.5 * jnp.sum(nu_s**2, axis=-1)  # (E, n) log k_a(z_i, μ)
    log_Q = (
        (log_k[ia] + 0.5 * jnp.sum(u * Au, -1))[:, :, None]
        + (log_k[ib] + 0.5 * jnp.sum(w * Aw, -1))[:, None, :]
        + jnp.einsum("pid,pjd->pij", u, Aw)
        - 0.5 * _chol_logdet(chol)[:, None, None]
    )
    Q = jnp.exp(log_Q)  # (P, n, n)
    if weights is not None:
        return jnp.einsum("pij,pij->p", weights, Q), None, ia, ib
    second = jnp.einsum("pi,pij,pj->p", beta[ia], Q, beta[ib])
    trace = None
    if inv is not None:
        diag_pairs = np.nonzero(ia == ib)[0]  # pairs (a, a) in the order a = 0..E-1
        trace = jnp.einsum("eij,eij->e", inv, Q[diag_pairs])
    return second, trace, ia, ib


def se_moments(
    inputs: jax.Array,
    beta: jax.Array,
    lengthscale: jax.Array,
    signal_var: jax.Array,
    mean: jax.Array,
    cov: jax.Array,
    *,
    inv: jax.Array | None = None,
    second_moment_jitter: float = 0.0,
    weights: jax.Array | None = None,
) -> GaussianMap:
    """Moments of ``f(z) = [Σ_i β_{a,i} k_a(z, z_i)]_a`` at ``z ~ N(mean, cov)`` (docs/pilco.md).

    Args:
      inputs: (n, D) training inputs / inducing inputs / RBF centres z_i.
      beta: (E, n) weights β_a.
      lengthscale: (E, D) ℓ_a (Λ_a = diag(ℓ_a²)).
      signal_var: (E,) σ_{f,a}².
      mean, cov: the Gaussian input, (D,) and (D, D).
      inv: (E, n, n) ``(K_a + σ_n²I)⁻¹`` (full GP) or ``K_mm⁻¹ − B_a⁻¹`` (FITC) to include the
        model-uncertainty term ``δ_ab(σ_{f,a}² − tr[inv_a Q^{aa}])``; None leaves it out
        (a static choice: nothing of it is traced).
      second_moment_jitter: added to the diagonal of ``E[f fᵀ]`` before centring (PILCO's 1e-6
        for the RBF controller).
      weights: :func:`pair_weights` of ``(beta, inv)``, precomputed: the same moments (to rounding)
        with the β and trace terms in one pass over each Q; needs ``inv``.

    Returns:
      ``GaussianMap(M (E,), S (E, E), C (D, E))``.
    """
    M, C, nu_s = _mean_and_cross(inputs, beta, lengthscale, signal_var, mean, cov)
    if weights is not None and inv is None:
        raise ValueError("weights carry the model-uncertainty term: pass inv with them")
    second, trace, ia, ib = _pair_second_moments(inputs, beta, lengthscale, signal_var, mean, cov, nu_s, inv,
                                                 weights)
    n_out = M.shape[0]
    ff = jnp.zeros((n_out, n_out), dtype=M.dtype).at[ia, ib].set(second).at[ib, ia].set(second)
    diag = jnp.full((n_out,), second_moment_jitter, dtype=M.dtype)
    if weights is not None:
        diag = diag + signal_var
    elif trace is not None:
        diag = diag + signal_var - trace
    S = ff + jnp.diag(diag) - jnp.outer(M, M)
    return GaussianMap(M, 0.5 * (S + S.T), C)


def gp_moments(post: GPPosterior | WeightedGP, mean: jax.Array, cov: jax.Array, *,
               model_uncertainty: bool = True) -> GaussianMap:
    """The latent GP ``Δ = f(z)`` at ``z ~ N(mean, cov)``, full or FITC posterior alike.

    ``model_uncertainty`` (static) keeps the ``E_z[var_f f_a(z)]`` term of ``S``; False drops it
    and its O(E n²) trace. No noise variance σ_n² is added (the latent function is predicted).
    Padded rows (β = 0, zero rows/columns of ``inv``) contribute exactly nothing. With
    ``model_uncertainty`` the β and trace terms are one pass over each Q (:func:`pair_weights`,
    precomputed in a :class:`WeightedGP`, else formed here).
    """
    if isinstance(post, WeightedGP):
        post, weights = post.post, post.weights
    elif model_uncertainty:
        weights = pair_weights(post.beta, post.inv)
    hyper = post.hyper
    return se_moments(
        post.inputs,
        post.beta,
        jnp.exp(hyper.log_lengthscale),
        jnp.exp(2.0 * hyper.log_signal),
        mean,
        cov,
        inv=post.inv if model_uncertainty else None,
        weights=weights if model_uncertainty else None,
    )
