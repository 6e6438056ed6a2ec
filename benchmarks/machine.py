"""The machine's speed, measured in the same run as a benchmark: a speed figure is quoted with it.

    from machine import gemm_gflops   # in a script run as ``python benchmarks/NAME.py``
"""

from __future__ import annotations

import time

import jax
import numpy as np


def gemm_gflops(n: int = 512, reps: int = 9) -> float:
    """Median rate (Gflop/s) of an n×n by n×n product in the default float type (float64 where the
    caller enabled it), measured now."""
    a = jax.random.normal(jax.random.PRNGKey(0), (n, n))
    f = jax.jit(lambda x: x @ x)
    f(a).block_until_ready()
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        f(a).block_until_ready()
        times.append(time.perf_counter() - t)
    return 2 * n**3 / np.median(times) / 1e9
