"""What each particle contributes at a step: its cost for the returns and its cost gradient.

The reverse sweep asks its estimator's cost terms, at step t, for ``c_i`` (added to the returns
``G``) and ``∂c_i/∂x_i`` (started down the pathwise chain): a :class:`StepCosts`. Three kinds,
built by :func:`plain_costs`, :func:`shaped_costs` and :func:`density_estimation_costs`:

* the plain cost: ``c(x_i)`` and ``∇c(x_i)``;
* Gaussian shaping (thesis §3.3.2, Alg. 6): with the particle fit ``μ̂ = mean_i x_i``,
  ``Σ̂ = E[x xᵀ] − μ̂ μ̂ᵀ`` (1/P) and ``Ē = E_{N(μ̂, Σ̂)}[c]`` in closed form, the LR cost
  ``g_i = ∂Ē/∂μ̂ · m_i + ⟨∂Ē/∂Σ̂, v_i − 2 m_i μ̂ᵀ⟩`` (``m_i = x_i − μ̂``, ``v_i = x_i x_iᵀ − E[x xᵀ]``)
  and the RP cost gradient ``P·dĒ/dx_i = ∂Ē/∂μ̂ + 2 Sym(∂Ē/∂Σ̂) m_i``;
* DEL down the whole pathwise chain (the thesis preset's reading of §3.3.1, :func:`thesis_estimator`
  ``("del")``): with ``q = N(μ̂, Σ̂)`` (unbiased covariance) fitted pathwise,
  ``S = (1/P) Σ_j (G_j − b) log q(x_j)`` with the samples ``x_j`` held fixed, the cost
  gradient is ``P·∂S/∂x_i`` through the fit only, carried to θ through every earlier step. As the
  returns ``G`` already hold the later costs, a cost at step s is counted once for every step
  t ≤ s whose fit it moves (docs/estimator-bias.md). Weighted by each step's own cost ``c_j``
  instead of ``G_j`` (``weights="cost"``), each cost is counted once. The library's DEL takes the
  ``G``-weighted ``P·∂S/∂x_i`` one step to θ instead (:func:`pipps.propagation.parts.density_lr`).

Per-particle returns are summed without the 1/P; the sweep divides at the end, so that a
particle's gradient is ``∂G_i/∂θ`` and the estimate is their mean.

Each is a :class:`~pipps.propagation.pieces.CostTerms`. DEL with the "previous" baseline keeps the
previous iteration's mean return per step as its state (:class:`~pipps.propagation.pieces.PreviousBaseline`);
the others have none.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from pipps.propagation.pieces import MeanReturn, PreviousBaseline, Stateless, StepCosts
from pipps.propagation.strategy import strategy

DEL_BASELINES = ("previous", "none")
#: what weighs each particle's fitted score in the whole-chain DEL: its return-to-go ``G_{i,t}`` (the
#: thesis preset) or the step's own cost ``c_{i,t}``
DEL_WEIGHTS = ("returns", "cost")


def plain_terms(cost, x: jax.Array, c: jax.Array, *, gradient: bool):
    """(c_i, ∇c(x_i) or None, the step's objective mean_i c_i)."""
    dc = jax.vmap(jax.grad(cost))(x) if gradient else None
    return c, dc, jnp.mean(c)


def particle_fit(x: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(μ̂, Σ̂, E[x xᵀ]) with Σ̂ = E[x xᵀ] − μ̂ μ̂ᵀ, all 1/P (as thesis Alg. 6 fits them)."""
    P = x.shape[0]
    mu = jnp.mean(x, axis=0)
    second = x.T @ x / P
    return mu, second - jnp.outer(mu, mu), second


def shaping_terms(cost, x: jax.Array, *, lr_costs: bool, gradient: bool):
    """Gaussian shaping: (g_i or None, P·dĒ/dx_i or None, Ē)."""
    mu, cov, second = particle_fit(x)
    expected = lambda m, S: cost.expected(m, S)[0]  # noqa: E731
    value, (g_mu, g_cov) = jax.value_and_grad(expected, argnums=(0, 1))(mu, cov)
    g_sym = 0.5 * (g_cov + g_cov.T)
    m = x - mu
    c = dc = None
    if lr_costs:
        quad = jnp.einsum("pd,de,pe->p", x, g_sym, x) - jnp.sum(g_sym * second)
        c = m @ g_mu + quad - 2.0 * (m @ g_sym) @ mu
    if gradient:
        dc = g_mu[None, :] + 2.0 * m @ g_sym
    return c, dc, value


def gaussian_logpdf(x: jax.Array, mean: jax.Array, cov: jax.Array) -> jax.Array:
    """log N(x_j | mean, cov) for rows x (P, D), by a Cholesky factor."""
    chol = jnp.linalg.cholesky(cov)
    sol = jax.scipy.linalg.solve_triangular(chol, (x - mean).T, lower=True)
    D = x.shape[-1]
    return -0.5 * jnp.sum(sol**2, axis=0) - jnp.sum(jnp.log(jnp.diag(chol))) - 0.5 * D * jnp.log(2 * jnp.pi)


def del_gradient(x: jax.Array, returns: jax.Array, baseline: jax.Array, jitter: float = 1e-12) -> jax.Array:
    """DEL's ``P·∂S/∂x_i`` (the module docstring): the fitted density's score at the fixed samples,
    differentiated through the fit ``μ̂, Σ̂`` with respect to each particle.

    Raises:
      ValueError: ``P ≤ D``: the unbiased covariance of P particles has rank at most P − 1, so the
        fitted density of D-dimensional particles is degenerate and its score undefined (float64's
        jitter hides it as a meaningless finite number, float32's Cholesky returns NaN).
    """
    P, D = x.shape
    if P <= D:
        raise ValueError(f"DEL fits a Gaussian to the particles and needs more particles than state dimensions: "
                         f"got P = {P} particles of dimension D = {D} (need P > D)")
    advantage = jax.lax.stop_gradient(returns - baseline)
    samples = jax.lax.stop_gradient(x)

    def surrogate(xfit):
        mu = jnp.mean(xfit, axis=0)
        centred = xfit - mu
        cov = centred.T @ centred / (P - 1) + jitter * jnp.eye(D)
        return jnp.mean(advantage * gaussian_logpdf(samples, mu, cov))

    return P * jax.grad(surrogate)(x)


@strategy
class PlainCosts(Stateless):
    """The particles' own costs ``c(x_i)`` and ``∇c(x_i)`` (RP, LR and TP)."""

    feeds_likelihood_ratio = True

    def returns(self, cost, x, c):
        del cost, x
        return c

    def step(self, state, cost, x, c, returns_next, *, gradient: bool) -> tuple[tuple, StepCosts]:
        del returns_next
        return state, StepCosts(*plain_terms(cost, x, c, gradient=gradient))


@strategy
class ShapedCosts(Stateless):
    """Gaussian shaping (thesis Alg. 6): ``g_i`` for the returns, ``P·dĒ/dx_i`` for the pathwise chain."""

    feeds_likelihood_ratio = True

    def returns(self, cost, x, c):
        del c
        return shaping_terms(cost, x, lr_costs=True, gradient=False)[0]

    def step(self, state, cost, x, c, returns_next, *, gradient: bool) -> tuple[tuple, StepCosts]:
        del c, returns_next
        return state, StepCosts(*shaping_terms(cost, x, lr_costs=True, gradient=gradient))


@strategy
class DensityEstimationCosts(PreviousBaseline):
    """DEL down the whole pathwise chain: the particles' own costs for the returns and the
    surrogate's ``P·∂S/∂x_i`` instead of ``∇c(x_i)``.

    ``baseline``: ``b_t`` of the surrogate, "previous" (the previous iteration's mean weight, the
    state) or "none". ``weights``: what weighs particle i's fitted score at step t, its return-to-go
    ``G_{i,t}`` ("returns", the thesis preset's reading of §3.3.1: a cost at step s is then counted
    once for every step t ≤ s whose fit it moves) or the step's own cost ``c_{i,t}`` ("cost": the LR
    identity ``∇E[c_t] = E[c_t ∇_θ log p_t(x_t)]`` of each step's marginal, counting each cost once).
    """

    baseline: str = "previous"
    weights: str = "returns"

    feeds_likelihood_ratio = False
    fits_density = True  # a Gaussian fitted to the particles at every step

    def init(self, context) -> MeanReturn | tuple:
        state = super().init(context)
        if self.weights == "cost" and self.baseline == "previous":
            g = state.mean_return  # the mean return-to-go per step; a step's mean cost is its difference
            state = MeanReturn(g - jnp.concatenate([g[1:], jnp.zeros_like(g[:1])]))
        return state

    def returns(self, cost, x, c):
        del cost, x
        return c

    def step(self, state, cost, x, c, returns_next, *, gradient: bool) -> tuple[MeanReturn | tuple, StepCosts]:
        del cost
        weights = c if self.weights == "cost" else returns_next + c
        b, next_state = self.previous_baseline(state, weights)
        dc = del_gradient(x, weights, b) if gradient else None
        return next_state, StepCosts(c, dc, jnp.mean(c))


def plain_costs() -> PlainCosts:
    """Cost terms of RP, LR and TP: the particles' own costs."""
    return PlainCosts()


def shaped_costs() -> ShapedCosts:
    """Cost terms of GTP and GLR: the Gaussian-shaped costs (thesis §3.3.2)."""
    return ShapedCosts()


def density_estimation_costs(baseline: str = "previous", weights: str = "returns") -> DensityEstimationCosts:
    """Cost terms of the whole-chain DEL with the surrogate's baseline, "previous" or "none", and its
    weights, "returns" (returns-to-go: the thesis preset's DEL) or "cost" (each step's own cost)."""
    if baseline not in DEL_BASELINES:
        raise ValueError(f"DEL's baseline must be one of {DEL_BASELINES}, got {baseline!r}")
    if weights not in DEL_WEIGHTS:
        raise ValueError(f"DEL's weights must be one of {DEL_WEIGHTS}, got {weights!r}")
    return DensityEstimationCosts(baseline, weights)
