"""Seconds per value-and-gradient for each estimator (docs/estimators.md, "Speed").

Fixed protocol: the thesis-preset cart-pole (D = 4 states, raw 4-dim policy and GP inputs,
Dz = 5), a full GP with N = 300 training points and fixed hyperparameters (the cost of a
prediction does not depend on their values), the thesis RBF policy with 50 centres,
P = 300 particles, T = 30 steps. Every variant is one jitted function of (key, policy);
it is compiled once, then timed over ``--repeats`` calls with fresh keys (median and
interquartile range of wall seconds, ``block_until_ready``). Ratios are to RP.

"autodiff" is ``jax.value_and_grad`` of the plainly written reparameterized rollout
(:func:`pipps.particles.forward.reparameterized_objective`), the reference for RP's overhead.

    JAX_PLATFORMS=cpu python benchmarks/estimator_speed.py            # the documented numbers
    JAX_PLATFORMS=cpu python benchmarks/estimator_speed.py --quick    # a smoke run
    JAX_PLATFORMS=cpu taskset -c 0 python benchmarks/estimator_speed.py --only forward,tp --repeats 7  # one core
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

import pipps
from machine import gemm_gflops  # benchmarks/machine.py
from pipps.gp import GPConfig, GPHyper, full_posterior, make_data
from pipps.particles.forward import RolloutConfig, particle_rollout, reparameterized_objective, sample_noise
from pipps.policies import init_rbf_policy
from pipps.propagation.estimators import estimator, thesis_estimator
from pipps.propagation.estimate import estimate, init_estimator_state
from pipps.tasks.presets import make_task

pipps.enable_float64()


def cartpole_model(n: int, seed: int = 0):
    """A full-GP posterior over cart-pole-shaped data (Dz = 5, E = 4) with fixed hyperparameters."""
    rng = np.random.default_rng(seed)
    scale = np.array([1.0, 2.0, 5.0, 2.0, 8.0])  # x, v, ω, θ, u spreads of swing-up data
    z = rng.normal(size=(n, 5)) * scale
    y = 0.1 * np.sin(z[:, :4] / scale[:4]) + 0.01 * rng.normal(size=(n, 4))
    hyper = GPHyper(
        jnp.log(jnp.tile(jnp.asarray(scale), (4, 1))), jnp.log(jnp.full(4, 0.1)), jnp.log(jnp.full(4, 0.01))
    )
    post, _, _ = full_posterior(hyper, make_data(z, y), GPConfig())
    return post


VARIANTS = {
    # label: (estimator name — or (name, estimator settings), or ("thesis", name) for the thesis
    # preset's choices —, None for autodiff or "forward" for the rollout alone; RolloutConfig overrides)
    "forward only (rollout + model Jacobians)": ("forward", {}),
    "autodiff (jax.value_and_grad)": (None, {}),
    "rp": ("rp", {}),
    "rp −σ_f": ("rp", {"model_variance": False}),
    "gr": ("rp", {"resampling": "gaussian"}),
    "lr (BIW)": ("lr", {}),
    "lr_plain": ("lr_plain", {}),
    "tp": ("tp", {}),
    "tp −σ_f": ("tp", {"model_variance": False}),
    "tp previous": (("tp", {"k_lr": "previous"}), {}),
    "tpx": ("tpx", {}),
    "tpx previous": (("tpx", {"k_lr": "previous"}), {}),
    "gtp": ("gtp", {}),
    "glr": ("glr", {}),
    "tp (thesis preset: k_LR and baseline from the batch)": (("thesis", "tp"), {}),
    "del (thesis preset: the fit's derivative down the whole chain, returns-to-go)": (("thesis", "del"), {}),
    "del (library: one step to θ)": ("del", {}),
    "del_cost (DEL_c: each step's own cost, down the whole chain)": ("del_cost", {}),
}


def make_call(task, model, policy, name, overrides, P, T):
    cfg = RolloutConfig(num_particles=P, horizon=T, **overrides)
    if name == "forward":
        def fwd(key, pol):
            return particle_rollout(task, pol, model, sample_noise(key, task, cfg), cfg, jacobian=True).objective

        return jax.jit(fwd)
    if name is None:
        def f(key, pol):
            return jax.value_and_grad(lambda p: reparameterized_objective(task, p, model, sample_noise(key, task, cfg), cfg))(pol)

        return jax.jit(f)
    if isinstance(name, str):
        est = estimator(name)
    elif name[0] == "thesis":
        est = thesis_estimator(name[1])
    else:
        est = estimator(name[0], **name[1])
    state = init_estimator_state(jax.random.PRNGKey(123), policy, model, problem=task, config=cfg, estimator=est)

    def g(key, pol):
        _, e = estimate(key, state, pol, model, problem=task, config=cfg, estimator=est)
        return e.value, e.grad

    return jax.jit(g)


def time_call(fn, policy, repeats: int):
    jax.block_until_ready(fn(jax.random.PRNGKey(0), policy))  # compile
    times = []
    for i in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(jax.random.PRNGKey(i + 1), policy))
        times.append(time.perf_counter() - t0)
    return np.median(times), np.percentile(times, 25), np.percentile(times, 75)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--particles", type=int, default=300)
    ap.add_argument("--horizon", type=int, default=30)
    ap.add_argument("--data", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--quick", action="store_true", help="P=50, N=50, T=10, 3 repeats")
    ap.add_argument("--only", default="", help="comma-separated first words of the variants to time, e.g. forward,rp,tp,lr")
    args = ap.parse_args(argv)
    if args.quick:
        args.particles, args.data, args.horizon, args.repeats = 50, 50, 10, 3
    task = make_task("cartpole_swingup", horizon=args.horizon).problem  # the estimators only plan
    model = cartpole_model(args.data)
    policy = init_rbf_policy(jax.random.PRNGKey(0), 50, np.zeros(4), np.diag([0.1, 1.0, 4.0, 1.0]), task.u_max)
    print(f"# estimator speed: P={args.particles}, T={args.horizon}, N={args.data}, D=4, Dz=5, RBF 50 centres")
    print(f"# machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, jax {jax.__version__}, {jax.devices()[0].platform}")
    print(f"# float64 GEMM (512³) at the start: {gemm_gflops():.1f} Gflop/s")
    results = {}
    only = {w for w in args.only.split(",") if w}
    for label, (name, overrides) in VARIANTS.items():
        if only and label.split()[0] not in only | {"rp"}:  # RP is the ratios' reference
            continue
        fn = make_call(task, model, policy, name, overrides, args.particles, args.horizon)
        results[label] = time_call(fn, policy, args.repeats)
    rp = results["rp"][0]
    print("\n| variant | median s | IQR s | ratio to RP |\n|---|---|---|---|")
    for label, (med, q1, q3) in results.items():
        print(f"| {label} | {med:.4f} | {q1:.4f}–{q3:.4f} | {med / rp:.2f} |")
    print(f"# float64 GEMM (512³) at the end: {gemm_gflops():.1f} Gflop/s")


if __name__ == "__main__":
    main()
