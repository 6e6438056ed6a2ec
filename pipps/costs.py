"""Saturating costs on the model state and their Gaussian expectations (docs/costs.md).

Every cost here is ``c(x) = 1 − exp(−½ (φ(x) − z)ᵀ W (φ(x) − z))`` (PILCO's convention)
with the feature map ``φ`` = an optional linear extension ``y = L x`` followed by the trig
augmentation ``[y; sin y_a, cos y_a (a in angle_idx)]``. The thesis writes the same
function as ``1 − exp(−(φ − z)ᵀ Q (φ − z))``, so ``W = 2Q`` (thesis eq. 4.1).

A :class:`SaturatingCost` is static configuration (numpy constants closed over by jitted
code), like :class:`pipps.tasks.base.Problem`; it satisfies the ``Cost`` protocol there.
``cost(x)`` is exact per state (vmappable over particles); ``cost.expected(mean, cov)``
is PILCO's moment-matched ``(E[c], Var[c])``: exact through the linear map and the closed-form expectation, an
approximation only where the non-Gaussian trig features are replaced by a Gaussian.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from pipps.gaussian import expected_saturating_cost, linear_map, trig_augment

CARTPOLE_POLE_LENGTH = 0.5  # l (m), PILCO's cart-pole (docs/task-cartpole.md)
UNICYCLE_COST_WHEEL_RADIUS = 0.22  # r_w in the cost (the dynamics use 0.225), PILCO's loss_unicycle.m
UNICYCLE_COST_HEIGHT = 0.81  # r = r_f + r_t, PILCO's loss_unicycle.m


def _frozen(a, ndim: int, name: str) -> np.ndarray:
    """A read-only float64 copy of `a`, checked to have `ndim` axes."""
    arr = np.array(a, dtype=np.float64)
    if arr.ndim != ndim:
        raise ValueError(f"{name} must be {ndim}-dimensional, got shape {arr.shape}")
    arr.setflags(write=False)
    return arr


@dataclasses.dataclass(frozen=True, eq=False)
class SaturatingCost:
    """``c(x) = 1 − exp(−½ (φ(x) − z)ᵀ W (φ(x) − z))`` on the model state ``x``.

    ``W`` (F, F) and ``target`` z (F,) live in feature space; ``linear`` (E, D) is the
    optional extension ``y = L x`` (None: ``y = x``); ``angle_idx`` indexes ``y``.
    F = E + 2·len(angle_idx).
    """

    W: np.ndarray
    target: np.ndarray
    linear: np.ndarray | None = None
    angle_idx: tuple[int, ...] = ()
    name: str = "saturating"

    def __post_init__(self):
        # Normalize the fields in place (a frozen dataclass needs object.__setattr__).
        object.__setattr__(self, "W", _frozen(self.W, 2, "W"))
        object.__setattr__(self, "target", _frozen(self.target, 1, "target"))
        if self.linear is not None:
            object.__setattr__(self, "linear", _frozen(self.linear, 2, "linear"))
        object.__setattr__(self, "angle_idx", tuple(int(a) for a in self.angle_idx))
        n_feat = self.extended_dim + 2 * len(self.angle_idx)
        if self.W.shape != (n_feat, n_feat) or self.target.shape != (n_feat,):
            raise ValueError(
                f"W {self.W.shape} and target {self.target.shape} must match the "
                f"{n_feat} features of φ"
            )
        if not np.allclose(self.W, self.W.T, rtol=0.0, atol=1e-14):
            raise ValueError("W must be symmetric")
        if any(not 0 <= a < self.extended_dim for a in self.angle_idx):
            raise ValueError(f"angle_idx {self.angle_idx} out of range for {self.extended_dim}")

    @property
    def extended_dim(self) -> int:
        """E: dimension of ``y = L x`` (the model state itself without an extension)."""
        if self.linear is not None:
            return self.linear.shape[0]
        return self.W.shape[0] - 2 * len(self.angle_idx)

    @property
    def model_dim(self) -> int:
        """D: dimension of the model state the cost is defined on."""
        return self.linear.shape[1] if self.linear is not None else self.extended_dim

    @property
    def feature_dim(self) -> int:
        return self.W.shape[0]

    def features(self, x: jax.Array) -> jax.Array:
        """φ(x) = [Lx; sin (Lx)_a, cos (Lx)_a]; leading batch axes are allowed."""
        y = x if self.linear is None else x @ self.linear.T
        if not self.angle_idx:
            return y
        a = y[..., np.asarray(self.angle_idx)]
        trig = jnp.stack([jnp.sin(a), jnp.cos(a)], axis=-1).reshape(*a.shape[:-1], 2 * a.shape[-1])
        return jnp.concatenate([y, trig], axis=-1)

    def __call__(self, x: jax.Array) -> jax.Array:
        """c(x) for a model state (leading batch axes allowed, so also vmappable)."""
        d = self.features(x) - self.target
        return 1.0 - jnp.exp(-0.5 * jnp.einsum("...i,ij,...j->...", d, self.W, d))

    def feature_moments(self, mean: jax.Array, cov: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Moment-matched Gaussian over φ(x) for x ~ N(mean, cov): linear map, then the trig augmentation."""
        if self.linear is not None:
            mean, cov, _ = linear_map(mean, cov, self.linear)
        if self.angle_idx:
            mean, cov, _ = trig_augment(mean, cov, self.angle_idx)
        return mean, cov

    def expected(self, mean: jax.Array, cov: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(E[c], Var[c]) for x ~ N(mean, cov): :meth:`feature_moments`, then the closed form."""
        m, S = self.feature_moments(mean, cov)
        return expected_saturating_cost(m, S, self.W, self.target)


def cartpole_angle_cost(scale: float = 1.0) -> SaturatingCost:
    """Thesis Angle Cost ``1 − exp(−scale·[x_c² + (θ − π)²])`` on ``[x_c, v, ω, θ]``.

    Thesis form ``Q = scale·diag(1, 0, 0, 1)`` (``diag(1, 1, 0, 0)`` on its ``(s, β)``),
    ours ``W = 2Q``, target ``[0, 0, 0, π]``: the raw angle, so only the upright position
    reached by swinging in the positive direction (θ = +π) costs 0 (docs/costs.md, "Interpretations").
    ``scale = 0.01`` is the thesis' "Q multiplied by 0.01" experiment.
    """
    Q = scale * np.diag([1.0, 0.0, 0.0, 1.0])
    return SaturatingCost(W=2.0 * Q, target=np.array([0.0, 0.0, 0.0, np.pi]), name="angle")


def cartpole_tip_cost(
    l: float = CARTPOLE_POLE_LENGTH, sigma_c: float = 0.25  # noqa: E741 (the thesis' name)
) -> SaturatingCost:
    """PILCO's tip-distance cost ``1 − exp(−d²/(2σ_c²))`` (PILCO's ``loss_cp.m``).

    ``d² = (x_c + l sin θ)² + l²(1 + cos θ)²`` is the squared distance of the pole tip from
    the upright tip; on ``x̃ = [x_c, v, ω, θ, sin θ, cos θ]`` it is ``(x̃ − z)ᵀQ(x̃ − z)``
    with ``Q₁₁ = 1, Q₁₅ = Q₅₁ = l, Q₅₅ = Q₆₆ = l²``, ``z = [0, 0, 0, π, 0, −1]``;
    ``W = Q/σ_c²`` (the thesis' ``Q`` is ``W/2``).
    """
    Q = np.zeros((6, 6))
    Q[0, 0] = 1.0
    Q[0, 4] = Q[4, 0] = l
    Q[4, 4] = Q[5, 5] = l**2
    target = np.array([0.0, 0.0, 0.0, np.pi, 0.0, -1.0])
    return SaturatingCost(W=Q / sigma_c**2, target=target, angle_idx=(3,), name="tip")


def unicycle_cost(
    r_w: float = UNICYCLE_COST_WHEEL_RADIUS, r: float = UNICYCLE_COST_HEIGHT
) -> SaturatingCost:
    """PILCO's unicycle cost (``loss_unicycle.m``) on the 10-dim model state.

    Model state ``[θ̇, φ̇, ψ̇_w, ψ̇_f, ψ̇_t, x_c, y_c, θ, φ, ψ_f]``; ``y = [x; α, β]`` with
    ``α = θ − ψ_f``, ``β = θ + ψ_f`` (indices 10, 11); trig of ``(θ, α, β, ψ_f)`` appends
    ``sin θ, cos θ, sin α, cos α, sin β, cos β, sin ψ_f, cos ψ_f`` at 12..19.
    ``½ (φ−z)ᵀW(φ−z) = ½[8 d_z² + ½ d_x² + ½ d_y² + φ²/(16π²)]``, target 1 on the cosines.
    """
    theta, yaw, pitch = 7, 8, 9
    L = np.zeros((12, 10))
    L[:10, :10] = np.eye(10)
    L[10, theta], L[10, pitch] = 1.0, -1.0  # α = θ − ψ_f
    L[11, theta], L[11, pitch] = 1.0, 1.0  # β = θ + ψ_f
    angle_idx = (theta, 10, 11, pitch)
    sin_theta, cos_theta, cos_alpha, cos_beta, sin_pitch, cos_pitch = 12, 13, 15, 17, 18, 19
    x_c, y_c = 5, 6

    W = np.zeros((20, 20))

    def add_outer(idx, coef, weight):
        c = np.asarray(coef, dtype=np.float64)
        W[np.ix_(idx, idx)] += weight * np.outer(c, c)

    add_outer([cos_theta, cos_alpha, cos_beta], [r_w, r / 2, r / 2], 8.0)  # height d_z
    add_outer([x_c, sin_pitch], [1.0, -r], 0.5)  # d_x
    add_outer([y_c, sin_theta], [1.0, -(r + r_w)], 0.5)  # d_y
    W[yaw, yaw] += 1.0 / (4.0 * np.pi) ** 2  # heading

    target = np.zeros(20)
    target[[cos_theta, cos_alpha, cos_beta, cos_pitch]] = 1.0
    return SaturatingCost(W=W, target=target, linear=L, angle_idx=angle_idx, name="unicycle")
