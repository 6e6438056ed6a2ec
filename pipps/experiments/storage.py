"""Where results go: output checks before any work, one writer per result file, and what an existing
file means for a new run (docs/reliability.md).

A result file is an experiment's identity: its configuration (``config_json``, ``config_hash``)
names what produced it, and its name (:func:`pipps.experiments.config.experiment_name`) is unique
to that configuration. This module keeps the two honest:

* :func:`check_output_file` / :func:`check_output_folder` verify, before anything is computed,
  that the result can be written there (the folder exists or can be made, is a folder, and a file
  can be created in it), raising :class:`OutputError` with a one-line reason.
* :class:`ResultLock` is an exclusive, non-blocking lock on one result file (``flock`` on a hidden
  ``.NAME.lock`` beside it, released by the kernel if the holder dies). Every process that writes
  a result holds it for the whole experiment and decides what to do with an existing file only
  once it holds it, so two runs or sweeps never write one file, and a sweep never reruns an
  experiment that another process finished in the meantime.
* :func:`existing_result` classifies what is at a path for a configuration: nothing, a complete or
  an unfinished result of the same experiment, another experiment, or a damaged file.
* :func:`claim_sweep_folder` writes or checks the folder's manifest ``.pipps-sweep.json`` (the
  experiment preset and the settings that depart from it), so one folder holds one protocol.
* :func:`check_new_file` and :func:`publish` guard every other output (a study, a bench, a
  recording, a PNG): an existing file is replaced only with ``--overwrite``, an experiment result
  never (:func:`is_experiment_result`), and the new file is written beside its target and moved
  into place whole.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import json
import os
import time
from pathlib import Path
from typing import Any, Iterator

from pipps.experiments.config import ExperimentConfig, config_difference, departures, same_experiment


class OutputError(ValueError):
    """A result cannot be written where asked, or would replace another one; the message says which and why."""


class ResultBusy(OutputError):
    """Another process holds the result file's lock (it is running that experiment now)."""


# -- output paths ------------------------------------------------------------------------------------


def _probe_folder(folder: Path) -> None:
    """Create and remove a file in ``folder`` (which exists): the one test of writability that does not lie."""
    probe = folder / f".pipps-probe-{os.getpid()}"
    try:
        fd = os.open(probe, os.O_CREAT | os.O_WRONLY | os.O_EXCL, 0o644)
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        raise OutputError(f"cannot write in {folder}: {err.strerror or err}") from None


def _make_folder(folder: Path, create: bool) -> None:
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"{folder} is a file, not a folder")
    if not folder.exists():
        for parent in folder.parents:  # the nearest existing ancestor must be a folder
            if parent.exists():
                if not parent.is_dir():
                    raise OutputError(f"cannot create {folder}: {parent} is a file, not a folder")
                if not create:
                    _probe_folder(parent)
                break
        if not create:
            return
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise OutputError(f"cannot create folder {folder}: {err.strerror or err}") from None
    _probe_folder(folder)


def check_output_file(path: str | os.PathLike, *, create: bool = True) -> Path:
    """``path`` as a result file that can be written: its folder exists (made if ``create``) and is
    writable, and ``path`` is not a folder. Raises :class:`OutputError`."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{path} is a folder; give a result file's name (…/NAME.h5)")
    if path.suffix != ".h5":
        raise OutputError(f"{path}: a result file's name must end in .h5")
    _make_folder(path.parent if str(path.parent) else Path("."), create)
    return path


def check_output_folder(path: str | os.PathLike, *, create: bool = True) -> Path:
    """``path`` as a result folder: a folder (made if ``create``; with ``create=False`` its nearest
    existing ancestor must be writable) in which files can be written. Raises :class:`OutputError`."""
    path = Path(path)
    _make_folder(path, create)
    return path


def is_experiment_result(path: str | os.PathLike) -> bool:
    """Whether ``path`` is an HDF5 file that holds an experiment result (a ``config_json`` at its
    root), intact or not; a study, a bench, a recording or anything else is not."""
    import h5py

    path = Path(path)
    if not path.is_file():
        return False
    try:
        with h5py.File(path, "r") as f:
            return "config_json" in f.attrs or ("trials" in f and "schema_version" in f.attrs)
    except Exception:  # not HDF5, or unreadable: not a result this library wrote
        return False


def check_new_file(path: str | os.PathLike, *, overwrite: bool, option: str, suffix: str | None = None,
                   inputs: tuple = (), command: str = "pipps") -> Path:
    """``path`` as a new output of ``command`` (given as ``option``), checked before any work.

    Refused, with :class:`OutputError` naming the file and the option: a folder; a name without
    ``suffix``; one of the ``inputs`` the command reads; an experiment result, even with
    ``overwrite`` (no command but ``pipps run --overwrite`` replaces one); any other existing file
    unless ``overwrite``. The folder is made and probed as for a result (:func:`check_output_file`).
    """
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{option} {path}: is a folder; give a file name")
    if suffix is not None and path.suffix != suffix:
        raise OutputError(f"{option} {path}: the name must end in {suffix}")
    if path.exists():
        same = [p for p in inputs if Path(p).exists() and os.path.samefile(p, path)]
        if same:
            raise OutputError(f"{option} {path}: is a file this command reads; pick another {option}")
        if is_experiment_result(path):
            raise OutputError(f"{path} is an experiment result; {command} never writes over one, not even with "
                              f"--overwrite: pick another {option} (or move the result away yourself)")
        if not overwrite:
            raise OutputError(f"{path} exists; {command} replaces it only with --overwrite, or pick another {option}")
    _make_folder(path.parent if str(path.parent) else Path("."), True)
    return path


@contextlib.contextmanager
def publish(path: str | os.PathLike, *, overwrite: bool, command: str = "pipps") -> Iterator[Path]:
    """Yield a temporary name beside ``path`` (same suffix) to write the new file to; when the block
    ends without an error it becomes ``path`` in one step: renamed over an existing file only with
    ``overwrite`` (never over an experiment result that appeared meanwhile), else linked into place,
    so a file that appeared since :func:`check_new_file` is not replaced. On an error the temporary
    file is removed."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    try:
        yield tmp
        if not tmp.exists():
            raise OutputError(f"{path}: nothing was written")
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        if is_experiment_result(path):
            raise OutputError(f"{path} became an experiment result meanwhile; {command} leaves it alone")
        if overwrite:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path)
            except FileExistsError:
                raise OutputError(f"{path} appeared while {command} ran; it is left alone (--overwrite "
                                  "replaces it)") from None
            except OSError:  # a filesystem without hard links: check, then rename
                if path.exists():
                    raise OutputError(f"{path} appeared while {command} ran; it is left alone (--overwrite "
                                      "replaces it)") from None
                os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


# -- one writer per result ---------------------------------------------------------------------------


def lock_path(path: str | os.PathLike) -> Path:
    path = Path(path)
    return path.with_name(f".{path.name}.lock")


class ResultLock:
    """Exclusive lock on one result file for one process (module doc). Use as a context manager;
    raises :class:`ResultBusy` at once if another process holds it. Not re-entrant."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.lock = lock_path(self.path)
        self._fd: int | None = None

    def acquire(self) -> "ResultLock":
        import fcntl

        while True:
            try:
                fd = os.open(self.lock, os.O_CREAT | os.O_RDWR, 0o644)
            except OSError as err:
                raise OutputError(f"cannot create the lock file {self.lock}: {err.strerror or err}") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as err:
                if err.errno in (errno.ENOSYS, errno.EOPNOTSUPP, errno.ENOLCK):  # a filesystem without flock
                    import warnings

                    warnings.warn(f"{self.lock}: this filesystem does not support flock ({err.strerror}); "
                                  "running without the lock: do not start two sweeps on this folder", stacklevel=2)
                    self._fd = fd
                    return self
                os.close(fd)
                if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    holder = _read_holder(self.lock)
                    raise ResultBusy(f"{self.path} is being written by another process{holder}; "
                                     "wait for it or pick another output") from None
                raise OutputError(f"cannot lock {self.lock}: {err.strerror or err}") from None
            # the previous holder may have removed the lock file between our open and flock: retry on a live one
            try:
                same = os.fstat(fd).st_ino == os.stat(self.lock).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()} {os.uname().nodename if hasattr(os, 'uname') else ''}\n".encode())
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is None:
            return
        try:
            os.unlink(self.lock)  # while still held: a waiting process re-checks the inode (acquire)
        except OSError:
            pass
        os.close(self._fd)
        self._fd = None

    def __enter__(self) -> "ResultLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def _read_holder(lock: Path) -> str:
    try:
        text = lock.read_text().split()
    except OSError:
        return ""
    return f" (pid {text[0]}{' on ' + text[1] if len(text) > 1 else ''})" if text else ""


# -- what is already there -------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Existing:
    """What a path holds for a configuration. ``kind``: ``missing``, ``complete`` (this experiment,
    finished), ``unfinished`` (this experiment, ``trials`` of them stored), ``other`` (another
    experiment; ``detail`` names the settings that differ), ``damaged`` (``detail`` says why; a sweep sets
    it aside) or ``unreadable`` (another schema version, or a file another program holds: left alone)."""

    kind: str
    trials: int = 0
    detail: str = ""
    status: str = ""  # the file's status (running, complete, failed, interrupted) where it reads

    @property
    def interrupted(self) -> bool:
        """Stopped by Ctrl-C: ``interrupted``, or a file written before that status existed, which
        recorded the stop as ``failed`` with a ``KeyboardInterrupt``."""
        return self.status == "interrupted" or (self.status == "failed" and self.detail.startswith("KeyboardInterrupt"))

    def describe(self, total: int) -> str:
        """What an unfinished file holds, for a sweep's plan: ``trials 0-3 of 0-15 kept (interrupted, resumable)``."""
        kept = f"trials 0-{self.trials - 1} of 0-{total - 1} kept" if self.trials else "no trial kept"
        if self.interrupted:
            return f"{kept} (interrupted, resumable)"
        if self.status == "failed":
            return f"{kept} (failed: {self.detail.splitlines()[0] if self.detail else 'no message'}; resumable)"
        if self.status == "running":
            return f"{kept} (stopped while running, or running elsewhere; resumable)"
        return kept


def existing_result(path: str | os.PathLike, cfg: ExperimentConfig) -> Existing:
    from pipps.experiments.results import ResultError, verify_result

    path = Path(path)
    if not path.exists():
        return Existing("missing")
    try:
        status, stored, n = verify_result(path)
    except ResultError as err:
        text = str(err)
        if "schema version" in text or "lock" in text.lower():  # newer pipps, or held open elsewhere: not damage
            return Existing("unreadable", detail=text)
        return Existing("damaged", detail=text)
    word, _, error = status.partition(": ")
    if not same_experiment(stored, cfg):
        return Existing("other", n, config_difference(stored, cfg), word)
    if status == "complete" and n == cfg.num_trials:
        return Existing("complete", n, status=word)
    return Existing("unfinished", n, error, word)


def set_aside(path: str | os.PathLike) -> Path:
    """Rename a damaged file out of the way (``NAME.h5.damaged-TIMESTAMP``) instead of overwriting it."""
    path = Path(path)
    target = path.with_name(f"{path.name}.damaged-{time.strftime('%Y%m%dT%H%M%S')}-{os.getpid()}")
    os.replace(path, target)
    return target


# -- the sweep folder's manifest ----------------------------------------------------------------------

MANIFEST = ".pipps-sweep.json"


def _manifest_of(cfg: ExperimentConfig) -> dict[str, Any]:
    """``cfg``'s experiment preset and its departures from it, as they read back from JSON."""
    text = json.dumps({"protocol": cfg.protocol, "settings": {k: v for k, (v, _) in sorted(departures(cfg).items())}},
                      sort_keys=True, default=list)
    return json.loads(text)  # tuples as lists


def _sweep_manifest(configs: list[ExperimentConfig]) -> dict[str, Any]:
    """The manifest of a sweep: its experiment preset and the union of its experiments' departures.
    A method departs only in the settings it uses, so PILCO's cells of a ``--set num_particles=…``
    sweep follow the preset; two experiments that give one setting two values are refused."""
    mine = _manifest_of(configs[0])
    for cfg in configs[1:]:
        theirs = _manifest_of(cfg)
        clash = [k for k, v in theirs["settings"].items() if mine["settings"].get(k, v) != v]
        if theirs["protocol"] != mine["protocol"] or clash:
            raise OutputError("the sweep's experiments depart from their preset in different settings "
                              f"({theirs['settings']} against {mine['settings']})")
        mine["settings"].update(theirs["settings"])
    return mine


def _follows(cfg: ExperimentConfig, manifest: dict[str, Any]) -> bool:
    """Whether ``cfg`` belongs in a folder of ``manifest``: the same experiment preset, and departures
    from it that are the manifest's own in every setting its method uses."""
    wanted = {k: v for k, v in manifest.get("settings", {}).items() if k not in cfg.method_spec.unused}
    return _manifest_of(cfg) == {"protocol": manifest.get("protocol"), "settings": wanted}


def claim_sweep_folder(folder: str | os.PathLike, configs: list[ExperimentConfig], *, write: bool = True) -> None:
    """Check (and, with ``write``, create) the folder's manifest: every experiment a sweep puts in a
    folder follows one experiment preset with one set of departures from it, each in the settings
    its method uses (:func:`_follows`). A sweep whose settings differ from the folder's is refused
    by name before anything runs."""
    if not configs:
        return
    mine = _sweep_manifest(configs)
    path = Path(folder) / MANIFEST
    text = json.dumps(mine, sort_keys=True)
    if not path.exists():  # a folder from before manifests, or filled by `pipps run`: its files decide
        _check_existing_files(Path(folder), mine)
    if write:  # written whole to a temporary file, then linked into place: never seen half-written
        tmp = path.with_name(f".{MANIFEST}.tmp-{os.getpid()}")
        try:
            tmp.write_text(text + "\n")
            os.link(tmp, path)
            return
        except FileExistsError:
            pass
        except OSError as err:
            raise OutputError(f"cannot write {path}: {err.strerror or err}") from None
        finally:
            tmp.unlink(missing_ok=True)
    if not path.exists():
        return
    try:
        theirs = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise OutputError(f"{path} is not a readable sweep manifest ({err}); remove it or use another folder") from None
    if not all(_follows(cfg, theirs) for cfg in configs):
        raise OutputError(f"{folder} holds a sweep run with {_show(theirs)}; this one has {_show(mine)}. "
                          "One folder holds one protocol: use another --out")


def _show(m: dict[str, Any]) -> str:
    extra = ", ".join(f"{k}={v}" for k, v in m.get("settings", {}).items()) or "no --set"
    return f"--preset {m.get('protocol')} with {extra}"


def _check_existing_files(folder: Path, mine: dict[str, Any]) -> None:
    from pipps.experiments.results import ResultError, verify_result

    if not folder.is_dir():
        return
    for path in sorted(folder.glob("*.h5")):
        try:
            _, stored, _ = verify_result(path)
        except ResultError:
            continue  # damaged files are set aside when their experiment runs
        if not _follows(stored, mine):
            theirs = _manifest_of(stored)
            raise OutputError(f"{folder} holds {path.name}, run with {_show(theirs)}; this sweep has {_show(mine)}. "
                              "One folder holds one protocol: use another --out")
