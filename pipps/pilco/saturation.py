"""Moments of the saturated control ``u = ū ⊙ sat(ũ)`` for Gaussian ``ũ`` (PILCO's ``gSat.m``).

``sat(w) = (9 sin w + sin 3w)/8``, so ``u_a = ū_a Σ_{k∈{1,3}} γ_k sin(k ũ_a)`` with
``γ_1 = 9/8``, ``γ_3 = 1/8``. The vector ``[ũ; 3ũ]`` is (degenerate) Gaussian, so the
moments of all the sines — every pair ``(k ũ_a, l ũ_b)``, k, l ∈ {1, 3}, all outputs a, b —
come from the sin–sin formula of the trig features (:func:`pipps.gaussian.trig_moments`), and ``u`` is a
linear map of them. ``C = V⁻¹Cov[ũ, u] = E[∂u/∂ũ]ᵀ = diag(R)`` (Stein's lemma), with
``R_a = ū_a (9/8 e^{−V_aa/2} cos m_a + 3/8 e^{−9V_aa/2} cos 3m_a)``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from pipps.gaussian import GaussianMap, trig_moments

SAT_WEIGHTS = (9.0 / 8.0, 1.0 / 8.0)  # γ_1, γ_3
SAT_FREQUENCIES = (1.0, 3.0)


def saturation_moments(mean: jax.Array, cov: jax.Array, u_max) -> GaussianMap:
    """Moments of ``u = u_max ⊙ sat(ũ)`` for ``ũ ~ N(mean, cov)`` (the module docstring).

    Args:
      mean: (F,) mean of the unsquashed control ũ.
      cov: (F, F) covariance of ũ.
      u_max: (F,) control limits ū (static numbers or an array).

    Returns:
      ``GaussianMap(M (F,), S (F, F), C (F, F) = diag(R))``.
    """
    n_out = mean.shape[0]
    u_max = jnp.asarray(u_max, dtype=mean.dtype)
    # [ũ; 3ũ] = K ũ, K = [I; 3I]: the 2F "angles" whose sines make up sat(ũ).
    freq = np.repeat(np.asarray(SAT_FREQUENCIES), n_out)  # (2F,) = [1..1, 3..3]
    mean_k = freq * jnp.tile(mean, 2)
    cov_k = jnp.outer(freq, freq) * jnp.tile(cov, (2, 2))
    trig = trig_moments(mean_k, cov_k, tuple(range(2 * n_out)))
    sin_idx = np.arange(0, 4 * n_out, 2)  # (sin, cos) pairs: the sines sit at even slots
    e_sin = trig.M[sin_idx]  # (2F,) E[sin(k ũ_a)]
    cov_sin = trig.S[np.ix_(sin_idx, sin_idx)]  # (2F, 2F) Cov[sin(k ũ_a), sin(l ũ_b)]
    weights = np.repeat(np.asarray(SAT_WEIGHTS), n_out)  # (2F,) γ_k
    lin = jnp.tile(jnp.eye(n_out, dtype=mean.dtype), (1, 2)) * weights[None, :] * u_max[:, None]  # (F, 2F)
    M = lin @ e_sin
    S = lin @ cov_sin @ lin.T
    # R_a = ū_a Σ_k k γ_k E[cos(k ũ_a)] (E[d sin(kw)/dw] = k E[cos(kw)])
    e_cos = trig.M[sin_idx + 1].reshape(2, n_out)
    R = u_max * (SAT_WEIGHTS[0] * SAT_FREQUENCIES[0] * e_cos[0] + SAT_WEIGHTS[1] * SAT_FREQUENCIES[1] * e_cos[1])
    return GaussianMap(M, 0.5 * (S + S.T), jnp.diag(R))
