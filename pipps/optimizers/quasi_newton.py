"""Quasi-Newton minimisation with minimize.m semantics (docs/pilco.md, "The optimiser"), jittable and vmappable.

:func:`minimize` is dense BFGS (inverse Hessian initialised to I, ≤ 1000 parameters by default)
or L-BFGS (memory ``min(100, n)``) on a pytree, with a bracketing line search that accepts a
point when ``f(a) ≤ f(0) + ρ a f'(0)`` and ``|f'(a)| ≤ σ |f'(0)|`` (strong Wolfe, σ = 0.5 as in
minimize.m). Everything runs inside ``lax.while_loop`` (one loop over line searches, one over
the evaluations of a line search), so a whole optimisation is one compiled program and
``jax.vmap`` runs many seeds at once.

Budgets (minimize.m): ``length > 0`` allows at most ``length`` line searches, ``length < 0`` at
most ``|length|`` evaluations of value and gradient, the initial one included; a line search
makes at most ``max_evals_per_linesearch`` evaluations.

Line search (per evaluation): the first trial moves between ``min_first_step`` and
``max_first_step`` in parameter space (BFGS starts from the previously accepted step, L-BFGS
from 1, a steepest-descent (re)start from ``1/(1 − f'(0))``). While no bracket is known it
extrapolates by a cubic fit, kept within [1.1, 5]× the current step; once bracketed it
interpolates by a cubic fit kept 10 % away from the bracket ends (bisection when the fit is
unusable), with the bracket updates of Nocedal & Wright's Algorithms 3.5/3.6.

Failures: a trial whose value or gradient is NaN/Inf becomes the bracket's upper end (no slope
information) and the next trial bisects back toward the last good point. A line search that
ends without an acceptable point still moves to the best finite point it evaluated if that
point decreased the objective, then restarts along steepest descent (BFGS matrix reset to I,
L-BFGS memory cleared); two consecutive failed line searches stop the run. Only finite points
that decrease the objective are ever moved to, so the last good parameters are never lost, and
the returned parameters are the best point evaluated.

The GP fit uses :func:`pipps.gp.lbfgs.lbfgs_minimize` instead (optax's zoom line search, the same
safeguards); docs/architecture.md, "Two minimisers, on purpose", says why there are two.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

# stop reasons (QuasiNewtonTrace.stop_reason)
STOP_BUDGET = 0  # line-search or evaluation budget used up
STOP_FAILED = 1  # two consecutive failed line searches
STOP_GRADIENT = 2  # ‖∇f‖∞ ≤ grad_tol
STOP_NONFINITE_START = 3  # f or ∇f not finite at the start point: nothing was done


@dataclasses.dataclass(frozen=True)
class QuasiNewtonConfig:
    """Static settings of :func:`minimize` (hashable; a jit static argument).

    Attributes:
      length: > 0: max line searches; < 0: max evaluations (initial one counted). Not 0.
      max_evals_per_linesearch: MFEPLS (minimize.m's default 10; PILCO's policy search 30/20).
      method: ``"bfgs"``, ``"lbfgs"`` or ``"auto"`` (BFGS iff ≤ ``dense_limit`` parameters).
      memory: L-BFGS memory (capped at the number of parameters).
      sigma: curvature constant σ of the strong-Wolfe test.
      rho: sufficient-decrease constant ρ.
      max_first_step, min_first_step: bounds on the first trial's move ‖a d‖.
      extrapolation: (min, max) factor of each extrapolation step.
      interpolation_margin: fraction of the bracket a cubic interpolation stays away from its ends.
      grad_tol: stop when ‖∇f‖∞ ≤ grad_tol (0: only the budget and failures stop the run).
      dense_limit: the ``"auto"`` switch from BFGS to L-BFGS.
    """

    length: int = 100
    max_evals_per_linesearch: int = 10
    method: str = "auto"
    memory: int = 100
    sigma: float = 0.5
    rho: float = 1e-4
    max_first_step: float = 1.0
    min_first_step: float = 1e-7
    extrapolation: tuple[float, float] = (1.1, 5.0)
    interpolation_margin: float = 0.1
    grad_tol: float = 0.0
    dense_limit: int = 1000

    def __post_init__(self):
        if int(self.length) == 0:
            raise ValueError("length must be non-zero (> 0: line searches, < 0: evaluations)")
        if self.max_evals_per_linesearch < 1:
            raise ValueError(f"max_evals_per_linesearch must be >= 1, got {self.max_evals_per_linesearch}")
        if self.method not in ("auto", "bfgs", "lbfgs"):
            raise ValueError(f"method must be 'auto', 'bfgs' or 'lbfgs', got {self.method!r}")
        if not 0.0 < self.rho < self.sigma < 1.0:
            raise ValueError(f"need 0 < rho < sigma < 1, got rho={self.rho}, sigma={self.sigma}")
        if not 0.0 < self.min_first_step <= self.max_first_step:
            raise ValueError("need 0 < min_first_step <= max_first_step")
        lo, hi = self.extrapolation
        if not 1.0 < lo <= hi:
            raise ValueError(f"extrapolation factors must satisfy 1 < min <= max, got {self.extrapolation}")
        if not 0.0 <= self.interpolation_margin < 0.5:
            raise ValueError("interpolation_margin must be in [0, 0.5)")
        if self.memory < 1:
            raise ValueError("memory must be >= 1")

    @property
    def max_linesearches(self) -> int:
        """An upper bound on the number of line searches (the trace length minus 1)."""
        return abs(int(self.length)) if self.length > 0 else max(abs(int(self.length)) - 1, 0)


class QuasiNewtonTrace(NamedTuple):
    """What :func:`minimize` did. Per-line-search arrays have length ``max_linesearches + 1``.

    Entry 0 is the start; entry ``k`` is after line search ``k``; entries past
    ``num_linesearches`` are NaN / -1 / False.
    """

    values: jax.Array  # objective at the iterate
    evaluations: jax.Array  # cumulative evaluations (the start's evaluation counts 1)
    failed: jax.Array  # line search k ended without an acceptable point
    value_init: jax.Array  # f(x0)
    value: jax.Array  # f at the returned (best) point
    grad_norm: jax.Array  # ‖∇f‖∞ at the returned point
    num_linesearches: jax.Array
    num_evaluations: jax.Array
    num_failures: jax.Array
    stop_reason: jax.Array  # STOP_* code


# -- helpers --------------------------------------------------------------------------------------


def _finite(f, g) -> jax.Array:
    return jnp.isfinite(f) & jnp.all(jnp.isfinite(g))


def _cubic_minimiser(a, fa, da, b, fb, db):
    """Minimiser of the cubic through (a, fa, f'a), (b, fb, f'b) (N&W eq. 3.59) and whether it exists."""
    d1 = da + db - 3.0 * (fa - fb) / (a - b)
    disc = d1 * d1 - da * db
    d2 = jnp.sign(b - a) * jnp.sqrt(jnp.maximum(disc, 0.0))
    x = b - (b - a) * (db + d2 - d1) / (db - da + 2.0 * d2)
    return x, (disc >= 0.0) & jnp.isfinite(x)


class _LineSearch(NamedTuple):
    k: jax.Array  # evaluations made
    a_t: jax.Array  # next trial
    a_lo: jax.Array
    f_lo: jax.Array
    d_lo: jax.Array
    a_hi: jax.Array
    f_hi: jax.Array
    d_hi: jax.Array
    hi_info: jax.Array  # the upper end has finite value and slope
    bracketed: jax.Array
    a_best: jax.Array
    f_best: jax.Array
    g_best: jax.Array
    a_acc: jax.Array
    f_acc: jax.Array
    g_acc: jax.Array
    success: jax.Array
    done: jax.Array


def _line_search(vg, x, d, f0, g0, d0, a_init, max_evals, cfg: QuasiNewtonConfig) -> _LineSearch:
    """Bracketing strong-Wolfe line search along ``d`` from ``x`` (one evaluation per loop step)."""
    dtype = f0.dtype
    zero = jnp.zeros((), dtype)
    ext_min, ext_max = cfg.extrapolation
    margin = cfg.interpolation_margin

    def cond(s: _LineSearch):
        return ~s.done & (s.k < max_evals)

    def body(s: _LineSearch) -> _LineSearch:
        a_t = s.a_t
        f_t, g_t = vg(x + a_t * d)
        ok = _finite(f_t, g_t)
        d_t = jnp.where(ok, jnp.vdot(g_t, d), zero)
        f_t = jnp.where(ok, f_t, jnp.inf)
        better = ok & (f_t < s.f_best)
        a_best = jnp.where(better, a_t, s.a_best)
        f_best = jnp.where(better, f_t, s.f_best)
        g_best = jnp.where(better, g_t, s.g_best)
        armijo = ok & (f_t <= f0 + cfg.rho * a_t * d0)
        accept = armijo & (jnp.abs(d_t) <= -cfg.sigma * d0)

        # bracket update (N&W Alg. 3.5 / 3.6); a non-finite point is an upper end without information
        to_hi = ~armijo | (f_t >= s.f_lo)
        to_lo = ~to_hi  # finite, sufficient decrease, lower than lo
        flip = to_lo & jnp.where(s.bracketed, d_t * (s.a_hi - s.a_lo) >= 0.0, d_t >= 0.0)
        new_hi = to_hi | flip
        a_hi = jnp.where(to_hi, a_t, jnp.where(flip, s.a_lo, s.a_hi))
        f_hi = jnp.where(to_hi, f_t, jnp.where(flip, s.f_lo, s.f_hi))
        d_hi = jnp.where(to_hi, d_t, jnp.where(flip, s.d_lo, s.d_hi))
        hi_info = jnp.where(to_hi, ok, jnp.where(flip, True, s.hi_info))
        bracketed = s.bracketed | new_hi
        a_lo = jnp.where(to_lo, a_t, s.a_lo)
        f_lo = jnp.where(to_lo, f_t, s.f_lo)
        d_lo = jnp.where(to_lo, d_t, s.d_lo)

        # next trial: interpolate inside the bracket, or extrapolate beyond a_t
        lo_s, hi_s = jnp.minimum(a_lo, a_hi), jnp.maximum(a_lo, a_hi)
        width = hi_s - lo_s
        cubic_in, valid_in = _cubic_minimiser(a_lo, f_lo, d_lo, a_hi, f_hi, d_hi)
        interp = jnp.where(valid_in & hi_info, cubic_in, 0.5 * (lo_s + hi_s))
        interp = jnp.clip(interp, lo_s + margin * width, hi_s - margin * width)
        cubic_ex, valid_ex = _cubic_minimiser(s.a_lo, s.f_lo, s.d_lo, a_t, f_t, d_t)
        extrap = jnp.where(valid_ex & (cubic_ex > a_t), cubic_ex, ext_max * a_t)
        extrap = jnp.clip(extrap, ext_min * a_t, ext_max * a_t)
        a_next = jnp.where(bracketed, interp, extrap)
        tiny = bracketed & (width <= 1e-12 * jnp.maximum(hi_s, jnp.finfo(dtype).tiny))
        return _LineSearch(
            k=s.k + 1, a_t=a_next, a_lo=a_lo, f_lo=f_lo, d_lo=d_lo, a_hi=a_hi, f_hi=f_hi, d_hi=d_hi,
            hi_info=hi_info, bracketed=bracketed, a_best=a_best, f_best=f_best, g_best=g_best,
            a_acc=jnp.where(accept, a_t, s.a_acc), f_acc=jnp.where(accept, f_t, s.f_acc),
            g_acc=jnp.where(accept, g_t, s.g_acc), success=accept, done=accept | tiny,
        )

    init = _LineSearch(
        k=jnp.asarray(0), a_t=a_init, a_lo=zero, f_lo=f0, d_lo=d0, a_hi=zero, f_hi=f0, d_hi=d0,
        hi_info=jnp.asarray(False), bracketed=jnp.asarray(False), a_best=zero, f_best=f0, g_best=g0,
        a_acc=zero, f_acc=f0, g_acc=g0, success=jnp.asarray(False), done=jnp.asarray(False),
    )
    return jax.lax.while_loop(cond, body, init)


# -- directions -----------------------------------------------------------------------------------


class _Bfgs(NamedTuple):
    H: jax.Array  # (n, n) inverse-Hessian approximation


class _Lbfgs(NamedTuple):
    S: jax.Array  # (m, n) steps, circular
    Y: jax.Array  # (m, n) gradient changes
    rho: jax.Array  # (m,) 1/(sᵀy)
    head: jax.Array  # next slot
    count: jax.Array  # pairs stored


def _direction_init(n: int, dense: bool, memory: int, dtype):
    if dense:
        return _Bfgs(jnp.eye(n, dtype=dtype))
    m = min(memory, n)
    return _Lbfgs(jnp.zeros((m, n), dtype), jnp.zeros((m, n), dtype), jnp.zeros((m,), dtype),
                  jnp.asarray(0), jnp.asarray(0))


def _direction(state, g):
    if isinstance(state, _Bfgs):
        return -(state.H @ g)
    m = state.S.shape[0]

    def newest_first(k, carry):
        q, alphas = carry
        i = (state.head - 1 - k) % m
        use = k < state.count
        a = jnp.where(use, state.rho[i] * jnp.vdot(state.S[i], q), 0.0)
        return q - a * state.Y[i], alphas.at[k].set(a)

    q, alphas = jax.lax.fori_loop(0, m, newest_first, (g, jnp.zeros((m,), g.dtype)))
    newest = (state.head - 1) % m
    yy = jnp.vdot(state.Y[newest], state.Y[newest])
    gamma = jnp.where(state.count > 0, 1.0 / jnp.where(yy > 0, state.rho[newest] * yy, 1.0), 1.0)

    def oldest_first(j, r):
        k = m - 1 - j
        i = (state.head - 1 - k) % m
        use = k < state.count
        b = state.rho[i] * jnp.vdot(state.Y[i], r)
        return r + jnp.where(use, alphas[k] - b, 0.0) * state.S[i]

    return -jax.lax.fori_loop(0, m, oldest_first, gamma * q)


def _direction_update(state, s, y):
    sy = jnp.vdot(s, y)
    ok = (sy > 1e-12 * jnp.linalg.norm(s) * jnp.linalg.norm(y)) & jnp.isfinite(sy)
    if isinstance(state, _Bfgs):
        H = state.H
        Hy = H @ y
        sy_safe = jnp.where(ok, sy, 1.0)
        H_new = H + ((sy + jnp.vdot(y, Hy)) / sy_safe**2) * jnp.outer(s, s) - (jnp.outer(Hy, s) + jnp.outer(s, Hy)) / sy_safe
        return _Bfgs(jnp.where(ok, 0.5 * (H_new + H_new.T), H))
    m = state.S.shape[0]
    new = _Lbfgs(
        state.S.at[state.head].set(s), state.Y.at[state.head].set(y),
        state.rho.at[state.head].set(1.0 / jnp.where(ok, sy, 1.0)),
        (state.head + 1) % m, jnp.minimum(state.count + 1, m),
    )
    return jax.tree.map(lambda a, b: jnp.where(ok, a, b), new, state)


def _direction_reset(state):
    if isinstance(state, _Bfgs):
        return _Bfgs(jnp.eye(state.H.shape[0], dtype=state.H.dtype))
    return state._replace(count=jnp.zeros_like(state.count), head=jnp.zeros_like(state.head))


# -- the driver -----------------------------------------------------------------------------------


class _Outer(NamedTuple):
    x: jax.Array  # the iterate
    f: jax.Array
    g: jax.Array
    x_best: jax.Array  # the best point evaluated so far
    f_best: jax.Array
    g_best: jax.Array
    direction: object
    step: jax.Array  # previously accepted step length a
    restart: jax.Array  # next direction is steepest descent
    iters: jax.Array
    evals: jax.Array
    consecutive: jax.Array
    failures: jax.Array
    values: jax.Array
    evaluations: jax.Array
    failed: jax.Array


def minimize(
    fun: Callable | None,
    x0,
    config: QuasiNewtonConfig = QuasiNewtonConfig(),
    *,
    value_and_grad: Callable | None = None,
):
    """Minimise a scalar function of a pytree from ``x0`` as minimize.m does; pure, jittable, vmappable.

    Args:
      fun: ``fun(params) -> scalar``; differentiated with ``jax.value_and_grad`` unless
        ``value_and_grad`` is given.
      x0: the start (any pytree of float arrays).
      config: static budgets and line-search constants.
      value_and_grad: optional ``params -> (value, grad pytree)``, e.g. a gradient estimator.

    Returns:
      ``(params, trace)``: the best point evaluated (never worse than ``x0``; ``x0`` itself if
      ``f(x0)`` or its gradient is not finite) and a :class:`QuasiNewtonTrace`.
    """
    flat0, unravel = ravel_pytree(x0)
    if not jnp.issubdtype(flat0.dtype, jnp.floating):
        raise ValueError(f"x0 must hold floating-point arrays, got {flat0.dtype}")
    if value_and_grad is None:
        if fun is None:
            raise ValueError("give fun or value_and_grad")
        value_and_grad = jax.value_and_grad(fun)

    def vg(flat):
        f, g = value_and_grad(unravel(flat))
        return jnp.asarray(f, flat0.dtype), ravel_pytree(g)[0].astype(flat0.dtype)

    n = flat0.size
    dense = config.method == "bfgs" or (config.method == "auto" and n <= config.dense_limit)
    length = int(config.length)
    budget_evals = length < 0
    n_trace = config.max_linesearches + 1
    dtype = flat0.dtype

    f0, g0 = vg(flat0)
    start_ok = _finite(f0, g0)

    def keep_going(s: _Outer):
        more = (s.iters < length) if not budget_evals else (s.evals < -length)
        return more & (s.consecutive < 2) & (jnp.max(jnp.abs(s.g)) > config.grad_tol) & start_ok

    def body(s: _Outer) -> _Outer:
        d = jnp.where(s.restart, -s.g, _direction(s.direction, s.g))
        d0 = jnp.vdot(s.g, d)
        not_descent = ~(d0 < 0.0)
        restart = s.restart | not_descent
        d = jnp.where(not_descent, -s.g, d)
        d0 = jnp.where(not_descent, -jnp.vdot(s.g, s.g), d0)
        d_norm = jnp.linalg.norm(d)
        a = jnp.where(restart, 1.0 / (1.0 - d0), s.step if dense else jnp.ones((), dtype))
        a = jnp.clip(a, config.min_first_step / d_norm, config.max_first_step / d_norm)
        max_evals = config.max_evals_per_linesearch
        if budget_evals:
            max_evals = jnp.minimum(max_evals, -length - s.evals)
        ls = _line_search(vg, s.x, d, s.f, s.g, d0, a, max_evals, config)

        moved = ls.success | (ls.f_best < s.f)
        a_new = jnp.where(ls.success, ls.a_acc, ls.a_best)
        f_new = jnp.where(ls.success, ls.f_acc, ls.f_best)
        g_new = jnp.where(ls.success, ls.g_acc, ls.g_best)
        x = jnp.where(moved, s.x + a_new * d, s.x)
        f = jnp.where(moved, f_new, s.f)
        g = jnp.where(moved, g_new, s.g)
        updated = _direction_update(s.direction, a_new * d, g_new - s.g)
        direction = jax.tree.map(
            lambda u, r: jnp.where(ls.success, u, r), updated, _direction_reset(s.direction)
        )
        improved = ls.f_best < s.f_best
        x_best = jnp.where(improved, s.x + ls.a_best * d, s.x_best)
        f_best = jnp.where(improved, ls.f_best, s.f_best)
        g_best = jnp.where(improved, ls.g_best, s.g_best)
        iters = s.iters + 1
        evals = s.evals + ls.k
        failed_now = ~ls.success
        return _Outer(
            x=x, f=f, g=g, x_best=x_best, f_best=f_best, g_best=g_best, direction=direction,
            step=jnp.where(ls.success, ls.a_acc, s.step),
            restart=failed_now,
            iters=iters, evals=evals,
            consecutive=jnp.where(failed_now, s.consecutive + 1, 0),
            failures=s.failures + failed_now,
            values=s.values.at[iters].set(f),
            evaluations=s.evaluations.at[iters].set(evals),
            failed=s.failed.at[iters].set(failed_now),
        )

    init = _Outer(
        x=flat0, f=f0, g=g0, x_best=flat0, f_best=f0, g_best=g0, direction=_direction_init(n, dense, config.memory, dtype),
        step=jnp.ones((), dtype), restart=jnp.asarray(True),
        iters=jnp.asarray(0), evals=jnp.asarray(1), consecutive=jnp.asarray(0), failures=jnp.asarray(0),
        values=jnp.full((n_trace,), jnp.nan, dtype).at[0].set(f0),
        evaluations=jnp.full((n_trace,), -1).at[0].set(1),
        failed=jnp.zeros((n_trace,), bool),
    )
    s = jax.lax.while_loop(keep_going, body, init)
    grad_norm = jnp.max(jnp.abs(s.g_best))
    reason = jnp.where(
        ~start_ok, STOP_NONFINITE_START,
        jnp.where(s.consecutive >= 2, STOP_FAILED,
                  jnp.where(jnp.max(jnp.abs(s.g)) <= config.grad_tol, STOP_GRADIENT, STOP_BUDGET)),
    )
    trace = QuasiNewtonTrace(
        values=s.values, evaluations=s.evaluations, failed=s.failed, value_init=f0, value=s.f_best,
        grad_norm=grad_norm, num_linesearches=s.iters, num_evaluations=s.evals,
        num_failures=s.failures, stop_reason=reason,
    )
    return unravel(s.x_best), trace


__all__ = [
    "QuasiNewtonConfig", "QuasiNewtonTrace", "STOP_BUDGET", "STOP_FAILED", "STOP_GRADIENT",
    "STOP_NONFINITE_START", "minimize",
]
