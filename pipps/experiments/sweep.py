"""Sweeps: a grid of experiments run in parallel worker processes, resumable, one file each.

``run_sweep(configs, out_dir, jobs)`` writes ``out_dir/<experiment_name(cfg)>.h5`` per
configuration. Before running, every existing file is verified (:func:`check_result`): a
complete, intact result is skipped; a missing, half-written (``status=running``), failed or
corrupt one is run again from scratch. Results are written atomically after every trial, so a
killed sweep loses at most the experiments in flight, and because every experiment is a
deterministic function of its configuration, a killed-and-resumed sweep gives the same results
as an uninterrupted one.

Workers are separate processes (``spawn``: JAX does not survive ``fork``). With more than one
job, each worker pins itself to one CPU of the sweep's own CPU set (round robin; Linux
``sched_setaffinity``), and XLA sizes its CPU thread pool from that affinity, so jobs do not
fight over cores. (``XLA_FLAGS=--xla_cpu_multi_thread_eigen=false`` does not do this on
jaxlib 0.10: a process with it still ran two threads, measured in docs/performance.md.)
"""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import multiprocessing as mp
import os
import time
import traceback
from pathlib import Path
from typing import Callable, Iterable

from pipps.experiments.config import ExperimentConfig


def _pin_worker(counter, cpus: tuple[int, ...]) -> None:
    """Pool initializer: pin this worker to the next CPU of ``cpus`` before JAX starts."""
    with counter.get_lock():
        slot = counter.value
        counter.value += 1
    if cpus and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {cpus[slot % len(cpus)]})


def worker_pool(jobs: int) -> cf.ProcessPoolExecutor:
    """``jobs`` spawn workers, each pinned to one CPU of this process's CPU set (see module doc)."""
    ctx = mp.get_context("spawn")
    cpus = tuple(sorted(os.sched_getaffinity(0))) if hasattr(os, "sched_getaffinity") else ()
    return cf.ProcessPoolExecutor(max_workers=jobs, mp_context=ctx, initializer=_pin_worker,
                                  initargs=(ctx.Value("i", 0), cpus))


def experiment_name(cfg: ExperimentConfig) -> str:
    """A file name that identifies the table cell and seed: ``task_cost_k_method_preset_sSEED``."""
    cost = cfg.cost or "default"
    if cfg.cost_scale != 1.0:
        cost += f"x{cfg.cost_scale:g}"
    return f"{cfg.task}_{cost}_k{cfg.k:g}_{cfg.method}_{cfg.preset}_s{cfg.seed}"


@dataclasses.dataclass
class SweepReport:
    ran: list[str]
    skipped: list[str]
    failed: dict[str, str]
    seconds: float


def _run_one(cfg: ExperimentConfig, path: str, quiet: bool = True) -> tuple[str, str]:
    """Worker: run one experiment, writing its file after every trial. Returns (path, error or "")."""
    from pipps.experiments.loop import run_experiment
    from pipps.experiments.results import write_result

    try:
        run_experiment(cfg, on_trial=lambda result: write_result(path, result))
        return path, ""
    except Exception as err:  # the file already records the failure
        return path, f"{type(err).__name__}: {err}\n{traceback.format_exc(limit=3) if not quiet else ''}"


def plan(configs: Iterable[ExperimentConfig], out_dir: str | os.PathLike) -> tuple[list[tuple[ExperimentConfig, Path]], list[Path]]:
    """Split the grid into (to run, already complete)."""
    from pipps.experiments.results import is_complete

    out = Path(out_dir)
    todo, done, seen = [], [], set()
    for cfg in configs:
        path = out / f"{experiment_name(cfg)}.h5"
        if path in seen:
            raise ValueError(f"two configurations in the sweep map to the same file {path.name}")
        seen.add(path)
        if is_complete(path):
            done.append(path)
        else:
            todo.append((cfg, path))
    return todo, done


def run_sweep(
    configs: Iterable[ExperimentConfig],
    out_dir: str | os.PathLike,
    *,
    jobs: int = 1,
    on_done: Callable[[str, str, int, int], None] | None = None,
) -> SweepReport:
    """Run every configuration whose result is not already complete; see the module docstring.

    ``on_done(path, error, finished, total)`` is called as each experiment ends.
    """
    if jobs < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    start = time.perf_counter()
    todo, done = plan(list(configs), out_dir)
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    ran, failed = [], {}
    total = len(todo)

    def record(path, err):
        (failed.__setitem__(path, err) if err else ran.append(path))
        if on_done:
            on_done(path, err, len(ran) + len(failed), total)

    if jobs == 1:
        for cfg, path in todo:
            record(*_run_one(cfg, str(path)))
    elif todo:
        with worker_pool(jobs) as pool:
            futures = [pool.submit(_run_one, cfg, str(path)) for cfg, path in todo]
            for fut in cf.as_completed(futures):
                record(*fut.result())
    return SweepReport(ran, [str(p) for p in done], failed, time.perf_counter() - start)
