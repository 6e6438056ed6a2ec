"""Figures of learning experiments, as rerun recordings (:mod:`pipps.charts`; ``pipps plot --figure``).

* :func:`record_cells` — the success-rate tables as a chart: per table, for each method against the
  table's rows (k), the headline rate (per trial by the return threshold; by the physical criterion
  where a task has no threshold) with its 95 % interval over seeds, the per-trial physical rate as a
  bar, every per-seed reading as a small marker of its own shape beside them (fractions of seeds, no
  interval), and the
  thesis' rate (Tables 4.1–4.4; the thesis has no such figure);
* :func:`record_curves` — one panel per table cell: the evaluated return per trial over the cell's
  seeds (median, interquartile band, each seed), with the success threshold (the learning-efficiency
  plots of thesis Figs. 4.16/4.17, per cell); for a task without a return threshold (the unicycle),
  whose success is judged on the fraction of rollouts meeting its criterion, that fraction per
  trial too;
* :func:`record_diagnostics` — per experiment group, the final trial's predicted trajectories of
  the task's panel component (:class:`pipps.tasks.PlotInfo`: the cart-pole's pole angle, the
  unicycle's wheel pitch) against the real rollout, TP's k_LR per time step and the per-step
  gradient variances (ours).

What differs between tasks comes from the task's record (:class:`pipps.tasks.TaskSpec`): its
success criterion (:mod:`pipps.reporting.verdicts`) and its :class:`~pipps.tasks.PlotInfo`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pipps import charts as ch
from pipps.experiments.methods import METHODS
from pipps.experiments.records import ExperimentResult, MomentPrediction, ParticlePrediction
from pipps.reporting.readings import reading
from pipps.reporting.tables import Cell, CellResult, Table, quartiles, seed_returns
from pipps.reporting.verdicts import criterion, reads_upright

PANEL = (480.0, 340.0)
#: one colour per experiment group in the diagnostics figure
PALETTE = [(31, 119, 180), (214, 39, 40), (44, 160, 44), (255, 127, 14), (148, 103, 189), (140, 86, 75)]


def method_color(method: str):
    """The method's colour in the registry (:mod:`pipps.experiments.methods`)."""
    return METHODS[method].colour


# -- table cells ------------------------------------------------------------------------------------------


def cells_figure(tables: list[tuple[Table, list[CellResult]]]) -> ch.Figure:
    """One panel per table: success rate (y) against the table's rows (x), methods side by side."""
    charts = []
    for table, results in tables:
        methods = _methods_with_results(table, results)
        x = ch.categorical("observation-noise variance multiplier k" if table.rows[0].startswith("k =") else "",
                           [row.removeprefix("k = ") for row in table.rows])
        y = ch.Axis("success rate", -0.04, 1.18, ticks=(0.0, 0.2, 0.4, 0.6, 0.8, 1.0),
                    tick_labels=("0", "0.2", "0.4", "0.6", "0.8", "1"))
        title = f"{table.title.split(' — ')[0]}: {table.title.split(' — ')[-1]}"
        charts.append(ch.chart(f"cells/table_{table.name.replace('.', '_')}", title, x, y,
                               (max(PANEL[0], 160.0 + 60.0 * len(table.rows) * max(1, len(methods))), PANEL[1] + 40)))
    width = max(c.size[0] for c in charts)
    charts = [ch.Chart(c.path, c.title, c.x, c.y, (width, c.size[1]), c.margins) for c in charts]
    methods = list(dict.fromkeys(m for t, rs in tables for m in _methods_with_results(t, rs)))
    per_trial_return = any(r.n and r.headline is not None and r.headline.reading.name == "trial_return"
                           for _, rs in tables for r in rs)
    headline = "rollouts with return < threshold" if per_trial_return else "rollouts meeting the physical criterion"
    keys = [*[ch.Key(METHODS[m].label, method_color(m), "interval") for m in methods],
            ch.Key(f"ours: fraction of {headline}, 95 % interval over seeds (label: seeds)", ch.GREY, "interval")]
    if per_trial_return:
        keys.append(ch.Key("ours: fraction of rollouts meeting the physical criterion", ch.GREY, "bar"))
    drawn = {name for _, rs in tables for r in rs if r.n for name in r.by_reading}
    keys += [ch.Key(f"ours: {reading(name).label} (fraction of seeds, no interval)", ch.GREY, shape, DOT_SIZE)
             for name, _, shape in SEED_DOTS if name in drawn]
    keys.append(ch.Key("thesis (100 seeds)", ch.GREY, "diamond"))
    return ch.figure(charts, 1 if len(charts) == 1 else 2, keys, "cells/legend")


#: the per-seed readings drawn beside each headline, in this order, as small hollow markers this many
#: pixels right of it (past the headline's cap and the physical bar), each its own shape; each is a
#: fraction of seeds
SEED_DOTS = (("seed_return", 13.0, "square"), ("system_trial", 22.0, "triangle"),
             ("seed_physical", 31.0, "cross"), ("system_physical", 40.0, "plus"))
#: the half-width of those markers (UI points), against the headline's radius 4
DOT_SIZE = 3.5


def _methods_with_results(table: Table, results: list[CellResult]) -> list[str]:
    return [m for m in table.methods if any(r.cell.method == m and r.n for r in results)]


def _dodge(i: int, n: int) -> float:
    return (i - (n - 1) / 2) * min(0.4, 0.8 / max(n, 1))


def record_cells(tables: list[tuple[Table, list[CellResult]]], out: str | Path) -> Path:
    """Recording of :func:`cells_figure`; ``tables`` pairs each table with :func:`pipps.reporting.tables.collect`'s cells."""
    fig = cells_figure(tables)
    with ch.recording(out, "pipps-cells", fig) as rec:
        ch.draw(rec, fig)
        for c, (table, results) in zip(fig.charts, tables):
            methods = _methods_with_results(table, results)
            by = {(r.cell.row, r.cell.method): r for r in results}
            for mi, m in enumerate(methods):
                color = method_color(m)
                rows = [(ri, by[(row, m)]) for ri, row in enumerate(table.rows) if (row, m) in by]
                have = [(ri, r) for ri, r in rows if r.n]
                x = np.array([ri + _dodge(mi, len(methods)) for ri, _ in have])
                rate = np.array([r.rate for _, r in have])
                lo = np.array([r.interval[0] for _, r in have])
                hi = np.array([r.interval[1] for _, r in have])
                ch.intervals(rec, c, f"{m}/interval", x, lo, hi, color, width=1.3)
                ch.points(rec, c, f"{m}/rate", x, rate, color, size=4.0)
                physical = [(xi, r.by_reading["trial_physical"].rate) for xi, (_, r) in zip(x, have)
                            if r.headline is not None and r.headline.reading.name != "trial_physical"
                            and "trial_physical" in r.by_reading]
                top = [max(h, r.cell.thesis or 0.0) for h, (_, r) in zip(hi, have)]  # the label above its cell's marks
                ch.text(rec, c, f"{m}/counts", x, top, [f"{r.n}" for _, r in have], above=True)
                if physical:
                    ch.markers(rec, c, f"{m}/physical_rate", [a for a, _ in physical], [b for _, b in physical], color,
                               "bar")
                _seed_dots(rec, c, m, x, [r for _, r in have], color)
                thesis = [(ri + _dodge(mi, len(methods)), r.cell.thesis) for ri, r in rows if r.cell.thesis is not None]
                if thesis:
                    ch.markers(rec, c, f"{m}/thesis", [a for a, _ in thesis], [b for _, b in thesis], color, "diamond")
    return Path(out)


def _seed_dots(rec, c: ch.Chart, method: str, x: np.ndarray, results: list[CellResult], color) -> None:
    """Each per-seed reading of each cell (:data:`SEED_DOTS`) as a small dot right of the cell's headline
    at ``x``: the fraction of seeds that pass it, without an interval."""
    per_unit = c.xy(1.0, 0.0)[0] - c.xy(0.0, 0.0)[0]  # pixels per unit of the categorical x axis
    for name, offset, shape in SEED_DOTS:
        got = [(xi + offset / per_unit, r.by_reading[name].rate) for xi, r in zip(x, results) if name in r.by_reading]
        if got:
            ch.markers(rec, c, f"{method}/{name}", [a for a, _ in got], [b for _, b in got], color, shape,
                       size=DOT_SIZE)


# -- learning curves per cell -----------------------------------------------------------------------------


def curves_figure(table: Table, cells: list[tuple[Cell, list[dict[str, Any]]]]) -> ch.Figure:
    """A panel per cell of ``table`` that has results, laid out as the table (rows × methods)."""
    cells = [(c, rs) for c, rs in cells if rs]
    if not cells:
        raise ValueError(f"table {table.name}: no cell has results to draw")
    rows = [row for row in table.rows if any(c.row == row for c, _ in cells)]
    methods = [m for m in table.methods if any(c.method == m for c, _ in cells)]
    returns = [seed_returns(rs) for _, rs in cells]
    cfg = cells[0][1][0]["config"]
    success, plot = criterion(cfg), cfg.task_spec.plot
    fractions = success.threshold is None  # judged by its criterion alone: its fraction per trial beside the return
    trials = max(r.shape[1] for r in returns)
    first = "0" if cfg.num_random == 1 else f"0–{cfg.num_random - 1}"
    x = ch.Axis(f"trial ({first}: random actions)", -0.5, trials - 0.5)
    ylabel = f"evaluated return (total cost, mean of {cfg.eval_rollouts} rollouts)"
    include = [0.0] if success.threshold is None else [0.0, success.threshold]
    if plot.log_returns:
        y = ch.Axis(ylabel, *ch.data_range(returns, log=True), log=True)
    else:
        y = ch.Axis(ylabel, *ch.data_range(returns, include=include, pad=0.04))
    by = {(c.row, c.method): (c, rs) for c, rs in cells}
    charts = []
    for row in rows:
        for m in methods:
            c, rs = by.get((row, m), (None, []))
            name = f"{row + ', ' if table.row_in_titles else ''}{METHODS[m].label}"
            path = (f"curves/{row}_{m}".replace(" ", "").replace("=", "").replace(".", "p").replace("⁻", "m")
                    .replace(",", "_"))
            seeds = f"{len(rs)} seed{'s' if len(rs) != 1 else ''}" if rs else "no results"
            charts.append(ch.chart(path, f"{name}: {seeds}", x, y, PANEL))
            if fractions:
                charts.append(ch.chart(f"{path}_{success.name}", f"{name}: rollouts {success.name}, {seeds}", x,
                                       ch.Axis(f"fraction of the {cfg.eval_rollouts} rollouts {success.name}", -0.04,
                                               1.04), PANEL))
    keys = [ch.Key("median over seeds", ch.BLACK), ch.Key("25–75 % of seeds", ch.lighter(ch.BLACK, 0.8), "band"),
            ch.Key("each seed", ch.lighter(ch.BLACK, 0.55), "line")]
    if fractions:
        keys.append(ch.Key(f"success: ≥ {success.fraction:.0%} of the final trial's rollouts {success.name}", ch.GREY,
                           "dash"))
    else:
        keys.append(ch.Key(f"thesis' success threshold: return < {success.threshold:g} (ours: the physical criterion)",
                           ch.GREY, "dash"))
    return ch.figure(charts, len(methods) * (2 if fractions else 1), keys, "curves/legend")


def record_curves(table: Table, cells: list[tuple[Cell, list[dict[str, Any]]]], out: str | Path) -> Path:
    """Recording of :func:`curves_figure`; ``cells`` pairs each cell with its counted result summaries
    (:func:`pipps.reporting.tables.cell_summaries`)."""
    fig = curves_figure(table, cells)
    with ch.recording(out, "pipps-curves", fig) as rec:
        ch.draw(rec, fig)
        charts = iter(fig.charts)
        rows = [row for row in table.rows if any(c.row == row and rs for c, rs in cells)]
        methods = [m for m in table.methods if any(c.method == m and rs for c, rs in cells)]
        lookup = {(c.row, c.method): rs for c, rs in cells if rs}
        success = criterion(next(iter(lookup.values()))[0]["config"])
        for row in rows:
            for m in methods:
                rs = lookup.get((row, m), [])
                panels = [next(charts)] + ([next(charts)] if success.threshold is None else [])
                if not rs:
                    continue
                success = criterion(rs[0]["config"])
                _draw_spread(rec, panels[0], seed_returns(rs), method_color(m))
                if success.threshold is None:
                    series = _criterion_series(rs, success)
                    n = min(len(f) for f in series)
                    _draw_spread(rec, panels[1], np.array([f[:n] for f in series], dtype=float), method_color(m))
                    _hline(rec, panels[1], success.fraction)
                else:
                    _hline(rec, panels[0], success.threshold)
    return Path(out)


def _criterion_series(rs: list[dict[str, Any]], success) -> list[np.ndarray]:
    """Each result's fraction of evaluation rollouts meeting the criterion, per trial: the stored
    ``upright_fraction`` for a "never fell" rule (every file has it), else ``balanced_fraction``."""
    key = "upright_fraction" if reads_upright(success) else "balanced_fraction"
    return [np.asarray(s[key], dtype=float) for s in rs]


def _draw_spread(rec, c: ch.Chart, values: np.ndarray, color) -> None:
    t = np.arange(values.shape[1])
    q25, med, q75 = quartiles(values)
    ch.band(rec, c, "quartiles", t, q25, q75, ch.lighter(color, 0.8))
    for i, v in enumerate(values):
        ch.line(rec, c, f"seeds/{i}", t, v, ch.lighter(color, 0.55), width=0.6)
    ch.line(rec, c, "median", t, med, color, width=1.6, order=20.0)


def _hline(rec, c: ch.Chart, y: float) -> None:
    ch.line(rec, c, "threshold", [c.x.lo, c.x.hi], [y, y], ch.GREY, width=1.0, dash=True, order=15.0)


# -- final-trial diagnostics ----------------------------------------------------------------------------------


def group_label(r: ExperimentResult) -> str:
    """A group's name for a reader: method, k, and the settings that set it apart."""
    c = r.config
    spec = c.task_spec
    cost = c.cost_name
    text = f"{METHODS[c.method].label}, k = {c.k:g}"
    if len(spec.costs) > 1:  # the cost sets groups apart only where the task has several
        text += f", {cost} cost"
    if c.centre_std is None and c.policy == "rbf" and c.policy_init == "start":
        text += ", start-state centres"
    return text


def diagnostics_figure(groups: list[tuple[str, ExperimentResult]]) -> ch.Figure:
    """Per group the final trial's predictions; then k_LR and the gradient variances per time step."""
    charts = [prediction_chart(f"diagnostics/predictions_{gi}",
                               f"{group_label(r)}, seed {r.config.seed}: final trial {r.trials[-1].index}", r)
              for gi, (_, r) in enumerate(groups)]
    with_diag = [(n, r) for n, r in groups if r.trials[-1].diagnostics is not None]
    if with_diag:
        T = max(len(r.trials[-1].diagnostics.k_lr) for _, r in with_diag)
        step = ch.Axis("time step t", 0.5, T + 0.5)
        variances = [getattr(r.trials[-1].diagnostics, f"var_{p}") for _, r in with_diag for p in ("rp", "lr")]
        charts.append(ch.chart("diagnostics/k_lr", "k_LR per step, mean over the final trial's policy steps", step,
                               ch.Axis("k_LR: weight of the LR estimate", -0.04, 1.04), PANEL))
        charts.append(ch.chart("diagnostics/variance", "gradient variance per step (same average)", step,
                               ch.Axis("variance of the step's gradient", *ch.data_range(variances, log=True), log=True), PANEL))
    keys = [ch.Key(group_label(r), PALETTE[gi % len(PALETTE)]) for gi, (_, r) in enumerate(groups)]
    keys += [ch.Key("real rollout", ch.BLACK), ch.Key("predicted particles", ch.lighter(ch.GREY, 0.4)),
             ch.Key("moment matching: mean ± 2 sd", ch.GREY, "dash")]
    if with_diag:
        keys += [ch.Key("σ²_RP: pathwise part", ch.GREY, "line"), ch.Key("σ²_LR: likelihood-ratio part", ch.GREY, "dash")]
    return ch.figure(charts, min(3, len(charts)), keys, "diagnostics/legend")


def _panel(r: ExperimentResult) -> tuple[int, np.ndarray, str, float]:
    """The task's panel component (:class:`pipps.tasks.PlotInfo`): its model-state index, the real
    rollout's values of it, its label, and the control interval."""
    from pipps.experiments.state import make_experiment_task

    plot = r.config.task_spec.plot
    task = make_experiment_task(r.config)
    final = r.trials[-1]
    if plot.panel_true is not None:
        real = final.states[:, plot.panel_true]
    else:  # the real rollout in the model state's coordinates
        import jax

        real = np.asarray(jax.vmap(task.simulator.sim_to_model)(np.asarray(final.states)))[:, plot.panel]
    return plot.panel, np.asarray(real), plot.label(plot.panel), task.problem.dt


def prediction_chart(path: str, title: str, r: ExperimentResult, size=PANEL) -> ch.Chart:
    """A chart of the final trial's panel component (the angle) against time (s), its range fitted to
    the real rollout and the prediction."""
    final = r.trials[-1]
    idx, real, label, dt = _panel(r)
    values = [real]
    pred = final.predicted
    if isinstance(pred, ParticlePrediction):
        values.append(pred.particles[:, :, idx])
    elif isinstance(pred, MomentPrediction):
        m, s = _gaussian_angle(pred, idx)
        values += [m - 2 * s, m + 2 * s]
    T = final.states.shape[0] - 1
    return ch.chart(path, title, ch.Axis("time (s)", -0.02 * T * dt, 1.02 * T * dt), ch.Axis(label, *ch.data_range(values)), size)


def _gaussian_angle(pred: MomentPrediction, idx: int) -> tuple[np.ndarray, np.ndarray]:
    return pred.mean[:, idx], np.sqrt(np.maximum(pred.cov[:, idx, idx], 0.0))


def record_diagnostics(groups: list[tuple[str, ExperimentResult]], out: str | Path) -> Path:
    """Recording of :func:`diagnostics_figure`; ``groups`` pairs a group's name with one of its results."""
    fig = diagnostics_figure(groups)
    with ch.recording(out, "pipps-diagnostics", fig) as rec:
        ch.draw(rec, fig)
        for gi, (_, r) in enumerate(groups):
            draw_prediction(rec, fig.charts[gi], r, PALETTE[gi % len(PALETTE)])
        if len(fig.charts) > len(groups):
            k_chart, v_chart = fig.charts[len(groups):]
            for gi, (_, r) in enumerate(groups):
                d = r.trials[-1].diagnostics
                if d is None:
                    continue
                color = PALETTE[gi % len(PALETTE)]
                t = np.arange(1, len(d.k_lr) + 1)
                ch.line(rec, k_chart, f"group_{gi}", t, d.k_lr, color, width=1.4)
                ch.line(rec, v_chart, f"group_{gi}/rp", t, d.var_rp, color, width=1.4)
                ch.line(rec, v_chart, f"group_{gi}/lr", t, d.var_lr, color, width=1.4, dash=True)
    return Path(out)


def draw_prediction(rec, c: ch.Chart, r: ExperimentResult, color) -> None:
    """The final trial's predicted panel component (particles, or PILCO's mean ± 2 sd) and the real rollout."""
    final = r.trials[-1]
    idx, real_all, _, dt = _panel(r)
    pred = final.predicted
    if isinstance(pred, ParticlePrediction):
        x = pred.particles[:, :, idx]
        t = np.arange(x.shape[0]) * dt
        for j in range(x.shape[1]):
            ch.line(rec, c, f"particles/{j}", t, x[:, j], ch.lighter(color, 0.45), width=0.6, order=5.0)
    elif isinstance(pred, MomentPrediction):
        m, s = _gaussian_angle(pred, idx)
        t = np.arange(len(m)) * dt
        ch.line(rec, c, "gaussian/mean", t, m, color, width=1.4)
        for k in (-2.0, 2.0):
            ch.line(rec, c, f"gaussian/{'lo' if k < 0 else 'hi'}", t, m + k * s, color, width=1.0, dash=True)
    valid = np.concatenate([[True], np.asarray(final.valid, bool)])
    real = real_all[valid]
    ch.line(rec, c, "real", np.arange(len(real)) * dt, real, ch.BLACK, width=1.6, order=20.0)
