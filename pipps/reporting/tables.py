"""The success-rate tables: the thesis' (Tables 4.1–4.4 of thesis §4.5.4), and one per task of your own.

Each table is a list of cells; a cell is a set of configuration values (task, cost, k, method)
and the thesis' success rate. ``table_configs(table, seeds, preset)`` expands a table into the
configurations of a sweep; ``render_table(table, results)`` prints, as markdown, each cell's headline
rate with its 95 % interval over seeds and the number of seeds next to the thesis value, then every
reading of every cell (:mod:`pipps.reporting.readings`) and the difference of two methods under
every reading. A task that
no thesis table has gets its own (:func:`task_table`: methods against k, no thesis values).
Whether an experiment succeeded is its task's verdict (:mod:`pipps.reporting.verdicts`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, Iterable

import numpy as np

from pipps.experiments.config import ConfigError, ExperimentConfig, canonical, resolve_config
from pipps.experiments.methods import METHODS
from pipps.reporting import readings
from pipps.reporting.readings import wilson_interval


@dataclasses.dataclass(frozen=True)
class Cell:
    row: str  # the row label, e.g. "k = 1" or "Angle, k = 10⁻²"
    method: str
    values: tuple[tuple[str, Any], ...]  # configuration values that define the cell
    thesis: float | None


@dataclasses.dataclass(frozen=True)
class Table:
    name: str
    title: str
    task: str
    rows: tuple[str, ...]
    methods: tuple[str, ...]
    cells: tuple[Cell, ...]
    row_in_titles: bool = True  # the figures name a panel's row (False: a table of one row named after its task)
    thesis: bool = True  # one of the thesis' tables (False: a task's own, without thesis values)


def _k_label(k: float) -> str:
    return "10⁻²" if k == 0.01 else f"{k:g}"


def _grid(name, title, task, cost, rows_k, methods, values_by_row):
    cells = []
    for k, row_values in zip(rows_k, values_by_row):
        for m, v in zip(methods, row_values):
            if v is not None:
                cells.append(Cell(f"k = {_k_label(k)}", m, (("cost", cost), ("k", k)), v))
    return Table(name, title, task, tuple(f"k = {_k_label(k)}" for k in rows_k), tuple(methods), tuple(cells))


_T41_METHODS = ("pilco", "rp", "rp_fs", "gr", "gr_fs", "lr", "tp", "tp-sf", "tp+sn")
_T41 = [
    [0.88, 0.69, 0.24, 0.63, 0.74, 0.57, 0.82, None, 0.96],
    [0.79, 0.74, 0.23, 0.89, 0.71, 0.96, 0.99, 0.93, None],
    [0.70, 0.58, 0.08, 0.62, 0.41, 0.94, 0.95, 0.87, None],
    [0.37, 0.44, 0.04, 0.34, 0.25, 0.86, 0.83, 0.78, None],
    [0.01, 0.11, 0.00, 0.08, 0.02, 0.45, 0.40, 0.42, None],
]
_T42_METHODS = ("pilco", "rp", "rp_fs", "gr", "gr_fs", "lr", "tp")
_T42 = [[0.92, 0.44, 0.20, 0.47, 0.78, 0.36, 0.54], [0.73, 0.15, 0.08, 0.68, 0.50, 0.28, 0.48]]
_T43_METHODS = ("pilco", "rp", "gr", "lr", "tp", "gtp", "glr", "gtp+sn")
_T43 = [
    ("angle", 0.01, [0.88, 0.69, 0.63, 0.57, 0.82, 0.65, 0.42, 0.88]),
    ("angle", 1.0, [0.79, 0.74, 0.89, 0.96, 0.99, 0.90, 0.93, None]),
    ("tip", 0.01, [0.92, 0.44, 0.47, 0.36, 0.54, 0.60, 0.45, 0.80]),
    ("tip", 1.0, [0.73, 0.15, 0.68, 0.28, 0.48, 0.69, 0.35, None]),
]
_T44_METHODS = ("pilco", "rp", "rp_fs", "gr", "gr_fs", "lr", "tp")
_T44 = [0.91, 0.80, 0.39, 0.96, 0.63, 0.47, 0.94]


def _table_43() -> Table:
    cells, rows = [], []
    for cost, k, vals in _T43:
        row = f"{cost.capitalize()}, k = {_k_label(k)}"
        rows.append(row)
        cells += [Cell(row, m, (("cost", cost), ("k", k)), v) for m, v in zip(_T43_METHODS, vals) if v is not None]
    return Table("4.3", "Table 4.3 — Gaussian shaping, cart-pole swing-up", "cartpole_swingup", tuple(rows),
                 _T43_METHODS, tuple(cells))


def _extra() -> Table:
    row = "Angle, k = 1, Q × 0.01"
    cells = (Cell(row, "tp", (("cost", "angle"), ("k", 1.0), ("cost_scale", 0.01)), 0.97),
             Cell(row, "pilco", (("cost", "angle"), ("k", 1.0), ("cost_scale", 0.01)), 0.46))
    return Table("q001", "Angle Cost with Q × 0.01 (thesis §4.5.4 text)", "cartpole_swingup", (row,), ("pilco", "tp"), cells)


def _robust() -> Table:
    """Suh et al.'s robust weight inside the thesis' TP on Table 4.1's k = 1 cell, TP beside it (no thesis
    value: the thesis has no such method; docs/contact.md, "Through the learning loop")."""
    row = "Angle, k = 1"
    cells = (Cell(row, "tp-robust", (("cost", "angle"), ("k", 1.0)), None),
             Cell(row, "tp", (("cost", "angle"), ("k", 1.0)), 0.99))
    return Table("robust", "TP with the robust (AoBG) weight, Table 4.1's k = 1 cell, TP beside it", "cartpole_swingup",
                 (row,), ("tp-robust", "tp"), cells)


def _del() -> Table:
    """DEL on cart-pole balancing, TP beside it on the same task (the thesis reports DEL's rate only as
    "non-trivial" and draws both learning curves, Fig. 4.17a); DEL_c, DEL weighted by each step's own
    cost, is a third reading of the thesis' DEL (docs/estimator-bias.md)."""
    row = "Angle, k = 1"
    methods = ("del", "del-cost", "tp")
    cells = tuple(Cell(row, m, (("cost", "angle"), ("k", 1.0)), None) for m in methods)
    return Table("del", "DEL on cart-pole balancing, TP beside it (thesis: a non-trivial rate, figure only)",
                 "cartpole_balance", (row,), methods, cells)


TABLES: dict[str, Table] = {
    "4.1": _grid("4.1", "Table 4.1 — cart-pole swing-up, Angle Cost", "cartpole_swingup", "angle",
                 [0.01, 1.0, 4.0, 9.0, 16.0], _T41_METHODS, _T41),
    "4.2": _grid("4.2", "Table 4.2 — cart-pole swing-up, Tip Cost", "cartpole_swingup", "tip",
                 [0.01, 1.0], _T42_METHODS, _T42),
    "4.3": _table_43(),
    "4.4": Table("4.4", "Table 4.4 — unicycle balancing", "unicycle", ("unicycle",), _T44_METHODS,
                 tuple(Cell("unicycle", m, (), v) for m, v in zip(_T44_METHODS, _T44)), row_in_titles=False),
    "q001": _extra(),
    "del": _del(),
    "robust": _robust(),
}


def get_table(name: str) -> Table:
    if name not in TABLES:
        raise ValueError(f"unknown table {name!r}; choose one of {', '.join(TABLES)}")
    return TABLES[name]


def task_table(task: str, ks=(1.0,), methods=("tp",)) -> Table:
    """The table of a task no thesis table has: one row per noise multiplier in ``ks``, one column
    per method in ``methods`` (registry order), no thesis values. Its cells take the task's
    default cost, so it counts the results of any cost only where the task has one."""
    ks = sorted({float(k) for k in ks})
    methods = tuple(m for m in METHODS if m in set(methods))
    rows = tuple(f"k = {_k_label(k)}" for k in ks)
    cells = tuple(Cell(row, m, (("k", k),), None) for row, k in zip(rows, ks) for m in methods)
    return Table(task, f"Task {task} — success rate per method and noise multiplier (no thesis values)", task, rows,
                 methods, cells, thesis=False)


def result_tables(summaries: list[dict[str, Any]]) -> list[Table]:
    """A :func:`task_table` for each task of ``summaries`` that no thesis table has, with the noise
    multipliers and methods its results ran."""
    thesis = {t.task for t in TABLES.values()}
    by_task: dict[str, list[ExperimentConfig]] = {}
    for s in summaries:
        if s["config"].task not in thesis:
            by_task.setdefault(s["config"].task, []).append(s["config"])
    return [task_table(task, {c.k for c in cfgs}, {c.method for c in cfgs}) for task, cfgs in by_task.items()]


def select_cells(table: Table, methods: Iterable[str] | None = None, ks: Iterable[float] | None = None) -> list[Cell]:
    """The table's cells, optionally restricted to some methods and noise multipliers."""
    cells = list(table.cells)
    if methods is not None:
        methods = list(methods)
        bad = [m for m in methods if m not in METHODS]
        if bad:
            raise ValueError(f"method: unknown {bad}; choose from {', '.join(METHODS)}")
        cells = [c for c in cells if c.method in methods]
    if ks is not None:
        ks = [float(k) for k in ks]
        cells = [c for c in cells if dict(c.values).get("k", 1.0) in ks]
    return cells


def table_configs(
    table: str | Table,
    seeds: int | Iterable[int],
    preset: str = "thesis",
    *,
    methods: Iterable[str] | None = None,
    ks: Iterable[float] | None = None,
    overrides: dict[str, Any] | None = None,
) -> list[ExperimentConfig]:
    """Every (cell × seed) configuration of a table. Seeds are ordered outermost, so a sweep
    cut short has a few seeds of every cell rather than all seeds of a few cells.

    Each override applies to the cells whose method uses it (``num_particles`` to the particle
    methods, not to PILCO); one that no selected method uses is refused by name."""
    t = get_table(table) if isinstance(table, str) else table
    seed_list = list(range(seeds)) if isinstance(seeds, int) else list(seeds)
    cells = select_cells(t, methods, ks)
    overrides = overrides or {}
    chosen = sorted({c.method for c in cells})
    for name in overrides:
        key = name.replace("-", "_")
        if chosen and all(key in METHODS[m].unused for m in chosen):
            raise ConfigError(f"{key}: no method of the sweep uses it ({', '.join(chosen)})")
    return [resolve_config(preset, t.task, method=c.method, seed=s, **dict(c.values), **_used(c.method, overrides))
            for s in seed_list for c in cells]


def _used(method: str, overrides: dict[str, Any]) -> dict[str, Any]:
    """The overrides ``method`` uses."""
    return {k: v for k, v in overrides.items() if k.replace("-", "_") not in METHODS[method].unused}


def _cell_key(values: dict[str, Any], method: str, cfg: ExperimentConfig) -> bool:
    if cfg.method != method:
        return False
    for name, v in values.items():
        got = cfg.cost_name if name == "cost" else getattr(cfg, name)
        if isinstance(v, float) and isinstance(got, (int, float)):
            if not math.isclose(float(got), v, rel_tol=1e-9):
                return False
        elif got != v:
            return False
    return True


#: Re-simulated evaluation returns must equal the stored ones to this relative tolerance: the true
#: system is deterministic given the keys, so only rounding (another CPU) may separate them.
RESIM_TOLERANCE = 1e-6


def returns_reproduced(returns, stored) -> bool:
    """Re-simulated ``returns`` equal the ``stored`` ones within :data:`RESIM_TOLERANCE` of their size."""
    stored = np.asarray(stored, dtype=float)
    gap = float(np.max(np.abs(np.asarray(returns, dtype=float) - stored)))
    return gap <= RESIM_TOLERANCE * max(1.0, float(np.max(np.abs(stored))))


def judge(summaries: list[dict[str, Any]], resimulator=None) -> list[dict[str, Any]]:
    """Add both verdicts to result summaries (:func:`pipps.experiments.results.read_summary`), in place,
    each the task's (:func:`pipps.reporting.verdicts.verdict`):

    * ``success``: the physical criterion (decides). Files written before the per-rollout flags
      were stored (cart-pole) are re-simulated: the final trial's own evaluation rollouts are rerun
      with the stored policy and keys (``resimulated``; the returns must match the stored ones,
      ``resim_error`` is the largest difference);
    * ``return_success``: the task's return threshold (the thesis' counting; None for a task
      without one, as the unicycle);
    * ``final_balanced``: the final trial's fraction of rollouts meeting the physical criterion;
    * ``flip`` / ``return_flip``: the probability that a fresh evaluation flips each verdict;
    * ``final_se``: the standard error of the final evaluated return;
    * ``per_seed``: the seed's value under every reading of a success rate
      (:func:`pipps.reporting.readings.seed_values`).
    """
    from pipps.reporting import verdicts as v

    for s in summaries:
        cfg = s["config"]
        rets = np.asarray(s["final_eval_returns"], dtype=float)
        s["final_se"] = v.standard_error(rets)
        flags = s["final_eval_upright"] if v.reads_upright(v.criterion(cfg)) else s.get("final_eval_balanced")
        if flags is None:
            flags = _resimulated_flags(s, rets, resimulator)
        verdict = v.verdict(cfg, rets, flags)
        s["final_balanced"] = verdict.fraction
        s["success"] = verdict.success
        s["return_success"] = verdict.return_success
        s["return_flip"] = math.nan if verdict.threshold is None else v.flip_probability_return(rets, verdict.threshold)
        n = len(rets)
        s["flip"] = v.flip_probability_fraction(int(round(verdict.fraction * n)), n, verdict.required)
        threshold = verdict.threshold is not None
        s["per_seed"] = readings.seed_values(
            cfg.seed, rets, flags, s.get("final_trial_return") if threshold else None, verdict.threshold,
            verdict.required, v.system_trial_success(cfg, s.get("final_trial_states"), s.get("final_trial_valid")))
    return summaries


def _resimulated_flags(s: dict[str, Any], rets: np.ndarray, resimulator) -> np.ndarray:
    """The criterion's flags of a file written before they were stored: its final trial's own evaluation
    rollouts rerun (:class:`pipps.experiments.resimulate.Resimulator`), checked against the stored returns."""
    from pipps.experiments.resimulate import Resimulator
    from pipps.experiments.results import ResultError, read_result

    resimulator = resimulator or Resimulator()
    result = read_result(s["path"], verify=False)
    ret, _, flags = resimulator.trial(result, len(result.trials) - 1)
    s["resimulated"] = True
    s["resim_error"] = float(np.max(np.abs(ret - rets)))
    if not returns_reproduced(ret, rets):
        raise ResultError(f"{s['path']}: re-simulating its final evaluation gives returns that differ from "
                          f"the stored ones by {s['resim_error']:.2g}; its physical verdict cannot be "
                          "re-judged (another simulator or policy layout?)")
    return flags


def fisher_exact(a_successes: int, a_n: int, b_successes: int, b_n: int) -> float:
    """Two-sided p-value of Fisher's exact test that two success rates are equal."""
    from scipy.stats import fisher_exact as fe

    return float(fe([[a_successes, a_n - a_successes], [b_successes, b_n - b_successes]])[1])


def difference_interval(a_successes: int, a_n: int, b_successes: int, b_n: int) -> tuple[float, float]:
    """95 % interval of the difference of two independent rates (Newcombe's hybrid score method,
    built from the two Wilson intervals; Newcombe 1998, method 10)."""
    p1, p2 = a_successes / a_n, b_successes / b_n
    l1, u1 = wilson_interval(a_successes, a_n)
    l2, u2 = wilson_interval(b_successes, b_n)
    d = p1 - p2
    return (d - math.sqrt((p1 - l1) ** 2 + (u2 - p2) ** 2), d + math.sqrt((u1 - p1) ** 2 + (p2 - l2) ** 2))


@dataclasses.dataclass
class CellResult:
    cell: Cell
    successes: int
    n: int
    seeds: list[int]
    mean_final_return: float
    mean_wall_seconds: float
    mixed: tuple[str, ...] = ()  # settings (other than the seed) that differ between the cell's results
    return_successes: int | None = None  # by the thesis' return threshold (None: not applicable)
    disagree: tuple[int, ...] = ()  # seeds whose two verdicts differ
    unsure: tuple[int, ...] = ()  # seeds whose verdict a fresh evaluation flips with probability > 5 %
    final_returns: tuple[float, ...] = ()  # each counted seed's final evaluated return, in seed order
    final_balanced: tuple[float, ...] = ()  # each seed's fraction of final rollouts meeting the criterion (judged only)
    verdicts: tuple[bool, ...] = ()  # each counted seed's physical verdict, in seed order
    per_seed: tuple[readings.SeedValues, ...] = ()  # each counted seed's value under every reading

    @functools.cached_property
    def by_reading(self) -> dict[str, readings.Rate]:
        """The cell's rate under every reading that applies (:mod:`pipps.reporting.readings`)."""
        return readings.rates(self.per_seed)

    @property
    def headline(self) -> readings.Rate | None:
        """The rate the tables lead with: per trial by the return threshold (the thesis' counting,
        docs/results.md), or per trial by the physical criterion where a task has no threshold."""
        got = self.by_reading
        return got.get(readings.HEADLINE) or got.get("trial_physical")

    @property
    def rate(self) -> float:
        h = self.headline
        return h.rate if h is not None else math.nan

    @property
    def interval(self) -> tuple[float, float]:
        h = self.headline
        return h.interval if h is not None else (0.0, 1.0)

    @property
    def agrees(self) -> bool | None:
        """Whether the thesis value lies inside the headline rate's 95 % interval (None without data or thesis value)."""
        h = self.headline
        return None if h is None or self.cell.thesis is None else h.covers(self.cell.thesis)


def _settings(cfg: ExperimentConfig) -> dict[str, Any]:
    """A configuration's identity (:func:`pipps.experiments.config.canonical`: the default cost named,
    settings the method does not use and computational ones left out) other than the seed."""
    return {k: v for k, v in canonical(cfg).items() if k != "seed"}


def counts(cfg: ExperimentConfig, preset: str = "thesis", custom: bool = False, vary: str | None = None) -> str:
    """Why a result does not count in the tables of experiment preset ``preset`` ("" when it does):
    it was run with another preset, or (unless ``custom``) its settings depart from the preset's in
    a setting other than ``vary`` (the setting a comparison groups by, :func:`split_by`)."""
    from pipps.experiments.config import ConfigError, departures

    if cfg.protocol != preset:
        return f"run with --preset {cfg.protocol} (this table counts --preset {preset}; pipps table --preset {cfg.protocol})"
    if custom:
        return ""
    try:
        diff = departures(cfg)
    except ConfigError as err:
        return f"not expressible by the {preset} preset ({err})"
    diff.pop(vary, None)
    if diff:
        shown = ", ".join(f"{k}={v!r} (preset: {p!r})" for k, (v, p) in sorted(diff.items()))
        return f"departs from the {preset} preset: {shown} (pipps table --custom counts it)"
    return ""


def cell_summaries(table: Table, cell: Cell, summaries: list[dict[str, Any]], preset: str | None = "thesis",
                   custom: bool = False) -> list[dict[str, Any]]:
    """The summaries that count in ``cell`` (:func:`collect` says which), seeds in order."""
    values = dict(cell.values)
    rows = [s for s in summaries if s["config"].task == table.task and _cell_key(values, cell.method, s["config"])
            and (preset is None or not counts(s["config"], preset, custom))]
    return sorted(rows, key=lambda s: s["config"].seed)


def judge_counted(summaries: list[dict[str, Any]], preset: str = "thesis", custom: bool = False,
                  ) -> tuple[list[dict[str, Any]], dict[str, str]]:
    """:func:`judge` the summaries that count for ``preset`` (:func:`counts`), with one re-simulator
    (one compiled evaluation per configuration shape). Returns the judged summaries and, by path, the
    error of each legacy file whose evaluation does not re-simulate (left out)."""
    from pipps.experiments.resimulate import Resimulator
    from pipps.experiments.results import ResultError

    judged, errors, resimulator = [], {}, Resimulator()
    for s in summaries:
        if counts(s["config"], preset, custom):
            continue
        try:
            judged += judge([s], resimulator)
        except ResultError as err:
            errors[s["path"]] = str(err)
    return judged, errors


def collect(table: Table, summaries: list[dict[str, Any]], preset: str | None = "thesis",
            custom: bool = False) -> list[CellResult]:
    """Group result summaries (:func:`pipps.experiments.results.read_summary`) into the table's cells.

    A result counts when it ran with experiment preset ``preset`` and, unless ``custom``, follows it
    in every setting but the cell's and the seed (:func:`counts`); ``preset=None`` counts every
    result (the pooled settings are then named in ``mixed``)."""
    out = []
    for cell in table.cells:
        rows = cell_summaries(table, cell, summaries, preset, custom)
        n = len(rows)
        dicts = [_settings(r["config"]) for r in rows]
        mixed = tuple(sorted(k for k in (dicts[0] if dicts else {}) if any(d[k] != dicts[0][k] for d in dicts)))
        judged = [s for s in rows if s.get("return_success") is not None]
        out.append(CellResult(
            cell, sum(bool(s["success"]) for s in rows), n, sorted(s["config"].seed for s in rows),
            float(sum(s["final_return"] for s in rows) / n) if n else math.nan,
            float(sum(s["wall_seconds"] for s in rows) / n) if n else math.nan, mixed,
            sum(bool(s["return_success"]) for s in judged) if judged else None,
            tuple(sorted(s["config"].seed for s in judged if s["return_success"] != s["success"])),
            tuple(sorted(s["config"].seed for s in rows if s.get("flip", 0.0) > 0.05)),
            tuple(float(s["final_return"]) for s in rows),
            tuple(float(s["final_balanced"]) for s in rows if s.get("final_balanced") is not None),
            tuple(bool(s["success"]) for s in rows),
            tuple(s["per_seed"] for s in rows if "per_seed" in s)))
    return out


def _headline_caption(results: list[CellResult]) -> str:
    """What the headline rate of these cells counts, in words."""
    kinds = {r.headline.reading.name for r in results if r.n and r.headline is not None}
    if kinds == {"trial_physical"}:
        return "the fraction of the final policy's evaluation rollouts meeting the physical criterion, averaged over seeds"
    return ("the fraction of the final policy's evaluation rollouts with return below the threshold, averaged over "
            "seeds (the thesis' counting)")


def render_table(table: Table, results: list[CellResult], *, show_empty: bool = False,
                 compare: tuple[str, str] = ("tp", "pilco")) -> str:
    """Markdown, three parts. (1) The thesis' layout (rows × methods), each cell the headline rate
    (:attr:`CellResult.headline`) with its 95 % interval over seeds and the number of seeds, next to
    the thesis' value (``!`` where the thesis value lies outside our interval). (2) Every reading of
    every cell side by side (:mod:`pipps.reporting.readings`). (3) Where both methods of
    ``compare`` have results in a row, their difference under every reading with its interval and
    the permutation p over seeds. Under the tables: the seeds whose per-seed physical and return
    verdicts differ and those a fresh evaluation would flip with probability above 5 %."""
    by = {(r.cell.row, r.cell.method): r for r in results}
    methods = [m for m in table.methods if show_empty or any(by.get((row, m)) and by[(row, m)].n for row in table.rows)]
    if not methods:
        return f"**{table.title}**: no complete results for this table."
    labels = {m: METHODS[m].label for m in methods}
    lines = [f"**{table.title}** — ours: {_headline_caption(results)} [95 % interval over seeds] (seeds) / thesis "
             "(`!`: the thesis value lies outside our interval)", "",
             "| | " + " | ".join(labels.values()) + " |", "|---" * (len(labels) + 1) + "|"]
    for row in table.rows:
        cells = []
        for m in methods:
            r = by.get((row, m))
            if r is None:
                cells.append("")
                continue
            thesis = "–" if r.cell.thesis is None else f"{r.cell.thesis:.2f}"
            if not r.n:
                cells.append(f"— / {thesis}")
                continue
            lo, hi = r.interval
            flag = " !" if r.agrees is False else ""
            cells.append(f"{r.rate:.2f} [{lo:.2f}, {hi:.2f}] ({r.n}) / {thesis}{flag}")
        if any(c and not c.startswith("—") for c in cells) or show_empty:
            lines.append(f"| {row} | " + " | ".join(cells) + " |")
    lines += ["", render_readings(table, results)]
    diffs = render_differences(table, results, compare)
    if diffs:
        lines += ["", diffs]
    lines += _closing(_cell_notes(results), any(r.unsure for r in results))
    return "\n".join(lines)


def _present_readings(results: list[CellResult]) -> list[readings.Reading]:
    have = {name for r in results for name in r.by_reading}
    return [rd for rd in readings.READINGS if rd.name in have]


def _reading_cells(r: CellResult, shown: list[readings.Reading]) -> list[str]:
    """A cell's rate under each of ``shown`` with its interval over seeds ("–" where it does not apply)."""
    got = r.by_reading
    return [got[rd.name].text() if rd.name in got else "–" for rd in shown]


def _reading_head(shown: list[readings.Reading]) -> list[str]:
    return [("**" + rd.label + "**") if rd.name == readings.HEADLINE else rd.label for rd in shown]


_READINGS_TITLE = "every reading [95 % interval over seeds] (docs/results.md, \"How a success rate is counted\")"


def render_readings(table: Table, results: list[CellResult]) -> str:
    """Markdown: one row per cell with results, its rate under every reading with the 95 % interval
    over seeds (per-seed readings also as a count), the thesis' value beside."""
    shown = _present_readings(results)
    head = ["", "method", "seeds", "thesis", *_reading_head(shown)]
    lines = [f"**{table.title}**, {_READINGS_TITLE}", "", "| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for r in results:
        if not r.n:
            continue
        lines.append(f"| {r.cell.row} | {METHODS[r.cell.method].label} | {r.n} | {_thesis(r.cell)} | "
                     + " | ".join(_reading_cells(r, shown)) + " |")
    return "\n".join(lines)


def _thesis(cell: Cell) -> str:
    return "–" if cell.thesis is None else f"{cell.thesis:.2f}"


def _difference_cells(a: CellResult, b: CellResult, shown: list[readings.Reading]) -> list[str]:
    """``a − b`` under each of ``shown`` (:func:`pipps.reporting.readings.compare`; "–" where a reading
    applies to only one of them)."""
    ga, gb = a.by_reading, b.by_reading
    return [readings.compare(ga[rd.name], gb[rd.name]).text() if rd.name in ga and rd.name in gb else "–"
            for rd in shown]


def render_differences(table: Table, results: list[CellResult], compare: tuple[str, str] = ("tp", "pilco")) -> str:
    """Markdown: per row where both methods of ``compare`` have results, ``a − b`` under every reading:
    the difference with Newcombe's interval from the two seed-level intervals and the two-sided
    permutation p over seeds (:func:`pipps.reporting.readings.compare`), and the thesis' difference."""
    a, b = compare
    by = {(r.cell.row, r.cell.method): r for r in results}
    shown = _present_readings(results)
    lines = []
    for row in table.rows:
        ra, rb = by.get((row, a)), by.get((row, b))
        if not (ra and rb and ra.n and rb.n):
            continue
        thesis = "–" if ra.cell.thesis is None or rb.cell.thesis is None else f"{ra.cell.thesis - rb.cell.thesis:+.2f}"
        lines.append(f"| {row} | {thesis} | " + " | ".join(_difference_cells(ra, rb, shown)) + " |")
    if not lines:
        return ""
    la, lb = METHODS[a].label, METHODS[b].label
    return "\n".join([f"**{table.title}**, {la} − {lb} under every reading [95 % interval], permutation p over seeds",
                      "", "| | thesis | " + " | ".join(rd.label for rd in shown) + " |",
                      "|---" * (len(shown) + 2) + "|", *lines])


def render_group_readings(table: Table, setting: str, groups: list[tuple[Any, list[CellResult]]]) -> str:
    """Markdown: :func:`render_readings` for a comparison by ``setting`` (``groups`` as in
    :func:`render_comparison`): one row per cell and value with results, in table order, each
    value's rate under every reading with its 95 % interval over seeds. "" without results."""
    shown = _present_readings([r for _, results in groups for r in results])
    by = [(value, {(r.cell.row, r.cell.method): r for r in results}) for value, results in groups]
    rows = []
    for cell in table.cells:
        for value, got in by:
            r = got.get((cell.row, cell.method))
            if r is not None and r.n:
                rows.append(f"| {cell.row} | {METHODS[cell.method].label} | {value} | {r.n} | {_thesis(cell)} | "
                            + " | ".join(_reading_cells(r, shown)) + " |")
    if not rows:
        return ""
    head = ["", "method", setting, "seeds", "thesis", *_reading_head(shown)]
    return "\n".join([f"**{table.title}**, by {setting}, {_READINGS_TITLE}", "", "| " + " | ".join(head) + " |",
                      "|---" * len(head) + "|", *rows])


def render_group_differences(table: Table, setting: str, groups: list[tuple[Any, list[CellResult]]]) -> str:
    """Markdown: with exactly two values of ``setting``, per cell that both have results, the first
    minus the second under every reading, as :func:`render_differences` does for two methods:
    Newcombe's interval from the two seed-level intervals and the permutation p over seeds (the two
    values' seeds taken as independent; :func:`render_paired` pairs them). "" otherwise."""
    if len(groups) != 2:
        return ""
    (a, ra_all), (b, rb_all) = groups
    shown = _present_readings(ra_all + rb_all)
    rb_by = {(r.cell.row, r.cell.method): r for r in rb_all}
    lines = []
    for ra in ra_all:
        rb = rb_by.get((ra.cell.row, ra.cell.method))
        if ra.n and rb is not None and rb.n:
            lines.append(f"| {ra.cell.row} | {METHODS[ra.cell.method].label} | "
                         + " | ".join(_difference_cells(ra, rb, shown)) + " |")
    if not lines:
        return ""
    return "\n".join([f"**{table.title}**, {setting} = {a} − {b} under every reading [95 % interval], permutation p "
                      "over seeds", "", "| | method | " + " | ".join(rd.label for rd in shown) + " |",
                      "|---" * (len(shown) + 2) + "|", *lines])


def _signed_rank(d: np.ndarray) -> str:
    """The median of paired differences and the two-sided Wilcoxon signed-rank p (scipy's default
    method: exact for up to 50 pairs without ties or zeros; zero differences dropped)."""
    from scipy.stats import wilcoxon

    p = wilcoxon(d).pvalue if np.any(d != 0) else 1.0
    return f"{np.median(d):+.2f}, p = {p:.2g}"


def render_paired(table: Table, setting: str, groups: list[tuple[Any, list[CellResult]]]) -> str:
    """Markdown: for two values of ``setting``, each cell's seeds that both values ran, paired. A
    seed fixes the random trial, the initial policy and every key, so the two runs of a seed share
    their start and part only where the setting acts (common random numbers): the verdicts as a 2×2
    count with McNemar's exact p (a binomial test on the discordant seeds), and the median of the
    per-seed differences of final return and of balanced fraction with the Wilcoxon signed-rank p.
    "" unless there are two values and a cell whose seeds overlap."""
    from scipy.stats import binomtest

    if len(groups) != 2:
        return ""
    (a, ra_all), (b, rb_all) = groups
    rb_by = {(r.cell.row, r.cell.method): r for r in rb_all}
    lines = []
    for ra in ra_all:
        rb = rb_by.get((ra.cell.row, ra.cell.method))
        common = sorted(set(ra.seeds) & set(rb.seeds)) if rb is not None else []
        if not common:
            continue
        ia, ib = ([r.seeds.index(s) for s in common] for r in (ra, rb))
        va, vb = np.array(ra.verdicts)[ia], np.array(rb.verdicts)[ib]
        only_a, only_b = int(np.sum(va & ~vb)), int(np.sum(vb & ~va))
        mcnemar = binomtest(only_a, only_a + only_b, 0.5).pvalue if only_a + only_b else 1.0
        ret = _signed_rank(np.array(ra.final_returns)[ia] - np.array(rb.final_returns)[ib])
        judged = len(ra.final_balanced) == len(ra.seeds) and len(rb.final_balanced) == len(rb.seeds)
        bal = _signed_rank(np.array(ra.final_balanced)[ia] - np.array(rb.final_balanced)[ib]) if judged else ""
        lines.append(f"| {ra.cell.row} | {METHODS[ra.cell.method].label} | {_seed_ranges(common)} | "
                     f"{int(np.sum(va & vb))} / {only_a} / {only_b} / {int(np.sum(~va & ~vb))} | {mcnemar:.2g} | "
                     f"{ret} | {bal} |")
    if not lines:
        return ""
    return "\n".join([f"**{table.title}**, {setting} = {a} against {b}, paired by seed (the seeds both ran: "
                      "same random trial, initial policy and keys)", "",
                      f"| | method | seeds | success: both / only {a} / only {b} / neither | McNemar exact p | "
                      f"final return {a} − {b}: median, Wilcoxon p | balanced {a} − {b}: median, Wilcoxon p |",
                      "|---|---|---|---|---|---|---|", *lines])


def _cell_notes(results: list[CellResult], group: str = "") -> list[str]:
    """The lines under a table: cells that pool differing settings, seeds whose two verdicts differ,
    and seeds a fresh evaluation would flip with probability above 5 %; ``group`` names the
    comparison group the cells belong to."""
    notes = []
    for r in results:
        name = f"{r.cell.row}, {METHODS[r.cell.method].label}" + (f", {group}" if group else "")
        if r.mixed:
            notes.append(f"Warning: {name} pools results whose settings differ in {', '.join(r.mixed)}; read them "
                         "from separate folders.")
        if r.disagree:
            notes.append(f"{name}: the per-seed verdicts by the return threshold and by the physical criterion differ "
                         f"on seed(s) {', '.join(map(str, r.disagree))}.")
        if r.unsure:
            notes.append(f"{name}: a fresh evaluation would flip the per-seed physical verdict with probability > 5 % "
                         f"on seed(s) {', '.join(map(str, r.unsure))}.")
    return notes


#: the line under a table's notes when some verdict is near its line: the command that checks it
RESIMULATE_HINT = ("To check such seeds, `pipps resimulate FILES --fresh 300` reruns their final policies on the true "
                   "system with new rollouts.")


def _closing(notes: list[str], unsure: bool) -> list[str]:
    """``notes`` as the lines under a table, with :data:`RESIMULATE_HINT` once where some cell has
    seeds a fresh evaluation would flip (``unsure``)."""
    if not notes:
        return []
    return ["", *notes, *([RESIMULATE_HINT] if unsure else [])]


def comparable_settings() -> tuple[str, ...]:
    """The settings :func:`split_by` may group by: every setting of an experiment's identity
    (:func:`pipps.experiments.config.canonical`) other than the seed."""
    cfg = resolve_config("thesis", "cartpole_swingup")
    return tuple(k for k in canonical(cfg) if k != "seed")


def split_by(summaries: list[dict[str, Any]], setting: str) -> list[tuple[Any, list[dict[str, Any]]]]:
    """The summaries grouped by the value of one setting, as the experiment's identity has it
    (:func:`canonical`: a setting the method does not use reads as its preset's value), the groups in
    the order their first summary comes."""
    if setting not in comparable_settings():
        raise ValueError(f"cannot group by {setting!r}: choose a setting of the experiment "
                         f"({', '.join(comparable_settings())})")
    groups: dict[str, tuple[Any, list[dict[str, Any]]]] = {}
    for s in summaries:
        value = canonical(s["config"])[setting]
        groups.setdefault(repr(value), (value, []))[1].append(s)
    return list(groups.values())


def grouped(table: Table, setting: str, values: Iterable[Any]) -> Table:
    """``table`` with each row once per value of ``setting`` (:func:`split_by`'s groups), the value in
    the row's name (``"k = 1, estimator_choices = library"``), so that the groups' cells stand side by
    side in one figure; a cell keeps its method and values, so :func:`cell_summaries` of one group's
    results fills it. A table named after its task alone gets the values as its rows' names."""
    values = list(values)

    def name(row: str, value: Any) -> str:
        return f"{row + ', ' if table.row_in_titles else ''}{setting} = {value}"

    rows = tuple(name(row, v) for row in table.rows for v in values)
    cells = tuple(dataclasses.replace(c, row=name(c.row, v)) for c in table.cells for v in values)
    return dataclasses.replace(table, title=f"{table.title}, by {setting}", rows=rows, cells=cells, row_in_titles=True)


def group_table(table: Table, setting: str, value: Any) -> Table:
    """``table`` for one value of ``setting`` (:func:`split_by`'s group): the same rows and cells, the
    value in its name and title, so that each group draws as a panel of its own."""
    slug = "".join(ch if ch.isalnum() else "_" for ch in f"{setting}_{value}")
    return dataclasses.replace(table, name=f"{table.name}_{slug}", title=f"{table.title}, {setting} = {value}")


def _rate(r: CellResult | None) -> str:
    """A cell's headline rate with its interval and seeds, and its per-seed physical count."""
    if r is None or not r.n or r.headline is None:
        return "—"
    return f"{r.headline.text()} ({r.n}) · physical {r.successes}/{r.n}"


def _difference(a: int, an: int, b: int, bn: int) -> str:
    lo, hi = difference_interval(a, an, b, bn)
    return f"{a / an - b / bn:+.2f} [{lo:+.2f}, {hi:+.2f}], p = {fisher_exact(a, an, b, bn):.2g}"


def _shift(a: tuple[float, ...], b: tuple[float, ...]) -> str:
    """Medians of two samples and the two-sided Mann–Whitney p that neither tends to exceed the other:
    exact where no value is tied, else the normal approximation with the tie correction (the exact
    null distribution assumes no ties)."""
    from scipy.stats import mannwhitneyu

    if not a or not b:
        return ""
    tied = len(set(a) | set(b)) < len(a) + len(b)
    p = mannwhitneyu(a, b, alternative="two-sided", method="asymptotic" if tied else "exact").pvalue
    return f"{np.median(a):.2f} vs {np.median(b):.2f}, p = {p:.2g}"


def render_comparison(table: Table, setting: str, groups: list[tuple[Any, list[CellResult]]]) -> str:
    """Markdown: the table's cells side by side for each value of ``setting`` (``groups``: value and
    :func:`collect` of that value's results), one row per cell with results, the thesis value beside:
    each value's headline rate with its interval over seeds and its per-seed physical count. With
    exactly two values, the first minus the second: under the headline reading (Newcombe's interval
    from the seed-level intervals, permutation p over seeds), under the per-seed physical criterion
    and the per-seed return threshold (Newcombe's interval and Fisher's exact p); and, with more
    power than a rate at ten seeds, the two medians of the seeds' final returns and of their
    fractions of rollouts balanced, each with the Mann–Whitney p. Under the table, each group's
    seeds on which the two per-seed verdicts differ or that a fresh evaluation would flip with
    probability above 5 %."""
    by = [{(r.cell.row, r.cell.method): r for r in results} for _, results in groups]
    names = [f"{setting} = {value}" for value, _ in groups]
    paired = len(groups) == 2
    head = ["", "method", "thesis", *names]
    if paired:
        a, b = (str(value) for value, _ in groups)
        head += [f"headline: {a} − {b} [95 %], permutation p", f"per seed, physical: {a} − {b} [95 %], Fisher p",
                 f"per seed, return: {a} − {b} [95 %], Fisher p",
                 f"final return, median: {a} vs {b}, Mann–Whitney p", f"balanced, median: {a} vs {b}, Mann–Whitney p"]
    lines = [f"**{table.title}**, by {setting} — headline rate ({_headline_caption([r for _, rs in groups for r in rs])}) "
             "[95 % interval over seeds] (seeds) · successes by the per-seed physical criterion", "",
             "| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for cell in table.cells:
        key = (cell.row, cell.method)
        rs = [g.get(key) for g in by]
        if not any(r is not None and r.n for r in rs):
            continue
        thesis = "–" if cell.thesis is None else f"{cell.thesis:.2f}"
        row = [cell.row, METHODS[cell.method].label, thesis, *(_rate(r) for r in rs)]
        if paired:
            ra, rb = rs
            both = ra is not None and rb is not None and ra.n and rb.n
            heads = both and ra.headline is not None and rb.headline is not None and \
                ra.headline.reading == rb.headline.reading
            row.append(readings.compare(ra.headline, rb.headline).text() if heads else "")
            row.append(_difference(ra.successes, ra.n, rb.successes, rb.n) if both else "")
            by_return = both and ra.return_successes is not None and rb.return_successes is not None
            row.append(_difference(ra.return_successes, ra.n, rb.return_successes, rb.n) if by_return else "")
            row.append(_shift(ra.final_returns, rb.final_returns) if both else "")
            row.append(_shift(ra.final_balanced, rb.final_balanced) if both else "")
        lines.append("| " + " | ".join(row) + " |")
    if len(lines) == 4:
        return f"**{table.title}**, by {setting}: no complete results for this table."
    notes = [note for name, (_, results) in zip(names, groups) for note in _cell_notes(results, name)]
    return "\n".join(lines + _closing(notes, any(r.unsure for _, results in groups for r in results)))


def render_curves(summaries: list[dict[str, Any]]) -> str:
    """Markdown: the evaluated return per trial of every result (one row each), seeds sorted, and the
    final trial's fraction of rollouts meeting the physical criterion (balanced: cart-pole; upright:
    unicycle) with the standard error of its final return, where :func:`judge` added them."""
    rows = sorted(summaries, key=lambda s: (s["config"].task, s["config"].method, s["config"].k, s["config"].seed))
    if not rows:
        return ""
    n = max(len(s["eval_return"]) for s in rows)
    lines = ["| experiment | success (return) | " + " | ".join(str(i) for i in range(n))
             + " | final ± SE | final balanced / upright | wall (min) |", "|---" * (n + 5) + "|"]
    for s in rows:
        c = s["config"]
        vals = [f"{v:.1f}" for v in s["eval_return"]] + [""] * (n - len(s["eval_return"]))
        ret = "" if s.get("return_success") is None else f" ({'yes' if s['return_success'] else 'no'})"
        frac = s.get("final_balanced")
        frac = "" if frac is None else f"{frac:.2f}"
        se = s.get("final_se", math.nan)
        lines.append(f"| {c.task} {METHODS[c.method].label} k={c.k:g} seed {c.seed} | {'yes' if s['success'] else 'no'}{ret} | "
                     + " | ".join(vals) + f" | {s['eval_return'][-1]:.1f} ± {se:.1f} | {frac} | {s['wall_seconds'] / 60:.0f} |")
    return "\n".join(lines)


def seed_returns(summaries: list[dict[str, Any]]) -> np.ndarray:
    """(seeds, trials) evaluated returns over the trials every seed has."""
    n = min(len(s["eval_return"]) for s in summaries)
    return np.array([np.asarray(s["eval_return"][:n], dtype=float) for s in summaries])


def quartiles(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(25th percentile, median, 75th percentile) over the seeds (axis 0), per trial (linear interpolation)."""
    q = np.percentile(values, [25.0, 50.0, 75.0], axis=0)
    return q[0], q[1], q[2]


def render_cell_curves(table: Table, summaries: list[dict[str, Any]], preset: str | None = "thesis",
                       custom: bool = False) -> str:
    """Markdown: per cell with results, the median and the 25th and 75th percentiles over its seeds of
    the evaluated return per trial — the curves figure's bold line and band, as numbers. Cells count
    as in :func:`collect`."""
    cells = [(cell, cell_summaries(table, cell, summaries, preset, custom)) for cell in table.cells]
    cells = [(cell, rows) for cell, rows in cells if rows]
    if not cells:
        return ""
    returns = [seed_returns(rows) for _, rows in cells]
    n = max(r.shape[1] for r in returns)
    lines = [f"**{table.title}**, evaluated return per trial over each cell's seeds: median [25th, 75th percentile]", "",
             "| | method | seeds | " + " | ".join(str(i) for i in range(n)) + " |", "|---" * (n + 3) + "|"]
    for (cell, rows), r in zip(cells, returns):
        q25, med, q75 = quartiles(r)
        vals = [f"{m:.2f} [{a:.2f}, {b:.2f}]" for a, m, b in zip(q25, med, q75)] + [""] * (n - r.shape[1])
        lines.append(f"| {cell.row} | {METHODS[cell.method].label} | {len(rows)} | " + " | ".join(vals) + " |")
    return "\n".join(lines)


def _seed_ranges(seeds: list[int]) -> str:
    """Sorted, distinct seeds as ranges: ``[0, 1, 2, 5, 7, 8]`` -> ``"0–2, 5, 7–8"``."""
    parts, start = [], None
    for i, seed in enumerate(seeds):
        if start is None:
            start = seed
        if i + 1 == len(seeds) or seeds[i + 1] != seed + 1:
            parts.append(f"{start}" if start == seed else f"{start}–{seed}")
            start = None
    return ", ".join(parts)


def render_seeds(table: Table, summaries: list[dict[str, Any]], preset: str | None = "thesis",
                 custom: bool = False) -> str:
    """Markdown: one row per cell with results, its seeds in order with each seed's final evaluated
    return (the mean of the final trial's evaluation rollouts) and the fraction of those rollouts that
    meet the physical criterion (balanced: cart-pole; upright: unicycle), then the cell's count by the
    criterion and, for the cart-pole, by the thesis' return threshold. ``summaries`` must have
    passed through :func:`judge` (``final_balanced``); the cells count as in :func:`collect`."""
    lines = []
    for cell in table.cells:
        rows = cell_summaries(table, cell, summaries, preset, custom)
        if not rows:
            continue
        judged = [s for s in rows if s.get("return_success") is not None]
        by_return = f"{sum(bool(s['return_success']) for s in judged)} / {len(judged)}" if judged else "–"
        below = [s["per_seed"].get("trial_return") if "per_seed" in s else None for s in rows]
        below = "–" if any(b is None for b in below) else ", ".join(f"{b:.2f}" for b in below)
        lines.append(f"| {cell.row} | {METHODS[cell.method].label} | {_seed_ranges([s['config'].seed for s in rows])} | "
                     + ", ".join(f"{s['final_return']:.2f}" for s in rows) + f" | {below} | "
                     + ", ".join(f"{s['final_balanced']:.2f}" for s in rows) + " | "
                     + f"{sum(bool(s['success']) for s in rows)} / {len(rows)} | {by_return} |")
    if not lines:
        return ""
    return "\n".join([f"**{table.title}**, every counted seed: final returns (the mean of the final trial's evaluation "
                      "rollouts), the fraction of those rollouts below the threshold and the fraction meeting the "
                      "physical criterion, and the per-seed counts", "",
                      "| | method | seeds | final returns | below-threshold fractions | balanced / upright fractions "
                      "| per seed, physical | per seed, mean return |",
                      "|---|---|---|---|---|---|---|---|", *lines])
