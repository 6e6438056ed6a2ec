"""What every contact example shares: the record of an example, one-step problems, and exact smoothing.

A :class:`ContactExample` is one of Suh et al.'s problems as this library runs it: the planning
:class:`~pipps.tasks.base.Problem` (state, actions, horizon, cost), the known simulator (an object
with ``step(x, u)``, :mod:`pipps.particles.simulator`), the decision variables (an
:class:`~pipps.policies.OpenLoopPolicy` or a feedback policy), the action noise ``σ`` that defines
the randomised-smoothing objective ``F(θ) = E_w f(θ + σ w)``, and — where it is known — the exact
``F`` and ``∇F``.

**One-step problems** ``f(θ + w)`` (the Heaviside, Fig. 1's three problems): the state is one
number, the step index 0 before the step and ``f(u)`` after it, and the cost is that number, so the
objective is ``E f(θ + σ w)`` and every estimator through the action node sees exactly Suh et al.'s
``f``: the FoBG is ``f'(θ + σ w)``, the ZoBG ``f(θ + σ w) w / σ`` (:func:`one_step_problem`).

**Exact smoothing** of a one-dimensional ``f`` with known discontinuities (:func:`smoothed`):
``F(θ) = ∫ f(θ + σ w) φ(w) dw`` and ``∇F(θ) = (1/σ) ∫ f(θ + σ w) w φ(w) dw`` by adaptive quadrature
(``scipy.integrate.quad``) split at every discontinuity, over ``|w| ≤ 12``; the quadrature's own
error estimate is returned with the values (below 10⁻⁷ of ∇F on every example here).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax.numpy as jnp
import numpy as np
from scipy import integrate, stats

from pipps.tasks.base import Problem


@dataclasses.dataclass(frozen=True, eq=False)
class ContactExample:
    """One example: its problem, simulator, starting decision, action noise and (where known) exact ∇F."""

    name: str
    title: str  # what the source calls it (figure or example number)
    problem: Problem
    simulator: Any  # has step(x, u) -> x'
    policy: Any  # the decision variables θ (a pytree)
    action_noise: float  # σ of the randomised smoothing u = π + σ w
    exact: Callable[[Any], tuple[float, np.ndarray, float]] | None = None  # policy -> (F, ∇F flat, error bound)


class _Cost:
    """c(x) = x[0]: the one-step state after the step is f(u) itself."""

    def __call__(self, x):
        return x[0]


def one_step_problem(name: str) -> Problem:
    """The :class:`Problem` of a one-step ``f(θ + w)`` (module doc): state 1, action 1, horizon 1."""
    return Problem(name=name, dt=1.0, horizon=1, u_max=np.ones(1), model_init_mean=np.zeros(1),
                   model_init_cov=np.zeros((1, 1)), cost=_Cost())


def smoothed(f: Callable[[float], float], theta: float, sigma: float, breaks=()) -> tuple[float, float, float]:
    """``(F(θ), ∇F(θ), error)`` of ``F(θ) = E f(θ + σ w)`` by quadrature split at the points ``breaks``
    (in θ + σw units) where ``f`` jumps or kinks; ``error`` is the larger of the two quadratures'
    absolute error estimates."""
    inner = sorted(w for w in ((b - theta) / sigma for b in breaks) if -12.0 < w < 12.0)
    points = [-12.0, *inner, 12.0]
    F = dF = err = 0.0
    for lo, hi in zip(points[:-1], points[1:]):
        v, e1 = integrate.quad(lambda w: f(theta + sigma * w) * stats.norm.pdf(w), lo, hi, epsabs=1e-13, limit=200)
        g, e2 = integrate.quad(lambda w: f(theta + sigma * w) * w * stats.norm.pdf(w), lo, hi, epsabs=1e-13, limit=200)
        F, dF, err = F + v, dF + g / sigma, max(err, e1, e2 / sigma)
    return F, dF, err


def scalar_of(policy) -> float:
    """θ of a one-step problem's policy (an OpenLoopPolicy of one step and one action)."""
    return float(np.asarray(policy.actions).reshape(-1)[0])


def as_policy(theta: float):
    from pipps.policies import OpenLoopPolicy

    return OpenLoopPolicy(jnp.full((1, 1), float(theta)))
