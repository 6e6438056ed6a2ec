"""Is a refactor free? Compare the compiled TP policy-gradient program of two code versions.

Lowers one thesis TP estimate (``tp`` with ``k_lr="batch"``, 300 particles) on the model and policy of
a stored trial, compiles it, and writes the optimised HLO's instructions with the metadata that
names source files and lines removed (``stack_frame_id``, ``metadata``) and the instruction numbers
normalised. Two code versions that produce the same file run the same machine program, so neither
is slower; the printed objective and first gradient entry show the numbers too. It runs on code
before and after the change of ``estimate``'s return order to ``(state, estimate)``, and before and after the pieces
came to own their state (``propagation/config.py`` became ``estimators.py``, ``task=`` became
``problem=``, the state a tuple of the pieces' states; both start from a zero "previous" baseline).

    PYTHONPATH=OLD_TREE taskset -c 0 python benchmarks/program_identity.py FILE.h5 TRIAL old.txt
    PYTHONPATH=NEW_TREE taskset -c 0 python benchmarks/program_identity.py FILE.h5 TRIAL new.txt
    cmp old.txt new.txt

Pin both to the same number of CPUs: XLA partitions loops by its thread count, which changes the
program (and its rounding).
"""

from __future__ import annotations

import hashlib
import importlib
import inspect
import re
import sys

import jax
import jax.numpy as jnp

import pipps
from pipps.particles.forward import RolloutConfig
from pipps.studies import load_snapshot

try:
    from pipps.propagation.estimators import estimator
except ImportError:  # before the pieces owned their state
    from pipps.propagation.config import estimator

_estimate = importlib.import_module("pipps.propagation.estimate")
estimate = _estimate.estimate

if hasattr(pipps, "enable_float64"):  # since float64 became the caller's choice; before, importing pipps enabled it
    pipps.enable_float64()


def instructions(hlo: str) -> str:
    """The HLO's instruction lines, source metadata removed and instruction numbers normalised."""
    lines = [ln for ln in hlo.splitlines() if " = " in ln]
    out = []
    for ln in lines:
        ln = re.sub(r", metadata=\{[^}]*\}", "", ln)
        ln = re.sub(r", stack_frame_id=[0-9]+", "", ln)
        out.append(re.sub(r"\.[0-9]+", ".N", ln))
    return "\n".join(out) + "\n"


def main(path: str, trial: int, out: str) -> None:
    snap = load_snapshot(path, trial, gp_chunk=1)
    T = snap.task.horizon
    est = estimator("tp", k_lr="batch")
    config = RolloutConfig(num_particles=300)
    params = inspect.signature(estimate).parameters
    if hasattr(_estimate, "EstimatorState") and "baseline" in _estimate.EstimatorState._fields:  # one central state
        state = _estimate.EstimatorState(jnp.zeros(T), jnp.full((T,), 0.5), jnp.asarray(False))
    else:  # each piece's own, from the same numbers: the "previous" baseline zero (no extra rollout)
        from pipps.propagation.pieces import InitContext

        state = est.init(InitContext(T, snap.task.action_dim, lambda: jnp.zeros(T)))
    state_first = "tuple[EstimatorState, Estimate]" in inspect.getsource(estimate)
    where = {"problem" if "problem" in params else "task": snap.task}

    def value_and_grad(key, policy):
        pair = estimate(key, state, policy, snap.model, **where, config=config, estimator=est)
        e = pair[1] if state_first else pair[0]
        return e.value, e.grad

    program = jax.jit(value_and_grad)
    key = jax.random.key(0)
    text = instructions(program.lower(key, snap.policy).compile().as_text())
    with open(out, "w") as fh:
        fh.write(text)
    value, grad = program(key, snap.policy)
    first = float(jax.tree_util.tree_leaves(grad)[0].ravel()[0])
    print(f"{out}: {text.count(chr(10))} instructions, sha256 {hashlib.sha256(text.encode()).hexdigest()[:16]}; "
          f"objective {float(value)!r}, first gradient entry {first!r}")


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), sys.argv[3])
