"""Seconds to compile one thesis TP policy step, without and with JAX's persistent compilation cache
(docs/performance.md, "Compilation"). Run it three times: no cache, a cold cache folder, the same folder again.

    F=results/thesis/cartpole_swingup_angle_k1_tp_thesis_s1.h5
    taskset -c 1 python benchmarks/compile_cache.py $F 10                      # no cache
    taskset -c 1 python benchmarks/compile_cache.py $F 10 /tmp/pipps-cc        # cold: compiles and stores
    taskset -c 1 python benchmarks/compile_cache.py $F 10 /tmp/pipps-cc        # warm: loads
"""
import sys
import time

t0 = time.perf_counter()
import jax  # noqa: E402

if len(sys.argv) > 3:
    jax.config.update("jax_compilation_cache_dir", sys.argv[3])
import pipps  # noqa: E402
from pipps.experiments.methods import particle_method  # noqa: E402
from pipps.optimizers.normalized import normalized_momentum  # noqa: E402
from pipps.propagation.update import init_policy_opt_state, make_policy_optimizer  # noqa: E402
from pipps.studies import load_snapshot  # noqa: E402

pipps.enable_float64()

snap = load_snapshot(sys.argv[1], int(sys.argv[2]))
cfg = snap.config
rcfg, est = particle_method(cfg)
opt = normalized_momentum(cfg.learning_rate, cfg.momentum)
run = make_policy_optimizer(snap.task, rcfg, est, opt)
st = init_policy_opt_state(jax.random.PRNGKey(0), snap.policy, snap.model, problem=snap.task, config=rcfg,
                           estimator=est, optimizer=opt)
jax.block_until_ready(st)
t = time.perf_counter()
jax.block_until_ready(run(jax.random.PRNGKey(1), st, snap.model, num_steps=1))
first = time.perf_counter() - t
t = time.perf_counter()
jax.block_until_ready(run(jax.random.PRNGKey(1), st, snap.model, num_steps=1))
second = time.perf_counter() - t
print(f"first call {first:.1f} s, second {second:.2f} s: compilation ~{first - second:.1f} s; "
      f"process {time.perf_counter() - t0:.1f} s")
