"""Sweeps: a grid of experiments run in parallel worker processes, resumable, one file each.

``run_sweep(configs, out_dir, jobs)`` writes ``out_dir/<experiment_name(cfg)>.h5`` per
configuration. Before running, every existing file is verified (:func:`check_result`): a
complete, intact result is skipped; a missing, half-written (``status=running``), failed or
corrupt one is run again from scratch. Results are written atomically after every trial, so a
killed sweep loses at most the experiments in flight, and because every experiment is a
deterministic function of its configuration, a killed-and-resumed sweep gives the same results
as an uninterrupted one.

Workers are separate processes (``spawn``: JAX does not survive ``fork``); with more than one
job each worker's XLA CPU backend is limited to one intra-op thread so jobs do not fight over
cores.
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

SINGLE_THREAD_XLA = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


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
        saved = os.environ.get("XLA_FLAGS")
        os.environ["XLA_FLAGS"] = f"{saved or ''} {SINGLE_THREAD_XLA}".strip()
        try:
            with cf.ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn")) as pool:
                futures = [pool.submit(_run_one, cfg, str(path)) for cfg, path in todo]
                for fut in cf.as_completed(futures):
                    record(*fut.result())
        finally:
            if saved is None:
                os.environ.pop("XLA_FLAGS", None)
            else:
                os.environ["XLA_FLAGS"] = saved
    return SweepReport(ran, [str(p) for p in done], failed, time.perf_counter() - start)
