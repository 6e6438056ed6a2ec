"""The three problems of Suh et al.'s Fig. 1 ("Pathologies", Fig. 1): a drop, a throw, a collision.

The source draws them, and their smoothed objectives, without equations; these are this library's
readings, each a one-step problem ``f(θ + w)`` (:func:`pipps.systems.contact.base.one_step_problem`)
whose physics is written in closed form (free flight, then the contact rule at the event), so the
exact smoothed objective and gradient follow by quadrature split at the discontinuity
(:func:`~pipps.systems.contact.base.smoothed`). ``g = 9.81 m/s²``. Each cost is minus the quantity the
source maximises.

* **Drop** (A, "maximise the ball's height after dropping"): a ball launched horizontally at speed θ
  from height ``h0 = 1`` above a table of height ``h1 = 0.5`` and half-width ``L = 1`` centred under
  the launch point lands at ``x = θ √(2 (h0 − h1)/g)``; it stays on the table (an inelastic landing)
  if ``|x| ≤ L``, else falls to the floor: ``y = h1·1[|x| ≤ L]``. Piecewise constant: every
  first-order sample is 0.
* **Throw** (B, "maximise the distance thrown, with a wall that results in an inelastic impact"): a
  ball thrown from the ground at angle θ (radians) and speed ``v0 = 5`` lands at
  ``R(θ) = v0² sin 2θ / g``; a wall of height ``hw = 0.5`` at ``d = 1.5`` stops it dead if the ball
  reaches the wall's plane below its top (``R > d`` and ``y(d) < hw``), and it drops at ``d``.
  Distance ``R`` or ``d``. The window of clear throws, ``39.7° ≤ θ ≤ 68.7°``, holds the optimum 45°;
  below it the distance is constant (the FoBG is 0) and jumps by ``R(39.7°) − d = 1.0`` at its edge.
* **Pivot** (C, "maximise the angular momentum transferred to a pivoting bar through a collision"): a
  ball of mass ``m = 1`` moving horizontally at ``v = 1`` at height θ above the pivot of a bar of length
  ``L = 1`` and inertia ``I = 2`` about the pivot sticks to it (perfectly inelastic); the bar's angular
  momentum is ``I m v θ / (I + m θ²)`` for ``0 ≤ θ ≤ L`` and 0 if the ball misses. It increases up to
  the bar's tip and drops to 0 past it: the optimum of ``f`` sits on its discontinuity, and the
  first-order gradient points over the edge, while the smoothed optimum lies below it.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
from jax.tree_util import register_dataclass

from pipps.systems.contact.base import ContactExample, as_policy, one_step_problem, scalar_of, smoothed

G = 9.81


@register_dataclass
@dataclasses.dataclass(frozen=True)
class Drop:
    """``step(x, u) = [−y(u)]`` (module doc, A)."""

    h0: float = dataclasses.field(default=1.0, metadata=dict(static=True))
    h1: float = dataclasses.field(default=0.5, metadata=dict(static=True))
    half_width: float = dataclasses.field(default=1.0, metadata=dict(static=True))

    @property
    def flight(self) -> float:
        return math.sqrt(2.0 * (self.h0 - self.h1) / G)

    def value(self, v):
        return jnp.where(jnp.abs(v * self.flight) <= self.half_width, self.h1, 0.0)

    def step(self, x, u):
        del x
        return -self.value(u)

    @property
    def breaks(self):
        return (-self.half_width / self.flight, self.half_width / self.flight)


@register_dataclass
@dataclasses.dataclass(frozen=True)
class Throw:
    """``step(x, u) = [−distance(u)]`` (module doc, B)."""

    v0: float = dataclasses.field(default=5.0, metadata=dict(static=True))
    wall_x: float = dataclasses.field(default=1.5, metadata=dict(static=True))
    wall_height: float = dataclasses.field(default=0.5, metadata=dict(static=True))

    def value(self, theta):
        R = self.v0**2 * jnp.sin(2.0 * theta) / G
        y_wall = self.wall_x * jnp.tan(theta) - G * self.wall_x**2 / (2.0 * self.v0**2 * jnp.cos(theta) ** 2)
        blocked = (R > self.wall_x) & (y_wall < self.wall_height)
        return jnp.where(blocked, self.wall_x, R)

    def step(self, x, u):
        del x
        return -self.value(u)

    @property
    def breaks(self):
        """The angles where the ball's height at the wall equals the wall's (the window's edges), and
        where the range equals the wall's distance."""
        a = G * self.wall_x**2 / (2.0 * self.v0**2)
        disc = self.wall_x**2 - 4.0 * a * (a + self.wall_height)
        clear = [math.atan((self.wall_x + s * math.sqrt(disc)) / (2.0 * a)) for s in (-1.0, 1.0)] if disc > 0 else []
        reach = 0.5 * math.asin(min(1.0, self.wall_x * G / self.v0**2))
        return tuple(sorted(clear + [reach, 0.5 * math.pi - reach]))


@register_dataclass
@dataclasses.dataclass(frozen=True)
class Pivot:
    """``step(x, u) = [−I m v u / (I + m u²)]`` on the bar, 0 off it (module doc, C)."""

    mass: float = dataclasses.field(default=1.0, metadata=dict(static=True))
    speed: float = dataclasses.field(default=1.0, metadata=dict(static=True))
    length: float = dataclasses.field(default=1.0, metadata=dict(static=True))
    inertia: float = dataclasses.field(default=2.0, metadata=dict(static=True))

    def value(self, r):
        on_bar = (r >= 0.0) & (r <= self.length)
        return jnp.where(on_bar, self.inertia * self.mass * self.speed * r / (self.inertia + self.mass * r**2), 0.0)

    def step(self, x, u):
        del x
        return -self.value(u)

    @property
    def breaks(self):
        return (0.0, self.length)


def _example(name, title, sim, theta, sigma) -> ContactExample:
    def f(v):  # the cost of one action, in numpy (float64 through jnp, on the host)
        return float(np.asarray(sim.step(None, jnp.asarray([v])))[0])

    def exact(policy):
        F, dF, err = smoothed(f, scalar_of(policy), sigma, sim.breaks)
        return F, np.array([dF]), err

    return ContactExample(name, title, one_step_problem(name), sim, as_policy(theta), sigma, exact)


def drop(theta: float = 2.5, sigma: float = 1.0) -> ContactExample:
    return _example("drop", "Fig. 1A (drop: the ball's height after landing)", Drop(), theta, sigma)


def throw(theta: float = math.radians(35.0), sigma: float = math.radians(6.0)) -> ContactExample:
    return _example("throw", "Fig. 1B (throw with an inelastic wall)", Throw(), theta, sigma)


def pivot(theta: float = 0.8, sigma: float = 0.1) -> ContactExample:
    return _example("pivot", "Fig. 1C (angular momentum transferred to a pivoting bar)", Pivot(), theta, sigma)
