"""Before/after check of the learning loop: run tiny experiments with the pipps on PYTHONPATH, and
compare two folders of their result files entry by entry (made for the change to one loop for the
unbatched and the batched runs, typed trial records, ``restore``; docs/architecture.md).

    PYTHONPATH=/path/to/old/checkout python benchmarks/loop_reference.py run /tmp/before
    PYTHONPATH=. python benchmarks/loop_reference.py run /tmp/after
    python benchmarks/loop_reference.py compare /tmp/before /tmp/after
    PYTHONPATH=TREE taskset -c 1 python benchmarks/loop_reference.py methods DIR   # per tree, then compare
    PYTHONPATH=. python benchmarks/loop_reference.py time      # seconds of one tiny unbatched run

``run`` covers every path of the loop: an unbatched TP run whose GP turns FITC (full and sparse
warm starts), PILCO, a fixed-seed method, the low-rank variance, two seeds batched by ``lax.map``
and by ``vmap``, a resume from trial 3, and the other built-in tasks (unicycle TP and PILCO,
cart-pole balancing) and the pilco task preset (TP and PILCO). ``compare`` requires every dataset and attribute to be
equal bit for bit (value, dtype, shape, compression), except the seconds of the timings, the wall
time and the versions, which no two runs share. Both parts use only what every pipps version since
the batched mode has (``run_experiment``, ``run_batched``, ``write_result``, ``read_result``).

``methods`` runs the methods of the thesis tables (PILCO, RP, GR, GR_FS, LR, TP, TP−σ_f, GTP, GLR,
DEL; :data:`METHOD_RUNS`) as tiny experiments of the *thesis* preset (thesis estimators, the Angle
and the Tip Cost, the unicycle, cart-pole balancing; 1–3 minutes each on a shared core, mostly
compilation). Before a queue of thesis cells moves to newer code, equal files show that the seeds
it adds pool with those the older code ran. Pin both runs to the same single CPU (``taskset -c``):
XLA partitions its loops by its thread count, and so its rounding.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import h5py
import numpy as np

SMALL = dict(num_learned=3, num_particles=8, policy_evals=6, eval_rollouts=3, gp_max_iters=10, progress_chunk=4,
             store_particles=4, fitc_threshold=40, num_inducing=20, fitc_iters=5, fitc_first_iters=5)


def _small(seed, **kw):
    from pipps.experiments import resolve_config
    from pipps.experiments.methods import METHODS

    unused = METHODS[kw.get("method", "tp")].unused
    return resolve_config("quick", "cartpole_swingup", **{**{k: v for k, v in SMALL.items() if k not in unused},
                                                          "seed": seed, **kw})


def _float64():
    import pipps

    if hasattr(pipps, "enable_float64"):
        pipps.enable_float64()


def run(out: Path) -> None:
    from pipps.experiments import run_experiment
    from pipps.experiments.batched import run_batched
    from pipps.experiments.results import read_result, write_result

    _float64()
    out.mkdir(parents=True, exist_ok=True)

    def single(name, cfg, resume=None):
        start = time.perf_counter()
        run_experiment(cfg, resume=resume, on_trial=lambda r: write_result(out / f"{name}.h5", r))
        print(f"{name}: {time.perf_counter() - start:.1f} s")

    single("tp_s0", _small(0))
    single("pilco_s1", _small(1, method="pilco", pilco_linesearches=5, num_learned=2))
    single("rp_fs_s2", _small(2, method="rp_fs", num_learned=2))
    single("lowrank_s4", _small(4, variance_tol=1e-3, num_learned=2))
    for batching in ("map", "vmap"):
        def write(results, batching=batching):
            for r in results:
                write_result(out / f"{batching}_s{r.config.seed}.h5", r)

        start = time.perf_counter()
        run_batched([_small(s) for s in (0, 3)], on_trial=write, batching=batching)
        print(f"{batching}: {time.perf_counter() - start:.1f} s")
    whole = read_result(out / "tp_s0.h5")
    part = type(whole)(whole.config, whole.trials[:3], "failed", "KeyboardInterrupt: ", 5.0)
    single("tp_s0_resumed", _small(0), resume=part)
    # the other built-in tasks and the pilco task preset: criteria without a return threshold
    # (the unicycle's "upright"), cart-pole balancing, the tip cost with PILCO's task budget
    from pipps.experiments import resolve_config

    tiny = dict(num_learned=2, num_particles=8, policy_evals=6, eval_rollouts=3, gp_max_iters=10, progress_chunk=4,
                store_particles=4)
    single("unicycle_tp", resolve_config("quick", "unicycle", seed=0, **tiny, num_random=2))
    single("unicycle_pilco", resolve_config("quick", "unicycle", seed=1, method="pilco", pilco_linesearches=3,
                                            num_learned=1, eval_rollouts=3, gp_max_iters=10, num_random=2))
    single("balance_tp", resolve_config("quick", "cartpole_balance", seed=2, **tiny))
    single("pilcopreset_tp", resolve_config("pilco", "cartpole_swingup", seed=3, **tiny))
    single("pilcopreset_pilco", resolve_config("pilco", "cartpole_swingup", seed=4, method="pilco", num_learned=1,
                                               pilco_linesearches=4, eval_rollouts=3, gp_max_iters=10))


#: The tiny thesis-preset runs of ``methods``: (file name, task, method, overrides). One run per code
#: path the thesis cells take: each estimator (RP, LR, TP, GTP, GLR, DEL), Gaussian resampling (GR),
#: the GP variance left out (TP−σ_f), the fixed-seed quasi-Newton search (GR_FS; RP_FS differs from it
#: only by the resampling), PILCO's moment matching, and each task and cost.
METHOD_RUNS = (
    [(f"angle_{m}", "cartpole_swingup", m, {}) for m in ("rp", "gr", "gr_fs", "lr", "tp", "tp-sf", "glr")]
    + [(f"tip_{m}", "cartpole_swingup", m, {"cost": "tip"}) for m in ("gtp", "pilco")]
    + [(f"unicycle_{m}", "unicycle", m, {}) for m in ("tp", "pilco")]
    + [("balance_del", "cartpole_balance", "del", {})])


def methods(out: Path) -> None:
    """Every method of the thesis tables on a tiny thesis-preset experiment (:data:`METHOD_RUNS`)."""
    from pipps.experiments import resolve_config, run_experiment
    from pipps.experiments.methods import METHODS
    from pipps.experiments.results import write_result

    _float64()
    out.mkdir(parents=True, exist_ok=True)
    for seed, (name, task, method, extra) in enumerate(METHOD_RUNS):
        if method == "pilco":
            size = dict(num_learned=1, pilco_linesearches=3, eval_rollouts=3, gp_max_iters=10)
        else:
            size = {k: v for k, v in SMALL.items() if k not in METHODS[method].unused}
            size["num_learned"] = 2
        cfg = resolve_config("thesis", task, method=method, seed=seed, **size, **extra)
        start = time.perf_counter()
        run_experiment(cfg, on_trial=lambda r, name=name: write_result(out / f"{name}.h5", r))
        print(f"{name}: {time.perf_counter() - start:.1f} s", flush=True)


def _entries(g: h5py.Group, prefix: str = "") -> dict:
    out = {f"{prefix}@{k}": (v,) for k, v in g.attrs.items() if k != "wall_seconds"}
    for k, v in g.items():
        if k in ("versions", "timings"):
            out[f"{prefix}/{k}/"] = (sorted(v.attrs),)  # which phases were timed, not their seconds
        elif isinstance(v, h5py.Dataset):
            out[f"{prefix}/{k}"] = (v[()], str(v.dtype), v.shape, v.compression)
        else:
            out.update(_entries(v, f"{prefix}/{k}"))
    return out


def _same(a: tuple, b: tuple) -> bool:
    x, y = np.asarray(a[0]), np.asarray(b[0])
    return (a[1:] == b[1:] and x.dtype == y.dtype and x.shape == y.shape
            and np.array_equal(x, y, equal_nan=x.dtype.kind in "fc"))


def compare(before: Path, after: Path) -> int:
    bad = 0
    for p in sorted(before.glob("*.h5")):
        q = after / p.name
        if not q.exists():
            print(f"{p.name}: missing in {after}")
            bad += 1
            continue
        with h5py.File(p) as f, h5py.File(q) as g:
            a, b = _entries(f), _entries(g)
        diff = [k for k in sorted(set(a) | set(b)) if k not in a or k not in b or not _same(a[k], b[k])]
        print(f"{p.name}: {len(a)} entries, " + ("identical" if not diff else f"{len(diff)} differ: {diff[:10]}"))
        bad += bool(diff)
    return 1 if bad else 0


def time_one() -> None:
    """Wall and CPU seconds (all threads) of one tiny unbatched TP run (3 learned trials, FITC from
    trial 2) in this process, compiling included. On a shared machine the CPU seconds are the steadier."""
    from pipps.experiments import run_experiment

    _float64()
    start, cpu = time.perf_counter(), time.process_time()
    run_experiment(_small(0))
    print(f"{time.perf_counter() - start:.2f} s wall, {time.process_time() - cpu:.2f} s CPU")


if __name__ == "__main__":
    command = sys.argv[1]
    if command == "run":
        run(Path(sys.argv[2]))
    elif command == "compare":
        sys.exit(compare(Path(sys.argv[2]), Path(sys.argv[3])))
    elif command == "methods":
        methods(Path(sys.argv[2]))
    elif command == "time":
        time_one()
    else:
        sys.exit(f"unknown command {command!r}: run OUT, methods OUT, compare BEFORE AFTER, or time")
