"""The TP gradient on the certified low-rank variance against the exact variance, same random numbers
(the criterion we set: the difference below 1 % of the gradient's own Monte Carlo spread).

For each snapshot and tolerance: R keys; per key the thesis-preset TP gradient (P = 300) on the exact
model and on the low-rank model, from the same state and noise. Reported: the largest
‖g_lowrank − g_exact‖ over keys, the Monte Carlo spread of g_exact (the root of the trace of its
covariance over the keys), and their ratio.

    taskset -c 1 python benchmarks/variance_gradient.py results/thesis/cartpole_swingup_angle_k1_tp_thesis_s1.h5:10 \\
        results/thesis/cartpole_swingup_angle_k1_tp_thesis_s0.h5:7 --tols 1e-1,1e-2,1e-4 --repeats 10
"""

import argparse

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

import pipps
from pipps.experiments.methods import particle_method
from pipps.gp.lowrank import low_rank_model
from pipps.propagation.estimate import estimate, init_estimator_state
from pipps.studies import load_snapshot

pipps.enable_float64()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("snapshots", nargs="+", help="FILE:TRIAL")
    ap.add_argument("--tols", default="1e-1,1e-2,1e-4")
    ap.add_argument("--repeats", type=int, default=10)
    args = ap.parse_args()
    print("| snapshot | tol | ranks | max ‖Δg‖ | MC spread of g | ratio |")
    print("|---|---|---|---|---|---|")
    for spec in args.snapshots:
        path, trial = spec.rsplit(":", 1)
        snap = load_snapshot(path, int(trial))
        rcfg, est = particle_method(snap.config)
        kw = dict(problem=snap.task, config=rcfg, estimator=est)
        grad = jax.jit(lambda key, state, model: ravel_pytree(estimate(key, state, snap.policy, model, **kw)[1].grad)[0])
        state = init_estimator_state(jax.random.PRNGKey(99), snap.policy, snap.model, **kw)
        keys = [jax.random.PRNGKey(1000 + r) for r in range(args.repeats)]
        exact = np.stack([np.asarray(grad(k, state, snap.model)) for k in keys])
        spread = float(np.sqrt(np.sum(np.var(exact, axis=0, ddof=1))))
        for tol in [float(t) for t in args.tols.split(",")]:
            model, ranks = low_rank_model(snap.model, snap.data, tol, sparse=snap.sparse, jitter=snap.jitter)
            approx = np.stack([np.asarray(grad(k, state, model)) for k in keys])
            diff = float(np.max(np.linalg.norm(approx - exact, axis=1)))
            name = f"{path.rsplit('/', 1)[-1].replace('cartpole_swingup_angle_', '').replace('.h5', '')} t{trial}"
            print(f"| {name} | {tol:g} | {ranks.tolist()} | {diff:.3g} | {spread:.3g} | {diff / spread:.2%} |")


if __name__ == "__main__":
    main()
