"""Cholesky with adaptive jitter (reported, never silent).

A failed Cholesky in JAX returns NaNs instead of raising. :func:`adaptive_cholesky` tries the
base jitter, then escalates ×10 (starting from ``jitter_min · scale``) until the factor is
finite, and returns the jitter it used so that callers can report it (training must survive
ill-conditioned data; docs/gp.md, "Noise floor, std floors and jitter — all reported").
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def adaptive_cholesky(
    a: jax.Array,
    *,
    base_jitter: float | jax.Array,
    jitter_min: float,
    scale: jax.Array,
    max_tries: int,
    diag_mask: jax.Array | None = None,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Lower Cholesky factor of ``a + j·diag(diag_mask)`` with the smallest j on the schedule.

    Schedule: j₀ = base_jitter; j_{k+1} = max(10 j_k, jitter_min · scale). At most ``max_tries``
    escalations (a ``lax.while_loop``: not reverse-differentiable; use it outside gradients).

    Args:
      a: (n, n) symmetric matrix.
      base_jitter: first jitter tried.
      jitter_min: first non-zero jitter relative to ``scale``.
      scale: typical diagonal magnitude (e.g. σ_f² + σ_n²); padded rows must not enter it.
      max_tries: number of escalations before giving up.
      diag_mask: (n,) where the jitter is added (default: everywhere). Padded rows are left
        alone so that they keep exactly no effect.

    Returns:
      (L, jitter, ok): the factor (NaN if all tries failed), the jitter used, and whether the
      factor is finite.
    """
    n = a.shape[-1]
    d = jnp.ones((n,), a.dtype) if diag_mask is None else diag_mask.astype(a.dtype)
    base = jnp.asarray(base_jitter, a.dtype)

    def chol(j):
        return jnp.linalg.cholesky(a + j * jnp.diag(d))

    def failed(chol_l):
        return ~jnp.all(jnp.isfinite(chol_l))

    def cond(state):
        k, _, chol_l = state
        return failed(chol_l) & (k < max_tries)

    def body(state):
        k, j, _ = state
        j_new = jnp.maximum(10.0 * j, jitter_min * scale)
        return k + 1, j_new, chol(j_new)

    _, jitter, chol_l = jax.lax.while_loop(cond, body, (jnp.asarray(0), base, chol(base)))
    return chol_l, jitter, ~failed(chol_l)


def chol_inverse(chol_l: jax.Array) -> jax.Array:
    """A⁻¹ from the lower factor L of A (symmetrised): (n, n)."""
    n = chol_l.shape[-1]
    linv = jax.scipy.linalg.solve_triangular(chol_l, jnp.eye(n, dtype=chol_l.dtype), lower=True)
    inv = linv.T @ linv
    return 0.5 * (inv + inv.T)


def map_outputs(fn, xs, batching: str = "auto"):
    """Apply ``fn`` to each slice of the pytree ``xs`` along its leading (output) axis.

    ``batching``: "vmap" (one batched program), "map" (``lax.map``, one output after the
    other) or "auto" (``map`` on CPU, ``vmap`` elsewhere; resolved at trace time).

    Why not always vmap: jaxlib 0.10.x runs batched LAPACK calls (Cholesky, triangular solve)
    on CPU through a thread-pool batch map that deadlocks when the XLA thunk executor runs
    several of them concurrently inside loops (observed here on a 2-core machine: vmapped
    L-BFGS over outputs hung forever for N ≥ ~100). Unbatched calls run inline.
    """
    how = batching
    if how == "auto":
        how = "map" if jax.default_backend() == "cpu" else "vmap"
    if how == "map":
        return jax.lax.map(fn, xs)
    if how == "vmap":
        return jax.vmap(fn)(xs)
    raise ValueError(f"batching must be 'auto', 'map' or 'vmap', got {batching!r}")


def stack_trees(trees):
    """Stack equally shaped pytrees along a new leading axis (the inverse of indexing it)."""
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *trees)
