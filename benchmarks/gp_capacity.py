"""What padding the GP data to capacities costs: one policy evaluation at the padded and at the exact
size, trial by trial, on a real run's models (docs/performance.md, "Exact GP capacities").

For each learned full-GP trial of a result file, the model the trial planned on is rebuilt twice
(:func:`pipps.studies.load_snapshot`): padded to multiples of 100 (the capacities every file before
exact capacities used) and unpadded (``gp_chunk=1``). A particle method's file is timed on its TP
policy step (the file's estimator and particle count, 20 steps per call, best of 3 after a compiling
call); a PILCO file on its moment-matching value-and-gradient (best of 5). A float64 GEMM rate is
measured in the same process. The last line sums per-evaluation seconds times evaluations per trial
(``policy_evals`` for particle methods; for PILCO the evaluations its trace records).

    JAX_PLATFORMS=cpu taskset -c 1 python benchmarks/gp_capacity.py results/thesis/cartpole_swingup_angle_k1_tp_thesis_s1.h5
    JAX_PLATFORMS=cpu taskset -c 1 python benchmarks/gp_capacity.py results/thesis/cartpole_swingup_angle_k9_pilco_thesis_s0.h5
"""

from __future__ import annotations

import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import pipps
from pipps.experiments.methods import particle_method
from pipps.experiments.results import read_result
from pipps.optimizers.normalized import normalized_momentum
from pipps.propagation.update import init_policy_opt_state, make_policy_optimizer
from pipps.studies import load_snapshot

pipps.enable_float64()


def gemm_rate(m: int = 300) -> float:
    a, b = jnp.ones((1200, m)), jnp.ones((m, m))
    f = jax.jit(lambda a, b: a @ b)
    f(a, b).block_until_ready()
    t = time.perf_counter()
    for _ in range(20):
        f(a, b).block_until_ready()
    return 2 * 1200 * m * m * 20 / (time.perf_counter() - t) / 1e9


def tp_step_seconds(snap, steps: int = 20, reps: int = 3) -> float:
    rcfg, est = particle_method(snap.config)
    opt = normalized_momentum(snap.config.learning_rate, snap.config.momentum)
    run = make_policy_optimizer(snap.task, rcfg, est, opt)
    state = init_policy_opt_state(jax.random.PRNGKey(0), snap.policy, snap.model, problem=snap.task, config=rcfg,
                                  estimator=est, optimizer=opt)
    jax.block_until_ready(run(jax.random.PRNGKey(1), state, snap.model, num_steps=steps))
    best = np.inf
    for r in range(reps):
        t = time.perf_counter()
        jax.block_until_ready(run(jax.random.PRNGKey(2 + r), state, snap.model, num_steps=steps))
        best = min(best, time.perf_counter() - t)
    return best / steps


def mm_seconds(snap, reps: int = 5) -> float:
    f = snap.mm_value_and_grad()
    jax.block_until_ready(f(snap.theta))
    best = np.inf
    for _ in range(reps):
        t = time.perf_counter()
        jax.block_until_ready(f(snap.theta))
        best = min(best, time.perf_counter() - t)
    return best


def main(path: str) -> None:
    result = read_result(path)
    cfg = result.config
    full = [t.index for t in result.trials if t.kind == "learned" and not t.gp.sparse]
    print(f"{path}: {cfg.method}, GEMM {gemm_rate():.1f} Gflop/s (float64, 1200x300x300)")
    total = {100: 0.0, 1: 0.0}
    for i in full:
        evals = cfg.policy_evals if not cfg.is_pilco else int(result.trials[i].opt_trace.evaluations[-1])
        row = []
        for chunk in (100, 1):
            snap = load_snapshot(path, i, gp_chunk=chunk)
            s = mm_seconds(snap) if cfg.is_pilco else tp_step_seconds(snap)
            total[chunk] += s * evals
            row.append((snap.model.inputs.shape[0], s))
        (m_pad, s_pad), (m_exact, s_exact) = row
        print(f"trial {i:2d}: N = {m_exact:3d}, {evals} evaluations; padded to {m_pad}: {s_pad * 1e3:6.1f} ms, "
              f"exact: {s_exact * 1e3:6.1f} ms ({s_pad / s_exact:.2f}x)")
    print(f"full-GP trials {full[0]}-{full[-1]}: {total[100]:.0f} s padded, {total[1]:.0f} s exact "
          f"(saves {total[100] - total[1]:.0f} s)")


if __name__ == "__main__":
    main(sys.argv[1])
