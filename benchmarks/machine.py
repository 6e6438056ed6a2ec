"""The machine's speed, measured in the same run as a benchmark: a speed figure is quoted with it.

    from machine import gemm_gflops   # in a script run as ``python benchmarks/NAME.py``

Run as a script it prints the float64 GEMM rates of a lent device (the GPU scripts in
``experiments/`` do so before their cells), one product shape per argument: ``N`` for an N×N by
N×N product, ``BxN`` for B batched N×N products:

    python3 benchmarks/machine.py 8192 400x300 40x300
"""

from __future__ import annotations

import sys
import time

import jax
import numpy as np


def gemm_rate(shape: tuple[int, ...], reps: int = 9, median: bool = True) -> tuple[float, float]:
    """(Gflop/s, seconds per product) of ``x @ x`` for ``x`` of ``shape`` (N×N or B×N×N) in the
    default float type (float64 where the caller enabled it), measured now in wall time. ``median``:
    the median of ``reps`` timed products; otherwise their mean, timed as one stream."""
    a = jax.random.normal(jax.random.PRNGKey(0), shape)
    f = jax.jit(lambda x: x @ x)
    f(a).block_until_ready()
    if median:
        times = []
        for _ in range(reps):
            t = time.perf_counter()
            f(a).block_until_ready()
            times.append(time.perf_counter() - t)
        seconds = float(np.median(times))
    else:
        t = time.perf_counter()
        for _ in range(reps):
            c = f(a)
        c.block_until_ready()
        seconds = (time.perf_counter() - t) / reps
    n = shape[-1]
    flops = 2 * int(np.prod(shape)) * n  # each of the B·n·n entries of the product: n multiply-adds
    return flops / seconds / 1e9, seconds


def gemm_gflops(n: int = 512, reps: int = 9) -> float:
    """Median rate (Gflop/s) of an n×n by n×n product in the default float type (float64 where the
    caller enabled it), measured now."""
    return gemm_rate((n, n), reps)[0]


def _shape(arg: str) -> tuple[int, ...]:
    batch, _, n = arg.rpartition("x")
    try:
        return (int(batch), int(n), int(n)) if batch else (int(n), int(n))
    except ValueError:
        sys.exit(f"machine.py: error: {arg!r} is not a product shape (N or BxN)")


if __name__ == "__main__":
    shapes = [_shape(arg) for arg in sys.argv[1:] or ["8192"]]
    jax.config.update("jax_enable_x64", True)
    print("jax", jax.__version__, jax.devices())
    for shape in shapes:
        gflops, seconds = gemm_rate(shape, reps=20, median=False)
        print(f"float64 GEMM {shape} @ {shape}: {gflops / 1e3:.2f} Tflop/s ({seconds * 1e3:.3f} ms)")
