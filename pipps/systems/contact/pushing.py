"""One-dimensional pushing through contact, three ways (Suh et al., "Pathologies", Examples III.7, IV.1, IV.2;
Figs. 5 and 6).

A pusher (mass ``m1``, position ``x1``, velocity ``v1``) driven by a force ``u`` pushes a box (``m2``,
``x2``, ``v2``) that lies ahead of it; the gap is ``g = x2 − x1`` (the two are points). The state is
``[t, x1, v1, x2, v2]`` (the step index first, for an open-loop input trajectory), the time step
``h``, the running cost ``c = (x2 − x_goal)²`` on every state after the first. The contact model:

* ``"penalty"`` (Example III.7): a spring of stiffness ``k`` and damping ``c`` acts while the two
  overlap, ``f = max(0, k·max(0, −g) + c·(v1 − v2))·1[g < 0]``, integrated semi-implicitly
  (``v ← v + h a``, then ``x ← x + h v``). Stiff contact needs large ``k``; in contact the step is
  stable while ``h² k / m_r < 4 − 2hc/m_r`` (``m_r = m1 m2/(m1 + m2)``; k < 1.98·10⁴ at the defaults)
  and amplifies each contact oscillation beyond.
* ``"implicit"`` (Example IV.1, two bodies): the time-stepping QP
  ``min ½ m1 (v1⁺ − v1)² + ½ m2 (v2⁺ − v2)² − h u v1⁺`` s.t. ``g/h + v2⁺ − v1⁺ ≥ 0``, whose
  solution is closed form: with the free velocities ``v1' = v1 + h u/m1``, ``v2' = v2`` and
  ``s' = g/h + v2' − v1'``, the contact impulse is ``λ = max(0, −s')/μ``, ``μ = 1/m1 + 1/m2``, and
  ``v1⁺ = v1' − λ/m1``, ``v2⁺ = v2' + λ/m2``; then ``x ← x + h v⁺``. No stiffness, no penetration.
* ``"barrier"`` (Example IV.2, two bodies): the constraint replaced by the log-barrier
  ``−(1/κ) log(g/h + v2⁺ − v1⁺)``; the optimality condition ``s = s' + μ/(κ s)`` gives
  ``s = (s' + √(s'² + 4μ/κ))/2`` and ``λ = (s − s')/μ``: a force field that pushes before contact,
  with weight κ (κ → ∞: the QP).

For Fig. 6, :func:`wall_step` is the single point mass against a wall occupying ``x ≤ 0`` (Example IV.1,
eq. 2–3; IV.2, eq. 4–5; the penalty spring beside them): ``x⁺`` as a function of the impulse ``u``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax.tree_util import register_dataclass

from pipps.policies import OpenLoopPolicy
from pipps.systems.contact.base import ContactExample
from pipps.tasks.base import Problem

MODELS = ("penalty", "implicit", "barrier")


def _static(default):
    return dataclasses.field(default=default, metadata=dict(static=True))


@register_dataclass
@dataclasses.dataclass(frozen=True)
class Pushing:
    """The pusher and the box (module doc); ``stiffness``, ``damping`` and ``kappa`` are traced."""

    stiffness: jax.Array = 100.0  # k, penalty
    damping: jax.Array = 1.0  # c, penalty
    kappa: jax.Array = 100.0  # κ, barrier
    model: str = _static("penalty")
    m1: float = _static(1.0)
    m2: float = _static(1.0)
    h: float = _static(0.01)

    def __post_init__(self):
        if self.model not in MODELS:
            raise ValueError(f"contact model must be one of {MODELS}, got {self.model!r}")

    def step(self, x, u):
        t, x1, v1, x2, v2 = x
        force = u[0]
        if self.model == "penalty":
            gap = x2 - x1
            f = jnp.where(gap < 0.0, jnp.maximum(0.0, -self.stiffness * gap + self.damping * (v1 - v2)), 0.0)
            v1n = v1 + self.h * (force - f) / self.m1
            v2n = v2 + self.h * f / self.m2
        else:
            mu = 1.0 / self.m1 + 1.0 / self.m2
            v1f = v1 + self.h * force / self.m1
            s_free = (x2 - x1) / self.h + v2 - v1f
            if self.model == "implicit":
                lam = jnp.maximum(0.0, -s_free) / mu
            else:
                s = 0.5 * (s_free + jnp.sqrt(s_free**2 + 4.0 * mu / self.kappa))
                lam = (s - s_free) / mu
            v1n, v2n = v1f - lam / self.m1, v2 + lam / self.m2
        return jnp.stack([t + 1.0, x1 + self.h * v1n, v1n, x2 + self.h * v2n, v2n])

    @property
    def stable_stiffness(self) -> float:
        """The penalty spring's largest stiffness the semi-implicit step keeps stable in contact,
        ``(4 − 2hc/m_r) m_r / h²`` (the damped oscillator's semi-implicit Euler map has its eigenvalues
        inside the unit circle below it; ``4 m_r/h²`` without damping). Needs a float damping."""
        m_r = self.m1 * self.m2 / (self.m1 + self.m2)
        return (4.0 - 2.0 * self.h * float(self.damping) / m_r) * m_r / self.h**2


@dataclasses.dataclass(frozen=True)
class _GoalCost:
    goal: float

    def __call__(self, x):
        return (x[3] - self.goal) ** 2


def pushing(model: str = "penalty", stiffness: float = 100.0, kappa: float = 100.0, *, horizon: int = 40,
            gap: float = 0.05, goal: float = 0.3, force: float = 2.0, sigma: float = 0.1, damping: float = 1.0,
            h: float = 0.01) -> ContactExample:
    """Fig. 5's problem: the gradient of ``V_1`` with respect to the input trajectory ``u_{1:H}``
    (an open-loop policy, every force ``force`` to begin with), noise ``σ`` on each input."""
    problem = Problem(name=f"pushing_{model}", dt=h, horizon=horizon, u_max=np.ones(1),
                      model_init_mean=np.array([0.0, 0.0, 0.0, gap, 0.0]), model_init_cov=np.zeros((5, 5)),
                      cost=_GoalCost(goal), policy_input_idx=(0,))
    sim = Pushing(jnp.asarray(float(stiffness)), jnp.asarray(float(damping)), jnp.asarray(float(kappa)), model, h=h)
    policy = OpenLoopPolicy(jnp.full((horizon, 1), float(force)))
    label = {"penalty": f"k = {stiffness:g}", "implicit": "implicit", "barrier": f"kappa = {kappa:g}"}[model]
    return ContactExample(f"pushing_{model}", f"Example III.7 / IV.1 / IV.2, Fig. 5 (pushing, {model}, {label})",
                          problem, sim, policy, sigma)


def wall_step(model: str, u, *, x: float = 0.0, v: float = 0.0, m: float = 1.0, h: float = 0.1,
              kappa: float = 100.0, stiffness: float = 100.0):
    """``x⁺`` of a point mass at ``(x, v)`` after the impulse ``u``, against a wall at ``x ≤ 0`` (Fig. 6):
    "implicit" (eq. 2–3: ``v⁺ = max(v + u/m, −x/h)``), "barrier" (eq. 5: ``x⁺ = h s``,
    ``s = (b + √(b² + 4m/κ))/(2m)``, ``b = m(x/h + v) + u``) or "penalty" (semi-implicit, the spring
    ``k·max(0, −x)``, which lets the mass into the wall)."""
    u = jnp.asarray(u, float)
    if model == "implicit":
        return x + h * jnp.maximum(v + u / m, -x / h)
    if model == "barrier":
        b = m * (x / h + v) + u
        return h * (b + jnp.sqrt(b**2 + 4.0 * m / kappa)) / (2.0 * m)
    if model == "penalty":
        return x + h * (v + (u + h * stiffness * max(0.0, -x)) / m)
    raise ValueError(f"contact model must be one of {MODELS}, got {model!r}")
