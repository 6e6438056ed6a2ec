"""A full-GP posterior whose predictive variance keeps only the directions it needs, with a
certificate (docs/performance.md, "The certified low-rank variance, measured").

For one output with ``K = U diag(λ) Uᵀ`` on the real (unpadded) points and ``σ² = σ_n² + jitter``,

    A = (K + σ²I)⁻¹ = P/σ² − U diag(d) Uᵀ,    d_i = λ_i / (σ² (λ_i + σ²)),

with P the projector on the real points. The predictive variance ``σ_f² − kᵀAk`` and the product
``w = A k`` the Jacobian needs become ``‖Pk‖²/σ² − Σ_i d_i (u_iᵀk)²`` and ``Pk/σ² − U (d ⊙ Uᵀk)``.
Keeping the r largest λ overestimates ``kᵀAk`` by ``e = Σ_{i>r} d_i (u_iᵀk)²`` ≥ 0, and since
``Σ_i (u_iᵀk)²/λ_i = kᵀK⁺k ≤ k(z, z) = σ_f²`` for any input z (the Schur complement of the kernel
matrix of the data and z is ≥ 0),

    0 ≤ e ≤ max_{i>r} λ_i d_i σ_f² = λ_{r+1}² σ_f² / (σ² (λ_{r+1} + σ²)),

a bound that holds for every particle before any particle is drawn. :func:`low_rank_posterior`
keeps, per output, the fewest directions whose bound is below ``tol·σ²``; the kept width is
rounded up to a multiple of ``bucket`` (unused columns have d = 0) so that a run compiles a
handful of shapes. The work per particle is 4·M·r flops against 2·M² for the exact product.

**FITC** (:func:`low_rank_fitc_posterior`). The variance is ``σ_f² − kᵀ inv k`` with
``inv = K_mm⁻¹ − B⁻¹`` over the M inducing inputs. With ``L Lᵀ = K_mm + ρI`` (ρ ≥ 0, the
posterior's jitter) and ``Lᵀ inv L = W diag(g) Wᵀ`` (g descending), ``v_i = L⁻ᵀ w_i`` gives
``kᵀ inv k = Σ_i g_i (v_iᵀk)²`` and ``inv k = Σ_i g_i v_i (v_iᵀk)``: the same form as above
with no ``‖Pk‖²`` term and coefficients ``−g``. Keeping the r largest g changes ``kᵀ inv k`` by
``Σ_{i>r} g_i (w_iᵀL⁻¹k)²``, and ``Σ_i (w_iᵀL⁻¹k)² = kᵀ(K_mm + ρI)⁻¹k ≤ σ_f²`` (the Schur
complement of the inducing inputs' and z's kernel matrix, with ρI added to a block, stays ≥ 0), so

    |e| ≤ max_{i>r} |g_i| σ_f²,

again for every input. (``g_i = s_i/(1 + s_i)`` for the eigenvalues s of the whitened data
precision ``L⁻¹K_mn Λ⁻¹ K_nm L⁻ᵀ`` when ρ is the posterior's own jitter; the bound is linear in
the dropped g, not quadratic as for the full GP, but FITC's spectra fall fast: docs/performance.md.)
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from pipps.gp.kernel import se_ard
from pipps.gp.types import GPData, GPHyper, GPPosterior


class LowRankPosterior(NamedTuple):
    """A full-GP or FITC posterior with the variance in the low-rank form of the module docstring.

    Attributes:
      hyper, inputs, beta: as in :class:`pipps.gp.GPPosterior` (the mean is exact).
      basis: per output a (M, R_a) array, the kept eigenvectors of its K (zero on padded rows);
        R_a is the output's rank rounded up to a multiple of ``bucket``.
      coef: per output (R_a,), d_i of the kept directions (0 in columns beyond the output's rank).
      inv_noise: (E,) 1/σ² (σ² = σ_n² + the posterior's jitter); None for FITC, which has no ‖Pk‖² term
        (static: a FITC rollout computes none of it).
      mask: (M,) 1.0 on real rows, 0.0 on padded ones; None for FITC (inducing inputs are never padded).
      bound: (E,) the certified bound on the variance error, in units of σ² (FITC: σ_n²).
    """

    hyper: GPHyper
    inputs: jax.Array
    beta: jax.Array
    basis: tuple
    coef: tuple
    inv_noise: jax.Array
    mask: jax.Array
    bound: jax.Array

    @property
    def noise_variance(self) -> jax.Array:
        return self.hyper.noise_variance


def spectrum_bounds(lam: np.ndarray, sf2: float, s2: float) -> np.ndarray:
    """``b[r]``: the certified error bound (units of σ²) when the r largest of ``lam`` (descending) are kept."""
    tail = np.concatenate([lam, [0.0]])  # keeping all: the bound is 0
    return tail ** 2 * sf2 / (s2 * (tail + s2)) / s2


def low_rank_posterior(post: GPPosterior, data: GPData, tol: float, *, jitter=None,
                       bucket: int = 25) -> tuple[LowRankPosterior, np.ndarray]:
    """The low-rank form of a full-GP ``post`` trained on ``data`` (module docstring), keeping per
    output the fewest directions whose certified variance error is below ``tol·σ²``.

    Returns ``(posterior, ranks (E,))``. ``jitter`` (E,): what the posterior's Cholesky added to
    σ_n² (``FitInfo.posterior_jitter``; default none). Runs on the host, once per trained model.
    """
    if not tol > 0:
        raise ValueError(f"tol must be > 0 (the exact variance is the plain posterior), got {tol}")
    if post.inputs.shape != data.inputs.shape:
        raise ValueError("low_rank_posterior needs the full GP posterior of these data (FITC has its own form)")
    mask = np.asarray(data.mask)
    x = np.asarray(post.inputs)  # the inputs the posterior was built from (cleaned; real rows first)
    hyper = post.hyper
    E, M = np.asarray(post.beta).shape
    s2 = np.exp(2.0 * np.asarray(hyper.log_noise)) + (np.zeros(E) if jitter is None else np.asarray(jitter))
    sf2 = np.exp(2.0 * np.asarray(hyper.log_signal))
    pair = mask[:, None] & mask[None, :]
    bases, coefs, ranks, bounds = [], [], [], []
    for a in range(E):
        k = np.where(pair, np.asarray(se_ard(jnp.asarray(x), jnp.asarray(x), hyper.log_lengthscale[a],
                                             hyper.log_signal[a])), 0.0)
        lam, vec = np.linalg.eigh(k)
        order = np.argsort(lam)[::-1]
        lam, vec = np.clip(lam[order], 0.0, None), vec[:, order]
        b = spectrum_bounds(lam, sf2[a], s2[a])
        r = int(np.argmax(b <= tol))  # b[M] = 0, so some r qualifies
        bases.append(vec)
        coefs.append(np.where(np.arange(M) < r, lam / (s2[a] * (lam + s2[a])), 0.0))
        ranks.append(r)
        bounds.append(b[r])
    widths = [int(min(M, max(bucket, -(-r // bucket) * bucket))) for r in ranks]
    basis = tuple(jnp.asarray(v[:, :n] * mask[:, None]) for v, n in zip(bases, widths))
    coef = tuple(jnp.asarray(c[:n]) for c, n in zip(coefs, widths))
    lr = LowRankPosterior(hyper, post.inputs, post.beta, basis, coef, jnp.asarray(1.0 / s2),
                          jnp.asarray(mask, dtype=post.beta.dtype), jnp.asarray(bounds))
    return lr, np.asarray(ranks)


def low_rank_fitc_posterior(post: GPPosterior, tol: float, *, jitter=None,
                            bucket: int = 25) -> tuple[LowRankPosterior, np.ndarray]:
    """The low-rank form of a FITC ``post`` (module docstring, "FITC"), keeping per output the fewest
    directions whose certified variance error is below ``tol·σ_n²``. ``jitter`` (E,): the ridge ρ
    the posterior put on K_mm (``FitInfo.posterior_jitter``); any ρ ≥ 0 keeps the bound valid, the
    posterior's own makes it tightest. Returns ``(posterior, ranks (E,))``; host-side, once per model.
    """
    if not tol > 0:
        raise ValueError(f"tol must be > 0 (the exact variance is the plain posterior), got {tol}")
    xu = np.asarray(post.inputs)
    hyper = post.hyper
    inv = np.asarray(post.inv)
    E, M = np.asarray(post.beta).shape
    rho = np.zeros(E) if jitter is None else np.asarray(jitter, dtype=float)
    s2 = np.exp(2.0 * np.asarray(hyper.log_noise))
    sf2 = np.exp(2.0 * np.asarray(hyper.log_signal))
    bases, coefs, ranks, bounds = [], [], [], []
    for a in range(E):
        kmm = np.asarray(se_ard(jnp.asarray(xu), jnp.asarray(xu), hyper.log_lengthscale[a], hyper.log_signal[a]))
        chol = np.linalg.cholesky(kmm + rho[a] * np.eye(M))
        g, w = np.linalg.eigh(chol.T @ inv[a] @ chol)
        order = np.argsort(g)[::-1]
        g, w = g[order], w[:, order]
        tail = np.maximum.accumulate(np.abs(np.concatenate([g, [0.0]]))[::-1])[::-1]  # max_{i≥r} |g_i|
        b = tail * sf2[a] / s2[a]
        r = int(np.argmax(b <= tol))
        v = np.linalg.solve(chol.T, w)  # v_i = L⁻ᵀ w_i
        bases.append(v)
        coefs.append(np.where(np.arange(M) < r, -g, 0.0))
        ranks.append(r)
        bounds.append(b[r])
    widths = [int(min(M, max(bucket, -(-r // bucket) * bucket))) for r in ranks]
    basis = tuple(jnp.asarray(v[:, :n]) for v, n in zip(bases, widths))
    coef = tuple(jnp.asarray(c[:n]) for c, n in zip(coefs, widths))
    lr = LowRankPosterior(hyper, post.inputs, post.beta, basis, coef, None, None, jnp.asarray(bounds))
    return lr, np.asarray(ranks)


def low_rank_model(post: GPPosterior, data: GPData, tol: float, *, sparse: bool, jitter=None,
                   bucket: int = 25) -> tuple[LowRankPosterior, np.ndarray]:
    """:func:`low_rank_fitc_posterior` for a FITC ``post`` (``sparse``), else :func:`low_rank_posterior`."""
    if sparse:
        return low_rank_fitc_posterior(post, tol, jitter=jitter, bucket=bucket)
    return low_rank_posterior(post, data, tol, jitter=jitter, bucket=bucket)


def low_rank_quad(post: LowRankPosterior, ks: jax.Array):
    """``(kᵀAk (E, P), A k (E, P, M))`` in the low-rank form; ``ks`` (E, P, M) kernel rows."""
    km = ks if post.mask is None else ks * post.mask[None, None, :]
    quads, ws = [], []
    for a, (u, d) in enumerate(zip(post.basis, post.coef)):  # one pair of (P, M) x (M, R_a) products per output
        c = km[a] @ u  # U_rᵀ k
        quad, w = -(c * c) @ d, -(c * d[None, :]) @ u.T
        if post.inv_noise is not None:  # full GP: the ‖Pk‖²/σ² term
            quad, w = quad + jnp.sum(km[a] * km[a], axis=-1) * post.inv_noise[a], w + km[a] * post.inv_noise[a]
        quads.append(quad)
        ws.append(w)
    return jnp.stack(quads), jnp.stack(ws)
