"""The thesis' RMSprop-like normalized step with momentum, as an optax transformation (thesis §4.5.1).

``m ← γ m + g / sqrt(g² + V[g])``, ``θ ← θ − α m``, elementwise, where ``V[g]`` is the
per-parameter variance of the mean gradient estimated from the batch (per-particle
contributions' variance divided by P). Each normalized term lies in [−1, 1], so a parameter moves
at most ``α/(1−γ)`` per iteration at steady state — a step that is large where the gradient is
clear of its noise and small where it is not. Thesis: ``α = 5·10⁻⁴``, ``γ = 0.9``.

``V[g]`` arrives as an extra argument of ``update`` (optax's ``GradientTransformationExtraArgs``)::

    opt = normalized_momentum()
    state = opt.init(params)
    updates, state = opt.update(grad, state, params, grad_variance=var)
    params = optax.apply_updates(params, updates)

Where ``g² + V = 0`` the term is 0 (no information, no step).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax


class NormalizedMomentumState(NamedTuple):
    momentum: Any  # same pytree as the parameters


def normalized_term(g: jax.Array, v: jax.Array) -> jax.Array:
    """g / sqrt(g² + V), 0 where g² + V = 0."""
    den = jnp.sqrt(g * g + v)
    return jnp.where(den > 0, g / jnp.where(den > 0, den, 1.0), 0.0)


def normalized_momentum(learning_rate: float = 5e-4, momentum: float = 0.9) -> optax.GradientTransformationExtraArgs:
    """The thesis optimizer (§4.5.1). ``update`` requires ``grad_variance=V[g]``."""
    if not learning_rate > 0:
        raise ValueError(f"learning_rate must be positive, got {learning_rate}")
    if not 0.0 <= momentum < 1.0:
        raise ValueError(f"momentum must lie in [0, 1), got {momentum}")

    def init(params):
        return NormalizedMomentumState(jax.tree.map(jnp.zeros_like, params))

    def update(updates, state, params=None, *, grad_variance=None, **extra):
        del params, extra
        if grad_variance is None:
            raise ValueError("normalized_momentum.update needs grad_variance=V[g] (the per-parameter variance)")
        m = jax.tree.map(
            lambda m0, g, v: momentum * m0 + normalized_term(g, v), state.momentum, updates, grad_variance
        )
        return jax.tree.map(lambda mi: -learning_rate * mi, m), NormalizedMomentumState(m)

    return optax.GradientTransformationExtraArgs(init, update)
