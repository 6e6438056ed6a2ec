"""The checks shared by tests/test_costs.py and tests/test_pilco.py: Monte Carlo sampling and
z-scores of a scalar's mean and variance, and PILCO's finite-difference gradient check (``checkgrad.m``).

Monte Carlo: a fixed key, ``N_MC`` samples, tolerances of ``z_bound(n, FAMILY_ALPHA)`` standard
errors (Bonferroni over the n comparisons a test makes). Finite differences: central, step
``FD_STEP``, per output ``d = ‖g_fd − g‖/‖g_fd + g‖`` required below ``FD_TOL``; covariances enter
through their lower triangle with symmetric perturbations (``sym_from_tril``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

N_MC = 1_000_000
FAMILY_ALPHA = 1e-3
FD_STEP = 1e-4  # PILCO's checkgrad.m
FD_TOL = 1e-6


def normal_samples(seed, n, dim):
    return np.asarray(jax.random.normal(jax.random.key(seed), (n, dim), dtype=jnp.float64))


def moments_of_variance_z(c, expected_mean, expected_var):
    """z-scores of the sample mean and variance of scalar samples c (SE² of var: (m₄ − s⁴)/n)."""
    n = len(c)
    mean, var = c.mean(), c.var(ddof=1)
    se_mean = np.sqrt(var / n)
    se_var = np.sqrt((np.mean((c - mean) ** 4) - var**2) / n)
    return abs(mean - expected_mean) / se_mean, abs(var - expected_var) / se_var


def sym_from_tril(v, dim):
    """Symmetric matrix from its lower triangle (off-diagonals perturbed symmetrically)."""
    rows, cols = np.tril_indices(dim)
    low = jnp.zeros((dim, dim), v.dtype).at[rows, cols].set(v)
    return low + low.T - jnp.diag(jnp.diagonal(low))


def tril_of(m):
    return jnp.asarray(m)[np.tril_indices(m.shape[0])]


def checkgrad(f, p):
    """PILCO's checkgrad.m check for every output of ``f`` at ``p``: ``(d, g)``, with ``g`` the autodiff
    Jacobian (outputs × parameters) and ``d`` per output.

    Outputs whose largest finite-difference derivative is below 1e-5 while d > 1e-3 are "not
    testable" (d is NaN there): the difference quotient is rounding noise.
    """
    p = jnp.asarray(p)
    # Two programs, not one: in a single program XLA may run the Jacobian's and the differences'
    # batched LAPACK calls concurrently, and jaxlib 0.10's CPU batch map deadlocks on that
    # (docs/gp.md; the unicycle cost's gradient check hung in one program)
    g = np.asarray(jax.jit(jax.jacfwd(f))(p)).reshape(-1, p.size)
    steps = FD_STEP * jnp.eye(p.size, dtype=p.dtype)
    f_batch = jax.jit(jax.vmap(f))
    g_fd = np.asarray((f_batch(p + steps) - f_batch(p - steps)) / (2 * FD_STEP)).reshape(p.size, -1).T
    num = np.linalg.norm(g_fd - g, axis=1)
    den = np.linalg.norm(g_fd + g, axis=1)
    d = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    untestable = (np.abs(g_fd).max(axis=1) < 1e-5) & (d > 1e-3)
    return np.where(untestable, np.nan, d), g


def assert_fd(d, label):
    """More than half of the outputs testable, and every testable one within ``FD_TOL``."""
    finite = d[np.isfinite(d)]
    print(f"FD {label}: max d = {np.max(finite):.2e} over {finite.size} testable outputs of {d.size}")
    assert finite.size > 0.5 * d.size, (label, finite.size, d.size)
    assert np.max(finite) < FD_TOL, (label, np.max(finite))
