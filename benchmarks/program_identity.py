"""Is a refactor free? Compare the compiled policy-gradient programs of two code versions.

For each estimator asked for, lowers one estimate (300 particles) on the model and policy of a
stored trial, compiles it, and writes the optimised HLO's instructions, with the metadata that
names source files and lines removed (``stack_frame_id``, ``metadata``) and the instruction numbers
normalised, to ``OUT_DIR/NAME.txt``; it prints each file's instruction count and sha256, the
objective and the first gradient entry. Two code versions that write the same file run the same
machine program, so neither is slower.

The estimators are given as the studies' specs, ``NAME`` or ``NAME:SETTING=VALUE[:...]``
(``--estimator``, repeatable or a comma list). By default: every named estimator of the registry
(``pipps.propagation.estimators.ESTIMATORS``) that the registry before the pieces came to own their
state had too (``rp lr lr_plain tp tp_plain tpx gtp glr del``, the library's compositions), and the
thesis TP, ``tp:k_lr=batch`` (file ``tp_k_lr_batch.txt``). ``tp:k_lr=cross_fit`` (the cross-fitted
schedule) can be asked for. ``del`` names another estimator since 2026-11-27 (the library's DEL takes
its density fit's derivative one step to θ; the earlier ``del`` is ``thesis_estimator("del")``): across
that change its program differs by design.

Every estimate starts from the same zero-initialised state in both code versions: a "previous"
baseline of zeros (no extra rollout) and, for a weight source with memory, no previous k_LR (a cold
start). The state is a constant of the compiled program. It runs on code before and after the
pieces came to own their state (``propagation/config.py`` became ``estimators.py``, ``task=``
became ``problem=``, the state a tuple of the pieces' states) and before and after ``estimate``
returned ``(state, estimate)``.

    git worktree add BEFORE_TREE BEFORE_COMMIT
    cd benchmarks
    PYTHONPATH=BEFORE_TREE taskset -c 1 python program_identity.py FILE.h5 TRIAL before/
    PYTHONPATH=AFTER_TREE taskset -c 1 python program_identity.py FILE.h5 TRIAL after/
    for f in before/*.txt; do cmp "$f" "after/${f#before/}"; done

Pin both to the same single CPU: XLA partitions loops by its thread count, which changes the
program (and its rounding). Existing output files are refused unless ``--overwrite``.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import importlib
import inspect
import re
import sys
from pathlib import Path

import jax
import jax.numpy as jnp

import pipps
from pipps.particles.forward import RolloutConfig
from pipps.studies import load_snapshot

try:
    _estimators = importlib.import_module("pipps.propagation.estimators")
except ImportError:  # before the pieces owned their state
    _estimators = importlib.import_module("pipps.propagation.config")
estimator = _estimators.estimator

_estimate = importlib.import_module("pipps.propagation.estimate")
estimate = _estimate.estimate

try:
    from pipps.experiments.storage import check_new_file, publish
except ImportError:  # an older tree: a plain check, and a plain write
    check_new_file = publish = None

if hasattr(pipps, "enable_float64"):  # since float64 became the caller's choice; before, importing pipps enabled it
    pipps.enable_float64()

#: The named estimators the registry had before the pieces came to own their state.
BEFORE_PIECES_OWNED_STATE = ("rp", "lr", "lr_plain", "tp", "tp_plain", "tpx", "gtp", "glr", "del")
THESIS_TP = "tp:k_lr=batch"


def default_specs() -> list[str]:
    """The registry's names that existed before the refactor, in its order, and the thesis TP."""
    return [n for n in _estimators.ESTIMATORS if n in BEFORE_PIECES_OWNED_STATE] + [THESIS_TP]


def _parse_spec_before(spec: str) -> tuple[str, dict]:
    """The library's ``parse_spec`` for a tree older than it (the run before the pieces owned their
    state): ``"tp:k_lr=batch"`` → ("tp", {"k_lr": "batch"}); a value that reads as a number is one."""
    name, *items = spec.strip().split(":")
    settings = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"estimator {spec!r}: expected NAME or NAME:SETTING=VALUE[:SETTING=VALUE...]")
        try:
            settings[key.strip()] = float(value)
        except ValueError:
            settings[key.strip()] = value.strip()
    return name, settings


parse_spec = getattr(_estimators, "parse_spec", _parse_spec_before)


def file_name(spec: str) -> str:
    """``tp:k_lr=batch`` → ``tp_k_lr_batch.txt``."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", spec.strip()) + ".txt"


def instructions(hlo: str) -> str:
    """The HLO's instruction lines, source metadata removed and instruction numbers normalised."""
    lines = [ln for ln in hlo.splitlines() if " = " in ln]
    out = []
    for ln in lines:
        ln = re.sub(r", metadata=\{[^}]*\}", "", ln)
        ln = re.sub(r", stack_frame_id=[0-9]+", "", ln)
        out.append(re.sub(r"\.[0-9]+", ".N", ln))
    return "\n".join(out) + "\n"


def zero_state(est, steps: int, num_actions: int):
    """The state before the first estimate, the same numbers in every code version: the "previous"
    baseline zero (no extra rollout), no previous k_LR (``has_previous`` false)."""
    if hasattr(_estimate, "EstimatorState") and "baseline" in _estimate.EstimatorState._fields:  # one central state
        combiner = est.combiner
        weight_shape = combiner.weight_shape(num_actions) if hasattr(combiner, "weight_shape") else ()
        return _estimate.EstimatorState(jnp.zeros(steps), jnp.zeros((steps, *weight_shape)), jnp.asarray(False))
    from pipps.propagation.pieces import InitContext  # each piece's own state

    return est.init(InitContext(steps, num_actions, lambda: jnp.zeros(steps)))


def check_output(path: Path, overwrite: bool) -> None:
    if check_new_file is not None:
        check_new_file(path, overwrite=overwrite, option="OUT_DIR", suffix=".txt", command="program_identity.py")
    elif path.exists() and not overwrite:
        raise SystemExit(f"{path} exists; program_identity.py replaces it only with --overwrite")
    else:
        path.parent.mkdir(parents=True, exist_ok=True)


@contextlib.contextmanager
def written(path: Path, overwrite: bool):
    if publish is not None:
        with publish(path, overwrite=overwrite, command="program_identity.py") as tmp:
            yield tmp
    else:
        yield path


def compile_one(snap, spec: str, particles: int):
    """(instruction text, objective, first gradient entry) of one estimator's compiled estimate."""
    name, settings = parse_spec(spec)
    est = estimator(name, **settings)
    state = zero_state(est, snap.task.horizon, snap.task.action_dim)
    config = RolloutConfig(num_particles=particles)
    params = inspect.signature(estimate).parameters
    state_first = "tuple[EstimatorState, Estimate]" in inspect.getsource(estimate)
    where = {"problem" if "problem" in params else "task": snap.task}

    def value_and_grad(key, policy):
        pair = estimate(key, state, policy, snap.model, **where, config=config, estimator=est)
        e = pair[1] if state_first else pair[0]
        return e.value, e.grad

    program = jax.jit(value_and_grad)
    key = jax.random.key(0)
    text = instructions(program.lower(key, snap.policy).compile().as_text())
    value, grad = program(key, snap.policy)
    first = float(jax.tree_util.tree_leaves(grad)[0].ravel()[0])
    return text, float(value), first


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     epilog=__doc__.split("\n\n", 1)[1],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("file", help="a result file (read only)")
    parser.add_argument("trial", type=int, help="a learned trial of it: its policy and GP model")
    parser.add_argument("out_dir", type=Path, metavar="OUT_DIR", help="where NAME.txt is written per estimator")
    parser.add_argument("--estimator", action="append", metavar="SPEC",
                        help="NAME or NAME:SETTING=VALUE[:...]; repeatable or a comma list (default: "
                             + ", ".join(BEFORE_PIECES_OWNED_STATE) + f", {THESIS_TP})")
    parser.add_argument("--particles", type=int, default=300, help="particles per estimate (default 300)")
    parser.add_argument("--overwrite", action="store_true", help="replace existing output files")
    args = parser.parse_args(argv)

    specs = [s.strip() for arg in args.estimator for s in arg.split(",") if s.strip()] if args.estimator else default_specs()
    for spec in specs:
        name, _ = parse_spec(spec)
        if name not in _estimators.ESTIMATORS:
            parser.error(f"--estimator {spec}: unknown name {name!r}; this tree's registry has {tuple(_estimators.ESTIMATORS)}")
    paths = {spec: args.out_dir / file_name(spec) for spec in specs}
    if len(set(paths.values())) != len(paths):
        parser.error("two estimators would write the same file")
    try:
        for path in paths.values():
            check_output(path, args.overwrite)
    except Exception as err:  # OutputError: the refusal says which file and why
        sys.exit(f"program_identity.py: {err}")

    snap = load_snapshot(args.file, args.trial, gp_chunk=1)
    for spec, path in paths.items():
        text, value, first = compile_one(snap, spec, args.particles)
        with written(path, args.overwrite) as tmp:
            with open(tmp, "w") as fh:
                fh.write(text)
        print(f"{spec:16s} {path}: {text.count(chr(10))} instructions, sha256 {hashlib.sha256(text.encode()).hexdigest()}; "
              f"objective {value!r}, first gradient entry {first!r}", flush=True)


if __name__ == "__main__":
    main()
