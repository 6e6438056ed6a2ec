"""The quasi-Newton minimiser (minimize.m semantics): convergence, exact budgets, NaN/Inf and failed line searches.

Evaluations are counted independently of the optimiser's own bookkeeping with a host callback
inside the objective, and every evaluated point is logged, so "the best point" and "the budget"
are checked against what actually happened.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pipps.optimizers import (
    STOP_BUDGET,
    STOP_FAILED,
    STOP_GRADIENT,
    STOP_NONFINITE_START,
    QuasiNewtonConfig,
    minimize,
)


def rosenbrock(x):
    return jnp.sum(100.0 * (x[1:] - x[:-1] ** 2) ** 2 + (1.0 - x[:-1]) ** 2)


def rosen_start(n):
    return jnp.full((n,), -1.2).at[1::2].set(1.0)


class Logger:
    """Wraps an objective so that every evaluation (point, value) is recorded on the host."""

    def __init__(self, fun):
        self.fun = fun
        self.points, self.values = [], []

    def _record(self, x, f):
        self.points.append(np.asarray(x).copy())
        self.values.append(float(f))

    def __call__(self, x):
        f = self.fun(x)
        jax.debug.callback(self._record, x, f)
        return f


def run(fun, x0, **cfg):
    config = QuasiNewtonConfig(**cfg)
    return jax.jit(lambda x: minimize(fun, x, config))(x0)


@pytest.mark.parametrize("method", ["bfgs", "lbfgs"])
def test_minimises_an_ill_conditioned_quadratic(method):
    rng = np.random.default_rng(0)
    Q, _ = np.linalg.qr(rng.normal(size=(8, 8)))
    A = jnp.asarray(Q @ np.diag(np.logspace(0, 3, 8)) @ Q.T)
    x_star = jnp.asarray(rng.normal(size=8))

    def f(x):
        d = x - x_star
        return 0.5 * d @ A @ d

    x, tr = run(f, jnp.zeros(8), length=200, method=method, grad_tol=1e-10)
    np.testing.assert_allclose(np.asarray(x), np.asarray(x_star), rtol=0, atol=1e-8)
    assert int(tr.stop_reason) in (STOP_GRADIENT, STOP_FAILED)
    assert float(tr.value) < 1e-14


@pytest.mark.parametrize("method, n", [("bfgs", 2), ("bfgs", 10), ("lbfgs", 2), ("lbfgs", 6)])
def test_minimises_rosenbrock(method, n):
    x0 = rosen_start(2) if n == 2 else jnp.zeros(n)  # (for n ≥ 4 there is a local minimum near x₁ = −1)
    x, tr = run(rosenbrock, x0, length=400, max_evals_per_linesearch=20, method=method)
    np.testing.assert_allclose(np.asarray(x), np.ones(n), rtol=0, atol=1e-6)
    vals = np.asarray(tr.values)[: int(tr.num_linesearches) + 1]
    assert np.all(np.diff(vals) <= 0)  # the iterates never get worse


def test_line_search_budget_is_exact():
    fun = Logger(rosenbrock)
    x, tr = run(fun, rosen_start(2), length=5, max_evals_per_linesearch=30)
    assert int(tr.num_linesearches) == 5
    assert int(tr.num_evaluations) == len(fun.values)  # the optimiser's count is honest
    vals = np.asarray(tr.values)
    assert vals.shape == (6,) and np.all(np.isfinite(vals))
    evals = np.asarray(tr.evaluations)
    assert evals[0] == 1 and evals[-1] == len(fun.values)
    assert np.all(np.diff(evals) >= 1) and np.all(np.diff(evals) <= 30)
    assert int(tr.stop_reason) == STOP_BUDGET


@pytest.mark.parametrize("budget", [1, 7, 40])
def test_evaluation_budget_is_exact(budget):
    fun = Logger(rosenbrock)
    x, tr = run(fun, rosen_start(2), length=-budget, max_evals_per_linesearch=6)
    assert len(fun.values) == budget == int(tr.num_evaluations)
    k = int(tr.num_linesearches)
    evals = np.asarray(tr.evaluations)[: k + 1]
    assert evals[-1] == budget and np.all(np.diff(evals) <= 6)
    if budget == 1:
        assert k == 0 and np.array_equal(np.asarray(x), np.asarray(rosen_start(2)))


def test_evaluations_per_line_search_are_capped():
    """With MFEPLS = 1 on Rosenbrock no line search may use a second evaluation."""
    fun = Logger(rosenbrock)
    _, tr = run(fun, rosen_start(2), length=30, max_evals_per_linesearch=1)
    k = int(tr.num_linesearches)
    assert np.all(np.diff(np.asarray(tr.evaluations)[: k + 1]) == 1)
    assert len(fun.values) == 1 + k


def test_returns_the_best_point_evaluated():
    fun = Logger(rosenbrock)
    x, tr = run(fun, rosen_start(2), length=12, max_evals_per_linesearch=8)
    best = int(np.argmin(fun.values))
    assert float(tr.value) == fun.values[best]
    np.testing.assert_array_equal(np.asarray(x), fun.points[best])


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_recovers_from_a_nonfinite_region_on_the_way(bad):
    """f = Σ log cosh(x − 1), NaN/Inf where x₀ > 1.5: an extrapolating trial lands there and is
    bisected back; the minimiser (x = 1, inside the good region) is reached all the same."""
    def f(x):
        return jnp.where(x[0] > 1.5, bad, jnp.sum(jnp.log(jnp.cosh(x - 1.0))))

    fun = Logger(f)
    x, tr = run(fun, jnp.array([-8.0, -3.0, 0.0]), length=60, max_evals_per_linesearch=10, grad_tol=1e-10)
    assert any(not np.isfinite(v) for v in fun.values)  # the bad region was hit
    np.testing.assert_allclose(np.asarray(x), 1.0, atol=1e-6)
    assert float(tr.value) == min(v for v in fun.values if np.isfinite(v))


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_keeps_the_last_good_point_at_a_nonfinite_wall(bad):
    """f = ‖x − 1‖² but NaN/Inf where x₀ > 0.5 (the minimiser is beyond the wall): trials are
    bisected back, the result is the best finite point evaluated, never a non-finite one."""
    def f(x):
        return jnp.where(x[0] > 0.5, bad, jnp.sum((x - 1.0) ** 2))

    fun = Logger(f)
    x0 = jnp.array([-1.0, -1.0, 0.0])
    x, tr = run(fun, x0, length=40, max_evals_per_linesearch=10)
    assert any(not np.isfinite(v) for v in fun.values)
    assert np.all(np.isfinite(np.asarray(x))) and float(x[0]) <= 0.5
    assert float(tr.value) == pytest.approx(float(f(x)), rel=1e-15)
    assert float(tr.value) < 0.2 * float(f(x0))
    finite = [(v, p) for v, p in zip(fun.values, fun.points) if np.isfinite(v)]
    v_best, p_best = min(finite, key=lambda vp: vp[0])
    assert float(tr.value) == v_best
    np.testing.assert_array_equal(np.asarray(x), p_best)
    assert np.all(np.isfinite(np.asarray(tr.values)[: int(tr.num_linesearches) + 1]))


def test_nan_gradient_is_treated_like_a_nan_value():
    def f(x):
        return jnp.sum((x - 2.0) ** 2) + jnp.where(x[0] > 1.0, jnp.sqrt(-jnp.abs(x[0])), 0.0) * 0.0

    x, tr = run(f, jnp.array([0.0, 0.0]), length=30)
    assert np.all(np.isfinite(np.asarray(x))) and float(x[0]) <= 1.0 and np.isfinite(float(tr.value))


def test_two_failed_line_searches_stop_and_keep_the_start():
    """NaN everywhere except at the start: two consecutive failures, x0 returned unchanged."""
    x0 = jnp.array([0.3, -0.2])

    def f(x):
        return jnp.where(jnp.all(x == x0), jnp.sum(x**2), jnp.nan)

    fun = Logger(f)
    x, tr = run(fun, x0, length=50, max_evals_per_linesearch=5)
    np.testing.assert_array_equal(np.asarray(x), np.asarray(x0))
    assert int(tr.stop_reason) == STOP_FAILED
    assert int(tr.num_linesearches) == 2 and int(tr.num_failures) == 2
    assert list(np.asarray(tr.failed)[:3]) == [False, True, True]
    assert len(fun.values) == 1 + 2 * 5
    assert float(tr.value) == float(f(x0))


def test_nonfinite_start_returns_the_start():
    fun = Logger(lambda x: jnp.log(x[0]) + x[1])
    x, tr = run(fun, jnp.array([-1.0, 2.0]), length=10)
    np.testing.assert_array_equal(np.asarray(x), [-1.0, 2.0])
    assert int(tr.stop_reason) == STOP_NONFINITE_START and len(fun.values) == 1


def test_failing_line_search_moves_to_its_best_point():
    """f = −Σx (unbounded): the slope never shrinks, so no point passes the curvature test; the
    line search fails but must still move to its best (farthest) point, then restart."""
    fun = Logger(lambda x: -jnp.sum(x))
    x, tr = run(fun, jnp.zeros(3), length=1, max_evals_per_linesearch=6)
    assert int(tr.num_linesearches) == 1 and bool(tr.failed[1])
    assert float(tr.value) < float(tr.value_init)
    best = int(np.argmin(fun.values))
    np.testing.assert_array_equal(np.asarray(x), fun.points[best])
    # extrapolation grew the step: each trial between 1.1× and 5× the previous one
    steps = np.array([p[0] for p in fun.points[1:]])
    assert np.all(steps[1:] / steps[:-1] >= 1.1 - 1e-12) and np.all(steps[1:] / steps[:-1] <= 5 + 1e-12)


def test_first_trial_step_is_clipped_to_one_unit():
    fun = Logger(lambda x: 1e6 * jnp.sum((x - 100.0) ** 2) * 1e-6)
    run(fun, jnp.zeros(4), length=1, max_evals_per_linesearch=3)
    assert np.linalg.norm(fun.points[1] - fun.points[0]) <= 1.0 + 1e-12


def test_vmap_over_starts_equals_individual_runs():
    config = QuasiNewtonConfig(length=30, max_evals_per_linesearch=10)
    starts = jnp.array([[-1.2, 1.0], [0.5, 0.5], [2.0, -1.0]])
    xs, trs = jax.jit(jax.vmap(lambda x0: minimize(rosenbrock, x0, config)))(starts)
    single = jax.jit(lambda x0: minimize(rosenbrock, x0, config))
    for i in range(3):
        x, tr = single(starts[i])
        np.testing.assert_allclose(np.asarray(xs[i]), np.asarray(x), rtol=1e-12, atol=1e-14)
        assert int(trs.num_evaluations[i]) == int(tr.num_evaluations)


def test_pytree_parameters_and_custom_value_and_grad():
    target = {"W": jnp.arange(6.0).reshape(2, 3), "b": jnp.array([1.0, -1.0])}

    def f(p):
        return sum(jnp.sum((p[k] - target[k]) ** 2) for k in p)

    x0 = jax.tree.map(jnp.zeros_like, target)
    config = QuasiNewtonConfig(length=50, grad_tol=1e-12)
    x, _ = jax.jit(lambda p: minimize(f, p, config))(x0)
    for k in target:
        np.testing.assert_allclose(np.asarray(x[k]), np.asarray(target[k]), atol=1e-8)
    calls = []

    def vg(p):
        calls.append(1)  # traced once per call site (start, line search), not per evaluation
        return jax.value_and_grad(f)(p)

    x2, _ = jax.jit(lambda p: minimize(None, p, config, value_and_grad=vg))(x0)
    for k in target:
        np.testing.assert_allclose(np.asarray(x2[k]), np.asarray(target[k]), atol=1e-8)
    assert len(calls) == 2


def test_compiles_once():
    traces = []

    def f(x):
        traces.append(1)
        return rosenbrock(x)

    config = QuasiNewtonConfig(length=10)
    opt = jax.jit(lambda x0: minimize(f, x0, config))
    opt(jnp.array([-1.2, 1.0]))
    n = len(traces)
    opt(jnp.array([0.0, 0.0]))
    assert len(traces) == n


def test_config_validation():
    with pytest.raises(ValueError):
        QuasiNewtonConfig(length=0)
    with pytest.raises(ValueError):
        QuasiNewtonConfig(method="cg")
    with pytest.raises(ValueError):
        QuasiNewtonConfig(sigma=0.5, rho=0.6)
    with pytest.raises(ValueError):
        QuasiNewtonConfig(max_evals_per_linesearch=0)
    assert QuasiNewtonConfig(length=-150).max_linesearches == 149
