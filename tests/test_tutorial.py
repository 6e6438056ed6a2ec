"""docs/tutorial.md, run as written: its module, its commands and its Python, with tiny budgets.

The page's task module is written to a fresh folder under the name the page gives it; every
``pipps`` command of the page runs there in order through the command line's ``main`` (the
learning commands with tiny budgets added, the sweep over two seeds instead of five); then the
page's Python block runs with the same tiny budgets. What the page claims of each step is checked:
the run writes a complete result that records where its task came from, a resume of a complete
run changes nothing, the table names the task and the plot writes its recording.
"""

from __future__ import annotations

import re
import shlex
import sys
from pathlib import Path

import numpy as np
import pytest

import pipps.experiments
from pipps import cli
from pipps.experiments.records import ExperimentResult
from pipps.experiments.results import read_result, write_result
from pipps.tasks import registry

PAGE = Path(__file__).resolve().parents[1] / "docs" / "tutorial.md"
TINY = ["num_learned=1", "policy_evals=4", "progress_chunk=2", "eval_rollouts=3", "gp_max_iters=10",
        "store_particles=4"]


def _block(name: str) -> str:
    """The fenced code between ``<!-- pipps:NAME -->`` and ``<!-- /pipps -->``."""
    text = PAGE.read_text()
    m = re.search(rf"<!-- pipps:{name} -->\n```\w*\n(.*?)```\n<!-- /pipps -->", text, re.S)
    assert m, f"docs/tutorial.md has no code block marked {name}"
    return m.group(1)


def _commands() -> list[list[str]]:
    """Every ``pipps ...`` line of the page's bash blocks, in order."""
    text = PAGE.read_text()
    lines = []
    for block in re.findall(r"```bash\n(.*?)```", text, re.S):
        lines += [shlex.split(line.split("#")[0])[1:] for line in block.splitlines() if line.startswith("pipps ")]
    return lines


def test_the_module_is_the_committed_one():
    """experiments/pendulum_task.py is the page's module verbatim: the committed tutorial results
    (results/tutorial/) re-tabulate with it (``--task experiments.pendulum_task:pendulum``)."""
    committed = PAGE.parents[1] / "experiments" / "pendulum_task.py"
    assert committed.read_text() == _block("tutorial-module")


def test_the_module_is_short():
    """The page promises a system in one short module (code lines, docstrings and comments included)."""
    assert len(_block("tutorial-module").strip().splitlines()) <= 40


@pytest.fixture
def folder(tmp_path, monkeypatch):
    """An empty folder holding only the page's module, the current directory; the registry and the
    import path restored after."""
    (tmp_path / "pendulum_task.py").write_text(_block("tutorial-module"))
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", [str(tmp_path), *sys.path])
    before = dict(registry._REGISTERED)
    yield tmp_path
    registry._REGISTERED.clear()
    registry._REGISTERED.update(before)
    sys.modules.pop("pendulum_task", None)


def test_the_tutorial_runs_as_written(folder, capsys, monkeypatch):
    commands = _commands()
    assert [c[0] for c in commands] == ["run", "run", "sweep", "table", "plot"], commands
    for argv in commands:
        if argv[0] in ("run", "sweep") and "--resume" not in argv:
            argv = [*argv, *[a for s in TINY for a in ("--set", s)]]
        if argv[0] == "sweep":
            argv[argv.index("--seeds") + 1] = "2"
        if argv[0] in ("table", "plot"):
            argv = [*argv, "--custom"]  # the tiny budgets depart from the preset
        if "--resume" in argv:  # the page's Ctrl-C: keep the first trial, as an interrupted run leaves it
            full = read_result(folder / "runs/tutorial/s0.h5")
            write_result(folder / "runs/tutorial/s0.h5",
                         ExperimentResult(full.config, full.trials[:1], "interrupted", "KeyboardInterrupt: ", 1.0))
        code = cli.main(argv)
        out, err = capsys.readouterr()
        assert code == 0, (argv, out[-2000:], err[-2000:])
        if argv[0] == "table":
            assert "pendulum" in out
        if "--resume" in argv:  # ... and it continues to the uninterrupted result, bit for bit
            again = read_result(folder / "runs/tutorial/s0.h5")
            assert again.status == "complete" and again.resumed_at == [1]
            for a, b in zip(full.trials, again.trials, strict=True):
                for name in ("states", "observations", "actions", "eval_returns", "eval_balanced", "policy"):
                    assert np.array_equal(getattr(a, name), getattr(b, name)), name
    done = read_result(folder / "runs/tutorial/s0.h5")
    assert (done.config.task, done.config.task_source) == ("pendulum", "pendulum_task:pendulum")
    assert len(list((folder / "runs/tutorial").glob("*.h5"))) == 3  # s0 and the sweep's two seeds
    assert (folder / "tutorial.rrd").stat().st_size > 0

    # the Python block, with the same tiny budgets
    resolve = pipps.experiments.resolve_config
    monkeypatch.setattr(pipps.experiments, "resolve_config",
                        lambda *a, **k: resolve(*a, **k, **{s.split("=")[0]: int(s.split("=")[1]) for s in TINY}))
    exec(compile(_block("tutorial-python"), "docs/tutorial.md", "exec"), {"__name__": "tutorial"})
    printed = capsys.readouterr().out.strip().splitlines()
    returns = eval(printed[-2])  # noqa: S307 - the list the page prints
    assert len(returns) == 2 and all(0.0 <= r <= 30.0 for r in returns)
    assert printed[-1] in ("True", "False")
    assert (folder / "runs/tutorial/python_s0.h5").exists()
