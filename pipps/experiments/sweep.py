"""Sweeps: a grid of experiments run in parallel worker processes, resumable, one file each.

``run_sweep(configs, out_dir, jobs)`` writes ``out_dir/<experiment_name(cfg)>.h5`` per
configuration. Before running, every existing file is verified (:func:`verify_result`): a
complete, intact result is skipped; an intact unfinished one (``status=running`` or ``failed``)
is resumed from its last finished trial (``run_experiment(resume=...)``); a missing or corrupt
one is run from scratch; one that holds a different configuration (the same cell and seed with
other settings) stops the sweep before anything runs, naming the settings that differ. Results
are written atomically after every trial, so a killed sweep loses at most the trial in flight of
each running experiment, and because every experiment is a deterministic function of its
configuration and a resumed one continues from exactly the state it stopped in, a
killed-and-resumed sweep gives the same results as an uninterrupted one.

Workers are separate processes (``spawn``: JAX does not survive ``fork``) that switch on float64
(:func:`pipps.enable_float64`) as the ``pipps`` command does; a run in the calling process needs
the caller to have switched it on (:func:`~pipps.experiments.loop.run_experiment` raises otherwise).
With more than one job, each worker pins itself to CPUs of its CPU set that no other worker holds
(:func:`_pin_to_free_cpus`: a lock file per CPU, Linux ``sched_setaffinity``), and XLA sizes its
CPU thread pool from that affinity, so jobs do not fight over cores. :func:`cpu_layout` decides
how many workers and how many CPUs each: by default one worker per CPU (two pinned experiments
on two cores do twice the work of one; one experiment on two XLA threads only ~1.4× —
docs/performance.md), and when fewer experiments remain than CPUs, each worker gets an equal
share of them, so a lone experiment runs on every core it is given. (``XLA_FLAGS=--xla_cpu_multi_thread_eigen=false`` does not do this on
jaxlib 0.10: a process with it still ran two threads, measured in docs/performance.md.)

**Progress and Ctrl-C.** ``on_trial`` hears, from every worker, the start and the end of each
trial (its path, the worker's CPUs, the trial's seconds), so a caller can print progress after
every trial rather than every experiment. A ``KeyboardInterrupt`` in the sweep's process (Ctrl-C,
or SIGINT sent to it alone) stops the sweep within seconds: queued experiments are cancelled, each
worker gets SIGINT, writes its file as ``interrupted`` with every finished trial and starts nothing
new; a worker still busy after :data:`STOP_GRACE` seconds (inside one long compiled call) is killed,
its file keeping the trials it had finished (status ``running``), its lock released by the kernel.
The interrupt is then raised again for the caller to report what was kept. A pool worker takes
SIGTERM as it takes SIGINT, so a SIGTERM to the sweep's whole process group (``timeout``, a
service manager) also leaves each file ``interrupted``; the CLI turns SIGTERM to the sweep's process
into the same ``KeyboardInterrupt`` (:class:`pipps.cli.Terminated`), and a Ray session this
function starts does not take that handler away (``ray.init`` sets its own, which exits at once).

``backend="ray"`` runs the same plan on a Ray cluster (``address``; without one, ``ray.init()``
finds a running local cluster or starts a local instance, shut down again at the end): each
experiment is one Ray task with ``num_cpus=1`` that calls the same :func:`_run_one`, so the task
itself writes the result file, atomically, after every trial. ``out_dir`` must therefore be the
same path on every node (a shared filesystem). ``jobs`` caps the tasks in flight. Ray reserves a
CPU per task but does not say which, so a task pins itself the same way, in a fresh worker
process (``max_calls=1``) so the pinning precedes JAX.

A node lost mid-sweep (its raylet or the machine dies) takes its tasks' worker processes with it.
Ray runs such a task again on a node that is alive (up to :data:`RAY_RETRIES` times), and since
the file on the shared folder keeps every finished trial and the dead process's lock died with it,
the new task resumes the experiment from its last finished trial: the sweep finishes, with the
same results as an uninterrupted one. A task that runs out of retries is reported as failed, its
file keeping its finished trials for the next run of the same sweep to resume.
"""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import multiprocessing as mp
import os
import pkgutil
import queue as queues
import signal
import sys
import tempfile
import threading
import time
import traceback
from pathlib import Path
from typing import Callable, Iterable

from pipps.experiments.config import ExperimentConfig, experiment_name  # noqa: F401  (re-exported)


def available_cpus() -> int:
    """The CPUs this process may run on (its affinity; ``os.cpu_count()`` where there is none)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def accelerator_installed() -> bool:
    """Whether JAX may pick an accelerator: a PJRT plugin is installed and ``JAX_PLATFORMS`` does not
    pin the CPU. Checked without initialising JAX (a parent that did would hold the device's memory)."""
    import importlib.util

    if os.environ.get("JAX_PLATFORMS", "").split(",")[0].strip() == "cpu":
        return False
    try:
        import jax_plugins  # namespace package of the CUDA/ROCm/TPU plugins

        return any(True for _ in pkgutil.iter_modules(jax_plugins.__path__))
    except ImportError:
        return importlib.util.find_spec("libtpu") is not None


def cpu_layout(jobs: int | None, experiments: int, cpus: int) -> tuple[int, int]:
    """``(workers, cpus_per_worker)`` for ``experiments`` left to run on ``cpus`` CPUs.

    ``jobs=None`` (``--jobs auto``) asks for one worker per CPU (one in all where an accelerator is
    installed: workers would compete for its memory); an explicit ``jobs`` is a cap. Never
    more workers than experiments; the CPUs are shared out equally (at least one each), so two
    experiments on eight CPUs run four threads each, and one experiment runs on all of them.
    """
    if jobs is not None and jobs < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    if jobs is None:
        jobs = 1 if accelerator_installed() else cpus
    workers = max(1, min(jobs, experiments))
    return workers, max(1, cpus // workers)


def worker_pool(jobs: int, width: int = 1, events=None) -> cf.ProcessPoolExecutor:
    """``jobs`` spawn workers, each pinned to ``width`` CPUs no other pinned pipps process holds;
    ``events``: a queue (of the spawn context) the workers put their progress on."""
    return cf.ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn"),
                                  initializer=_start_worker, initargs=(width, events, True))


#: seconds a stopping sweep waits for its workers to write their files before it kills them
STOP_GRACE = 5.0

_events = None  # a worker's queue to the sweep's process (set by _start_worker)
_stopping = False  # a worker that got SIGINT: finish writing, start nothing new
_busy = False  # a worker is running an experiment (SIGINT interrupts it; an idle one just stops)
_in_worker = False  # this process is a sweep's pool worker
_takes_sigterm = False  # SIGTERM stops this worker as SIGINT does (pool workers; Ray's keep Ray's own)


def _on_sigint(signum, frame):
    """A sweep worker's SIGINT (or a pool worker's SIGTERM): stop the experiment it runs (its file is
    written as interrupted), once; later ones of either kind are ignored so that the file is written
    whole (the sweep kills a worker that is still running after its grace period)."""
    global _stopping
    # Later signals find this handler still installed and return at once. (Setting SIG_IGN instead
    # would make CPython print a "Signal 15 ignored due to race condition" traceback when a SIGTERM
    # to the group and the sweep's SIGINT arrive together.)
    if _stopping:
        return
    _stopping = True
    if _busy:
        raise KeyboardInterrupt


def _progress(path: str, report):
    """A run_experiment progress callback passing each trial's start and end to ``report`` (in the
    sweep's process) or to the worker's event queue; None when there is nobody to tell."""
    sink = report if report is not None else (_events.put if _events is not None else None)
    if sink is None:
        return None
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []

    def progress(event):
        if event["phase"] in ("trial", "evaluated"):
            sink({**{k: v for k, v in event.items() if isinstance(v, (int, float, str))}, "path": path,
                  "pid": os.getpid(), "cpus": cpus})

    return progress


@dataclasses.dataclass
class SweepReport:
    ran: list[str]
    skipped: list[str]
    failed: dict[str, str]
    seconds: float
    notes: dict[str, str] = dataclasses.field(default_factory=dict)  # what happened besides running: set aside, busy


def release_compiled() -> None:
    """Drop every compiled program this process holds (``jax.clear_caches``) once an experiment is done.

    A sweep runs many experiments in one process (in place, or in a pool worker; Ray starts a fresh
    worker per task, where this costs nothing), and
    the presets compile new programs every trial (the GP's exact data size). Each compiled program
    keeps its own memory mappings, never released while it is cached: a k = 9 sweep process died after
    seven thesis-preset experiments with "LLVM ERROR: Unable to allocate section memory", its
    mappings at Linux's default limit of 65,530 (``vm.max_map_count``; its twin had 61,497).
    ``jax.clear_caches()`` gives them back (measured: 300 small programs added 970 mappings, and
    clearing returned 888 of them); the next experiment compiles its own programs again, identical ones, so no result
    changes."""
    import gc

    import jax

    jax.clear_caches()
    gc.collect()


def _run_one(cfg: ExperimentConfig, path: str, quiet: bool = True, report=None) -> tuple[str, str, str]:
    """Worker: run (or resume) one experiment, writing its file after every trial.

    Everything is decided under the file's :class:`~pipps.experiments.storage.ResultLock`: a file
    another process is writing is left to it, one that became complete meanwhile is skipped, an
    unfinished one of this experiment is resumed, a damaged one is set aside (renamed, not
    overwritten). Returns ``(path, outcome, message)`` with outcome ``ran``, ``skipped`` or ``failed``.
    ``report`` hears each trial's start and end (:func:`_progress`).
    """
    from pipps.experiments.loop import run_experiment
    from pipps.experiments.results import read_result, write_result
    from pipps.experiments.storage import ResultBusy, ResultLock, existing_result, set_aside

    global _busy
    if _stopping:
        return path, "skipped", "the sweep is stopping"
    try:
        _busy = True
        with ResultLock(path):
            found = existing_result(path, cfg)
            if found.kind == "complete":
                return path, "skipped", "complete (finished by another process)"
            if found.kind == "other":
                return path, "failed", f"OutputError: {path} holds another configuration ({found.detail})"
            if found.kind == "unreadable":
                return path, "failed", f"OutputError: {path} cannot be read now ({found.detail}); left untouched"
            note = ""
            if found.kind == "damaged":
                note = f"set aside a damaged file as {set_aside(path).name}"
            resume = read_result(path, verify=False) if found.kind == "unfinished" and found.trials else None
            run_experiment(cfg, resume=resume, on_trial=lambda result: write_result(path, result),
                           progress=_progress(path, report))
            return path, "ran", note
    except ResultBusy as err:
        return path, "skipped", f"running in another process ({err})"
    except KeyboardInterrupt:
        if not _in_worker:  # in the sweep's own process: stop the sweep
            raise
        return path, "interrupted", "stopped by SIGINT; the file keeps every finished trial"
    except Exception as err:  # the file already records the failure
        return path, "failed", f"{type(err).__name__}: {err}\n{traceback.format_exc(limit=3) if not quiet else ''}"
    finally:
        _busy = False
        release_compiled()


def plan(
    configs: Iterable[ExperimentConfig], out_dir: str | os.PathLike
) -> tuple[list[tuple[ExperimentConfig, Path]], list[Path], list[int]]:
    """Split the grid into (to run or resume, already complete, the trial each of the first
    resumes at: 0 from scratch). Raises ValueError when a file in ``out_dir`` holds another
    configuration than the one the grid maps to it."""
    todo, done, starts = [], [], []
    for cfg, path, found in survey(configs, out_dir):
        if found.kind == "complete":
            done.append(path)
        else:  # missing or damaged (set aside when run): from scratch; unfinished: resumed
            todo.append((cfg, path))
            starts.append(found.trials if found.kind == "unfinished" else 0)
    return todo, done, starts


def survey(configs: Iterable[ExperimentConfig], out_dir: str | os.PathLike) -> list:
    """Every configuration with its file in ``out_dir`` and what the file holds
    (:class:`~pipps.experiments.storage.Existing`: its kind, finished trials and status, e.g. an
    interrupted run). Raises like :func:`plan`."""
    from pipps.experiments.storage import OutputError, existing_result

    out = Path(out_dir)
    rows, seen = [], set()
    for cfg in configs:
        path = out / f"{experiment_name(cfg)}.h5"
        if path in seen:
            raise ValueError(f"two configurations in the sweep map to the same file {path.name}")
        seen.add(path)
        found = existing_result(path, cfg)
        if found.kind == "other":
            raise OutputError(f"{path} holds another configuration ({found.detail}); "
                              "use another output folder, or remove the file to run this one")
        if found.kind == "unreadable":
            raise OutputError(f"{path} cannot be read now ({found.detail}); it is left untouched")
        rows.append((cfg, path, found))
    return rows


BACKENDS = ("local", "ray")


def run_sweep(
    configs: Iterable[ExperimentConfig],
    out_dir: str | os.PathLike,
    *,
    jobs: int | None = None,
    on_done: Callable[[str, str, int, int], None] | None = None,
    backend: str = "local",
    address: str | None = None,
    batched: bool = False,
    batching: str = "auto",
    on_trial: Callable[[dict], None] | None = None,
) -> SweepReport:
    """Run every configuration whose result is not already complete; see the module docstring.

    ``on_done(path, error, finished, total)`` is called as each experiment ends, ``on_trial(event)``
    as each trial starts (``phase="trial"``) and ends (``phase="evaluated"``, with its ``seconds``),
    with the experiment's ``path`` and the worker's ``pid`` and ``cpus`` (local backend, not
    batched). A ``KeyboardInterrupt`` stops the workers (module doc) and is raised again. ``backend``:
    ``"local"`` (``jobs`` worker processes) or ``"ray"`` (at most ``jobs`` Ray tasks in flight on
    the cluster at ``address``; a Ray session this process already has is used as it is).

    ``batched``: the unfinished seeds of each cell run as one batch in this process
    (:func:`pipps.experiments.batched.run_batched`, seed axis computed per ``batching``), one cell
    after the other; cells of methods that cannot be batched (PILCO, the fixed-seed methods) and
    cells with a single unfinished seed run as usual. Unfinished seeds resume from their last
    finished trial, batched with the seeds that stopped after the same trial.
    """
    if jobs is not None and jobs < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if address is not None and backend != "ray":
        raise ValueError("address is only used by the ray backend")
    if batched and backend != "local":
        raise ValueError("batched sweeps run on the local backend (one process, one accelerator)")
    ray = import_ray() if backend == "ray" else None
    from pipps.experiments.storage import check_output_folder, claim_sweep_folder

    start = time.perf_counter()
    configs = list(configs)
    todo, done, _ = plan(configs, out_dir)
    check_output_folder(out_dir)
    claim_sweep_folder(out_dir, configs)
    ran, failed, skipped, notes = [], {}, [str(p) for p in done], {}
    total = len(todo)

    def record(path, outcome, message=""):
        if outcome == "skipped":
            skipped.append(path)
            notes[path] = message
            return
        if outcome == "interrupted":  # a Ray task's worker got SIGINT: not complete, resumable
            outcome, message = "failed", f"interrupted: {message}"
        if outcome == "failed":
            failed[path] = message
        else:
            ran.append(path)
            if message:
                notes[path] = message
        if on_done:
            on_done(path, failed.get(path, ""), len(ran) + len(failed), total)

    if batched:
        todo = _run_batches(todo, batching, record)
    if ray is not None:
        if todo:
            _run_on_ray(ray, todo, len(todo) if jobs is None else jobs, address, record)
    elif todo:
        workers, width = cpu_layout(jobs, len(todo), available_cpus())
        if workers == 1:  # in this process, on every CPU it may use
            for cfg, path in todo:
                record(*_run_one(cfg, str(path), report=on_trial))
        else:
            _run_pool(todo, workers, width, record, on_trial, out_dir)
    return SweepReport(ran, skipped, failed, time.perf_counter() - start, notes)


def _run_pool(todo, workers: int, width: int, record, on_trial, out_dir) -> None:
    """Run ``todo`` on pinned worker processes, passing their trial events to ``on_trial``; on a
    ``KeyboardInterrupt`` stop them (:func:`_stop_workers`) and raise it again."""
    ctx = mp.get_context("spawn")
    events = ctx.Queue() if on_trial is not None else None
    pool = worker_pool(workers, width, events)
    futures = [pool.submit(_run_one, cfg, str(path)) for cfg, path in todo]
    pending = set(futures)
    try:
        while pending:
            finished, pending = cf.wait(pending, timeout=0.5, return_when=cf.FIRST_COMPLETED)
            _drain(events, on_trial)
            for fut in finished:
                record(*fut.result())
        _drain(events, on_trial)
    except KeyboardInterrupt:
        _stop_workers(pool, futures, [str(p) for _, p in todo], out_dir)
        raise
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown(wait=True)


def _drain(events, on_trial) -> None:
    while events is not None:
        try:
            event = events.get_nowait()
        except queues.Empty:
            return
        on_trial(event)


def _stop_workers(pool: cf.ProcessPoolExecutor, futures, paths: list[str], out_dir,
                  grace: float | None = None) -> list[int]:
    """Stop a sweep's workers within ``grace`` seconds (:data:`STOP_GRACE`): cancel what has not
    started, SIGINT every worker (it writes its file as interrupted and starts nothing new), wait
    for the running experiments to end, then kill whatever is left, remove the temporary files of
    the killed and the lock files nobody holds. Returns the pids it had to kill."""
    from pipps.experiments.storage import ResultBusy, ResultLock

    grace = STOP_GRACE if grace is None else grace
    for fut in futures:
        fut.cancel()
    procs = list(getattr(pool, "_processes", {}).values())
    for p in procs:
        try:
            os.kill(p.pid, signal.SIGINT)
        except (ProcessLookupError, TypeError):
            pass
    cf.wait([f for f in futures if not f.cancelled()], timeout=grace)
    pool.shutdown(wait=False, cancel_futures=True)
    deadline = time.monotonic() + 2.0
    for p in procs:
        p.join(max(0.0, deadline - time.monotonic()))
    killed = []
    for p in procs:
        if p.is_alive():
            killed.append(p.pid)
            p.kill()
            p.join(5.0)
    for pid in killed:  # a write cut short leaves its temporary file; the target is intact (atomic writes)
        for tmp in Path(out_dir).glob(f".*.tmp-{pid}"):
            tmp.unlink(missing_ok=True)
    for path in paths:  # the kernel released a killed holder's lock; take it once to remove the file
        try:
            with ResultLock(path):
                pass
        except ResultBusy:  # another sweep's process is writing it
            pass
        except OSError:
            pass
    return killed


def _run_batches(todo, batching: str, record) -> list:
    """Run each cell's unfinished seeds as one batch; return the experiments left to run one by one."""
    from pipps.experiments.batched import check_batchable

    cells: dict = {}
    for cfg, path in todo:
        cells.setdefault(dataclasses.replace(cfg, seed=0), []).append((cfg, path))
    rest = []
    for items in cells.values():
        cfgs = [cfg for cfg, _ in items]
        try:
            check_batchable(cfgs)
        except ValueError:
            rest += items
            continue
        if len(items) == 1:
            rest += items
            continue
        rest += _run_batch(cfgs, [str(p) for _, p in items], batching, record)
    return rest


def _run_batch(cfgs, paths: list[str], batching: str, record) -> list:
    """One cell's seeds as batches, each seed's file written after every trial, under the files'
    locks. Seeds whose file another process holds are skipped, complete ones too. Unfinished seeds
    resume: seeds that stopped after the same trial form one resumed batch (a GPU job cut off
    part-way loses at most the trial in flight); a seed alone at its trial is returned to run
    one by one."""
    from pipps.experiments.batched import run_batched
    from pipps.experiments.results import read_result, write_result
    from pipps.experiments.storage import ResultBusy, ResultLock, existing_result, set_aside

    rest, groups, locks = [], {}, {}
    try:
        for cfg, path in zip(cfgs, paths):
            lock = ResultLock(path)
            try:
                lock.acquire()
            except ResultBusy as err:
                record(path, "skipped", f"running in another process ({err})")
                continue
            found = existing_result(path, cfg)
            if found.kind == "complete":
                lock.release()
                record(path, "skipped", "complete (finished by another process)")
                continue
            if found.kind in ("other", "unreadable"):
                lock.release()
                record(path, "failed", f"OutputError: {path} holds another configuration or cannot be read now "
                                       f"({found.detail}); left untouched")
                continue
            if found.kind == "damaged":
                print(f"{path}: set aside a damaged file as {set_aside(path).name}", file=sys.stderr)
            resume = read_result(path, verify=False) if found.kind == "unfinished" and found.trials else None
            locks[path] = lock
            groups.setdefault(len(resume.trials) if resume else 0, []).append((cfg, path, resume))
        for n, items in sorted(groups.items()):
            if len(items) == 1:  # nothing to batch with: one by one (it takes its lock again)
                cfg, path, _ = items[0]
                locks.pop(path).release()
                rest.append((cfg, Path(path)))
                continue
            b_cfgs, b_paths = [c for c, _, _ in items], [p for _, p, _ in items]
            resumes = [r for _, _, r in items] if n else None

            def write(results, b_paths=b_paths):
                for r, p in zip(results, b_paths):
                    write_result(p, r)

            try:
                results = run_batched(b_cfgs, on_trial=write, batching=batching, resumes=resumes)
            except Exception as err:  # every file already records the failure
                for p in b_paths:
                    record(p, "failed", f"{type(err).__name__}: {err}")
                continue
            finally:
                release_compiled()
            for r, p in zip(results, b_paths):
                record(p, "ran" if r.status == "complete" else "failed", "" if r.status == "complete" else r.error)
        return rest
    finally:
        for lock in locks.values():
            lock.release()


# -- the Ray backend -------------------------------------------------------------------------------


def import_ray():
    """The ``ray`` module, or an ImportError that says how to install it."""
    try:
        import ray
    except ImportError as err:
        raise ImportError("the ray backend needs Ray: pip install 'pipps[ray]'") from err
    return ray


_cpu_locks: list[int] = []  # the open lock files that reserve this process's CPUs; released when it exits


def _pin_to_free_cpus(width: int = 1) -> set[int] | None:
    """Pin this process to ``width`` CPUs of its CPU set that no other process pinned this way holds.

    Each CPU has a lock file in the node's temporary folder; the first ``width`` this process can
    lock (``flock``, released by the kernel when the process exits) are its CPUs. Where none is
    free (more such processes than CPUs) it shares one (pid round robin), still one XLA thread;
    where fewer than ``width`` are free it takes those. Returns the CPUs, or None without Linux
    CPU affinity.
    """
    if not hasattr(os, "sched_setaffinity"):
        return None
    import fcntl

    cpus = sorted(os.sched_getaffinity(0))
    chosen: set[int] = set()
    try:
        folder = Path(tempfile.gettempdir()) / "pipps-cpu-locks"
        folder.mkdir(exist_ok=True)
        for cpu in cpus:
            if len(chosen) == width:
                break
            fd = os.open(folder / f"cpu{cpu}", os.O_CREAT | os.O_RDWR, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                continue
            _cpu_locks.append(fd)
            chosen.add(cpu)
    except OSError:  # no usable lock folder: keep the round-robin choice
        pass
    chosen = chosen or {cpus[os.getpid() % len(cpus)]}
    os.sched_setaffinity(0, chosen)
    return chosen


def _start_worker(width: int = 1, events=None, sigterm: bool = False) -> None:
    """A sweep worker's set-up, before JAX runs: pin to ``width`` free CPUs, switch on float64,
    keep the queue its progress goes to, and take SIGINT as "stop after writing" (:func:`_on_sigint`);
    ``sigterm``: SIGTERM too (a pool worker, which a signal to the sweep's whole process group, as
    ``timeout`` or a service manager sends, reaches beside the sweep; a Ray worker leaves SIGTERM to Ray)."""
    from pipps.precision import enable_float64

    global _events, _in_worker, _takes_sigterm
    _events, _in_worker, _takes_sigterm = events, True, sigterm
    signal.signal(signal.SIGINT, _on_sigint)
    if sigterm:
        signal.signal(signal.SIGTERM, _on_sigint)
    _pin_to_free_cpus(width)
    enable_float64()


def _pinned(fn, *args):
    """Ray task body: set the worker up (:func:`_start_worker`) before ``fn`` runs, then call it."""
    _start_worker(1)
    return fn(*args)


#: how many times Ray runs an experiment's task again after its worker process or its node died
#: (Ray's default for tasks, fixed here because the module doc and docs/reliability.md rely on it);
#: an exception the experiment raises is not retried: its file records it
RAY_RETRIES = 3


def ray_task(ray):
    """The remote function every sweep task runs: one CPU, a fresh worker process per task, run
    again elsewhere (:data:`RAY_RETRIES`) when its node dies.

    ``JAX_PLATFORMS`` travels with the task (``runtime_env``) when, and only when, it is set here.
    """
    options = dict(num_cpus=1, max_calls=1, max_retries=RAY_RETRIES, retry_exceptions=False)
    if "JAX_PLATFORMS" in os.environ:
        options["runtime_env"] = {"env_vars": {"JAX_PLATFORMS": os.environ["JAX_PLATFORMS"]}}
    return ray.remote(**options)(_pinned)


def _run_one_on_node(cfg: ExperimentConfig, path: str) -> tuple[str, str, str, str]:
    """:func:`_run_one` in a Ray task, with the name of the node that ran it."""
    import platform

    return (*_run_one(cfg, path), platform.node())


def _run_on_ray(ray, todo, jobs: int, address: str | None, record) -> None:
    """Submit ``todo`` as Ray tasks, at most ``jobs`` in flight, and ``record`` each as it ends.

    Each task carries its file's name as its Ray task name (``pipps NAME.h5``), for Ray's task
    listings. A task that says it ran but whose file this process cannot see wrote it on a disk of
    its node only: a failure, named as such."""
    started = not ray.is_initialized()
    if started:
        own = signal.getsignal(signal.SIGTERM) if threading.current_thread() is threading.main_thread() else None
        ray.init(address=address)  # sets a SIGTERM handler that exits at once
        if callable(own):  # the caller's handler (the CLI's stops the sweep as Ctrl-C does) stays
            signal.signal(signal.SIGTERM, own)
    try:
        task = ray_task(ray)
        queue = [(cfg, str(path), str(path.resolve())) for cfg, path in todo]
        in_flight = {}
        while queue or in_flight:
            while queue and len(in_flight) < jobs:
                cfg, name, absolute = queue.pop(0)
                ref = task.options(name=f"pipps {Path(name).name}").remote(_run_one_on_node, cfg, absolute)
                in_flight[ref] = (name, absolute)
            (ref,), _ = ray.wait(list(in_flight), num_returns=1)
            name, absolute = in_flight.pop(ref)
            try:
                _, outcome, message, node = ray.get(ref)
            except ray.exceptions.RayError as err:  # e.g. out of retries; the file keeps its finished trials
                first = str(err).strip().splitlines()[0] if str(err).strip() else "no message"
                record(name, "failed", f"{type(err).__name__}: {first} (the file keeps every finished trial; "
                                       "running the same sweep again resumes it)")
                continue
            if outcome == "ran" and not os.path.exists(absolute):
                outcome, message = "failed", (
                    f"OutputError: node {node} wrote {absolute}, but this machine does not see it: --out must be "
                    "a folder that every node and the launching machine share at the same path (the file is on "
                    f"{node}; copy it here to keep it)")
            record(name, outcome, message)
    finally:
        if started:
            ray.shutdown()  # stops a local instance this call started; only disconnects from a cluster
