"""pipps: model-based reinforcement learning with particle predictions (PIPPS) in JAX.

Importing :mod:`pipps` enables JAX's 64-bit mode (``jax_enable_x64``): the task
physics, GP training and every numerical check of this project are specified in
float64 (tasks.md §0). Code that wants float32 (e.g. fast rollouts) casts explicitly.
"""

import jax

jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"
