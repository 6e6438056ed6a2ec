"""PILCO's policy-input noise term on learned models: does a policy optimised as if it saw noisy
observations do better on the noisy cart-pole than one optimised on the latent state?

For each PILCO result file, the state at the start of the final learned trial's policy search is
restored (:func:`pipps.studies.load_snapshot`: the trial's GP, rebuilt from its stored
hyperparameters and inducing inputs on the data of the trials before it, and the policy the search
started from). From that warm start, on that model, PILCO's quasi-Newton search (the preset's
budget) runs twice: without the term (``off``: what the loop ran; it should land near the stored
policy) and with it (``on``: PILCO release V0.9's ``S + diag(σ_n²/2)`` for the policy's input,
docs/pilco.md). The stored policy and both new ones are evaluated with the same ``--rollouts``
fresh true-system rollouts (keys independent of the experiment's; common to the three policies,
so their differences are paired): the fraction of rollouts with return below the task's return
threshold (the cart-pole's 15), the mean return and the fraction meeting the task's success rule
(the cart-pole's: physically balanced, :func:`pipps.tasks.cartpole.balanced`). A file whose task
has no return threshold (the unicycle's) is refused.

    JAX_PLATFORMS=cpu taskset -c 1 python experiments/pilco_policy_noise.py --rollouts 300 \\
        --out pilco_policy_noise.json \\
        results/thesis/cartpole_swingup_angle_k9_pilco_thesis_s{0,1,2,3,4}.h5 \\
        results/thesis/cartpole_swingup_angle_k16_pilco_thesis_s{0,1,2,3,4}.h5

One row per file, then per k the means over files and the paired difference ``on − off`` with its
standard error over files. ``--out`` (JSON; an existing file is refused before any work unless
``--overwrite`` is given) is rewritten whole after every file, so a stopped run keeps what it
finished. Result files are only read.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

import pipps

VARIANTS = ("stored", "off", "on")
COMMAND = Path(__file__).name


def search_config(cfg, problem, policy_noise: bool):
    """The loop's PILCO search settings for ``cfg`` (pipps.experiments.programs), with the term on or off."""
    from pipps.pilco import PolicySearchConfig, pilco_budget

    budget = pilco_budget(problem) if cfg.pilco_linesearches is None else pilco_budget(problem,
                                                                                      length=cfg.pilco_linesearches)
    return PolicySearchConfig(optimizer=budget, horizon=cfg.horizon, policy_noise=policy_noise)


class Programs:
    """One task, objective and evaluation program per configuration shape, reused across files (the
    policy search compiles per task object: a file with the same k reuses the last one's)."""

    def __init__(self):
        self._tasks: dict = {}
        self._programs: dict = {}

    def task(self, cfg):
        from pipps.experiments.state import make_experiment_task

        key = (cfg.task, cfg.preset, cfg.k, cfg.cost, cfg.cost_scale, cfg.horizon)
        if key not in self._tasks:
            self._tasks[key] = make_experiment_task(cfg)
        return self._tasks[key]

    def objective(self, cfg, policy_noise: bool):
        """``(policy, model) -> J`` of the loop's search objective."""
        from pipps.pilco import objective

        problem = self.task(cfg).problem
        key = ("J", id(problem), policy_noise)
        if key not in self._programs:
            self._programs[key] = jax.jit(lambda p, m: objective(problem, p, m, horizon=cfg.horizon,
                                                                 policy_noise=policy_noise))
        return self._programs[key]

    def evaluate(self, cfg):
        """``(keys, policy) -> (returns, upright, balanced)`` on the true system (the loop's evaluation)."""
        from pipps.experiments.programs import evaluate_rollouts, success_rule

        task, rule = self.task(cfg), success_rule(cfg)
        key = ("eval", id(task), cfg.balance_steps, cfg.balance_angle, cfg.balance_position)
        if key not in self._programs:
            self._programs[key] = jax.jit(lambda keys, p: evaluate_rollouts(keys, task, p, rule))
        return self._programs[key]


def fresh_keys(key_seed: int, cfg, trial: int, n: int) -> jax.Array:
    """``n`` rollout keys from ``key_seed``, the experiment's seed and the trial, independent of the
    experiment's own keys (those come from ``PRNGKey(cfg.seed)``)."""
    root = jax.random.fold_in(jax.random.PRNGKey(key_seed), 7_000_003)
    return jax.random.split(jax.random.fold_in(jax.random.fold_in(root, cfg.seed), trial), n)


def measure(path: str, programs: Programs, rollouts: int, key_seed: int, trial: int | None) -> dict:
    from pipps.experiments.results import read_result
    from pipps.pilco import optimize_policy
    from pipps.studies import load_snapshot

    result = read_result(path)
    cfg = result.config
    if not cfg.is_pilco:
        raise SystemExit(f"{path}: a {cfg.method} result; this measures PILCO's search")
    if cfg.pilco_policy_noise:
        raise SystemExit(f"{path}: learned with the policy-input noise term on; pick a default PILCO result")
    threshold = cfg.task_spec.success_for(cfg).threshold
    if threshold is None:
        raise SystemExit(f"{path}: the {cfg.task_spec.label} has no return threshold; this measures the fraction "
                         "of returns below it")
    learned = [t.index for t in result.trials if t.kind == "learned"]
    trial = learned[-1] if trial is None else trial
    snap = load_snapshot(path, trial)
    task = programs.task(cfg)
    problem = task.problem
    unravel = ravel_pytree(snap.policy)[1]
    policies = {"stored": unravel(jnp.asarray(result.trials[trial].policy))}
    searches = {}
    for name, on in (("off", False), ("on", True)):
        start = time.perf_counter()
        policy, trace = optimize_policy(problem, snap.model, snap.policy, search_config(cfg, problem, on))
        trace = jax.device_get(trace)
        policies[name] = policy
        searches[name] = dict(seconds=time.perf_counter() - start, linesearches=int(trace.num_linesearches),
                              evaluations=int(trace.num_evaluations), value=float(trace.value))
    flat = {k: np.asarray(ravel_pytree(p)[0]) for k, p in policies.items()}
    objectives = {f"J_{o}({p})": float(programs.objective(cfg, o == "on")(policies[p], snap.model))
                  for p in VARIANTS for o in ("off", "on")}
    keys = fresh_keys(key_seed, cfg, trial, rollouts)
    evaluate = programs.evaluate(cfg)
    evaluations = {}
    for name in VARIANTS:
        returns, _, balanced = (np.asarray(a) for a in jax.device_get(evaluate(keys, policies[name])))
        evaluations[name] = dict(below_threshold=float(np.mean(returns < threshold)),
                                 mean_return=float(np.mean(returns)),
                                 se_return=float(np.std(returns, ddof=1) / math.sqrt(returns.size)),
                                 balanced=float(np.mean(balanced)))
    return dict(file=str(path), k=float(cfg.k), seed=int(cfg.seed), trial=int(trial), model_points=snap.num_points,
                sparse=bool(snap.sparse), threshold=float(threshold), searches=searches,
                objectives=objectives, evaluations=evaluations,
                off_vs_stored_max_abs=float(np.max(np.abs(flat["off"] - flat["stored"]))),
                stored_return_in_file=float(result.trials[trial].eval_return))


def row_text(r: dict) -> str:
    e, s = r["evaluations"], r["searches"]
    parts = [f"{Path(r['file']).name}: k={r['k']:g} s{r['seed']} trial {r['trial']} ({r['model_points']} points)"]
    for name in VARIANTS:
        v = e[name]
        parts.append(f"{name}: <{r['threshold']:g} {v['below_threshold']:.2f}, mean {v['mean_return']:.2f}"
                     f" ± {v['se_return']:.2f}, balanced {v['balanced']:.2f}")
    parts.append(f"J_off(off) {r['objectives']['J_off(off)']:.3f}, J_on(on) {r['objectives']['J_on(on)']:.3f}; "
                 f"|θ_off − θ_stored| ≤ {r['off_vs_stored_max_abs']:.2g}; search s off/on "
                 f"{s['off']['seconds']:.0f}/{s['on']['seconds']:.0f}")
    return "\n  ".join(parts)


def summary(rows: list[dict]) -> list[dict]:
    """Per k: means over files, and the paired difference on − off with its standard error over files."""
    out = []
    for k in sorted({r["k"] for r in rows}):
        group = [r for r in rows if r["k"] == k]
        entry = dict(k=k, files=len(group))
        for metric in ("below_threshold", "mean_return", "balanced"):
            for name in VARIANTS:
                entry[f"{metric}_{name}"] = float(np.mean([r["evaluations"][name][metric] for r in group]))
            diff = np.array([r["evaluations"]["on"][metric] - r["evaluations"]["off"][metric] for r in group])
            entry[f"{metric}_on_minus_off"] = float(diff.mean())
            entry[f"{metric}_on_minus_off_se"] = float(diff.std(ddof=1) / math.sqrt(diff.size)) if diff.size > 1 \
                else math.nan
        out.append(entry)
    return out


def summary_text(entry: dict) -> str:
    lines = [f"k={entry['k']:g} over {entry['files']} files:"]
    for metric, label in (("below_threshold", "fraction < threshold"), ("mean_return", "mean return"),
                          ("balanced", "balanced fraction")):
        values = ", ".join(f"{n} {entry[f'{metric}_{n}']:.3f}" for n in VARIANTS)
        lines.append(f"  {label}: {values}; on − off {entry[f'{metric}_on_minus_off']:+.3f} "
                     f"± {entry[f'{metric}_on_minus_off_se']:.3f} (SE over files)")
    return "\n".join(lines)


def write(out: Path, payload: dict, overwrite: bool) -> None:
    """Write ``out`` in one step (the library's :func:`pipps.experiments.storage.publish`): the first
    time over an existing file only with ``overwrite``, then over the script's own file."""
    from pipps.experiments.storage import publish

    with publish(out, overwrite=overwrite, command=COMMAND) as tmp:
        tmp.write_text(json.dumps(payload, indent=1) + "\n")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", nargs="+", help="PILCO result files (read only)")
    parser.add_argument("--out", required=True, type=Path,
                        help="JSON to write (an existing file is refused without --overwrite)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    parser.add_argument("--rollouts", type=int, default=300, help="fresh true-system rollouts per policy")
    parser.add_argument("--key-seed", type=int, default=0, help="seed of the fresh rollouts' keys")
    parser.add_argument("--trial", type=int, default=None, help="the learned trial (default: the last)")
    args = parser.parse_args(argv)
    if args.rollouts < 2:
        parser.error("--rollouts must be at least 2")
    from pipps.experiments.storage import OutputError, check_new_file

    try:  # before any work (docs/reliability.md)
        check_new_file(args.out, overwrite=args.overwrite, option="--out", suffix=".json", inputs=tuple(args.files),
                       command=COMMAND)
    except OutputError as err:
        parser.exit(2, f"{COMMAND}: error: {err}\n")
    pipps.enable_float64()
    from pipps.experiments.results import code_version

    programs = Programs()
    payload = dict(command=" ".join([Path(sys.argv[0]).name, *(argv if argv is not None else sys.argv[1:])]),
                   code_version=code_version(), rollouts=args.rollouts, key_seed=args.key_seed, rows=[], summary=[])
    start = time.perf_counter()
    for path in args.files:
        t0 = time.perf_counter()
        row = measure(path, programs, args.rollouts, args.key_seed, args.trial)
        row["seconds"] = time.perf_counter() - t0
        payload["rows"].append(row)
        payload["summary"] = summary(payload["rows"])
        write(args.out, payload, overwrite=args.overwrite or len(payload["rows"]) > 1)
        print(row_text(row) + f"\n  {row['seconds']:.0f} s", flush=True)
    for entry in payload["summary"]:
        print(summary_text(entry))
    print(f"{len(args.files)} files in {time.perf_counter() - start:.0f} s; written to {args.out}")


if __name__ == "__main__":
    main()
