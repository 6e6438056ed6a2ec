"""Copy a running queue's result files into the repository: each complete file into its results
folder (once; a file already there is left as it is), each unfinished one into
``results/in-progress/`` (replaced by its newer state), and the in-progress copy of a file that is
now complete removed. Files are read under no lock (h5py, read-only); one being written at that
moment is skipped with a note and taken on the next run.

    python experiments/sync_results.py runs/thesis:thesis runs/pilco-noise:pilco-noise

Each argument is ``QUEUE_FOLDER:RESULTS_SUBFOLDER``. After it: ``python
experiments/results_manifest.py > results/MANIFEST.md``, the rows of results/README.md, and
``python experiments/results_tables.py`` for the tables in README.md and docs/results.md.
"""

import argparse
import shutil
import sys
from pathlib import Path

import h5py

RESULTS = Path(__file__).resolve().parent.parent / "results"


def status(path: Path) -> str | None:
    """The file's ``status`` attribute, or None when it cannot be read now."""
    try:
        with h5py.File(path, "r") as f:
            st = f.attrs.get("status")
    except OSError:
        return None
    return st.decode() if isinstance(st, bytes) else st


def sync(source: Path, target: Path, in_progress: Path) -> list[str]:
    """Copy ``source``'s result files as the module doc says; returns one line per file it touched."""
    lines = []
    for path in sorted(source.glob("*.h5")):
        st = status(path)
        if st is None:
            lines.append(f"skipped (being written; next time): {path}")
        elif st == "complete":
            target.mkdir(parents=True, exist_ok=True)
            if not (target / path.name).exists():
                shutil.copy2(path, target / path.name)
                lines.append(f"complete: {target / path.name}")
            if (in_progress / path.name).exists():
                (in_progress / path.name).unlink()
                lines.append(f"removed from in-progress: {path.name}")
        else:
            in_progress.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, in_progress / path.name)
            lines.append(f"in progress ({st}): {in_progress / path.name}")
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("pairs", nargs="+", metavar="QUEUE_FOLDER:RESULTS_SUBFOLDER",
                        help="a queue's output folder and the folder under results/ its complete files go to")
    parser.add_argument("--results", type=Path, default=RESULTS, help="the repository's results folder")
    args = parser.parse_args(argv)
    for pair in args.pairs:
        source, sep, sub = pair.rpartition(":")
        if not sep or not source or not sub or Path(sub).is_absolute() or ".." in Path(sub).parts:
            parser.error(f"{pair!r}: expected QUEUE_FOLDER:RESULTS_SUBFOLDER, the subfolder relative to results/")
        if not Path(source).is_dir():
            parser.error(f"{source}: no such folder")
    for pair in args.pairs:
        source, _, sub = pair.rpartition(":")
        for line in sync(Path(source), args.results / sub, args.results / "in-progress"):
            print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
