"""Zero-order-hold integration of the true system over one control interval.

The reference integrates with MATLAB ``ode45`` at rtol = atol = 1e-12; any integrator
that reproduces the reference one-step vectors (docs/task-cartpole.md, docs/task-unicycle.md,
"Integrator and measured accuracy") to about 1e-9 is acceptable, and
the true system is never differentiated. We use classic fourth-order Runge–Kutta with
``substeps`` equal sub-steps of ``dt / substeps`` (a fixed-size ``lax.fori_loop``), so
the map is pure, jittable and vmappable, and its cost is fixed and known.

Measured accuracy: max abs error of one step against scipy ``solve_ivp`` (DOP853,
rtol = atol = 1e-12; it matches the reference vectors to 5e-13) at the reference states,
float64, by ``substeps`` (columns):

=========================================  =======  =======  =======  =======  =======  =======
case                                       10       20       50       100      134      200
=========================================  =======  =======  =======  =======  =======  =======
cart-pole ref. s, u = 4, dt = 0.1          1.6e-07  9.8e-09  2.5e-10  1.6e-11  4.8e-12  9.5e-13
cart-pole s = 0, u = 10, dt = 0.1          8.0e-07  4.6e-08  1.1e-09  6.8e-11  2.1e-11  4.1e-12
unicycle ref. s, u, dt = 0.15 (pilco)      3.7e-06  2.4e-07  6.3e-09  4.0e-10  1.2e-10  2.4e-11
unicycle ref. s, u, dt = 0.1 (thesis)      3.7e-07  2.4e-08  6.1e-10  3.7e-11  1.1e-11  1.3e-12
=========================================  =======  =======  =======  =======  =======  =======

The error falls as ``substeps⁻⁴``, as it should. The presets choose
``substeps = ceil(dt / h_max)`` with ``h_max`` = 1 ms for the cart-pole (100 sub-steps
at dt = 0.1 s) and 0.75 ms for the unicycle (200 at dt = 0.15 s, 134 at dt = 0.1 s),
so every reference step is reproduced to 1e-10 or better (a 10× margin on the 1e-9 required;
the unicycle at dt = 0.15 s needs more than 100 sub-steps for that). Along random-action
trajectories (one-step errors from the states visited, 10 rollouts each) the defaults
give at most 6e-9 for the cart-pole (u ~ U[-10, 10], 400 steps) and 2e-10 for the
unicycle while upright (u ~ U[-ū/5, ū/5], both dt), 1e-9 on the step on which it falls
(1e-8 with u ~ U[-ū, ū]). These are far below any observation noise in the study.
"""

from __future__ import annotations

import functools
from typing import Callable

import jax
import jax.numpy as jnp
from jax import lax


def rk4_step(ode: Callable[[jax.Array, jax.Array], jax.Array], s: jax.Array, u: jax.Array, h) -> jax.Array:
    """One classic fourth-order Runge–Kutta step of size ``h`` for ṡ = ode(s, u), u held."""
    k1 = ode(s, u)
    k2 = ode(s + 0.5 * h * k1, u)
    k3 = ode(s + 0.5 * h * k2, u)
    k4 = ode(s + h * k3, u)
    return s + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


@functools.partial(jax.jit, static_argnames=("ode", "substeps"))
def integrate_interval(
    ode: Callable[[jax.Array, jax.Array], jax.Array],
    s: jax.Array,
    u: jax.Array,
    dt,
    substeps: int,
) -> jax.Array:
    """State after one control interval ``dt`` of ṡ = ode(s, u) with u held constant (zero-order hold).

    Classic RK4 with ``substeps`` equal sub-steps (a positive Python int: it fixes the
    program). Pure; ``vmap`` over ``s`` and ``u`` works as usual. It is jitted with
    ``ode`` and ``substeps`` static, so that an eager call (e.g. ``Task.step`` outside
    jit) compiles once per (ode, substeps, shapes) instead of re-tracing the loop every
    call; inside a caller's jit it is simply inlined. ``ode`` must be hashable (a module
    function is; a fresh lambda per call recompiles). See the module docstring for the
    measured accuracy.
    """
    if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
        raise ValueError(f"substeps must be a positive integer, got {substeps!r}")
    s = jnp.asarray(s)
    u = jnp.asarray(u)
    h = dt / substeps

    def body(_, state):
        return rk4_step(ode, state, u, h)

    return lax.fori_loop(0, substeps, body, s)
