"""pipps: model-based reinforcement learning with particle predictions (PIPPS) in JAX.

Importing :mod:`pipps` or any of its modules has no side effect on the process: it does not switch
on JAX's 64-bit mode and does not register gymnasium environments. The library is specified in
float64; a program enables it once with :func:`enable_float64`, and the entry points
that need it raise :class:`Float64Required` otherwise (:mod:`pipps.precision`). The gymnasium ids
are registered by :func:`pipps.tasks.register_envs` (or ``gymnasium.make("pipps.tasks.envs:ID")``).
"""

from pipps.precision import Float64Required, enable_float64, float64_enabled

__version__ = "0.1.0"

__all__ = ["Float64Required", "__version__", "enable_float64", "float64_enabled"]
