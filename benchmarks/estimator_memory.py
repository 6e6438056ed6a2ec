"""Memory of one policy evaluation (value and gradient) per estimator, from XLA's buffer assignment.

The numbers behind :mod:`pipps.experiments.preflight`'s memory estimate: for each estimator,
particle count P, horizon T and GP size N, the compiled program's temporary, argument and output
bytes (``Compiled.memory_analysis()``), on the cart-pole-shaped model of
``benchmarks/estimator_speed.py`` (D = 4, Dz = 5, E = 4). Nothing is run, only compiled.

    JAX_PLATFORMS=cpu taskset -c 0 python benchmarks/estimator_memory.py
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

import pipps
from estimator_speed import cartpole_model, make_call  # benchmarks/estimator_speed.py
from pipps.experiments.preflight import evaluation_bytes
from pipps.policies import init_rbf_policy
from pipps.tasks.presets import make_task

pipps.enable_float64()


def compiled_bytes(name: str, P: int, T: int, N: int) -> int:
    task = make_task("cartpole_swingup", horizon=T).problem
    model = cartpole_model(N)
    policy = init_rbf_policy(jax.random.PRNGKey(0), 50, np.zeros(4), np.diag([0.1, 1.0, 4.0, 1.0]), task.u_max)
    fn = make_call(task, model, policy, name, {}, P, T)
    m = fn.lower(jax.random.PRNGKey(0), policy).compile().memory_analysis()
    return int(m.temp_size_in_bytes + m.argument_size_in_bytes + m.output_size_in_bytes)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--estimators", default="rp,lr,tp")
    ap.add_argument("--particles", default="50,200,800")
    ap.add_argument("--horizons", default="10,30")
    ap.add_argument("--data", default="30,300")
    args = ap.parse_args(argv)
    print("| estimator | P | T | N | XLA bytes | estimate | estimate / XLA |")
    print("|---|---|---|---|---|---|---|")
    for name in args.estimators.split(","):
        for P in map(int, args.particles.split(",")):
            for T in map(int, args.horizons.split(",")):
                for N in map(int, args.data.split(",")):
                    got = compiled_bytes(name, P, T, N)
                    est = evaluation_bytes(name, P, T, N, state_dim=4, input_dim=5, outputs=4)
                    print(f"| {name} | {P} | {T} | {N} | {got:.3g} | {est:.3g} | {est / got:.2f} |", flush=True)


if __name__ == "__main__":
    main()
