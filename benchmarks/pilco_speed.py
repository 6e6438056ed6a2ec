"""Seconds per PILCO objective-and-gradient (moment matching, thesis Alg. 2) on the thesis cart-pole.

Protocol (fixed): the thesis preset's cart-pole (raw 4-dim state, Angle Cost), H = 30, the thesis
RBF policy with 50 centres, a GP dynamics model on N training pairs from random rollouts of the
true system. ``jax.value_and_grad`` of ``pipps.pilco.objective`` is jitted, compiled once (timed
separately), then called ``--repeats`` times (≥ 10) with ``block_until_ready``; the median is
reported, with the machine, the JAX backend and the core count.

Models:
  full-300   full GP on N = 300 pairs, hyperparameters trained with ``pipps.gp.fit``;
  full-600   full GP on N = 600 pairs (same hyperparameters);
  fitc-600   FITC on N = 600 pairs with M = 300 inducing inputs (a random subset of the
             inputs; the inducing-input optimisation does not change the cost of J).

Usage::

    JAX_PLATFORMS=cpu python benchmarks/pilco_speed.py [--repeats 10] [--horizon 30] [--json out.json [--overwrite]]

An existing ``--json`` file is refused before any work unless ``--overwrite`` is given.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import jax
import numpy as np

import pipps
from pipps import gp
from pipps.experiments.storage import OutputError, check_new_file, publish
from pipps.gp.types import GPConfig
from pipps.pilco import objective
from pipps.policies import init_rbf_policy
from pipps.rollout import rollout, training_pairs
from pipps.tasks.presets import make_task

pipps.enable_float64()


def collect(task, n_pairs: int, seed: int = 0):
    """Random-rollout training pairs of the true system, exactly ``n_pairs`` of them."""
    xs, ys, i = [], [], 0
    while sum(len(x) for x in xs) < n_pairs:
        x, y = training_pairs(task, rollout(jax.random.key(seed + i), task))
        xs.append(x)
        ys.append(y)
        i += 1
    return np.concatenate(xs)[:n_pairs], np.concatenate(ys)[:n_pairs]


def build_models(task, n_full: int, n_fitc: int, num_inducing: int):
    x, y = collect(task, max(n_full, n_fitc))
    small = gp.make_data(x[:n_full], y[:n_full])
    t0 = time.perf_counter()
    post_small, _, _ = gp.fit(None, small)
    fit_s = time.perf_counter() - t0
    big = gp.make_data(x[:n_fitc], y[:n_fitc])
    config = GPConfig()
    full_big, _, _ = jax.jit(gp.full_posterior, static_argnames="config")(post_small.hyper, big, config)
    xu = gp.initial_inducing(jax.random.key(1), big, num_inducing)
    fitc_big, _, _ = jax.jit(gp.fitc_posterior, static_argnames="config")(post_small.hyper, big, xu, config)
    models = {f"full-{n_full}": post_small, f"full-{n_fitc}": full_big, f"fitc-{n_fitc} (M={num_inducing})": fitc_big}
    return models, fit_s


def time_value_and_grad(task, policy, model, horizon: int, repeats: int, checkpoint: bool):
    vg = jax.jit(jax.value_and_grad(lambda p, m: objective(task, p, m, horizon=horizon, checkpoint=checkpoint)))
    t0 = time.perf_counter()
    jax.block_until_ready(vg(policy, model))
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(vg(policy, model))
        times.append(time.perf_counter() - t0)
    return compile_s, times


def machine() -> dict:
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "cores_available": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
        "XLA_FLAGS": os.environ.get("XLA_FLAGS", ""),
        "load_average_1_5_15": os.getloadavg() if hasattr(os, "getloadavg") else None,
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--horizon", type=int, default=30)
    ap.add_argument("--centres", type=int, default=50)
    ap.add_argument("--n-full", type=int, default=300)
    ap.add_argument("--n-fitc", type=int, default=600)
    ap.add_argument("--inducing", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--checkpoint", action="store_true", help="also time the jax.checkpoint variant")
    ap.add_argument("--json", default=None, help="write the results here (an existing file is refused "
                                                 "without --overwrite)")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing --json file")
    args = ap.parse_args(argv)
    if args.repeats < 10:
        ap.error("the protocol needs at least 10 repeats")
    command = Path(__file__).name
    if args.json:  # before any work: an existing file is kept unless --overwrite (docs/reliability.md)
        try:
            check_new_file(args.json, overwrite=args.overwrite, option="--json", suffix=".json", command=command)
        except OutputError as err:
            ap.exit(2, f"{command}: error: {err}\n")

    task = make_task("cartpole_swingup", preset="thesis")
    policy = init_rbf_policy(jax.random.key(0), args.centres, task.model_init_mean, task.model_init_cov, task.u_max)
    models, fit_s = build_models(task, args.n_full, args.n_fitc, args.inducing)
    info = machine()
    print(f"machine: {info}")  # a high load average (other processes) inflates every number below
    print(f"GP hyperparameter training (N={args.n_full}, pipps.gp.fit, incl. compile): {fit_s:.1f} s")
    print(f"task: cartpole_swingup/thesis, H={args.horizon}, RBF policy {args.centres} centres")
    rows = []
    variants = [False, True] if args.checkpoint else [False]
    for name, model in models.items():
        for ck in variants:
            compile_s, times = time_value_and_grad(task, policy, model, args.horizon, args.repeats, ck)
            row = dict(model=name, checkpoint=ck, compile_s=compile_s, median_s=statistics.median(times),
                       min_s=min(times), max_s=max(times), repeats=len(times))
            rows.append(row)
            label = name + (" +checkpoint" if ck else "")
            print(f"{label:28s} median {row['median_s'] * 1e3:8.1f} ms  (min {row['min_s'] * 1e3:.1f}, "
                  f"max {row['max_s'] * 1e3:.1f}, n={len(times)}; first call incl. compile {compile_s:.1f} s)")
    if args.json:
        record = {k: v for k, v in vars(args).items() if k != "overwrite"}
        try:  # written beside it and moved into place whole; a file that appeared meanwhile is kept
            with publish(args.json, overwrite=args.overwrite, command=command) as tmp, open(tmp, "w") as fh:
                json.dump(dict(machine=info, args=record, fit_s=fit_s, results=rows), fh, indent=2)
        except OutputError as err:
            ap.exit(1, f"{command}: error: {err}\n")


if __name__ == "__main__":
    main()
