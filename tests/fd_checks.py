"""Finite-difference gradient checks (tasks.md §7.1), shared by the moment and cost tests."""

import jax
import jax.numpy as jnp
import numpy as np

FD_STEP = 1e-4  # tasks.md §7.1


def sym_from_tril(v, dim):
    """Symmetric matrix from its lower triangle (off-diagonals perturbed symmetrically)."""
    rows, cols = np.tril_indices(dim)
    low = jnp.zeros((dim, dim), v.dtype).at[rows, cols].set(v)
    return low + low.T - jnp.diag(jnp.diagonal(low))


def tril_of(m):
    return jnp.asarray(m)[np.tril_indices(m.shape[0])]


def checkgrad(f, p):
    """Per output, d = ‖g_fd − g‖/‖g_fd + g‖ with central step 1e-4; returns (d, autodiff Jacobian g).

    Outputs whose largest derivative is below 1e-5 while d > 1e-3 are "not testable" (NaN).
    """
    p = jnp.asarray(p)

    @jax.jit
    def both(p):
        steps = FD_STEP * jnp.eye(p.size, dtype=p.dtype)
        g = jax.jacfwd(f)(p).reshape(-1, p.size)
        fd = (jax.vmap(f)(p + steps) - jax.vmap(f)(p - steps)) / (2 * FD_STEP)
        return g, fd.reshape(p.size, -1).T

    g, g_fd = (np.asarray(a) for a in both(p))
    num = np.linalg.norm(g_fd - g, axis=1)
    den = np.linalg.norm(g_fd + g, axis=1)
    d = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    untestable = (np.abs(g_fd).max(axis=1) < 1e-5) & (d > 1e-3)
    return np.where(untestable, np.nan, d), g
