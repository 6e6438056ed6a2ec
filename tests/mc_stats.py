"""Monte Carlo z-scores shared by the moment tests (standard errors estimated from the samples)."""

import numpy as np


def mean_z(samples, expected):
    """z-scores of sample means against `expected`."""
    se = samples.std(axis=0, ddof=1) / np.sqrt(len(samples))
    return np.abs(samples.mean(axis=0) - expected) / se


def cov_z(samples, expected):
    """z-scores of every sample-covariance entry; SE² = (E[a_c² b_c²] − cov²)/n."""
    n = len(samples)
    centred = samples - samples.mean(axis=0)
    cov_hat = centred.T @ centred / (n - 1)
    sq = centred**2
    se = np.sqrt(np.maximum(sq.T @ sq / n - cov_hat**2, 0.0) / n)
    iu = np.triu_indices(samples.shape[1])
    return np.abs(cov_hat - expected)[iu] / se[iu]


def cross_z(u, y, expected):
    """z-scores of the Stein estimate mean(u yᵀ), u = Σ⁻¹(x − μ), of C = Σ⁻¹Cov[x, y]."""
    n = len(u)
    yc = y - y.mean(axis=0)
    c_hat = u.T @ yc / n
    se = np.sqrt(np.maximum((u**2).T @ (yc**2) / n - c_hat**2, 0.0) / n)
    return np.abs(c_hat - expected).ravel() / se.ravel()
