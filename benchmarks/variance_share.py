"""Seconds per TP policy step on a real snapshot: exact GP variance against the variance off (−σ_f),
with a float64 GEMM rate measured in the same process (docs/performance.md,
"The certified low-rank variance, measured").

    taskset -c 1 python benchmarks/variance_share.py results/thesis/cartpole_swingup_angle_k1_tp_thesis_s1.h5 10 1e-2,1e-4,1e-6
    python benchmarks/variance_share.py results/thesis/cartpole_swingup_angle_k1_tp_thesis_s1.h5 10   # all cores

Steps: 20 TP policy steps (P = 300, thesis estimator) per timing, best of 3 after a compiling call.
"""
import sys, time, dataclasses
import numpy as np, jax, jax.numpy as jnp
import pipps
from pipps.studies import load_snapshot
from pipps.experiments.methods import particle_method
from pipps.optimizers.normalized import normalized_momentum
from pipps.propagation.update import init_policy_opt_state, make_policy_optimizer
pipps.enable_float64()
snap = load_snapshot(sys.argv[1], int(sys.argv[2]))
cfg = snap.config
def timeit(rcfg, est, steps=20, reps=3):
    opt = normalized_momentum(cfg.learning_rate, cfg.momentum)
    run = make_policy_optimizer(snap.task, rcfg, est, opt)
    st = init_policy_opt_state(jax.random.PRNGKey(0), snap.policy, snap.model, problem=snap.task, config=rcfg, estimator=est, optimizer=opt)
    jax.block_until_ready(run(jax.random.PRNGKey(1), st, snap.model, num_steps=steps))
    best = 1e9
    for r in range(reps):
        t = time.perf_counter(); jax.block_until_ready(run(jax.random.PRNGKey(2+r), st, snap.model, num_steps=steps)); best = min(best, time.perf_counter()-t)
    return best/steps
rcfg, est = particle_method(cfg)
M = snap.model.inputs.shape[0]
a = jnp.ones((1200, M)); b = jnp.ones((M, M))
f = jax.jit(lambda a, b: a @ b); f(a, b).block_until_ready()
t = time.perf_counter(); [f(a, b).block_until_ready() for _ in range(20)]; g = 2*1200*M*M*20/(time.perf_counter()-t)/1e9
exact = timeit(rcfg, est)
off = timeit(dataclasses.replace(rcfg, model_variance=False), est)
print(f"N={snap.num_points} M={M} P={rcfg.num_particles}: GEMM {g:.1f} Gflop/s; TP step exact {exact*1e3:.1f} ms, "
      f"variance off {off*1e3:.1f} ms; variance share {(exact-off)/exact:.0%}")
from pipps.gp.lowrank import low_rank_model

for tol in [float(t) for t in (sys.argv[3].split(",") if len(sys.argv) > 3 else [])]:
    exact_model = snap.model
    snap.model, ranks = low_rank_model(exact_model, snap.data, tol, sparse=snap.sparse, jitter=snap.jitter)
    t_lr = timeit(rcfg, est)
    snap.model = exact_model
    print(f"  low-rank tol {tol:g} (ranks {ranks.tolist()}): TP step {t_lr*1e3:.1f} ms, {exact / t_lr:.2f}x the exact step")
