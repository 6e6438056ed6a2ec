"""Error of the float32 GP-variance product on GP models trained in a real experiment.

For chosen trials of a result file (a thesis-preset cart-pole run), rebuilds the full-GP
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
import json

import h5py
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from pipps.experiments.config import ExperimentConfig
from pipps.experiments.loop import gp_config, init_policy, make_experiment_task
from pipps.experiments.methods import particle_method
from pipps.gp import GPHyper, full_posterior, make_data, pad_to_capacity
from pipps.particles.forward import particle_rollout, sample_noise
from pipps.particles.models import model_output
from pipps.propagation.estimate import estimate, init_estimator_state
from pipps.rollout import Trajectory, training_pairs


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("result")
    ap.add_argument("--trials", default="3,6,10")
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args(argv)
    f = h5py.File(args.result, "r")
    cfg = ExperimentConfig(**json.loads(f.attrs["config_json"]))
    task = make_experiment_task(cfg)
    _, unravel = ravel_pytree(init_policy(jax.random.PRNGKey(0), cfg, task))
    rcfg, est = particle_method(cfg)
    print(f"# {args.result}: P={rcfg.num_particles}, T={rcfg.steps(task)}, {args.repeats} keys")
    print("| trial | N | max |Δv_f|/σ_n² | median |Δv_f|/σ_n² | ‖g32−g64‖ | sd of ‖g64‖ over keys | ‖g32−g64‖/‖g64‖ |")
    print("|---|---|---|---|---|---|---|")
    for k in map(int, args.trials.split(",")):
        xs, ys = [], []
        for j in range(k):
            t = f[f"trials/{j:03d}"]
            traj = Trajectory(*(jnp.asarray(t[n][()]) for n in ("states", "observations", "actions", "costs", "valid")))
            a, b = training_pairs(task, traj)
            xs.append(a)
            ys.append(b)
        g = f[f"trials/{k:03d}/gp"]
        hyper = GPHyper(*(jnp.asarray(g[n][()]) for n in ("log_lengthscale", "log_signal", "log_noise")))
        data = pad_to_capacity(make_data(np.concatenate(xs), np.concatenate(ys)), chunk=cfg.gp_chunk)
        post, _, ok = full_posterior(hyper, data, gp_config(cfg))
        assert bool(np.all(ok))
        policy = unravel(jnp.asarray(f[f"trials/{k:03d}/policy"][()]))
        rec = particle_rollout(task, policy, post, sample_noise(jax.random.PRNGKey(k), task, rcfg), rcfg, jacobian=False)
        z = jax.vmap(task.gp_input)(rec.x.reshape(-1, rec.x.shape[-1]), rec.u.reshape(-1, rec.u.shape[-1]))
        v64 = model_output(post, z, variance=True, jacobian=False).var
        v32 = model_output(post, z, variance=True, jacobian=False, precision="float32").var
        rel = np.abs(np.asarray(v32 - v64)) / np.asarray(post.noise_variance)[None, :]
        grads = {}
        for prec in ("float64", "float32"):
            rc = rcfg.__class__(**{**rcfg.__dict__, "variance_precision": prec})
            state = init_estimator_state(jax.random.PRNGKey(99), policy, post, task=task, config=rc, estimator=est)
            fn = jax.jit(lambda key, s=state, rc=rc: ravel_pytree(estimate(key, s, policy, post, task=task, config=rc, estimator=est)[0].grad)[0])
            grads[prec] = np.stack([np.asarray(fn(jax.random.PRNGKey(1000 + r))) for r in range(args.repeats)])
        diff = np.linalg.norm(grads["float32"] - grads["float64"], axis=1)
        norms = np.linalg.norm(grads["float64"], axis=1)
        spread = np.linalg.norm(grads["float64"] - grads["float64"].mean(0), axis=1)
        print(f"| {k} | {int(np.sum(np.asarray(data.mask)))} | {rel.max():.2e} | {np.median(rel):.2e} | {diff.mean():.2e} "
              f"| {spread.mean():.2e} | {np.mean(diff / norms):.2e} |")


if __name__ == "__main__":
    main()
