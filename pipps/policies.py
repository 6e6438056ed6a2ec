"""Policies: saturated RBF networks (thesis and PILCO parameterisations) and the linear policy.

Every policy is an immutable pytree whose leaves are exactly its trainable
parameters (stored unconstrained), with a pure ``__call__(v) -> u`` on one policy
input vector ``v = x̃[P]`` (vmap it over particles). The control limit ``u_max``
is static metadata, never a leaf, so it gets no gradient.

For the moment-matching baseline (docs/pilco.md) both RBF networks describe
themselves in one convention through :meth:`as_rbf`: an output is
``Σ_i β_i exp(-½ (v - c_i)ᵀ diag(ℓ²)⁻¹ (v - c_i))`` (signal variance 1).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.tree_util import register_dataclass

# PILCO's fixed RBF-controller hyperparameters (its ``congp.m``): never trained.
PILCO_RBF_SIGNAL_STD = 1.0
PILCO_RBF_NOISE_STD = 0.01


def saturate(w: jax.Array) -> jax.Array:
    """sat(w) = (9 sin w + sin 3w)/8 ∈ [-1, 1] (PILCO's ``gSat.m``; thesis §4.5.3)."""
    return (9.0 * jnp.sin(w) + jnp.sin(3.0 * w)) / 8.0


def _scaled(u_max: tuple[float, ...], s: jax.Array) -> jax.Array:
    """u_max ⊙ s in the dtype of s: the static limits must not promote a float32 policy to float64."""
    return jnp.asarray(u_max, dtype=s.dtype) * s


def _static(default=dataclasses.MISSING):
    return dataclasses.field(metadata=dict(static=True), default=default)


class RBFForm(NamedTuple):
    """An RBF network in PILCO's kernel convention (used by moment matching, docs/pilco.md).

    Output ``a`` is ``Σ_i beta[i, a] · exp(-½ (v - centres[i])ᵀ diag(lengthscale_sq[a])⁻¹ (v - centres[i]))``.
    """

    centres: jax.Array  # (n_c, D)
    beta: jax.Array  # (n_c, F)
    lengthscale_sq: jax.Array  # (F, D)


def _sq_dist_scaled(v: jax.Array, centres: jax.Array, inv_scale: jax.Array) -> jax.Array:
    """(v - c_i)ᵀ diag(inv_scale) (v - c_i) for every centre: (n_c,) or (n_c, F) if inv_scale is (F, D)."""
    diff = v[None, :] - centres  # (n_c, D)
    if inv_scale.ndim == 1:
        return jnp.sum(diff**2 * inv_scale, axis=-1)
    return jnp.einsum("nd,fd->nf", diff**2, inv_scale)


@register_dataclass
@dataclasses.dataclass(frozen=True)
class RBFPolicy:
    """The thesis' RBF policy (thesis §4.1; docs/policies.md).

    ``π̃(v) = Σ_i w_i exp(-(v - m_i)ᵀ Λ⁻¹ (v - m_i))`` — no ½ in the exponent, weights used
    directly, one diagonal Λ shared by all outputs and stored as ``log_lambda = log diag Λ`` —
    then ``u = u_max ⊙ sat(π̃)``. With 50 centres on the raw 4-dim cart-pole state this has
    50·4 + 50 + 4 = 254 parameters.
    """

    centres: jax.Array  # (n_c, D)
    weights: jax.Array  # (n_c, F)
    log_lambda: jax.Array  # (D,)
    u_max: tuple[float, ...] = _static()

    def unsquashed(self, v: jax.Array) -> jax.Array:
        """π̃(v), the output before saturation, shape (F,)."""
        phi = jnp.exp(-_sq_dist_scaled(v, self.centres, jnp.exp(-self.log_lambda)))
        return phi @ self.weights

    def __call__(self, v: jax.Array) -> jax.Array:
        return _scaled(self.u_max, saturate(self.unsquashed(v)))

    def as_rbf(self) -> RBFForm:
        # exp(-dᵀΛ⁻¹d) = exp(-½ dᵀ(Λ/2)⁻¹d): PILCO's ℓ² is Λ/2 and β = w.
        n_out = self.weights.shape[1]
        ell_sq = jnp.broadcast_to(0.5 * jnp.exp(self.log_lambda), (n_out, self.log_lambda.shape[0]))
        return RBFForm(self.centres, self.weights, ell_sq)


@register_dataclass
@dataclasses.dataclass(frozen=True)
class PilcoRBFPolicy:
    """PILCO's RBF controller (``congp.m``): the mean of a "deterministic GP", then saturation.

    ``π̃_a(v) = Σ_i β_{a,i} k(v, c_i)`` with ``k = σ_f² exp(-½ (v-c)ᵀ Λ_a⁻¹ (v-c))``,
    ``β_a = (K_a + σ_π² I)⁻¹ y_a``; σ_f = 1 and σ_π = 0.01 are fixed constants, not parameters.
    Trainable: the centres, the pseudo-targets ``y`` and ``log ℓ`` per output.
    """

    centres: jax.Array  # (n_c, D)
    pseudo_targets: jax.Array  # (n_c, F)
    log_lengthscale: jax.Array  # (F, D)
    u_max: tuple[float, ...] = _static()

    def beta(self) -> jax.Array:
        """β = (K + σ_π² I)⁻¹ y per output, shape (n_c, F)."""
        inv_ell_sq = jnp.exp(-2.0 * self.log_lengthscale)  # (F, D)
        diff = self.centres[:, None, :] - self.centres[None, :, :]  # (n, n, D)
        sq = jnp.einsum("ijd,fd->fij", diff**2, inv_ell_sq)
        K = PILCO_RBF_SIGNAL_STD**2 * jnp.exp(-0.5 * sq)
        n = self.centres.shape[0]
        Ky = K + PILCO_RBF_NOISE_STD**2 * jnp.eye(n, dtype=K.dtype)
        chol = jnp.linalg.cholesky(Ky)
        sol = jax.vmap(lambda L, y: jax.scipy.linalg.cho_solve((L, True), y))(chol, self.pseudo_targets.T)
        return sol.T

    def unsquashed(self, v: jax.Array) -> jax.Array:
        k = PILCO_RBF_SIGNAL_STD**2 * jnp.exp(
            -0.5 * _sq_dist_scaled(v, self.centres, jnp.exp(-2.0 * self.log_lengthscale))
        )  # (n_c, F)
        return jnp.sum(k * self.beta(), axis=0)

    def __call__(self, v: jax.Array) -> jax.Array:
        return _scaled(self.u_max, saturate(self.unsquashed(v)))

    def as_rbf(self) -> RBFForm:
        return RBFForm(self.centres, PILCO_RBF_SIGNAL_STD**2 * self.beta(), jnp.exp(2.0 * self.log_lengthscale))


@register_dataclass
@dataclasses.dataclass(frozen=True)
class LinearPolicy:
    """Linear saturated policy (PILCO's ``conlin.m``): ``u = u_max ⊙ sat(W v + b)``.

    ``saturated=False`` gives the plain linear map ``u = W v + b`` (``u_max`` unused): the
    linear-Gaussian test systems need it, because only then are the state distributions
    exactly Gaussian and the exact gradient closed form.
    """

    W: jax.Array  # (F, D)
    b: jax.Array  # (F,)
    u_max: tuple[float, ...] = _static()
    saturated: bool = _static(True)

    def unsquashed(self, v: jax.Array) -> jax.Array:
        return self.W @ v + self.b

    def __call__(self, v: jax.Array) -> jax.Array:
        if not self.saturated:
            return self.unsquashed(v)
        return _scaled(self.u_max, saturate(self.unsquashed(v)))


@register_dataclass
@dataclasses.dataclass(frozen=True)
class OpenLoopPolicy:
    """An open-loop action sequence: ``θ = actions`` (T, F), and ``u = actions[t]`` where the policy
    input is the step index ``t`` (the first input component, rounded and clipped to [0, T−1]).

    The decision variables of a trajectory optimisation, or with ``T = 1`` a constant action —
    the one-step problems ``f(θ + w)`` of Suh et al. (:mod:`pipps.systems.contact`), whose state
    carries its step index for this policy to read.
    """

    actions: jax.Array  # (T, F)

    def __call__(self, v: jax.Array) -> jax.Array:
        T = self.actions.shape[0]
        t = jnp.clip(jnp.round(v[0]).astype(jnp.int32), 0, T - 1)
        return self.actions[t]


Policy = RBFPolicy | PilcoRBFPolicy | LinearPolicy | OpenLoopPolicy


#: per policy type, each array field's shape in terms of its sizes: "n" centres, "D" policy-input
#: components, "F" controls
_FIELD_SHAPES = {
    RBFPolicy: dict(centres=("n", "D"), weights=("n", "F"), log_lambda=("D",)),
    PilcoRBFPolicy: dict(centres=("n", "D"), pseudo_targets=("n", "F"), log_lengthscale=("F", "D")),
    LinearPolicy: dict(W=("F", "D"), b=("F",)),
}
_SIZE_NAMES = {"D": "policy_input_dim", "F": "action_dim"}


def check_policy(policy, input_dim: int, action_dim: int) -> None:
    """Refuse a policy that does not fit a problem's policy input (``input_dim``, the problem's
    ``policy_input_dim``) and controls (``action_dim``), before JAX broadcasts it silently (centres
    of one component against a 3-dim input).

    A built-in policy is checked field by field; any other callable by the shape of its output on
    one input of ``input_dim`` components (:func:`jax.eval_shape`, nothing runs). Shapes only:
    tracers pass, so a jitted caller checks once, while tracing.

    Raises:
      ValueError: naming the field, the size the problem expects and the size it has.
    """
    fields = _FIELD_SHAPES.get(type(policy))
    if fields is None:
        _check_callable(policy, input_dim, action_dim)
        return
    sizes = {"D": input_dim, "F": action_dim}
    n = None
    for name, dims in fields.items():
        shape = tuple(jnp.shape(getattr(policy, name)))
        if len(shape) != len(dims):
            raise ValueError(f"policy.{name}: must have {len(dims)} dimensions {dims}, got shape {shape}")
        for axis, (dim, got) in enumerate(zip(dims, shape)):
            if dim == "n":
                n = got if n is None else n
                want, what = n, "centres (the same in every field)"
            else:
                want, what = sizes[dim], f"the problem's {_SIZE_NAMES[dim]}"
            if got != want:
                raise ValueError(f"policy.{name}: axis {axis} has size {got}, expected {want} ({what})")
    if len(policy.u_max) != action_dim:
        raise ValueError(f"policy.u_max: has {len(policy.u_max)} limits, expected {action_dim} "
                         "(the problem's action_dim)")


def _check_callable(policy, input_dim: int, action_dim: int) -> None:
    if not callable(policy):
        raise ValueError(f"policy: must be callable v -> u, got {type(policy).__name__}")
    try:
        out = jax.eval_shape(policy, jax.ShapeDtypeStruct((input_dim,), jnp.result_type(float)))
    except Exception as err:  # noqa: BLE001 - whatever the policy raises, say it in one line
        raise ValueError(f"policy: fails on an input of shape ({input_dim},) (the problem's policy_input_dim) "
                         f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''})") from None
    if getattr(out, "shape", None) != (action_dim,):
        raise ValueError(f"policy: returns shape {getattr(out, 'shape', type(out).__name__)}, expected "
                         f"({action_dim},) (the problem's action_dim)")


def num_parameters(policy: Policy) -> int:
    """Number of trainable scalars (the pytree's leaves)."""
    return int(sum(np.size(leaf) for leaf in jax.tree.leaves(policy)))


# -- initialisations --------------------------------------------------------------------------


def _u_max_tuple(u_max) -> tuple[float, ...]:
    u = tuple(float(v) for v in np.atleast_1d(np.asarray(u_max, dtype=float)))
    if not all(np.isfinite(u)) or any(v <= 0 for v in u):
        raise ValueError(f"u_max must be positive and finite, got {u}")
    return u


def _check_gaussian(mean, cov, name: str) -> tuple[np.ndarray, np.ndarray]:
    mean = np.asarray(mean, dtype=float)
    cov = np.asarray(cov, dtype=float)
    if mean.ndim != 1 or cov.shape != (mean.size, mean.size):
        raise ValueError(f"{name}: mean must be (D,) and cov (D, D); got {mean.shape} and {cov.shape}")
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
        raise ValueError(f"{name}: mean and cov must be finite")
    return mean, cov


def init_rbf_policy(
    key: jax.Array,
    n_centres: int,
    centre_mean,
    centre_cov,
    u_max,
    *,
    log_lambda=0.0,
    weight_scale: float = 0.1,
) -> RBFPolicy:
    """Thesis initialisation: centres ~ N(centre_mean, centre_cov), weights ~ weight_scale·N(0,1), Λ = exp(log_lambda).

    ``centre_mean/centre_cov`` are the start distribution in policy-input coordinates;
    ``log_lambda`` is a scalar or a (D,) vector (0 gives the thesis' Λ = I).
    """
    mean, cov = _check_gaussian(centre_mean, centre_cov, "init_rbf_policy")
    u = _u_max_tuple(u_max)
    if n_centres < 1:
        raise ValueError(f"n_centres must be >= 1, got {n_centres}")
    k_c, k_w = jax.random.split(key)
    centres = jax.random.multivariate_normal(k_c, jnp.asarray(mean), jnp.asarray(cov), (n_centres,), method="svd")
    weights = weight_scale * jax.random.normal(k_w, (n_centres, len(u)))
    log_lam = jnp.broadcast_to(jnp.asarray(log_lambda, dtype=float), mean.shape)
    return RBFPolicy(centres, weights, jnp.array(log_lam), u)


def init_rbf_policy_uniform(
    key: jax.Array,
    n_centres: int,
    low,
    high,
    u_max,
    *,
    log_lambda=0.0,
    weight_scale: float = 0.1,
) -> RBFPolicy:
    """Centres uniform on the box [low, high] (the `quick` preset's departure, docs/experiments.md "Presets")."""
    low = np.asarray(low, dtype=float)
    high = np.asarray(high, dtype=float)
    if low.shape != high.shape or low.ndim != 1 or np.any(high <= low):
        raise ValueError(f"init_rbf_policy_uniform: need low < high of the same (D,) shape, got {low}, {high}")
    u = _u_max_tuple(u_max)
    k_c, k_w = jax.random.split(key)
    centres = jax.random.uniform(k_c, (n_centres, low.size), minval=jnp.asarray(low), maxval=jnp.asarray(high))
    weights = weight_scale * jax.random.normal(k_w, (n_centres, len(u)))
    log_lam = jnp.broadcast_to(jnp.asarray(log_lambda, dtype=float), low.shape)
    return RBFPolicy(centres, weights, jnp.array(log_lam), u)


def init_pilco_rbf_policy(
    key: jax.Array,
    n_centres: int,
    centre_mean,
    centre_cov,
    u_max,
    *,
    lengthscale=None,
    target_scale: float = 0.1,
) -> PilcoRBFPolicy:
    """PILCO initialisation (``settings_cp.m``): centres ~ N(mean, cov), y ~ 0.1·N(0,1), ℓ given.

    ``lengthscale`` defaults to PILCO's cart-pole [1, 1, 1, 0.7, 0.7] when D = 5, else ones.
    """
    mean, cov = _check_gaussian(centre_mean, centre_cov, "init_pilco_rbf_policy")
    u = _u_max_tuple(u_max)
    d = mean.size
    if lengthscale is None:
        lengthscale = [1.0, 1.0, 1.0, 0.7, 0.7] if d == 5 else np.ones(d)
    ell = np.broadcast_to(np.asarray(lengthscale, dtype=float), (len(u), d))
    k_c, k_y = jax.random.split(key)
    centres = jax.random.multivariate_normal(k_c, jnp.asarray(mean), jnp.asarray(cov), (n_centres,), method="svd")
    targets = target_scale * jax.random.normal(k_y, (n_centres, len(u)))
    return PilcoRBFPolicy(centres, targets, jnp.log(jnp.asarray(ell)), u)


def init_linear_policy(
    key: jax.Array, input_dim: int, u_max, *, scale: float = 0.01, saturated: bool = True
) -> LinearPolicy:
    """Unicycle initialisation (PILCO's ``settings_unicycle.m``): W ~ 0.01·N(0,1), b = 0."""
    u = _u_max_tuple(u_max)
    W = scale * jax.random.normal(key, (len(u), input_dim))
    return LinearPolicy(W, jnp.zeros(len(u)), u, saturated)
