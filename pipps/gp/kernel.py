"""The SE-ARD kernel k_a(z, z') = σ_f,a² exp(−½ (z−z')ᵀ Λ_a⁻¹ (z−z')) (docs/gp.md, "Model").

The noise term σ_n² δ is added by the callers that build K_y. Every function takes the
hyperparameters of one output (``log_lengthscale`` (Dz,), ``log_signal`` ()) or of all
outputs (leading E axis); the batched versions use einsum over outputs, no Python loops.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from pipps.gp.types import GPHyper


def _centred(x1: jax.Array, x2: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Both point sets shifted by the first point of ``x2``.

    The first point rather than the mean: training data are padded at the end
    (:func:`pipps.gp.data.pad_to_capacity`), so ``x2[0]`` is a real point and a constant column
    becomes exactly 0 on every real row; a mean over padded rows would not be. Measured on degenerate data (tests/test_gp.py: a constant column at 0.7 whose length-scale
    the fit floors to 1e-6): uncentred, the scaled column is 7e5, its squares 5e11, and the Gram
    matrix had eigenvalues down to −2.6e-5 (as large as σ_n²) that depend on the CPU's summation
    order; centred, the constant column is exactly 0.
    """
    c = x2[0]
    return x1 - c, x2 - c


def scaled_sqdist(x1: jax.Array, x2: jax.Array, log_lengthscale: jax.Array) -> jax.Array:
    """(z−z')ᵀ Λ⁻¹ (z−z') for all pairs: x1 (n1, Dz), x2 (n2, Dz), log ℓ (Dz,) → (n1, n2).

    Uses ‖a‖² + ‖b‖² − 2 a·b on the length-scale-scaled inputs (O(n1 n2) memory, not
    O(n1 n2 Dz)), clamped at 0 against rounding. The inputs are first centred on the first point
    of ``x2`` (distances do not change): the expansion's rounding error is eps·(‖a‖² + ‖b‖²), so an
    input column far from 0 relative to its length-scale (a constant column with a floored ℓ, say)
    would otherwise swamp the true distances and make K indefinite (see :func:`_centred`).
    """
    x1, x2 = _centred(x1, x2)
    inv_ell = jnp.exp(-log_lengthscale)
    a = x1 * inv_ell
    b = x2 * inv_ell
    d2 = jnp.sum(a * a, -1)[:, None] + jnp.sum(b * b, -1)[None, :] - 2.0 * (a @ b.T)
    return jnp.maximum(d2, 0.0)


def se_ard(x1: jax.Array, x2: jax.Array, log_lengthscale: jax.Array, log_signal: jax.Array) -> jax.Array:
    """Noise-free SE-ARD Gram block of one output: (n1, n2)."""
    return jnp.exp(2.0 * log_signal - 0.5 * scaled_sqdist(x1, x2, log_lengthscale))


def se_ard_batched(hyper: GPHyper, x1: jax.Array, x2: jax.Array) -> jax.Array:
    """Noise-free SE-ARD Gram blocks of all E outputs: (E, n1, n2), fused over outputs."""
    x1, x2 = _centred(x1, x2)
    inv_ell = jnp.exp(-hyper.log_lengthscale)  # (E, Dz)
    a = jnp.einsum("id,ed->eid", x1, inv_ell)
    b = jnp.einsum("jd,ed->ejd", x2, inv_ell)
    d2 = (jnp.sum(a * a, -1)[:, :, None] + jnp.sum(b * b, -1)[:, None, :]
          - 2.0 * jnp.einsum("eid,ejd->eij", a, b))
    d2 = jnp.maximum(d2, 0.0)
    return jnp.exp(2.0 * hyper.log_signal[:, None, None] - 0.5 * d2)
