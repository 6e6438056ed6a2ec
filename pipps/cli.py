"""The ``pipps`` command line. Thin: parsing and printing only; the work is in library functions."""

from __future__ import annotations

import argparse
import sys


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def _nonnegative_float(text: str) -> float:
    value = float(text)
    if not value >= 0.0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pipps", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    ro = sub.add_parser("rollout", help="simulate a few episodes with a random policy and print the returns")
    ro.add_argument("--task", default="cartpole_swingup", choices=["cartpole_swingup", "cartpole_balance", "unicycle"])
    ro.add_argument("--preset", default="thesis", choices=["thesis", "pilco"])
    ro.add_argument("--k", type=_nonnegative_float, default=1.0, help="observation-noise variance multiplier")
    ro.add_argument("--policy", default="random-actions", choices=["random-actions", "random-policy"])
    ro.add_argument("--episodes", type=_positive_int, default=3)
    ro.add_argument("--seed", type=int, default=0)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "rollout":
        from pipps.demo import random_policy_rollouts

        rep = random_policy_rollouts(args.task, args.preset, args.k, args.policy, args.episodes, args.seed)
        print(f"{rep.task} ({rep.preset} preset, k={rep.k:g}), {rep.policy}:")
        for i, (ret, n) in enumerate(zip(rep.returns, rep.lengths)):
            print(f"  episode {i}: return (total cost) {ret:.4f} over {n} steps")
        print(f"  mean return {rep.returns.mean():.4f}")
        return 0
    return 2  # pragma: no cover - argparse enforces the choices


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
