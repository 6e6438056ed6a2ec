"""Seconds per PILCO value-and-gradient on the models a real PILCO run planned on (docs/pilco.md).

For each trial given, the model is rebuilt from the result file (:func:`pipps.studies.load_snapshot`)
and ``jax.value_and_grad`` of ``pipps.pilco.objective(..., checkpoint=True)`` (the policy search's
setting) is jitted, called once to compile, then timed 15 times; the median and minimum are
printed with a float64 GEMM rate measured in the same process.

    JAX_PLATFORMS=cpu taskset -c 1 python benchmarks/pilco_snapshot.py results/thesis/cartpole_swingup_angle_k9_pilco_thesis_s0.h5 10 13
"""

import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import pipps
from pipps.pilco.propagate import objective
from pipps.studies import load_snapshot

pipps.enable_float64()


def main(path: str, trials: list[int]) -> None:
    out = []
    for trial in trials:
        snap = load_snapshot(path, trial)
        f = jax.jit(jax.value_and_grad(lambda t, s=snap: objective(s.task, s.unravel(t), s.model, checkpoint=True)))
        jax.block_until_ready(f(snap.theta))
        ts = []
        for _ in range(15):
            t = time.perf_counter()
            jax.block_until_ready(f(snap.theta))
            ts.append(time.perf_counter() - t)
        out.append(f"trial {trial} (N={snap.num_points}, M={snap.model.inputs.shape[0]}): "
                   f"{np.median(ts) * 1e3:.1f} ms (min {min(ts) * 1e3:.1f})")
    a, b = jnp.ones((1200, 300)), jnp.ones((300, 300))
    g = jax.jit(lambda a, b: a @ b)
    g(a, b).block_until_ready()
    t = time.perf_counter()
    for _ in range(20):
        g(a, b).block_until_ready()
    print(f"GEMM {2 * 1200 * 300 * 300 * 20 / (time.perf_counter() - t) / 1e9:.1f} Gflop/s; " + "; ".join(out))


if __name__ == "__main__":
    main(sys.argv[1], [int(t) for t in sys.argv[2:]])
