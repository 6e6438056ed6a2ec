"""Dynamics-model predictions for a batch of particles, with their input Jacobians.

The particle rollout needs, per particle, the model's difference mean ``m(z)``, optionally
its epistemic variance ``v_f(z)``, and — for the custom backward pass — the Jacobians
``∂m/∂z`` and ``∂v_f/∂z``. Any model works that offers the GP's predictive interface:

* a :class:`pipps.gp.GPPosterior` (full or FITC): predictions by :func:`pipps.gp.predict`'s
  formulas and the Jacobians in closed form (below);
* any other object with ``predict(z (P, Dz), variance: bool) -> (mean (P, E), var (P, E) | None)``
  and ``noise_variance`` (E,) (e.g. :class:`pipps.systems.linear_gaussian.LinearGaussianModel`):
  the Jacobians by forward-mode autodiff per particle.

Closed-form GP Jacobians (SE-ARD kernel, docs/gp.md). With ``k_{a,m} = σ_f,a² exp(-½ Σ_d (z_d − x_{m,d})²/ℓ_{a,d}²)``:
``∂m_a/∂z = −Σ_m β_{a,m} k_{a,m} (z − x_m)/ℓ_a²`` and, with ``w_a = A_a k_a`` (the product the
variance ``σ_f² − k_aᵀ A_a k_a`` computes anyway), ``∂v_a/∂z = 2 Σ_m w_{a,m} k_{a,m} (z − x_m)/ℓ_a²``.
Both are O(P·E·M·Dz) once ``w`` is known, so the Jacobians cost far less than the O(P·E·M²)
variance itself; reverse-mode autodiff through ``k_aᵀ A_a k_a`` would instead redo an
O(M²) product per output cotangent. Where the variance is clamped at 0, its Jacobian is 0.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from pipps.gp.kernel import se_ard_batched
from pipps.gp.lowrank import LowRankPosterior, low_rank_quad
from pipps.gp.types import GPPosterior


class ModelOutput(NamedTuple):
    """Model predictions at P inputs. ``var``/``jac_var`` are None when the variance is off."""

    mean: jax.Array  # (P, E) difference mean m(z)
    var: jax.Array | None  # (P, E) epistemic variance v_f(z)
    jac_mean: jax.Array | None  # (P, E, Dz) ∂m/∂z
    jac_var: jax.Array | None  # (P, E, Dz) ∂v_f/∂z


def noise_variance(model) -> jax.Array:
    """(E,) the learned observation-noise variances σ_n² of the model."""
    return model.noise_variance


PRECISIONS = ("float64", "float32")


def _gp_output(post, z: jax.Array, variance: bool, jacobian: bool, precision: str) -> ModelOutput:
    ks = se_ard_batched(post.hyper, z, post.inputs)  # (E, P, M)
    mean = jnp.einsum("epm,em->pe", ks, post.beta)
    var = jac_mean = jac_var = None
    if variance and isinstance(post, LowRankPosterior):  # the certified low-rank form (pipps.gp.lowrank)
        quad, w = low_rank_quad(post, ks)
        raw = post.hyper.signal_variance[None, :] - quad.T
        var = jnp.maximum(raw, 0.0)
    elif variance:
        if precision == "float32":  # the O(P·E·M²) product alone in single precision (2× the flops/s)
            low = jnp.float32
            w = jnp.einsum("emn,epn->epm", post.inv.astype(low), ks.astype(low)).astype(ks.dtype)
        else:
            w = jnp.einsum("emn,epn->epm", post.inv, ks)  # A_a k_a, the O(P·E·M²) step
        quad = jnp.sum(ks * w, axis=-1).T  # (P, E)
        raw = post.hyper.signal_variance[None, :] - quad
        var = jnp.maximum(raw, 0.0)
    if jacobian:
        inv_ell_sq = jnp.exp(-2.0 * post.hyper.log_lengthscale)  # (E, Dz)
        # Σ_m c_{a,p,m} (z_p − x_m)/ℓ_a² for a coefficient array c, without forming (E, P, M, Dz).
        def weighted_diff(c):
            s = jnp.sum(c, axis=-1)  # (E, P)
            cx = jnp.einsum("epm,md->epd", c, post.inputs)
            return (s[..., None] * z[None] - cx) * inv_ell_sq[:, None, :]  # (E, P, Dz)

        jac_mean = -jnp.transpose(weighted_diff(ks * post.beta[:, None, :]), (1, 0, 2))
        if variance:
            jv = 2.0 * jnp.transpose(weighted_diff(ks * w), (1, 0, 2))
            jac_var = jnp.where((raw > 0.0)[..., None], jv, 0.0)
    return ModelOutput(mean, var, jac_mean, jac_var)


def _generic_output(model, z: jax.Array, variance: bool, jacobian: bool) -> ModelOutput:
    if not jacobian:
        mean, var = model.predict(z, variance=variance)
        return ModelOutput(mean, var if variance else None, None, None)

    def one(zi):
        m, v = model.predict(zi[None], variance=variance)
        return (m[0], v[0]) if variance else (m[0],)

    def one_with_jac(zi):
        out = one(zi)
        jac = jax.jacfwd(one)(zi)
        return out, jac

    out, jac = jax.vmap(one_with_jac)(z)
    if variance:
        return ModelOutput(out[0], out[1], jac[0], jac[1])
    return ModelOutput(out[0], None, jac[0], None)


def model_output(model, z: jax.Array, *, variance: bool, jacobian: bool, precision: str = "float64") -> ModelOutput:
    """Predictions (and, if ``jacobian``, input Jacobians) of ``model`` at ``z`` (P, Dz).

    ``variance`` and ``jacobian`` are static: with ``variance=False`` nothing of the variance
    path is traced (the ``−σ_f`` variant; tasks never pay for what they do not use).
    ``precision`` (static) is the precision of the GP variance's ``A_a k_a`` product, the
    O(P·E·M²) step; everything else, and the sum ``σ_f² − k_aᵀ(A_a k_a)``, stays in the input
    precision. "float32" halves that step's time on CPU; its error is measured in
    docs/performance.md. Models other than a GP posterior always use their own precision.
    """
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if isinstance(model, (GPPosterior, LowRankPosterior)):
        if z.ndim != 2 or z.shape[1] != model.inputs.shape[1]:
            raise ValueError(f"model input must have shape (P, {model.inputs.shape[1]}), got {z.shape}")
        return _gp_output(model, z, variance, jacobian, precision)
    return _generic_output(model, z, variance, jacobian)
