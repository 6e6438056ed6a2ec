"""The figures (pipps.charts, pipps.reporting.figures, pipps.studies.figures, ``pipps plot --figure``).

Each figure is recorded from small synthetic results and read back from the .rrd with rerun's own
reader: the entities and their geometry (where the data land on the axes), and the blueprint (every
viewer panel hidden, 2-d views without title bars, bounds). Rendering a PNG needs the viewer and a
virtual display; that test is marked slow.
"""

from __future__ import annotations

import dataclasses
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipps import charts as ch
from pipps.cli import main
from pipps.experiments.config import resolve_config
from pipps.reporting.readings import clustered_interval, seed_values
from pipps.experiments.records import (Diagnostics, ExperimentResult, MomentPrediction, ParticlePrediction, Timings,
                                       TrialResult)
from pipps.reporting.tables import TABLES, cell_summaries, collect, wilson_interval
from pipps.studies.bench import BenchEntry, BenchResult
from pipps.studies.gradients import LandscapeResult, Samples, VarianceResult, interval

ROOT = Path(__file__).resolve().parents[1]
UNICYCLE = sorted((ROOT / "results/thesis").glob("unicycle_default_k1_tp_thesis_s*.h5"))


def read_rrd(path):
    """(recording, blueprint): entity path → component → values, for every static chunk, and whether any
    chunk of the recording is on a timeline."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)

    def entities(stream):
        out, timed = {}, False
        for c in stream:
            timed |= not c.is_static and bool(set(c.timeline_names) - {"log_time", "log_tick"})
            rb = c.to_record_batch()
            comps = out.setdefault(c.entity_path, {})
            for name in rb.schema.names:
                if ":" in name:  # a component: one list of instances per row, concatenated
                    rows = rb.column(name).to_pylist()
                    comps.setdefault(name.split(":", 1)[1], []).extend(v for row in rows for v in (row or []))
        return out, timed

    rec, timed = entities(reader.stream())
    bp, _ = entities(reader.stream(store=reader.blueprints()[0]))
    return rec, bp, timed


def strips(rec, path):
    return [np.array(s) for s in rec[path]["strips"]]


def positions(rec, path):
    return np.array(rec[path]["positions"]).reshape(-1, 2)


def labels(rec, prefix):
    return [t for p, comps in rec.items() if p.startswith(prefix) for t in comps.get("labels", [])]


def assert_clean_figure(bp, charts):
    """Every viewer panel hidden, one title-less 2-d view per chart, bounded to the chart's nominal panel."""
    for panel in ("/top_panel", "/blueprint_panel", "/selection_panel", "/time_panel"):
        assert bp[panel]["state"] == [1], panel  # PanelState.Hidden
    views = {v["space_origin"][0]: k for k, v in bp.items() if "space_origin" in v}
    for c in charts:
        key = views[f"/{c.path}"]
        assert bp[key]["class_identifier"] == ["2D"] and bp[key]["titlebar"] == [False]
        bounds = bp[f"{key}/VisualBounds2D"]["range"][0]
        assert bounds["x_range"] == [0.0, c.size[0]] and bounds["y_range"] == [-c.size[1], 0.0]


# -- the chart helper --------------------------------------------------------------------------------------


def test_log_axis_places_equal_ratios_at_equal_distances_and_labels_decades():
    a = ch.Axis("P", 10.0, 1000.0, log=True)
    np.testing.assert_allclose(a.fraction([10.0, 100.0, 1000.0, 0.0]), [0.0, 0.5, 1.0, np.nan])
    values, names, minor = ch.Axis("v", 1.0, 1e21, log=True).tick_marks()
    assert names == ["1", "10⁴", "10⁸", "10¹²", "10¹⁶", "10²⁰"] and 1e3 in minor  # every 4th decade labelled
    assert ch.Axis("v", 0.02, 1.0, log=True).tick_marks()[1] == ["0.02", "0.05", "0.1", "0.2", "0.5", "1"]
    assert ch.Axis("x", 0.0, 1.0).tick_marks()[1] == ["0", "0.2", "0.4", "0.6", "0.8", "1.0"]
    assert ch.Axis("x", -30.0, 30.0).tick_marks()[1] == ["−20", "0", "20"]  # minus signs, not hyphens
    with pytest.raises(ValueError, match="log axis"):
        ch.Axis("v", 0.0, 1.0, log=True)


def test_clip_cuts_a_line_at_the_plot_box_and_breaks_it_at_undefined_points():
    c = ch.chart("t", "", ch.Axis("x", 0.0, 1.0), ch.Axis("y", 0.0, 1.0), (300.0, 300.0))
    left, _, bottom, _ = c.margins
    w, h = c.box
    pieces = ch.clip(c, c.xy([0.0, 0.5, 1.0], [0.5, 1.5, 0.5]))  # up through the top edge and back
    assert len(pieces) == 2
    np.testing.assert_allclose(pieces[0][-1], [left + 0.25 * w, -(bottom + h)])
    np.testing.assert_allclose(pieces[1][0], [left + 0.75 * w, -(bottom + h)])
    assert len(ch.clip(c, c.xy([0.1, 0.2, 0.3, 0.4], [0.1, np.nan, 0.3, 0.4]))) == 1  # the NaN breaks it


# -- study figures ----------------------------------------------------------------------------------------


def _samples(var, T=5, k=0.5):
    rng = np.random.default_rng(0)
    return Samples(rng.normal(size=8) * math.sqrt(var), var, np.full(T, k), 0)


def _variance_result():
    P = np.array([10, 100, 1000])
    grid = {"rp": [[_samples(1e3 / p) for p in P], [_samples(1e18) for _ in P]],
            "lr": [[_samples(1e4 / p) for p in P], [_samples(3e4 / p) for p in P]],
            "tp": [[_samples(2e3 / p) for p in P], [_samples(1e4 / p) for p in P]]}
    return VarianceResult("src.h5", 3, np.array([0.0, 1.5]), P, np.ones(2), "random", 20, 0, "library", grid, 1.0)


def test_variance_figure_is_log_log_with_the_exploding_estimator_off_scale(tmp_path):
    from pipps.studies.figures import record_variance, variance_figure

    r = _variance_result()
    out = record_variance(r, tmp_path / "v.rrd")
    rec, bp, timed = read_rrd(out)
    fig, hidden = variance_figure(r)
    assert not timed  # all static: no timeline, no time cursor
    assert_clean_figure(bp, fig.charts + [fig.legend])
    assert [c.path for c in fig.charts] == ["variance/delta_0", "variance/delta_1", "variance/k_lr"]
    assert set(hidden[0]) == set() and set(hidden[1]) == {"rp"}
    # TP at Δ = 0 falls as 1/P: on log-log axes its three points are equally spaced on a straight line
    p = positions(rec, "/variance/delta_0/data/tp_points")
    assert len(p) == 3
    np.testing.assert_allclose(np.diff(p[:, 0]), np.diff(p[:, 0])[0], rtol=1e-5)  # positions are float32
    np.testing.assert_allclose(np.diff(p[:, 1]), np.diff(p[:, 1])[0], rtol=1e-5)
    c0 = fig.charts[0]
    np.testing.assert_allclose(p, c0.xy([10, 100, 1000], [200.0, 20.0, 2.0]), rtol=1e-5)
    # RP at Δ = 1.5 (10¹⁸) lies above the range: nothing of it is drawn, the panel says so
    assert positions(rec, "/variance/delta_1/data/rp_points").size == 0
    assert fig.charts[1].y.hi < 1e18
    assert any("RP off scale" in t for t in labels(rec, "/variance/delta_1/notes"))
    assert labels(rec, "/variance/delta_0/axes/xtick_labels") == ["10", "100", "1000"]
    assert labels(rec, "/variance/delta_0/axes/xlabel") == ["number of particles P"]
    assert "RP" in labels(rec, "/variance/legend") and "TP" in labels(rec, "/variance/legend")


def _landscape_result():
    deltas = np.linspace(0.0, 1.5, 4)
    samples = {"rp": [_samples(v) for v in (1.0, 2.0, 1e12, 1e16)], "tp": [_samples(v) for v in (1.0, 2.0, 3.0, 2.0)],
               "lr": [_samples(v) for v in (9.0, 8.0, 7.0, 6.0)]}
    return LandscapeResult("src.h5", 3, deltas, np.ones(2), "random", 1000, 8, 0, "library", np.array([10, 20, 28, 28.0]),
                           np.array([12, 22, 29, 29.0]), np.array([5, 3, 0.1, 0.0]), samples, 1.0)


def test_landscape_figure_marks_where_rp_leaves_the_gradient_panel(tmp_path):
    from pipps.studies.figures import landscape_figure, record_landscape

    r = _landscape_result()
    rec, bp, timed = read_rrd(record_landscape(r, tmp_path / "l.rrd"))
    fig, hidden = landscape_figure(r)
    assert not timed
    assert_clean_figure(bp, fig.charts)
    a, b, c = fig.charts
    assert set(hidden) == {"rp"} and c.y.log and not b.y.log
    rp = [interval(s.directional)[0] for s in r.samples["rp"]]
    outside = sum(not (b.y.lo <= m <= b.y.hi) for m in rp)
    assert outside >= 2
    assert len(strips(rec, "/landscape/gradient/data/rp/off_range")) == outside  # a triangle per point off the range
    assert len(positions(rec, "/landscape/gradient/data/rp/points")) == 4 - outside
    # the variance panel shows every estimator, RP's explosion included, on its log axis
    assert len(positions(rec, "/landscape/variance/data/rp_points")) == 4
    assert labels(rec, "/landscape/objective/axes/xlabel") == ["Δ: distance along d"]


def _bench_result():
    es = [[BenchEntry(n, p, t * p / 100, m / p, 0.1, 0) for n, t, m in (("rp", 0.02, 1e3), ("tp", 0.04, 5e3)) for p in (30, 300)]
          for _ in range(2)]
    es[1] = [e if e.estimator != "rp" else BenchEntry("rp", e.particles, e.seconds, 1e18, 1.0, 0) for e in es[1]]
    return BenchResult("src.h5", 3, np.array([0.0, 1.5]), np.ones(2), "random", np.zeros((2, 2)), np.array([0.5, 0.9]),
                       "tp", 300, es, 0.1, np.array([40.0, 6.0]), 20, 0, 1.0)


def test_bench_figure_is_log_log_and_marks_the_reference_error(tmp_path):
    from pipps.studies.figures import bench_figure, record_bench

    r = _bench_result()
    rec, bp, _ = read_rrd(record_bench(r, tmp_path / "b.rrd"))
    fig, hidden = bench_figure(r)
    assert_clean_figure(bp, fig.charts)
    c = fig.charts[0]
    assert c.x.log and c.y.log and hidden[1].keys() == {"rp"} and not hidden[0]
    small, large = (positions(rec, f"/bench/delta_0/data/tp_points/P_{p}")[0] for p in (30, 300))
    np.testing.assert_allclose(large, c.xy(0.12, 5e3 / 300))
    assert rec["/bench/delta_0/data/tp_points/P_300"]["radii"][0] < rec["/bench/delta_0/data/tp_points/P_30"]["radii"][0] < 0
    ref = strips(rec, "/bench/delta_0/data/reference_error")
    np.testing.assert_allclose(np.concatenate(ref)[:, 1], c.xy(1.0, 0.5)[1])  # the reference's own error, 0.5


# -- experiment figures --------------------------------------------------------------------------------------


def _summary(method, k, seed, returns, *, task="cartpole_swingup", success=True, return_success=True, upright=None,
             final=None):
    """A judged result summary; ``final = (passes, balanced)`` out of 10 final rollouts gives its per-seed readings."""
    cfg = resolve_config("thesis", task, method=method, seed=seed, **({"k": k, "cost": "angle"} if task != "unicycle" else {}))
    returns = np.asarray(returns, float)
    out = {"config": cfg, "eval_return": returns, "upright_fraction": np.ones(len(returns)) if upright is None else upright,
           "success": success, "return_success": return_success, "final_return": float(returns[-1]), "wall_seconds": 60.0,
           "path": f"{method}_{k}_{seed}.h5"}
    if final is not None:
        passes, balanced = final
        out["per_seed"] = seed_values(seed, np.where(np.arange(10) < passes, 10.0, 20.0), np.arange(10) < balanced,
                                      10.0, 15.0, 0.5)
    return out


def test_curves_figure_draws_median_quartiles_and_threshold_per_cell(tmp_path):
    from pipps.reporting.figures import curves_figure, record_curves

    rows = np.array([[30, 20, 10, 9], [30, 25, 15, 12], [30, 28, 20, 11], [30, 29, 27, 26.0]])
    summaries = [_summary("tp", 1.0, s, r) for s, r in enumerate(rows)] + [_summary("pilco", 9.0, 0, [30, 25, 19, 17.0])]
    table = TABLES["4.1"]
    cells = [(c, cell_summaries(table, c, summaries)) for c in table.cells]
    rec, bp, timed = read_rrd(record_curves(table, cells, tmp_path / "c.rrd"))
    fig = curves_figure(table, cells)
    assert not timed
    assert_clean_figure(bp, fig.charts)
    # laid out as the table: rows k = 1, 9; columns PILCO, TP (a cell without results is an empty panel)
    assert [c.title for c in fig.charts] == ["k = 1, PILCO: no results", "k = 1, TP: 4 seeds", "k = 9, PILCO: 1 seed",
                                             "k = 9, TP: no results"]
    assert fig.columns == 2
    tp = fig.charts[1]
    median = np.concatenate(strips(rec, f"/{tp.path}/data/median"))
    np.testing.assert_allclose(median, tp.xy(np.arange(4), np.median(rows, axis=0)))
    assert len([p for p in rec if p.startswith(f"/{tp.path}/data/seeds/")]) == 4
    band = np.concatenate(strips(rec, f"/{tp.path}/data/quartiles"))
    q25, q75 = np.percentile(rows, [25, 75], axis=0)
    at_trial_2 = band[np.isclose(band[:, 0], tp.xy(2.0, 0.0)[0], atol=0.6)][:, 1]
    np.testing.assert_allclose(sorted(at_trial_2)[0], tp.xy(2.0, q75[2])[1], atol=0.5)  # view y grows downwards
    np.testing.assert_allclose(sorted(at_trial_2)[-1], tp.xy(2.0, q25[2])[1], atol=0.5)
    threshold = np.concatenate(strips(rec, f"/{tp.path}/data/threshold"))
    np.testing.assert_allclose(threshold[:, 1], tp.xy(0.0, 15.0)[1])
    assert not any(p.startswith(f"/{fig.charts[0].path}/data") for p in rec)


def test_unicycle_curves_add_the_upright_fraction_on_which_success_is_judged(tmp_path):
    from pipps.reporting.figures import curves_figure

    table = TABLES["4.4"]
    s = [_summary("tp", 1.0, i, 15.0 / np.arange(1, 36), task="unicycle") for i in range(2)]
    fig = curves_figure(table, [(c, cell_summaries(table, c, s)) for c in table.cells])
    ret, upright = fig.charts
    assert ret.y.log and not upright.y.log and upright.y.label.startswith("fraction") and fig.columns == 2


def test_cells_figure_places_rates_intervals_and_thesis_values(tmp_path):
    from pipps.reporting.figures import cells_figure, record_cells

    tp_final = [(10, 10), (9, 8), (7, 6), (3, 0)]  # (rollouts below the threshold, rollouts balanced) of 10
    summaries = [_summary("tp", 1.0, s, [30, 10.0], success=s < 3, final=f) for s, f in enumerate(tp_final)]
    summaries += [_summary("pilco", 16.0, s, [30, 20.0], success=False, return_success=False, final=(2 - 2 * s, 0))
                  for s in range(2)]
    table = TABLES["4.1"]
    results = collect(table, summaries)
    rec, bp, _ = read_rrd(record_cells([(table, results)], tmp_path / "t.rrd"))
    fig = cells_figure([(table, results)])
    assert_clean_figure(bp, fig.charts)
    c = fig.charts[0]
    assert c.x.tick_labels == ("10⁻²", "1", "4", "9", "16")
    tp = positions(rec, f"/{c.path}/data/tp/rate")
    assert len(tp) == 1
    np.testing.assert_allclose(tp[0, 1], c.xy(0.0, 29 / 40)[1])  # the headline: per trial, return, averaged over seeds
    assert tp[0, 0] > c.xy(1.0, 0.0)[0]  # row "k = 1", TP to the right of its centre (PILCO would be left)
    assert positions(rec, f"/{c.path}/data/pilco/rate")[0, 0] < c.xy(4.0, 0.0)[0]
    lo, hi = clustered_interval([p for p, _ in tp_final], [10] * 4)
    bar = strips(rec, f"/{c.path}/data/tp/interval")[0][:, 1]
    np.testing.assert_allclose(sorted(bar), sorted(c.xy(1.0, [hi, lo])[:, 1]))
    assert labels(rec, f"/{c.path}/data/tp/counts") == ["4"] and labels(rec, f"/{c.path}/data/pilco/counts") == ["2"]
    # the label box hangs below its anchor: it must end above the highest mark of the cell (TP: the thesis' 0.99)
    anchor = positions(rec, f"/{c.path}/data/tp/counts")[0]
    assert anchor[1] + ch.LABEL_DROP + ch.TEXT_HEIGHT <= c.xy(0.0, 0.99)[1]
    anchor = positions(rec, f"/{c.path}/data/pilco/counts")[0]  # PILCO, k = 16: above its interval's top
    assert anchor[1] + ch.LABEL_DROP + ch.TEXT_HEIGHT <= c.xy(0.0, clustered_interval([2, 0], [10, 10])[1])[1]
    # the thesis' rate is marked in every row, ours or not: TP 0.82, 0.99, 0.95, 0.83, 0.40
    diamonds = strips(rec, f"/{c.path}/data/tp/thesis")
    assert len(diamonds) == 5
    centres = np.array([d[:-1].mean(0) for d in diamonds])
    np.testing.assert_allclose(centres[:, 1], c.xy(0.0, [0.82, 0.99, 0.95, 0.83, 0.40])[:, 1])
    physical = strips(rec, f"/{c.path}/data/tp/physical_rate")  # per trial, physical: 24 of 40 rollouts balanced
    np.testing.assert_allclose(physical[0][:, 1], c.xy(0.0, 24 / 40)[1])


def _trial(index, T=30, S=4, predicted=None, diagnostics=None):
    t = np.linspace(0, np.pi, T + 1)
    states = np.zeros((T + 1, S))
    states[:, 3] = t
    return TrialResult(index, "learned", states, states, np.zeros((T, 1)), np.ones(T), np.ones(T, bool), np.array([10.0]),
                       np.array([True]), np.zeros(3), Timings(), predicted=predicted, diagnostics=diagnostics)


def test_diagnostics_figure_has_time_and_angle_axes_and_per_step_panels(tmp_path):
    from pipps.reporting.figures import diagnostics_figure, record_diagnostics

    particles = np.repeat(np.linspace(0, 3.0, 31)[:, None, None], 4, axis=1) * np.ones((1, 1, 4))
    diag = Diagnostics(np.linspace(1, 0, 30), np.logspace(3, -1, 30), np.logspace(3, 1, 30), np.zeros(6), np.zeros(30))
    tp = ExperimentResult(resolve_config("thesis", "cartpole_swingup", method="tp"),
                          [_trial(1, predicted=ParticlePrediction(particles, np.zeros(30)), diagnostics=diag)])
    mean = np.zeros((31, 4))
    mean[:, 3] = np.linspace(0, 3.1, 31)
    pilco = ExperimentResult(resolve_config("thesis", "cartpole_swingup", method="pilco"),
                             [_trial(1, predicted=MomentPrediction(mean, np.tile(0.01 * np.eye(4), (31, 1, 1)), np.zeros(31)))])
    groups = [("tp", tp), ("pilco", pilco)]
    rec, bp, timed = read_rrd(record_diagnostics(groups, tmp_path / "d.rrd"))
    fig = diagnostics_figure(groups)
    assert not timed
    assert_clean_figure(bp, fig.charts)
    pred = fig.charts[0]
    assert pred.x.label == "time (s)" and pred.y.label == "pole angle θ (rad)"
    real = np.concatenate(strips(rec, f"/{pred.path}/data/real"))
    np.testing.assert_allclose(real, pred.xy(np.arange(31) * 0.1, np.linspace(0, np.pi, 31)))  # dt = 0.1 s
    assert len([p for p in rec if p.startswith(f"/{pred.path}/data/particles/")]) == 4
    assert {"/diagnostics/predictions_1/data/gaussian/lo", "/diagnostics/predictions_1/data/gaussian/hi"} <= set(rec)
    k_chart, v_chart = fig.charts[2:]
    assert v_chart.y.log and not k_chart.y.log
    assert "/diagnostics/k_lr/data/group_0" in rec and "/diagnostics/k_lr/data/group_1" not in rec  # PILCO has no k_LR


def test_overview_keeps_its_timeline_and_moves_the_legends_to_free_corners(tmp_path):
    from pipps.reporting.plot import record

    diag = Diagnostics(np.linspace(1, 0, 30), np.logspace(3, -1, 30), np.logspace(3, 1, 30), np.zeros(6), np.zeros(30))
    particles = np.zeros((31, 4, 4))
    r = ExperimentResult(resolve_config("thesis", "cartpole_swingup", method="tp"),
                         [_trial(0), _trial(1, predicted=ParticlePrediction(particles, np.zeros(30)), diagnostics=diag)])
    rec, bp, timed = read_rrd(record([r], tmp_path / "o.rrd"))
    assert timed  # explorable over the trial/step timeline, as before
    corners = sorted(v["corner"][0] for k, v in bp.items() if k.endswith("PlotLegend") and "corner" in v)
    assert corners == [2, 2, 3]  # Corner2D: RightTop (curves, k_LR), LeftBottom (the falling variances)
    assert any(p.startswith("/predictions/") and p.endswith("/axes/xlabel") for p in rec)


# -- the command line ----------------------------------------------------------------------------------------


def test_cli_plot_draws_the_committed_unicycle_cells_and_curves(tmp_path, capsys):
    out = tmp_path / "u.rrd"
    assert main(["plot", *map(str, UNICYCLE), "--figure", "curves", "--table", "4.4", "--out", str(out)]) == 0
    rec, _, _ = read_rrd(out)
    assert "/curves/unicycle_tp/data/median" in rec and "/curves/unicycle_tp_upright/data/threshold" in rec
    assert main(["plot", *map(str, UNICYCLE), "--figure", "cells", "--out", str(out)]) == 2  # exists: refused
    assert main(["plot", *map(str, UNICYCLE), "--figure", "cells", "--out", str(out), "--overwrite"]) == 0
    rec, _, _ = read_rrd(out)
    assert labels(rec, "/cells/table_4_4/data/tp/counts") == [f"{len(UNICYCLE)}"]
    assert f"success rates in table(s) 4.4 ({len(UNICYCLE)} results counted over their cells)" in capsys.readouterr().out


def test_cli_plot_draws_a_study_file_with_its_own_figure(tmp_path):
    from pipps.studies.gradients import write_study

    path = write_study(tmp_path / "v.h5", _variance_result())
    out = tmp_path / "v.rrd"
    assert main(["plot", str(path), "--out", str(out)]) == 0
    rec, _, _ = read_rrd(out)
    assert "/variance/delta_0/data/tp_points" in rec


@pytest.mark.parametrize("argv, needle", [
    (["--figure", "landscape"], "draws a study file"),
    (["--table", "4.4"], "--table selects"),
    (["--figure", "curves", "--table", "4.1"], "no result"),
])
def test_cli_plot_errors_name_the_problem(argv, needle, tmp_path, capsys):
    assert main(["plot", str(UNICYCLE[0]), "--out", str(tmp_path / "x.rrd"), *argv]) == 2
    assert needle in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:  # an unknown table is refused by argparse, before any file is read
        main(["plot", str(UNICYCLE[0]), "--out", str(tmp_path / "x.rrd"), "--table", "9.9"])
    assert exc.value.code == 2 and "unknown table '9.9'" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("xvfb-run") is None or shutil.which("rerun") is None, reason="needs xvfb-run and the viewer")
def test_rendered_figure_is_the_figure_alone(tmp_path):
    """Rendered headless, the PNG holds the figure only: white up to its corners (no menu bar, no timeline,
    no notification toasts), dark axis strokes inside, and the palette keeps it small."""
    from PIL import Image

    from pipps.reporting.plot import render_png
    from pipps.studies.figures import record_variance, variance_figure

    r = _variance_result()
    png = render_png(record_variance(r, tmp_path / "v.rrd"), tmp_path / "v.png", ch.size(variance_figure(r)[0]))
    im = np.asarray(Image.open(png).convert("RGB"))
    h, w, _ = im.shape
    assert (w, h) == tuple(2 * int(v) for v in ch.size(variance_figure(r)[0]).split("x"))
    for y, x in ((2, 2), (2, w - 3), (h - 3, 2), (h - 3, w - 3)):
        assert im[y, x].min() > 240, (y, x, im[y, x])
    assert (im.sum(axis=2) < 100).mean() > 0.002  # the black axes and text
    assert png.stat().st_size < 300_000


# -- SVG: the same geometry as one vector document ---------------------------------------------------------


def read_svg(path):
    """(width, height, circles (n, 3) cx cy r, polylines [(n, 2)], texts [(x, y, text)]) of a pipps SVG."""
    import xml.etree.ElementTree as ET

    root = ET.parse(path).getroot()
    ns = "{http://www.w3.org/2000/svg}"
    circles = [[float(e.get(k)) for k in ("cx", "cy", "r")] for e in root.iter(f"{ns}circle")]
    lines = [np.array([[float(v) for v in p.split(",")] for p in e.get("points").split()]) for e in root.iter(f"{ns}polyline")]
    texts = [(float(e.get("x")), float(e.get("y")), e.text) for e in root.iter(f"{ns}text")]
    rects = list(root.iter(f"{ns}rect"))
    assert len(rects) == 1 and rects[0].get("fill") == "white"  # the page; no box behind any text
    return float(root.get("width")), float(root.get("height")), np.array(circles).reshape(-1, 3), lines, texts


def test_svg_places_each_panel_in_the_grid_and_the_legend_below(tmp_path):
    x, y = ch.Axis("x", 0.0, 10.0), ch.Axis("y", 1.0, 100.0, log=True)
    charts = [ch.chart(f"f/p{i}", f"panel {i}", x, y, (300.0, 240.0)) for i in range(3)]
    fig = ch.figure(charts, 2, [ch.Key("data", (200, 0, 0), "point")])
    with ch.recording(tmp_path / "f.svg", "test", fig) as rec:
        ch.draw(rec, fig)
        for i, c in enumerate(charts):
            ch.points(rec, c, "pt", [2.0 + i], [10.0], (200, 0, 0), size=3.0)
    w, h, circles, lines, texts = read_svg(tmp_path / "f.svg")
    assert f"{w:.0f}x{h:.0f}" == ch.size(fig)
    below = circles[:, 1] > 2 * 240.0  # the legend strip below both rows holds the key's dot
    assert below.sum() == 1
    circles = circles[~below]
    # panel i sits at column i % 2, row i // 2; view y (≤ 0, up) becomes page y (down) from the panel's bottom
    for i, c in enumerate(charts):
        vx, vy = c.xy(2.0 + i, 10.0)
        np.testing.assert_allclose(circles[i], [vx + 300.0 * (i % 2), vy + 240.0 * (i // 2 + 1), 3.0])
    words = [t for _, _, t in texts]
    assert ["panel 0", "panel 1", "panel 2"] == [t for t in words if t.startswith("panel")]
    assert {"1", "10", "10²", "0", "2", "10"} <= set(words) and "data" in words  # plain labels, decades as powers
    # a y tick label sits level with its tick, left of the plot box
    c = charts[0]
    ty = [ty for tx, ty, t in texts if t == "10" and tx < c.margins[0]]  # panels 0 and 2 (column 0)
    np.testing.assert_allclose(ty, [c.xy(0.0, 10.0)[1] + 240.0, c.xy(0.0, 10.0)[1] + 480.0])
    assert len(lines) > 10  # box, ticks, grid


def test_a_legend_entry_wider_than_the_grid_widens_the_figure_and_centres_the_grid(tmp_path):
    """One narrow panel and a long key (Table 4.2's cells figure has two k values and this key): the
    legend strip grows to hold the entry, the page with it, and the panel sits centred above."""
    c = ch.chart("f/p", "p", ch.Axis("x", 0.0, 10.0), ch.Axis("y", 0.0, 1.0), (300.0, 240.0))
    long = ch.Key("ours: fraction of rollouts with return < threshold, 95 % interval over seeds (label: seeds)",
                  (90, 90, 90), "interval")
    fig = ch.figure([c], 1, [ch.Key("TP", (0, 0, 200), "interval"), long])
    need = ch.legend_width(fig.keys)
    assert need > 300.0 and fig.legend.size[0] == need and ch.size(fig).startswith(f"{int(round(need))}x")
    with ch.recording(tmp_path / "w.svg", "test", fig) as rec:
        ch.draw(rec, fig)
        ch.points(rec, c, "pt", [5.0], [0.5], (200, 0, 0), size=3.0)
    import xml.etree.ElementTree as ET

    w, h, circles, _, texts = read_svg(tmp_path / "w.svg")
    assert f"{w:.0f}x{h:.0f}" == ch.size(fig)
    for e in ET.parse(tmp_path / "w.svg").getroot().iter("{http://www.w3.org/2000/svg}text"):
        x, t = float(e.get("x")), e.text  # every label lies on the page: a legend's begins at x, others centre on it
        start = x if e.get("text-anchor") == "start" else x - ch.CHAR_WIDTH * len(t) / 2
        assert 0.0 <= start and start + ch.CHAR_WIDTH * len(t) <= w, t
        assert (e.get("text-anchor") == "start") == (t in ("TP", long.label)), t
    left = (w - 300.0) / 2
    vx, vy = c.xy(5.0, 0.5)
    assert any(np.allclose(p, [vx + left, vy + 240.0, 3.0]) for p in circles)
    # a grid at least as wide as its legend is unchanged
    assert ch.figure([c], 1, [ch.Key("TP", (0, 0, 200), "interval")]).legend.size[0] == 300.0


def test_svg_fills_a_band_as_one_polygon_clipped_to_the_plot_box(tmp_path):
    import xml.etree.ElementTree as ET

    c = ch.chart("f/p", "p", ch.Axis("x", 0.0, 10.0), ch.Axis("y", 0.0, 1.0), (300.0, 240.0))
    fig = ch.figure([c], 1)
    with ch.recording(tmp_path / "b.svg", "test", fig) as rec:
        ch.band(rec, c, "band", [0.0, 5.0, 10.0], [0.2, 0.4, 0.2], [0.6, 1.5, 0.6], (150, 150, 250))  # the middle runs off the top
    (poly,) = ET.parse(tmp_path / "b.svg").getroot().iter("{http://www.w3.org/2000/svg}polygon")
    p = np.array([[float(v) for v in q.split(",")] for q in poly.get("points").split()])
    np.testing.assert_allclose([p[:, 0].min(), p[:, 0].max()], c.xy([0.0, 10.0], 0.0)[:, 0], atol=1.0)
    top, bottom = c.xy(0.0, [1.0, 0.0])[:, 1] + 240.0
    assert p[:, 1].min() >= top - 1e-9 and p[:, 1].max() <= bottom  # clipped at the box's top edge
    mid = p[np.abs(p[:, 0] - c.xy(5.0, 0.0)[0]) < 0.6]  # at x = 5: from 0.4 up to the box's top
    np.testing.assert_allclose(sorted(mid[:, 1])[::len(mid) - 1], [top, c.xy(5.0, 0.4)[1] + 240.0], atol=0.5)


def test_svg_of_the_cells_figure_holds_the_recordings_marks_and_labels(tmp_path):
    from pipps.reporting.figures import cells_figure, record_cells

    summaries = [_summary("tp", 1.0, s, [30, 10.0], success=s < 3, final=f)
                 for s, f in enumerate([(10, 10), (9, 8), (7, 6), (3, 0)])]
    table = TABLES["4.1"]
    results = collect(table, summaries)
    rec, _, _ = read_rrd(record_cells([(table, results)], tmp_path / "t.rrd"))
    record_cells([(table, results)], tmp_path / "t.svg")
    fig = cells_figure([(table, results)])
    c = fig.charts[0]
    w, _, circles, _, texts = read_svg(tmp_path / "t.svg")
    left = (w - fig.columns * c.size[0]) / 2  # a one-method panel is narrower than its legend: centred
    rate = positions(rec, f"/{c.path}/data/tp/rate")[0] + [left, c.size[1]]
    assert np.min(np.linalg.norm(circles[:, :2] - rate, axis=1)) < 0.01  # the same point, on the page
    # every label of the recording is a text of the SVG, at the point the label box is centred on
    rrd_labels = sorted(t for comps in rec.values() for t in comps.get("labels", []))
    assert rrd_labels == sorted(t for _, _, t in texts)
    count = positions(rec, f"/{c.path}/data/tp/counts")[0] + [left, c.size[1] + ch.TEXT_HEIGHT / 2 + ch.LABEL_DROP]
    assert any(t == "4" and abs(x - count[0]) < 0.01 and abs(y - count[1]) < 0.01 for x, y, t in texts)


def test_svg_refuses_what_is_not_a_figure(tmp_path):
    fig = ch.figure([ch.chart("f/p", "p", ch.Axis("x", 0.0, 1.0), ch.Axis("y", 0.0, 1.0))], 1)
    with pytest.raises(ValueError, match="belongs to no panel"):
        with ch.recording(tmp_path / "a.svg", "test", fig) as rec:
            ch.points(rec, dataclasses.replace(fig.charts[0], path="elsewhere"), "pt", [0.5], [0.5], (0, 0, 0))
    assert not (tmp_path / "a.svg").exists()
    with pytest.raises(ValueError, match="only a figure"):
        with ch.recording(tmp_path / "b.svg", "test", ch.blueprint(fig)):
            pass


def test_cli_plot_writes_an_svg_beside_the_recording_and_keeps_an_existing_one(tmp_path, capsys):
    rrd, svg = tmp_path / "u.rrd", tmp_path / "u.svg"
    assert main(["plot", *map(str, UNICYCLE), "--figure", "curves", "--table", "4.4", "--out", str(rrd), "--svg", str(svg)]) == 0
    assert f"wrote {svg}" in capsys.readouterr().out
    _, _, _, lines, texts = read_svg(svg)
    assert lines and f"TP: {len(UNICYCLE)} seeds" in [t for _, _, t in texts]
    svg.write_text("mine")
    assert main(["plot", *map(str, UNICYCLE), "--figure", "cells", "--out", str(tmp_path / "c.rrd"), "--svg", str(svg)]) == 2
    assert "--overwrite" in capsys.readouterr().err and svg.read_text() == "mine" and not (tmp_path / "c.rrd").exists()
    assert main(["plot", *map(str, UNICYCLE), "--out", str(tmp_path / "o.rrd"), "--svg", str(tmp_path / "o.svg")]) == 2
    assert "the overview is an interactive recording" in capsys.readouterr().err
    assert not (tmp_path / "o.rrd").exists() and not (tmp_path / "o.svg").exists()


def test_cells_figure_draws_every_reading_of_a_hand_made_cell_in_the_svg(tmp_path):
    """Five TP seeds whose readings all differ: the headline (per trial, return) as the large dot with
    its interval, the per-trial physical rate as a bar, and each per-seed reading as a small marker of
    its own shape at its own place right of the headline, at the fraction of seeds that pass it; each
    named in the legend."""
    from pipps.reporting.figures import DOT_SIZE, SEED_DOTS, cells_figure, record_cells
    from pipps.reporting.readings import BY_NAME

    # (rollouts below the threshold, rollouts balanced) of 10, the final system trial's return and balance
    seeds = [(10, 10, 10.0, True), (9, 8, 10.0, False), (7, 7, 20.0, False), (3, 5, 20.0, False), (0, 1, 20.0, False)]
    summaries = []
    for s, (passes, balanced, system, flag) in enumerate(seeds):
        row = _summary("tp", 1.0, s, [30, 10.0], final=(passes, balanced))
        row["per_seed"] = seed_values(s, np.where(np.arange(10) < passes, 10.0, 20.0), np.arange(10) < balanced,
                                      system, 15.0, 0.5, flag)
        summaries.append(row)
    expected = {"seed_return": 3 / 5,  # mean returns 10, 11, 13, 17, 20
                "system_trial": 2 / 5, "seed_physical": 4 / 5,  # balanced 1.0, 0.8, 0.7, 0.5 (passes), 0.1
                "system_physical": 1 / 5}
    assert len(set(expected.values())) == 4
    table = TABLES["4.1"]
    results = collect(table, summaries)
    record_cells([(table, results)], tmp_path / "t.svg")
    fig = cells_figure([(table, results)])
    c = fig.charts[0]
    w, _, circles, lines, texts = read_svg(tmp_path / "t.svg")
    left = (w - fig.columns * c.size[0]) / 2

    def page(x, y):
        return c.xy(x, y) + [left, c.size[1]]

    panel = circles[circles[:, 1] < c.size[1]]  # the legend strip lies below the panel
    (head,) = panel[panel[:, 2] == 4.0]  # the headline: 29 of 50 rollouts below the threshold, seeds averaged
    np.testing.assert_allclose(head[1], page(0.0, 29 / 50)[1], atol=0.01)  # the SVG keeps 2 decimals
    assert len(SEED_DOTS) == len(expected) and len({shape for _, _, shape in SEED_DOTS}) == len(SEED_DOTS)
    strokes = {"square": [5], "triangle": [4], "cross": [2, 2], "plus": [2, 2]}  # polylines and their points
    for name, offset, shape in SEED_DOTS:
        want = np.array([head[0] + offset, page(0.0, expected[name])[1]])
        # the marker's polylines: those whose bounding box is centred there, DOT_SIZE on each side
        here = [p for p in lines if np.allclose((p.min(0) + p.max(0)) / 2, want, atol=0.01)
                and np.isclose((p.max(0) - p.min(0)).max(), 2 * DOT_SIZE, atol=0.02)]
        assert sorted(len(p) for p in here) == strokes[shape], (name, shape, here)
    # the per-trial physical rate: a bar through the headline's x at 31 of 50 rollouts balanced
    y_bal = page(0.0, 31 / 50)[1]
    assert any(len(p) == 2 and np.allclose(p[:, 1], y_bal, atol=0.01) and abs(p[:, 0].mean() - head[0]) < 0.01
               for p in lines)
    words = [t for _, _, t in texts]
    for name, _, _ in SEED_DOTS:
        assert f"ours: {BY_NAME[name].label} (fraction of seeds, no interval)" in words
