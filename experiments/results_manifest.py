#!/usr/bin/env python3
"""Print a Markdown manifest of committed result files: per folder, one table row per .h5 file.

    python experiments/results_manifest.py                 # every folder under results/
    python experiments/results_manifest.py results/thesis  # only these folders
    python experiments/results_manifest.py > results/MANIFEST.md

Experiment results (docs/results-schema.md) get: file, method, task / cost, k, seed, status, trials
finished / configured, the evaluated return of the last finished trial (the final return of a
complete file), the trials at which a later session resumed it (`resumed_at`), the code version
(`/versions` `code`: the git commit of the session that wrote the file last) and the device.
Gradient-study files (`pipps study`, `pipps bench`) get a table of their own.

Read-only (files are opened with h5py in mode "r"); needs only the standard library, h5py and numpy.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import h5py
import numpy as np

NONE = "__none__"


def _text(value) -> str:
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.ndarray) and value.shape == ():
        return _text(value[()])
    return str(value)


def _number(value) -> str:
    x = float(value)
    return str(int(x)) if x.is_integer() else f"{x:g}"


def short_code(code: str | None) -> str:
    """The code version with every 40-digit commit cut to its first 7 digits; `—` when not recorded."""
    if not code:
        return "— (not recorded)"
    return re.sub(r"\b([0-9a-f]{7})[0-9a-f]{33}\b", r"\1", code)


def _cost(name: str, task: str, stored: str) -> str:
    if stored and stored != NONE:
        return stored
    # the cost is in the file name, `<task>_<cost>_k<k>_...`, when the configuration left the task's default
    m = re.match(re.escape(task) + r"_(.+?)_k\d", name)
    return m.group(1) if m else "default"


def _device(versions) -> str:
    device = _text(versions.get("device", "")) if versions is not None else ""
    return device.replace("NVIDIA ", "") or "—"


def experiment_row(path: Path, f: h5py.File) -> list[str]:
    c = f["config"].attrs
    task = _text(c.get("task", "?"))
    configured = int(c["num_random"]) + int(c["num_learned"]) if "num_random" in c and "num_learned" in c else None
    done = int(f.attrs.get("num_trials_done", len(f["eval_return"]) if "eval_return" in f else 0))
    returns = np.asarray(f["eval_return"]) if "eval_return" in f else np.empty(0)
    last = f"{returns[-1]:.2f}" if returns.size else "—"
    resumed = f.attrs.get("resumed_at")
    resumed = ", ".join(str(int(i)) for i in resumed) if resumed is not None and len(resumed) else "—"
    versions = f["versions"].attrs if "versions" in f else None
    code = _text(versions["code"]) if versions is not None and "code" in versions else None
    return [f"`{path.name}`", _text(c.get("method", "?")), f"{task} / {_cost(path.name, task, _text(c.get('cost', NONE)))}",
            _number(c["k"]) if "k" in c else "—", str(int(c["seed"])) if "seed" in c else "—",
            _text(f.attrs.get("status", "?")), f"{done}/{configured}" if configured is not None else str(done),
            last, resumed, short_code(code), _device(versions)]


def study_row(path: Path, f: h5py.File) -> list[str]:
    a = f.attrs
    source = Path(_text(a.get("source", "—"))).name
    return [f"`{path.name}`", _text(a.get("study", "?")), f"`{source}`",
            str(int(a["trial"])) if "trial" in a else "—", short_code(None) if "version_code" not in a
            else short_code(_text(a["version_code"])), _text(a.get("version_device", "—"))]


EXPERIMENT_HEADER = ["file", "method", "task / cost", "k", "seed", "status", "trials", "final return",
                     "resumed at", "code", "device"]
STUDY_HEADER = ["file", "study", "snapshot (result file)", "trial", "code", "device"]


def table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + ["| " + " | ".join(r) + " |" for r in rows]


def folder_tables(folder: Path) -> list[str]:
    experiments, studies, unreadable = [], [], []
    for path in sorted(folder.glob("*.h5"), key=_natural):
        try:
            with h5py.File(path, "r") as f:
                if "config" in f and ("config_json" in f.attrs or "trials" in f):
                    experiments.append(experiment_row(path, f))
                elif "study" in f.attrs:
                    studies.append(study_row(path, f))
                else:
                    unreadable.append(f"`{path.name}` (not a pipps result)")
        except (OSError, KeyError, ValueError) as e:
            unreadable.append(f"`{path.name}` ({type(e).__name__}: {e})")
    if not (experiments or studies or unreadable):
        return []
    n = len(experiments) + len(studies)
    out = [f"## `{folder.name}/` ({n} file{'s' if n != 1 else ''})", ""]
    if experiments:
        out += table(EXPERIMENT_HEADER, experiments) + [""]
    if studies:
        out += table(STUDY_HEADER, studies) + [""]
    if unreadable:
        out += ["Not read: " + "; ".join(unreadable), ""]
    return out


def _natural(path: Path):
    """Sort `..._s2.h5` before `..._s10.h5`."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="*", type=Path,
                        help="folders of result files (default: every folder under results/)")
    args = parser.parse_args(argv)
    folders = args.folders or sorted(p for p in (Path(__file__).resolve().parents[1] / "results").iterdir()
                                     if p.is_dir())
    lines = ["# Result files, one row per file", "",
             "<!-- generated: python experiments/results_manifest.py > results/MANIFEST.md; do not edit by hand -->", "",
             "Read from the files themselves by `python experiments/results_manifest.py > results/MANIFEST.md`;",
             "what made each folder, and why files of different code versions pool, is in [README.md](README.md).",
             "*trials*: finished / configured. *final return*: the evaluated return of the last finished trial",
             "(of the final trial when `complete`). *resumed at*: the trial indices at which a later session",
             "continued the file (`resumed_at`). *code*: `/versions` `code`, the commit of the session that",
             "wrote the file last (cut to 7 digits; not recorded in files written before 2026-11-25).", ""]
    for folder in folders:
        if not folder.is_dir():
            print(f"results_manifest: {folder} is not a folder", file=sys.stderr)
            return 2
        lines += folder_tables(folder)
    print("\n".join(lines).rstrip())
    return 0


if __name__ == "__main__":
    sys.exit(main())
