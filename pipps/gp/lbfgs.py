"""A jittable, vmappable L-BFGS minimiser with a strong-Wolfe line search (GP training; docs/gp.md).

``optax.lbfgs`` (zoom line search, Nocedal & Wright Alg. 3.5/3.6) driven by a
``lax.while_loop``, with the safeguards of Rasmussen's minimize.m:

* a trial point whose value or gradient is NaN/Inf, or that does not strictly decrease the
  objective, is rejected: the iterate stays where it was and the L-BFGS memory is reset
  (a steepest-descent restart);
* two consecutive failed line searches stop the run;
* the budget is a number of line searches (``max_iters``), each with at most
  ``max_linesearch_steps`` evaluations; the run also stops when ‖∇f‖∞ ≤ ``grad_tol``.

Since only strictly decreasing, finite points are accepted, the returned point is the best
one seen and is never worse than the start.

:func:`pipps.optimizers.quasi_newton.minimize` has the same safeguards around minimize.m's line
search; the two stay separate because swapping line searches changes every fitted GP
(docs/architecture.md, "Two minimisers, on purpose").
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import optax


class MinimizeInfo(NamedTuple):
    value_init: jax.Array
    value: jax.Array
    iterations: jax.Array  # line searches run (accepted + failed)
    failures: jax.Array  # line searches whose point was rejected
    grad_norm: jax.Array  # ‖∇f‖∞ at the returned point


def _tree_where(cond, a, b):
    return jax.tree.map(lambda u, v: jnp.where(cond, u, v), a, b)


def _all_finite(tree) -> jax.Array:
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(tree)]))


def _inf_norm(tree) -> jax.Array:
    return jnp.max(jnp.stack([jnp.max(jnp.abs(leaf)) for leaf in jax.tree.leaves(tree)]))


def lbfgs_minimize(
    fun: Callable[[jax.Array], jax.Array],
    x0: jax.Array,
    *,
    max_iters: int,
    memory_size: int,
    max_linesearch_steps: int,
    grad_tol: float,
    stepsize_precision: float = 1e-12,
) -> tuple[jax.Array, MinimizeInfo]:
    """Minimise the scalar ``fun`` from ``x0``; returns (x_best, info). Pure and vmappable.

    If ``fun(x0)`` or its gradient is not finite, ``x0`` is returned unchanged.
    ``stepsize_precision`` is the zoom line search's smallest bracket (optax's default 1e-5
    is absolute and made line searches fail on steep FITC objectives that need steps ~1e-4).
    """
    opt = optax.lbfgs(
        memory_size=memory_size,
        linesearch=optax.scale_by_zoom_linesearch(
            max_linesearch_steps=max_linesearch_steps, initial_guess_strategy="one",
            stepsize_precision=stepsize_precision),
    )
    value_and_grad = jax.value_and_grad(fun)
    f0, g0 = value_and_grad(x0)
    start_ok = jnp.isfinite(f0) & _all_finite(g0)

    def cond(carry):
        k, _, _, g, _, consecutive, _ = carry
        return (k < max_iters) & (consecutive < 2) & (_inf_norm(g) > grad_tol) & start_ok

    def body(carry):
        k, x, f, g, state, consecutive, failures = carry
        updates, new_state = opt.update(g, state, x, value=f, grad=g, value_fn=fun)
        x_new = optax.apply_updates(x, updates)
        f_new = optax.tree.get(new_state, "value")
        g_new = optax.tree.get(new_state, "grad")
        ok = jnp.isfinite(f_new) & _all_finite(g_new) & (f_new < f)
        x, f, g = _tree_where(ok, (x_new, f_new, g_new), (x, f, g))
        state = _tree_where(ok, new_state, opt.init(x))
        consecutive = jnp.where(ok, 0, consecutive + 1)
        return k + 1, x, f, g, state, consecutive, failures + (~ok)

    init = (jnp.asarray(0), x0, f0, g0, opt.init(x0), jnp.asarray(0), jnp.asarray(0))
    k, x, f, g, _, _, failures = jax.lax.while_loop(cond, body, init)
    return x, MinimizeInfo(f0, f, k, failures, _inf_norm(g))
