"""Error of the float32 GP-variance product on GP models trained in a real experiment.

For chosen trials of a result file (a thesis-preset cart-pole run), rebuilds (pipps.studies.load_snapshot) the full-GP
model the policy was optimised on (the data of the earlier trials, the trial's stored
hyperparameters), then compares, with identical random numbers:

* the epistemic variance v_f at the particles of a P = 300 rollout under the trial's policy,
  float32 product against float64: the largest error relative to σ_n² (what it is added to);
* the TP gradient: ‖g32 − g64‖ against the Monte Carlo spread of g64 itself
  (the standard deviation of one estimate's norm over ``--repeats`` keys, i.e. the noise the
  optimiser sees anyway).

    python benchmarks/variance_precision.py results/thesis/cartpole_swingup_angle_k1_tp_thesis_s0.h5
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

import pipps
from pipps.experiments.methods import particle_method
from pipps.experiments.results import read_result
from pipps.particles.forward import particle_rollout, sample_noise
from pipps.particles.models import model_output
from pipps.propagation.estimate import estimate, init_estimator_state
from pipps.studies import load_snapshot

pipps.enable_float64()

def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("result")
    ap.add_argument("--trials", default="3,6,10")
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args(argv)
    snaps = {k: load_snapshot(args.result, k) for k in map(int, args.trials.split(","))}
    cfg = next(iter(snaps.values())).config
    stored = read_result(args.result).trials
    rcfg, est = particle_method(cfg)
    print(f"# {args.result}: P={rcfg.num_particles}, T={rcfg.steps(snaps[min(snaps)].task)}, {args.repeats} keys")
    print("| trial | N | max |Δv_f|/σ_n² | median |Δv_f|/σ_n² | ‖g32−g64‖ | sd of ‖g64‖ over keys | ‖g32−g64‖/‖g64‖ |")
    print("|---|---|---|---|---|---|---|")
    for k, snap in snaps.items():
        task, post = snap.task, snap.model  # the model trial k optimised on (pipps.studies.snapshot)
        policy = snap.unravel(jnp.asarray(stored[k].policy))  # the policy trial k ran (its optimisation's result)
        rec = particle_rollout(task, policy, post, sample_noise(jax.random.PRNGKey(k), task, rcfg), rcfg, jacobian=False)
        z = jax.vmap(task.gp_input)(rec.x.reshape(-1, rec.x.shape[-1]), rec.u.reshape(-1, rec.u.shape[-1]))
        v64 = model_output(post, z, variance=True, jacobian=False).var
        v32 = model_output(post, z, variance=True, jacobian=False, precision="float32").var
        rel = np.abs(np.asarray(v32 - v64)) / np.asarray(post.noise_variance)[None, :]
        grads = {}
        for prec in ("float64", "float32"):
            rc = rcfg.__class__(**{**rcfg.__dict__, "variance_precision": prec})
            state = init_estimator_state(jax.random.PRNGKey(99), policy, post, problem=task, config=rc, estimator=est)
            fn = jax.jit(lambda key, s=state, rc=rc: ravel_pytree(estimate(key, s, policy, post, problem=task, config=rc, estimator=est)[1].grad)[0])
            grads[prec] = np.stack([np.asarray(fn(jax.random.PRNGKey(1000 + r))) for r in range(args.repeats)])
        diff = np.linalg.norm(grads["float32"] - grads["float64"], axis=1)
        norms = np.linalg.norm(grads["float64"], axis=1)
        spread = np.linalg.norm(grads["float64"] - grads["float64"].mean(0), axis=1)
        print(f"| {k} | {snap.num_points} | {rel.max():.2e} | {np.median(rel):.2e} | {diff.mean():.2e} "
              f"| {spread.mean():.2e} | {np.mean(diff / norms):.2e} |")


if __name__ == "__main__":
    main()
