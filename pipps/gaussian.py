"""Closed-form Gaussian moment routines: trig features, linear maps, the saturating cost (docs/pilco.md).

Every routine takes one Gaussian ``v ~ N(mean, cov)`` (no batch axes; ``jax.vmap`` for
batches) and is a plain JAX function, differentiable in ``mean`` and ``cov``.

Gaussian-map convention (PILCO's; docs/pilco.md, "One step, block by block"): a map ``y = f(v)`` returns
``GaussianMap(M, S, C)`` with ``M = E[y]``, ``S = Cov[y]`` and ``C = Σ⁻¹ Cov[v, y]``.
``C`` is never obtained by inverting ``Σ``: for the maps here it is the closed form
``E[∂f/∂v]ᵀ`` (Stein's lemma), so ``Cov[v, y] = Σ C`` and, for any ``w`` jointly
Gaussian with ``v``, ``Cov[w, y] := Cov[w, v] C``.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

VARIANCE_FLOOR = 1e-12  # Var[c] below this is reported as 0 (docs/costs.md)


class GaussianMap(NamedTuple):
    """Moments of ``y = f(v)`` for ``v ~ N(μ, Σ)``: ``(M, S, C)`` of the convention above."""

    M: jax.Array  # (F,) E[y]
    S: jax.Array  # (F, F) Cov[y]
    C: jax.Array  # (D, F) Σ⁻¹ Cov[v, y]


def linear_map(
    mean: jax.Array, cov: jax.Array, L: jax.Array, offset: jax.Array | None = None
) -> GaussianMap:
    """y = L v (+ offset): exact, ``M = Lμ (+ b)``, ``S = LΣLᵀ``, ``C = Lᵀ``."""
    L = jnp.asarray(L)
    M = L @ mean
    if offset is not None:
        M = M + offset
    S = L @ cov @ L.T
    return GaussianMap(M, 0.5 * (S + S.T), L.T)


def _q_expm1(lq: jax.Array, q: jax.Array, v: jax.Array) -> jax.Array:
    """q·(e^v − 1) for q = e^{lq}: by expm1 where |v| < 1 (accuracy for small covariances),
    else as e^{lq + v} − q, which cannot overflow because |Σij| ≤ (Σii + Σjj)/2 makes lq + v ≤ 0.
    (q·expm1(v) alone is 0·inf = NaN once a variance exceeds ~709.) The branches take safe
    inputs so that neither produces a NaN gradient where it is not selected."""
    small = jnp.abs(v) < 1.0
    v_small = jnp.where(small, v, 0.0)
    v_large = jnp.where(small, 0.0, v)
    return jnp.where(small, q * jnp.expm1(v_small), jnp.exp(lq + v_large) - q)


def trig_moments(mean: jax.Array, cov: jax.Array, angle_idx: Sequence[int]) -> GaussianMap:
    """Moments of ``[sin v_a, cos v_a]`` (a in angle_idx, pairs in (sin, cos) order), PILCO's gTrig.m.

    All pairs (i, j) of listed angles are filled, including the cross terms between
    different angles. ``C[:, 2k] = e_k E[cos v_a]`` and ``C[:, 2k+1] = -e_k E[sin v_a]``
    (Stein's lemma), where ``e_k`` is the unit vector of angle ``a = angle_idx[k]``.
    """
    idx = np.asarray(angle_idx, dtype=int).reshape(-1)
    n_in, n_ang = mean.shape[0], idx.size
    mu = mean[idx]
    V = cov[np.ix_(idx, idx)]
    half_var = 0.5 * jnp.diagonal(V)
    damp = jnp.exp(-half_var)
    e_sin, e_cos = damp * jnp.sin(mu), damp * jnp.cos(mu)

    lq = -(half_var[:, None] + half_var[None, :])
    q = jnp.exp(lq)  # q = e^{-(Σii+Σjj)/2}
    ep = _q_expm1(lq, q, V)  # e⁺ − q
    em = _q_expm1(lq, q, -V)  # e⁻ − q
    diff = mu[:, None] - mu[None, :]
    summ = mu[:, None] + mu[None, :]
    ss = 0.5 * (ep * jnp.cos(diff) - em * jnp.cos(summ))  # Cov[sin v_i, sin v_j]
    cc = 0.5 * (ep * jnp.cos(diff) + em * jnp.cos(summ))  # Cov[cos v_i, cos v_j]
    sc = 0.5 * (ep * jnp.sin(diff) + em * jnp.sin(summ))  # Cov[sin v_i, cos v_j]

    M = jnp.stack([e_sin, e_cos], axis=-1).reshape(2 * n_ang)
    # blocks[i, p, j, r] = Cov[trig_p(v_i), trig_r(v_j)], p, r ∈ {sin, cos}
    blocks = jnp.stack(
        [jnp.stack([ss, sc], axis=-1), jnp.stack([sc.T, cc], axis=-1)], axis=1
    )  # (i, p, j, r)
    S = blocks.reshape(2 * n_ang, 2 * n_ang)
    S = 0.5 * (S + S.T)

    select = np.zeros((n_in, n_ang))
    select[idx, np.arange(n_ang)] = 1.0
    dtrig = jnp.stack([e_cos, -e_sin], axis=-1)  # E[d sin/dv], E[d cos/dv] per angle
    C = (select[:, :, None] * dtrig[None, :, :]).reshape(n_in, 2 * n_ang)
    return GaussianMap(M, S, C)


def append_map(mean: jax.Array, cov: jax.Array, g: GaussianMap) -> tuple[jax.Array, jax.Array]:
    """Joint Gaussian of ``[v; y]``: mean ``[μ; M]``, covariance ``[[Σ, ΣC], [CᵀΣ, S]]``."""
    cross = cov @ g.C
    joint_cov = jnp.block([[cov, cross], [cross.T, g.S]])
    return jnp.concatenate([mean, g.M]), joint_cov


def trig_augment(
    mean: jax.Array, cov: jax.Array, angle_idx: Sequence[int]
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Moments of ``x̃ = [x; sin x_a, cos x_a (a in angle_idx)]``, each pair in (sin, cos) order.

    Returns ``(mean_aug (D+2A,), cov_aug (D+2A, D+2A), C (D, 2A))`` where ``C`` is
    ``Σ⁻¹ Cov[x, trig]`` for the appended features only.
    """
    g = trig_moments(mean, cov, angle_idx)
    mean_aug, cov_aug = append_map(mean, cov, g)
    return mean_aug, cov_aug, g.C


def expected_saturating_cost(
    mean: jax.Array, cov: jax.Array, W: jax.Array, target: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """(E[c], Var[c]) of ``c(y) = 1 − exp(−½ (y−z)ᵀ W (y−z))`` for ``y ~ N(m, S)`` (PILCO's lossSat.m).

    ``E[c] = 1 − |I+SW|^{-1/2} exp(−½ dᵀ W (I+SW)⁻¹ d)`` and
    ``Var[c] = |I+2SW|^{-1/2} exp(−dᵀ W (I+2SW)⁻¹ d) − (1−E[c])²`` with ``d = m − z``;
    ``Var`` is set to 0 below 1e-12. For PSD ``S`` and ``W`` every eigenvalue of ``I + kSW``
    is ≥ 1, so the solves stay well conditioned however singular ``S`` is.
    """
    W = jnp.asarray(W)
    d = mean - jnp.asarray(target)
    eye = jnp.eye(d.shape[0], dtype=d.dtype)
    SW = cov @ W

    def gaussian_integral(k: float) -> jax.Array:
        """E[exp(−k/2 (y−z)ᵀW(y−z))] = |I+kSW|^{-1/2} exp(−k/2 dᵀW(I+kSW)⁻¹d)."""
        A = eye + k * SW
        quad = d @ W @ jnp.linalg.solve(A, d)
        _, logdet = jnp.linalg.slogdet(A)
        return jnp.exp(-0.5 * logdet - 0.5 * k * quad)

    e1 = gaussian_integral(1.0)
    var = gaussian_integral(2.0) - e1**2
    var = jnp.where(var < VARIANCE_FLOOR, 0.0, var)
    return 1.0 - e1, var
