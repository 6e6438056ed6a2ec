"""PILCO unicycle physics (``dynamics_unicycle.m``; docs/task-unicycle.md).

Simulator (ODE) state, 12-dim (the ODE variables of PILCO's ``settings_unicycle.m``), 0-based indices::

    s = [θ̇, φ̇, ψ̇_w, ψ̇_f, ψ̇_t,  x, y,  θ, φ, ψ_w, ψ_f, ψ_t]
         0   1    2    3    4   5  6   7  8   9   10   11

θ roll, φ yaw, ψ_w wheel angle, ψ_f pitch (frame), ψ_t turntable angle (rad, rad/s);
(x, y) the world position of the wheel contact point (m). Controls ``u = [u_t, u_w]``:
turntable and wheel motor torques (N m).

Model state, 10-dim (PILCO's GP state)::

    x = [θ̇, φ̇, ψ̇_w, ψ̇_f, ψ̇_t,  x_c, y_c,  θ, φ, ψ_f]
         0   1    2    3    4    5    6    7  8   9

with (x_c, y_c) the body-frame coordinates of the world origin.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


class UnicycleParams(NamedTuple):
    """Physical parameters (PILCO's): masses (kg), distances (m), inertias (kg m²)."""

    mw: float = 1.0  # wheel mass
    rw: float = 0.225  # wheel radius
    Aw: float = 0.0242  # wheel inertia perpendicular to the axle
    Cw: float = 0.0484  # wheel inertia about the axle
    mf: float = 23.5  # frame mass
    rf: float = 0.54  # wheel axle to frame centre of mass
    Af: float = 0.4248
    Bf: float = 0.4608
    Cf: float = 0.8292
    mt: float = 10.0  # turntable mass
    rt: float = 0.27  # frame centre of mass to turntable
    At: float = 1.3  # turntable inertia perpendicular to its axle
    Ct: float = 0.2  # turntable inertia about its axle
    g: float = 9.82  # the reference code's value (its documentation says 9.81)


UNICYCLE_PARAMS = UnicycleParams()

SIM_DIM = 12
MODEL_DIM = 10
#: simulator indices of the model-state components other than (x_c, y_c)
_RATES = (0, 1, 2, 3, 4)
_THETA, _PHI, _PSI_W, _PSI_F, _PSI_T = 7, 8, 9, 10, 11

#: Observation-noise standard deviations on the simulator state (PILCO's):
#: 0.01 on the five rates, 0.003 on x, y and the five angles.
UNICYCLE_OBS_STD = np.concatenate([np.full(5, 0.01), np.full(7, 0.003)])

#: Simulator start distribution (PILCO's): mean 0, independent components with
#: std 0.02 on the rates, 0.1 m on x and y, 0.02 on the angles.
UNICYCLE_INIT_MEAN = np.zeros(SIM_DIM)
UNICYCLE_INIT_STD = np.concatenate([np.full(5, 0.02), np.full(2, 0.1), np.full(5, 0.02)])
UNICYCLE_INIT_COV = np.diag(UNICYCLE_INIT_STD**2)

#: Planning start distribution: the exact mean and covariance of x(s0) (PILCO estimates it from
#: 1000 Monte Carlo samples instead). x_c, y_c are rotations of (x, y) by the independent yaw, so their mean is 0,
#: their variances stay 0.1², and every cross term vanishes.
UNICYCLE_MODEL_INIT_MEAN = np.zeros(MODEL_DIM)
UNICYCLE_MODEL_INIT_COV = np.diag(np.concatenate([np.full(5, 0.02**2), [0.01, 0.01], np.full(3, 0.02**2)]))


def _mass_matrix_and_bias(s: jax.Array, u: jax.Array, p: UnicycleParams) -> tuple[jax.Array, jax.Array]:
    """A(s) and b(s, u) of A q̈ + b = 0, q = (θ, φ, ψ_w, ψ_f, ψ_t) (docs/task-unicycle.md, "Physics")."""
    dth, dph, dpw, dpf, dpt = s[0], s[1], s[2], s[3], s[4]
    th, pf = s[_THETA], s[_PSI_F]
    ut, uw = u[0], u[1]
    rw, g = p.rw, p.g
    st, ct = jnp.sin(th), jnp.cos(th)
    sf, cf = jnp.sin(pf), jnp.cos(pf)
    r = p.rf + p.rt
    k1 = p.mf * p.rf**2 + p.mt * r**2
    k2 = p.mf * p.rf + p.mt * r
    msum = p.mw + p.mf + p.mt

    w1 = dph * sf * ct + dth * cf
    w2 = dph * cf * ct - dth * sf
    w3 = dpf - dph * st
    ww = dpw - dph * st
    wt = w2 + dpt
    a1 = dph * dpf * sf * ct + dph * dth * cf * st + dpf * dth * cf
    a2 = dph * dpf * cf * ct - dph * dth * sf * st - dpf * dth * sf

    def G(rho):
        return rw * dph * (sf * st * ww + cf * ct * dth) + rho * dph * dth * ct + w2 * (rw * dth + rho * w1)

    def H(rho):
        return rw * sf * w1 * ww + rho * a2 + w2 * (rw * cf * ww + rho * w3)

    def K(rho):
        return rw * dph * (sf * ct * dth - cf * st * ww) + w1 * (rw * dth + rho * w1) + rho * w3**2

    Y1 = -(p.Af + p.Ct) * a1 + (p.Bf - p.Cf) * w1 * w3
    Y2 = (
        -(p.Bf + p.At) * a2
        + (p.Af - p.Cf - p.At) * w2 * w3
        + p.Ct * w3 * wt
        + k2 * g * st
        - p.mf * p.rf * H(p.rf)
        - p.mt * r * H(r)
    )

    zero = jnp.zeros_like(th)
    c0 = p.Cw + p.At + k1
    A = jnp.stack(
        [
            jnp.stack([-p.Ct * sf, p.Ct * cf * ct, zero, zero, p.Ct + zero]),
            jnp.stack([zero, st * (c0 + rw * cf * k2), -rw * cf * k2, -c0 + zero, zero]),
            jnp.stack(
                [
                    sf * cf * (p.Bf + p.At - p.Af - p.Ct + k1) + rw * sf * k2,
                    ct * (p.Aw + cf**2 * (p.Af + p.Ct) + sf**2 * (p.Bf + p.At + k1)),
                    zero,
                    zero,
                    p.Ct * cf,
                ]
            ),
            jnp.stack(
                [
                    -p.Aw - rw**2 * msum - 2.0 * rw * cf * k2 - sf**2 * (p.Af + p.Ct) - cf**2 * (p.Bf + p.At + k1),
                    sf * ct * (cf * (p.Af + p.Ct - p.Bf - p.At - k1) - rw * k2),
                    zero,
                    zero,
                    p.Ct * sf,
                ]
            ),
            jnp.stack(
                [
                    zero,
                    st * (2.0 * p.Cw + p.At + k1 + 2.0 * rw * cf * k2 + rw**2 * msum),
                    -p.Cw - rw * cf * k2 - rw**2 * msum,
                    -(c0 + rw * cf * k2),
                    zero,
                ]
            ),
        ]
    )

    common = (p.At + p.Bf - p.Af) * w1 * w2 - p.Ct * w1 * wt + k2 * g * sf * ct + p.mf * p.rf * G(p.rf) + p.mt * r * G(r)
    b1 = -ut - p.Ct * a1
    b2 = -uw + (p.Cw + p.At) * dph * dth * ct + common
    b3 = -2.0 * p.Aw * dph * dth * st - p.Cw * dth * ww + cf * Y1 - sf * Y2
    b4 = (
        -p.Aw * dph**2 * st * ct
        - p.Cw * dph * ct * ww
        - rw * (p.mw * rw * dph * ct * ww - msum * g * st + p.mf * H(p.rf) + p.mt * H(r))
        + sf * Y1
        + cf * Y2
    )
    b5 = (
        (2.0 * p.Cw + p.At) * dph * dth * ct
        + common
        + rw
        * (
            2.0 * p.mw * rw * dph * dth * ct
            + sf * (p.mf * K(p.rf) + p.mt * K(r))
            + cf * (p.mf * G(p.rf) + p.mt * G(r))
        )
    )
    b = jnp.stack([b1, b2, b3, b4, b5])
    return A, b


def unicycle_ode(s: jax.Array, u: jax.Array, params: UnicycleParams = UNICYCLE_PARAMS) -> jax.Array:
    """ṡ for the 12-dim simulator state and torques u = [u_t, u_w].

    q̈ = −A(s)⁻¹ b(s, u) via ``jnp.linalg.solve``; ẋ = r_w ψ̇_w cos φ, ẏ = r_w ψ̇_w sin φ;
    each angle's derivative is its rate.
    """
    A, b = _mass_matrix_and_bias(s, u, params)
    qdd = -jnp.linalg.solve(A, b)
    dx, dy = _ground_velocity(s, params)
    return jnp.concatenate([qdd, jnp.stack([dx, dy]), s[0:5]])


def _ground_velocity(s: jax.Array, p: UnicycleParams = UNICYCLE_PARAMS) -> tuple[jax.Array, jax.Array]:
    """(ẋ, ẏ) = r_w ψ̇_w (cos φ, sin φ) (rolling without slip)."""
    phi = s[..., _PHI]
    v = p.rw * s[..., 2]
    return v * jnp.cos(phi), v * jnp.sin(phi)


def unicycle_origin_in_body_frame(s: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(x_c, y_c) = (−(x cos φ + y sin φ), x sin φ − y cos φ)."""
    x, y, phi = s[..., 5], s[..., 6], s[..., _PHI]
    c, sn = jnp.cos(phi), jnp.sin(phi)
    return -(x * c + y * sn), x * sn - y * c


def unicycle_derived(s: jax.Array, params: UnicycleParams = UNICYCLE_PARAMS) -> jax.Array:
    """(ẋ, ẏ, ẋ_c, ẏ_c, x_c, y_c) at simulator state(s) s (checked against reference values).

    (ẋ_c, ẏ_c) is the time derivative of (x_c, y_c):
    ẋ_c = −(ẋ cos φ + ẏ sin φ) + φ̇ y_c and ẏ_c = ẋ sin φ − ẏ cos φ − φ̇ x_c.
    """
    dx, dy = _ground_velocity(s, params)
    xc, yc = unicycle_origin_in_body_frame(s)
    phi, dphi = s[..., _PHI], s[..., 1]
    c, sn = jnp.cos(phi), jnp.sin(phi)
    dxc = -(dx * c + dy * sn) + dphi * yc
    dyc = dx * sn - dy * c - dphi * xc
    return jnp.stack([dx, dy, dxc, dyc, xc, yc], axis=-1)


def unicycle_full_state(s: jax.Array, params: UnicycleParams = UNICYCLE_PARAMS) -> jax.Array:
    """The reference's 18-dim recorded state (docs/task-unicycle.md, "States")::

    [ẋ, ẏ, ẋ_c, ẏ_c, θ̇, φ̇, ψ̇_w, ψ̇_f, ψ̇_t, x, y, x_c, y_c, θ, φ, ψ_w, ψ_f, ψ_t]
    """
    d = unicycle_derived(s, params)
    return jnp.concatenate([d[..., 0:4], s[..., 0:7], d[..., 4:6], s[..., 7:12]], axis=-1)


def unicycle_sim_to_model(s: jax.Array) -> jax.Array:
    """10-dim model state [θ̇, φ̇, ψ̇_w, ψ̇_f, ψ̇_t, x_c, y_c, θ, φ, ψ_f] (PILCO's)."""
    xc, yc = unicycle_origin_in_body_frame(s)
    return jnp.concatenate(
        [s[..., 0:5], jnp.stack([xc, yc], axis=-1), s[..., _THETA : _PHI + 1], s[..., _PSI_F : _PSI_F + 1]],
        axis=-1,
    )


def unicycle_fallen(s: jax.Array) -> jax.Array:
    """True when the robot has fallen: |θ| > π/2 or |ψ_f| > π/2 (PILCO's fall condition)."""
    half_pi = jnp.pi / 2
    return (jnp.abs(s[..., _THETA]) > half_pi) | (jnp.abs(s[..., _PSI_F]) > half_pi)
