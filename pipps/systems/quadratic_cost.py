"""A quadratic cost ``c(x) = (x − z)ᵀ Q (x − z)`` with closed-form Gaussian moments.

Used by the linear-Gaussian reference system (:mod:`pipps.systems.linear_gaussian`), where it
makes the exact objective and gradient closed form. For ``x ~ N(m, S)``, ``d = m − z`` and
symmetric ``Q``:

    E[c]   = tr(QS) + dᵀQd,
    Var[c] = 2 tr(QSQS) + 4 dᵀQSQd.

Like :class:`pipps.costs.SaturatingCost` it is static configuration (read-only numpy arrays)
satisfying the :class:`pipps.tasks.base.Cost` protocol.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True, eq=False)
class QuadraticCost:
    """``c(x) = (x − target)ᵀ Q (x − target)`` on the model state; ``Q`` symmetric PSD (D, D)."""

    Q: np.ndarray
    target: np.ndarray
    name: str = "quadratic"

    def __post_init__(self):
        Q = np.array(self.Q, dtype=np.float64)
        target = np.array(self.target, dtype=np.float64)
        if Q.ndim != 2 or Q.shape[0] != Q.shape[1] or target.shape != (Q.shape[0],):
            raise ValueError(f"Q must be (D, D) and target (D,), got {Q.shape} and {target.shape}")
        if not np.allclose(Q, Q.T, rtol=0.0, atol=1e-14):
            raise ValueError("Q must be symmetric")
        if np.linalg.eigvalsh(Q).min() < -1e-12:
            raise ValueError("Q must be positive semi-definite")
        Q.setflags(write=False)
        target.setflags(write=False)
        object.__setattr__(self, "Q", Q)
        object.__setattr__(self, "target", target)

    @property
    def model_dim(self) -> int:
        return self.Q.shape[0]

    def __call__(self, x: jax.Array) -> jax.Array:
        """c(x); leading batch axes allowed."""
        d = x - self.target
        return jnp.einsum("...i,ij,...j->...", d, self.Q, d)

    def expected(self, mean: jax.Array, cov: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(E[c], Var[c]) for x ~ N(mean, cov), exact."""
        d = mean - self.target
        QS = self.Q @ cov
        Qd = self.Q @ d
        e = jnp.trace(QS) + d @ Qd
        var = 2.0 * jnp.sum(QS * QS.T) + 4.0 * Qd @ cov @ Qd
        return e, var
