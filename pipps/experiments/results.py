"""Experiment results in HDF5 (h5py): one file per experiment, written atomically.

The schema (version :data:`SCHEMA_VERSION`) is documented in docs/results-schema.md. In short::

    /                      attrs: schema_version, status (running|complete|failed|interrupted), error,
                                  config_json, checksum, wall_seconds, num_trials_done,
                                  final_return, success
    /config                attrs: every ExperimentConfig field (None stored as "__none__")
    /versions              attrs: pipps, jax, jaxlib, numpy, h5py, python, platform, device, host
    /eval_return           (n,) mean evaluation return per finished trial
    /upright_fraction      (n,)
    /trials/NNN            a TrialResult (pipps.experiments.records); attrs kind, eval_return, upright_fraction
        states observations actions costs valid eval_returns eval_upright policy eval_balanced
        timings/           Timings: attrs, seconds per phase
        gp/                GPRecord: log_lengthscale log_signal log_noise objective [inducing ...];
                           attrs sparse, num_points, messages, capacity
        opt_trace/         StepTrace (per policy step) or SearchTrace (per quasi-Newton line search)
        diagnostics/       Diagnostics: per time step k_lr var_rp var_lr, k_lr_per_iteration, nonfinite_steps
        predicted/         ParticlePrediction (particles (T+1, S_p, D), cost_mean) or MomentPrediction

A trial is written by walking its records' fields (:func:`_write_record`): each field says whether
it is an attribute or a dataset, a nested record is a subgroup; the reader walks them back.

Every write goes to a temporary file in the same folder, is flushed to disk and then renamed
over the target (``os.replace``), so a reader never sees a half-written file under the final
name. ``checksum`` is a SHA-256 over the configuration and every trial's evaluation returns and
policy; :func:`check_result` recomputes it, so a file altered or damaged after writing is
reported as corrupt, not read.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import platform
import sys
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from pipps.experiments.config import (ExperimentConfig, UnavailableTask, config_difference, config_hash, from_dict,
                                      same_experiment, stored_dict)
from pipps.experiments.records import ExperimentResult, TrialResult, required_fields

SCHEMA_VERSION = 1
_TRIAL_ARRAYS = ("states", "observations", "actions", "costs", "valid", "eval_returns", "eval_upright", "policy")
NONE = "__none__"


class ResultError(ValueError):
    """A result file is missing, unreadable, incomplete or corrupt; the message says which."""


def versions() -> dict[str, str]:
    import h5py as _h5py
    import jax
    import jaxlib

    import pipps

    try:
        device = str(jax.devices()[0].device_kind)
    except Exception:  # pragma: no cover - no backend
        device = "unknown"
    return {"pipps": pipps.__version__, "code": code_version(), "jax": jax.__version__, "jaxlib": jaxlib.__version__,
            "numpy": np.__version__, "h5py": _h5py.__version__, "python": sys.version.split()[0],
            "platform": platform.platform(), "device": device,
            "host": platform.node()}  # the machine (a cluster's node) that wrote the file, i.e. ran its last trial


@functools.cache
def code_version() -> str:
    """The git commit of the pipps source that is running, ``+dirty`` when ``pipps/`` differs from
    it, or ``unknown`` outside a git checkout (an installed wheel): stored in every result file.

    A copied source tree can declare its commit in ``PIPPS_CODE_VERSION``: a lent GPU machine gets
    the working tree without this repository's ``.git`` (or with one at an older commit, so git
    there reports that commit ``+dirty``). A declared commit is stored as ``COMMIT (declared)``,
    with what git reports there appended, so a reader sees that git did not check it."""
    import os

    found = _git_version()
    declared = os.environ.get("PIPPS_CODE_VERSION", "").strip()
    if not declared:
        return found
    return f"{declared} (declared)" if found == "unknown" else f"{declared} (declared; git there: {found})"


def _git_version() -> str:
    import subprocess

    root = Path(__file__).resolve().parents[2]
    try:
        top = subprocess.run(["git", "-C", str(root), "rev-parse", "--show-toplevel"], capture_output=True,
                             text=True, timeout=10)
        if top.returncode != 0 or Path(top.stdout.strip()).resolve() != root:
            return "unknown"  # not the checkout pipps runs from (e.g. a wheel inside some other repository)
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=10)
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--", "pipps"],
                               capture_output=True, text=True, timeout=10)
        return head.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _checksum(config_json: str, trials) -> str:
    h = hashlib.sha256(config_json.encode())
    for t in trials:
        for arr in (t["eval_returns"], t["policy"]):
            h.update(np.ascontiguousarray(np.asarray(arr, dtype=np.float64)).tobytes())
    return h.hexdigest()


def _config_json(cfg: ExperimentConfig) -> str:
    return json.dumps(stored_dict(cfg), sort_keys=True)


def _write_loose(group: h5py.Group, name: str, value: Any) -> None:
    """An entry a record keeps in ``extra``: strings and scalars as attributes, the rest as datasets."""
    if isinstance(value, str) or (isinstance(value, (bool, int, float, np.generic)) and np.ndim(value) == 0):
        group.attrs[name] = value.item() if isinstance(value, np.generic) else value
    elif value is not None:
        group.create_dataset(name, data=np.asarray(value), compression="gzip" if np.size(value) > 256 else None)


def _write_record(group: h5py.Group, record) -> None:
    """Store a typed record (:mod:`pipps.experiments.records`) in ``group``, field by field as its
    metadata says: attributes, datasets, nested records as subgroups; None is left out."""
    for f in dataclasses.fields(record):
        how, value = f.metadata.get("h5"), getattr(record, f.name)
        if value is None or how is None:
            continue
        if how == "attr":
            group.attrs[f.name] = f.metadata["convert"](value)
        elif how == "array":
            value = np.asarray(value, dtype=f.metadata["dtype"])
            group.create_dataset(f.name, data=value,
                                 compression="gzip" if f.metadata["compress"] and value.size > 256 else None)
        elif how == "group":
            _write_record(group.create_group(f.name), value)
        elif how == "extra":
            for name, v in value.items():
                _write_loose(group, name, v)


def _write_trial(group: h5py.Group, t: TrialResult) -> None:
    group.attrs["eval_return"] = t.eval_return  # derived, for readers that look at one number
    group.attrs["upright_fraction"] = t.upright_fraction
    _write_record(group, t)


def write_result(path: str | os.PathLike, result: ExperimentResult) -> None:
    """Write ``result`` to ``path`` atomically (temporary file, fsync, rename)."""
    from pipps.reporting.verdicts import criterion, judge_return

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    cfg_json = _config_json(result.config)
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs["schema_version"] = SCHEMA_VERSION
            f.attrs["status"] = result.status
            f.attrs["error"] = result.error
            f.attrs["config_json"] = cfg_json
            f.attrs["config_hash"] = config_hash(result.config)
            f.attrs["wall_seconds"] = float(result.wall_seconds)
            f.attrs["resumed_at"] = np.asarray(result.resumed_at, dtype=np.int64)
            f.attrs["num_trials_done"] = len(result.trials)
            f.attrs["final_return"] = float(result.final_return)
            f.attrs["success"] = bool(result.success)
            if criterion(result.config).threshold is not None:  # a task with a return threshold (the cart-pole's)
                f.attrs["return_success"] = bool(result.status == "complete" and result.trials
                                                 and judge_return(result.config, result.trials[-1]))
            f.attrs["checksum"] = _checksum(cfg_json, [dict(eval_returns=t.eval_returns, policy=t.policy)
                                                       for t in result.trials])
            f.create_group("config").attrs.update(
                {k: (NONE if v is None else (list(v) if isinstance(v, tuple) else v))
                 for k, v in stored_dict(result.config).items()})
            f.create_group("versions").attrs.update(versions())
            f.create_dataset("eval_return", data=np.array([t.eval_return for t in result.trials], dtype=float))
            f.create_dataset("upright_fraction", data=np.array([t.upright_fraction for t in result.trials], dtype=float))
            f.create_dataset("balanced_fraction", data=np.array([t.balanced_fraction for t in result.trials], dtype=float))
            trials = f.create_group("trials")
            for t in result.trials:
                _write_trial(trials.create_group(f"{t.index:03d}"), t)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def study_file(kind: str) -> str:
    """What a file of ``pipps study`` or ``pipps bench`` (its ``study`` attribute: ``kind``) is, for a
    message where an experiment result was expected."""
    command = "pipps bench" if kind == "bench" else f"pipps study {kind}"
    return f"a {kind} study file ({command} output), not an experiment result"


def verify_result(path: Path) -> tuple[str, ExperimentConfig, int]:
    """Check a result file's integrity whatever its status: (status, configuration, trials stored).

    The file opens as HDF5, has this schema version, its trials are 000, 001, ... with every
    required array, and the checksum over the configuration and those trials matches.
    """
    if not path.exists():
        raise ResultError(f"{path}: no such result file")
    try:
        with h5py.File(path, "r") as f:
            if "study" in f.attrs and "config_json" not in f.attrs:
                raise ResultError(f"{path}: {study_file(str(f.attrs['study']))}")
            version = f.attrs.get("schema_version")
            if version != SCHEMA_VERSION:
                raise ResultError(f"{path}: schema version {version!r}, expected {SCHEMA_VERSION}")
            status = str(f.attrs.get("status"))
            cfg_json = f.attrs["config_json"]
            cfg = from_dict(json.loads(cfg_json))
            names = sorted(f["trials"].keys())
            recorded = f.attrs.get("num_trials_done")
            if recorded is not None and len(names) != int(recorded):
                raise ResultError(f"{path}: {len(names)} trials stored, the file records {int(recorded)}")
            if names != [f"{i:03d}" for i in range(len(names))]:
                raise ResultError(f"{path}: trial groups {names} are not 000, 001, ... in order")
            trials = []
            for n in names:
                g = f["trials"][n]
                missing = [a for a in _TRIAL_ARRAYS if a not in g]
                if missing:
                    raise ResultError(f"{path}: trial {n} lacks {missing}")
                trials.append(dict(eval_returns=g["eval_returns"][()], policy=g["policy"][()]))
            if _checksum(cfg_json, trials) != f.attrs.get("checksum"):
                raise ResultError(f"{path}: checksum mismatch (the file was altered or damaged)")
            error = str(f.attrs.get("error", ""))
    except (ResultError, UnavailableTask):  # an intact file whose task is not available here says so, not "unreadable"
        raise
    except Exception as err:  # h5py raises OSError/KeyError/... on damaged files
        raise ResultError(f"{path}: unreadable result file ({type(err).__name__}: {err})") from err
    if status == "failed":
        status = f"failed: {error}"
    return status, cfg, len(names)


def check_result(path: str | os.PathLike) -> str:
    """``"complete"`` for a whole, verified result; otherwise raise :class:`ResultError` saying why.

    Checks: the file opens as HDF5, has this schema version, says ``status=complete``, holds
    one group per trial of its configuration with every required array, and its checksum matches.
    """
    path = Path(path)
    status, cfg, n = verify_result(path)
    if status == "interrupted" or status.startswith("failed: KeyboardInterrupt"):  # older files said failed
        raise ResultError(f"{path}: interrupted after {n} of {cfg.num_trials} trials, resumable (pipps run --resume "
                          f"--out {path}, or the sweep that made it)")
    if status != "complete":
        raise ResultError(f"{path}: status is {status.split(':')[0]!r} (not complete)"
                          + (status[len("failed"):] if status.startswith("failed") else ""))
    if n != cfg.num_trials:
        raise ResultError(f"{path}: {n} trials stored, the configuration has {cfg.num_trials}")
    return "complete"


def stored_config(path: str | os.PathLike) -> ExperimentConfig:
    """The configuration of a verified (complete or partial) result file; ResultError if it is damaged."""
    return verify_result(Path(path))[1]


def partial_result(path: str | os.PathLike, cfg: ExperimentConfig) -> ExperimentResult | None:
    """What a sweep resumes ``cfg`` from: the finished trials of an intact, unfinished result of
    ``cfg`` at ``path``, or None when there is nothing to resume (no file, a damaged one, or no
    trial stored). A file of another configuration raises ResultError naming the settings that
    differ (a sweep must not overwrite, or skip, someone else's experiment)."""
    path = Path(path)
    try:
        status, stored, n = verify_result(path)
    except ResultError:
        return None
    if not same_experiment(stored, cfg):
        raise ResultError(f"{path}: holds another configuration ({config_difference(stored, cfg)}); "
                          "use another output folder or remove the file")
    if n == 0 or n > cfg.num_trials:
        return None
    return read_result(path, verify=False)


def is_complete(path: str | os.PathLike) -> bool:
    try:
        return check_result(path) == "complete"
    except ResultError:
        return False


def _entries(g: h5py.Group) -> dict[str, Any]:
    """A group's attributes and datasets by name (a name is one or the other: files resumed by older
    versions stored some scalars as datasets, docs/results-schema.md)."""
    out: dict[str, Any] = {k: v for k, v in g.attrs.items()}
    for k, v in g.items():
        if isinstance(v, h5py.Dataset):
            out[k] = v[()]
    return out


def _read_record(types: tuple[type, ...], g: h5py.Group, **known):
    """The typed record ``g`` holds: the first of ``types`` whose required fields are all there."""
    entries = _entries(g)
    present = set(entries) | set(g.keys()) | set(known)
    cls = next((c for c in types if required_fields(c) <= present), None)
    if cls is None:
        raise ResultError(f"{g.file.filename}: {g.name} holds {sorted(present)}, none of "
                          f"{', '.join(c.__name__ for c in types)}")
    kwargs: dict[str, Any] = dict(known)
    for f in dataclasses.fields(cls):
        how = f.metadata.get("h5")
        if how == "group" and f.name in g:
            kwargs[f.name] = _read_record(f.metadata["types"], g[f.name])
        elif how == "attr" and f.name in entries:
            kwargs[f.name] = f.metadata["convert"](entries.pop(f.name))
        elif how == "array" and f.name in entries:
            kwargs[f.name] = np.asarray(entries.pop(f.name))
    if any(f.metadata.get("h5") == "extra" for f in dataclasses.fields(cls)):
        kwargs["extra"] = entries  # what no field took
    return cls(**kwargs)


def read_result(path: str | os.PathLike, *, verify: bool = True) -> ExperimentResult:
    """Load a result file (verified by :func:`check_result` unless ``verify=False``)."""
    if verify:
        check_result(path)
    with h5py.File(path, "r") as f:
        cfg = from_dict(json.loads(f.attrs["config_json"]))
        trials = [_read_record((TrialResult,), f["trials"][n], index=int(n)) for n in sorted(f["trials"].keys())]
        return ExperimentResult(cfg, trials, str(f.attrs["status"]), str(f.attrs["error"]),
                                float(f.attrs["wall_seconds"]), [int(i) for i in f.attrs.get("resumed_at", [])])


def read_summary(path: str | os.PathLike) -> dict[str, Any]:
    """The few numbers the tables need, from a verified file: config, success, final return, wall time."""
    check_result(path)
    with h5py.File(path, "r") as f:
        last = f["trials"][sorted(f["trials"].keys())[-1]]
        return {"config": from_dict(json.loads(f.attrs["config_json"])), "success": bool(f.attrs["success"]),
                "final_return": float(f.attrs["final_return"]), "wall_seconds": float(f.attrs["wall_seconds"]),
                "eval_return": f["eval_return"][()], "upright_fraction": f["upright_fraction"][()], "path": str(path),
                # absent in files written before the physical criterion was stored (NaN per trial)
                "balanced_fraction": (f["balanced_fraction"][()] if "balanced_fraction" in f
                                      else np.full(len(f["eval_return"]), np.nan)),
                "final_eval_returns": last["eval_returns"][()],
                "final_eval_upright": last["eval_upright"][()],
                "final_trial_return": float(np.sum(last["costs"][()])),  # the final trial run on the system
                "final_trial_states": last["states"][()], "final_trial_valid": last["valid"][()],
                "final_eval_balanced": last["eval_balanced"][()] if "eval_balanced" in last else None}
