"""Coverage of the seed-level interval of a per-trial success rate (docs/results.md, "How a success
rate is counted"): seeds with success probabilities drawn from a Beta of known mean and intra-seed
correlation ρ, 30 rollouts each, the interval of :func:`pipps.reporting.readings.clustered_interval`
against the pooled Wilson interval that treats every rollout as independent.

    python experiments/readings_coverage.py --reps 300
"""

from __future__ import annotations

import argparse

import numpy as np

from pipps.reporting.readings import clustered_interval, wilson_interval


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=300, help="simulated cells per case")
    ap.add_argument("--seed", type=int, default=20261126)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    rates, iccs = (0.03, 0.1, 0.4, 0.8, 0.97), (0.05, 0.2, 0.5, 0.8)
    print(f"coverage of 95 % intervals over {args.reps} simulated cells of 30 rollouts per seed: "
          "seed-level (likelihood ratio on effective rollouts) / pooled Wilson (rollouts independent)")
    print("| seeds | rate | " + " | ".join(f"ρ = {c}" for c in iccs) + " |")
    print("|---" * (len(iccs) + 2) + "|")
    for n in (5, 10, 20):
        for p in rates:
            row = []
            for icc in iccs:
                s = 1 / icc - 1
                ours = naive = 0
                for _ in range(args.reps):
                    x = rng.binomial(30, rng.beta(p * s, (1 - p) * s, n))
                    lo, hi = clustered_interval(x, [30] * n)
                    ours += lo <= p <= hi
                    lo, hi = wilson_interval(int(x.sum()), 30 * n)
                    naive += lo <= p <= hi
                row.append(f"{ours / args.reps:.2f} / {naive / args.reps:.2f}")
            print(f"| {n} | {p} | " + " | ".join(row) + " |", flush=True)


if __name__ == "__main__":
    main()
