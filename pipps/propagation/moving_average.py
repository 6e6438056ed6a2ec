"""An exponential moving average of the earlier iterations' k_LR: a weight source with its own memory.

At optimizer iteration n the weight used at step t is the average of the batch weights of the
iterations before it,

``m_{n,t} = β m_{n−1,t} + (1 − β) k^batch_{n−1,t}``,   ``m_{1,t} = k^batch_{0,t}``,

and the first iteration (no earlier batch) uses its own batch weight, as "previous" does. With
``β = 0`` it is "previous" bit for bit; a larger ``β`` averages the weight over about ``1/(1 − β)``
iterations, so one batch whose variances are far off moves it less. Every weight it uses is built
from earlier batches only, independent of the particles it weighs, so total propagation with it is
exactly unbiased after the first iteration (docs/estimators.md, "Choosing k_LR").

Its state is the average and whether there is one yet, per step (and per node at the action nodes).
``β`` is traced: a new value does not recompile.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from pipps.propagation.strategy import strategy


class MovingAverage(NamedTuple):
    """The state: each leaf (T, *weight_shape)."""

    k: jax.Array  # m_t, the average of the earlier iterations' batch weights
    has_previous: jax.Array  # bool: False before the first estimate


@strategy(traced=("beta",))
class MovingAverageWeight:
    """k_LR from an exponential moving average, with factor ``beta``, of the earlier iterations' batch weights."""

    beta: float = 0.9

    k_lr = "moving_average"
    cold_start = True  # the first estimate falls back on its own batch's weight

    def init(self, context, weight_shape: tuple) -> MovingAverage:
        shape = (context.steps, *weight_shape)
        return MovingAverage(jnp.zeros(shape), jnp.zeros(shape, bool))

    def weight(self, state: MovingAverage, rule, g_rp, g_lr, k_batch) -> tuple[MovingAverage, jax.Array]:
        del rule, g_rp, g_lr
        k = jnp.where(state.has_previous, state.k, k_batch)
        average = jnp.where(state.has_previous, self.beta * state.k + (1.0 - self.beta) * k_batch, k_batch)
        return MovingAverage(average, jnp.ones(jnp.shape(k_batch), bool)), k


def moving_average(beta: float = 0.9) -> MovingAverageWeight:
    """The moving-average weight source; ``beta`` in [0, 1] (0: "previous")."""
    if not 0.0 <= float(beta) <= 1.0:
        raise ValueError(f"the moving average's beta must lie in [0, 1], got {beta}")
    return MovingAverageWeight(float(beta))
