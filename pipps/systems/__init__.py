"""Known reference systems for exactness tests (see :mod:`pipps.systems.linear_gaussian`)."""

from pipps.systems.linear_gaussian import (
    LinearGaussianModel,
    closed_loop,
    exact_objective,
    exact_trajectory,
    make_linear_gaussian_task,
    reference_system,
)
from pipps.systems.quadratic_cost import QuadraticCost

__all__ = [
    "LinearGaussianModel", "QuadraticCost", "closed_loop", "exact_objective", "exact_trajectory",
    "make_linear_gaussian_task", "reference_system",
]
