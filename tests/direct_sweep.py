"""Pieces of the backward pass written as plain loops with NumPy, the references the sweep is checked
against (thesis Alg. 3 and 5, eq. 4.2): the particle forward pass, the BIW weights and the LR ζ-gradient.

For models whose output noise does not depend on the input (the kicked rotor, the linear-Gaussian
systems, ``model_variance=False``): ``ζ_{t+1} = (x_t + μ(z_t), s)`` with ``s = sqrt(noise variance)``.
Used by tests/test_estimators_variance.py, tests/test_k_lr_rules.py and tests/test_action_nodes.py.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree


class Forward(NamedTuple):
    theta: np.ndarray  # the policy's flat parameters
    unravel: object  # flat parameters → policy
    xs: list  # x_0 … x_T, each (P, D)
    zetas: list  # ζ_1 … ζ_T, each (P, 2D): the next state's mean and standard deviation
    zeta_of: object  # (x, u) → ζ of the next state
    u_of: object  # (x, θ) → u


def forward(task, model, policy, noise) -> Forward:
    """The particle rollout of ``noise`` as a loop over t and i."""
    theta0, unravel = ravel_pytree(policy)
    s = np.sqrt(np.asarray(model.noise_variance))
    D = task.model_dim

    def u_of(x, th):
        return unravel(th)(task.policy_input(x))

    def zeta_of(x, u):
        m, _ = model.predict(task.gp_input(x, u)[None])
        return jnp.concatenate([x + m[0], jnp.asarray(s)])

    step = jax.jit(lambda x: zeta_of(x, u_of(x, theta0)))
    P, T = noise.x0.shape[0], noise.eps.shape[0]
    xs, zetas = [np.asarray(noise.x0)], []
    for t in range(T):
        z = np.stack([np.asarray(step(xs[-1][i])) for i in range(P)])
        zetas.append(z)
        xs.append(z[:, :D] + z[:, D:] * np.asarray(noise.eps[t]))
    return Forward(theta0, unravel, xs, zetas, zeta_of, u_of)


def biw_weights(x: np.ndarray, mu: np.ndarray, sd: np.ndarray) -> np.ndarray:
    """w[i, j] = p(x_j | ζ_i) / Σ_k p(x_j | ζ_k) (eq. 4.2), from raw log-densities."""
    P = x.shape[0]
    logp = np.array([[np.sum(-0.5 * ((x[j] - mu[i]) / sd[i]) ** 2 - np.log(sd[i])) for j in range(P)] for i in range(P)])
    return np.exp(logp - logp.max(0)) / np.exp(logp - logp.max(0)).sum(0)


def lr_zeta(i: int, w: np.ndarray, G: np.ndarray, baseline, x: np.ndarray, mu: np.ndarray, sd: np.ndarray) -> np.ndarray:
    """Component i's LR ζ-gradient Σ_j w_ij (G_j − b) ∇_ζ log p(x_j | ζ_i), as (∂μ, ∂s)."""
    return sum(
        w[i, j] * (G[j] - baseline)
        * np.concatenate([(x[j] - mu[i]) / sd[i] ** 2, ((x[j] - mu[i]) ** 2 - sd[i] ** 2) / sd[i] ** 3])
        for j in range(x.shape[0])
    )


def through_policy(task, f: Forward):
    """Jitted ``∂ζ_{t+1}/∂x_t`` and ``∂ζ_{t+1}/∂θ`` with the action's path through the policy, and ``∇c``."""
    zeta_next = lambda x, th: f.zeta_of(x, f.u_of(x, th))  # noqa: E731
    return jax.jit(jax.jacobian(zeta_next)), jax.jit(jax.jacobian(zeta_next, argnums=1)), jax.jit(jax.grad(task.cost))


def backward_steps(task, f: Forward):
    """``(t, x_t, μ_t, s_t, G_t)`` for t = T … 1, with the returns-to-go ``G_t = Σ_{τ ≥ t} c(x_τ)``."""
    D = task.model_dim
    G = np.zeros(f.xs[0].shape[0])
    for t in range(len(f.zetas), 0, -1):  # x_t = xs[t], ζ_t = zetas[t − 1]
        x = f.xs[t]
        G = G + np.asarray(jax.vmap(task.cost)(x))
        yield t, x, f.zetas[t - 1][:, :D], f.zetas[t - 1][:, D:], G
