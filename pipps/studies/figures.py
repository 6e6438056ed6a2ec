"""Figures of the gradient studies, as rerun recordings (:mod:`pipps.charts`).

* :func:`record_landscape` — thesis Fig. 4.2 (a: the objective along ``θ + Δ·d``; b: the gradient
  along d, here for every estimator as in Fig. 4.12) and the variance of ĝ·d on a log axis;
* :func:`record_variance` — thesis Fig. 4.13: tr Cov[ĝ] against the number of particles, log-log,
  one panel per Δ, and the per-step k_LR of every estimator that weighs two parts (TP's in the thesis);
* :func:`record_bench` — ours (no thesis figure): the MSE to the reference gradient against the
  seconds per estimate, log-log, one panel per Δ.

A series that lies orders of magnitude outside the others (RP where the dynamics are chaotic) would
flatten them against an axis; it is left off the axis range, clipped at the plot box, and its extent
written in the panel (:func:`off_scale`), as the thesis leaves RP out of Fig. 4.13b.

Labels and colours are the estimator registry's (:data:`pipps.propagation.estimators.ESTIMATORS`);
an estimator with settings (``"tp:k_lr=previous"``) is drawn lighter than its name's colour.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipps import charts as ch
from pipps.propagation.estimators import ESTIMATORS, parse_spec, spec_label
from pipps.studies.gradients import LandscapeResult, VarianceResult, interval

COLORS = {name: entry.colour for name, entry in ESTIMATORS.items()}
MM_COLOR = (190, 150, 0)
PANEL = (560.0, 400.0)
UNKNOWN_COLOR = (100, 100, 100)


def _spec(name: str) -> str:
    """The estimator of a series: ``"tp (variance tol 0.01)"`` → ``"tp"``."""
    return name.split(" (")[0]


def _known(name: str) -> bool:
    try:
        parse_spec(_spec(name))
    except ValueError:
        return False
    return True


def _color(name: str):
    """An estimator's colour from the registry; with settings, lighter; a series ``"tp (variance tol
    0.01)"`` takes its estimator's."""
    if not _known(name):
        return UNKNOWN_COLOR
    base, settings = parse_spec(_spec(name))
    rgb = ESTIMATORS[base].colour
    return tuple(int(round(c + 0.45 * (255 - c))) for c in rgb) if settings else rgb


def _label(name: str) -> str:
    spec, _, rest = name.partition(" (")
    return (spec_label(spec) if _known(spec) else spec) + (f" ({rest}" if rest else "")


def _weighs_parts(name: str) -> bool:
    """The series' estimator weighs two parts, so its per-step k_LR is a chosen weight worth plotting."""
    return _known(name) and ESTIMATORS[parse_spec(_spec(name))[0]].weighs_parts


def _sci(v: float) -> str:
    """3.2·10¹⁶"""
    if not np.isfinite(v) or v == 0:
        return f"{v:g}"
    e = int(np.floor(np.log10(abs(v))))
    return f"{v / 10.0**e:.1f}·{ch.power_of_ten(e)}"


def off_scale(extents: dict[str, float], factor: float) -> set[str]:
    """The series whose extent (largest magnitude) exceeds ``factor`` × the median extent of the others."""
    out = set()
    for n, v in extents.items():
        others = [w for m, w in extents.items() if m != n and np.isfinite(w)]
        if others and (not np.isfinite(v) or v > factor * float(np.median(others))):
            out.add(n)
    return out


def _estimator_keys(names) -> list[ch.Key]:
    return [ch.Key(_label(n), _color(n)) for n in names]


# -- landscape (Fig. 4.2 / 4.12) ---------------------------------------------------------------------


def landscape_figure(r: LandscapeResult) -> tuple[ch.Figure, dict[str, float]]:
    """The landscape's three panels with their legend, and the estimators off scale in (b) with their extent."""
    names = list(r.samples)
    stats = {n: np.array([interval(s.directional) for s in r.samples[n]]) for n in names}  # (nΔ, 2): mean, half
    extents = {n: float(np.nanmax(np.abs(st[:, 0]) + np.nan_to_num(st[:, 1]))) for n, st in stats.items()}
    extents["mm"] = float(np.max(np.abs(r.directional_mm)))
    hidden = off_scale(extents, 20.0) - {"mm"}
    shown = [np.concatenate([st[:, 0] - st[:, 1], st[:, 0] + st[:, 1]]) for n, st in stats.items() if n not in hidden]
    dx = ch.Axis("Δ: distance along d", *ch.data_range([r.deltas], pad=0.04))
    variances = [np.var(s.directional, ddof=1) for n in names for s in r.samples[n]]
    charts = [
        ch.chart("landscape/objective", f"(a) objective along θ + Δ·d, P = {r.particles}", dx,
                 ch.Axis("J: expected total cost", *ch.data_range([r.objective_fixed_seed, r.objective_mm])), PANEL),
        ch.chart("landscape/gradient", f"(b) ĝ·d: mean and 95 % interval, {r.repeats} repeats", dx,
                 ch.Axis("ĝ·d: gradient along d", *ch.data_range([*shown, r.directional_mm])), PANEL),
        ch.chart("landscape/variance", "(c) variance of ĝ·d over the repeats", dx,
                 ch.Axis("Var[ĝ·d]", *ch.data_range([variances], log=True), log=True), PANEL),
    ]
    keys = [ch.Key(f"J, particles (one fixed seed, P = {r.particles})", ch.BLACK),
            ch.Key("J and ∇J·d, moment matching (PILCO)", MM_COLOR, "dash"), *_estimator_keys(names)]
    return ch.figure(charts, 3, keys), {n: extents[n] for n in hidden}


def record_landscape(r: LandscapeResult, out: str | Path) -> Path:
    """Recording of :func:`landscape_figure`: (a) the objectives, (b) each estimator's mean ĝ·d with its
    95 % interval (markers dodged sideways) and the exact moment-matching derivative, (c) Var[ĝ·d]."""
    fig, hidden = landscape_figure(r)
    a, b, c = fig.charts
    names = list(r.samples)
    with ch.recording(out, "pipps-landscape", fig) as rec:
        ch.draw(rec, fig)
        ch.line(rec, a, "particles_fixed_seed", r.deltas, r.objective_fixed_seed, ch.BLACK, width=1.4)
        ch.line(rec, a, "moment_matching", r.deltas, r.objective_mm, MM_COLOR, width=1.4, dash=True)
        ch.line(rec, b, "moment_matching", r.deltas, r.directional_mm, MM_COLOR, width=1.4, dash=True)
        step = float(np.min(np.diff(r.deltas))) if len(r.deltas) > 1 else 1.0
        for i, n in enumerate(names):
            st = np.array([interval(s.directional) for s in r.samples[n]])
            x = r.deltas + (i - (len(names) - 1) / 2) * 0.1 * step
            shown = np.ones(len(x), bool)
            if n in hidden:  # only its points inside the range, and where it leaves it a mark on the edge
                shown = (st[:, 0] >= b.y.lo) & (st[:, 0] <= b.y.hi)
                ch.off_range(rec, b, f"{n}/off_range", x, st[:, 0], _color(n))
            ch.line(rec, b, f"{n}/mean", x, st[:, 0], _color(n), partial=n not in hidden)
            ch.points(rec, b, f"{n}/points", x, st[:, 0], _color(n), size=2.5)
            ch.intervals(rec, b, f"{n}/interval", x[shown], (st[:, 0] - st[:, 1])[shown], (st[:, 0] + st[:, 1])[shown],
                         _color(n), cap=2.5)
            var = [np.var(s.directional, ddof=1) for s in r.samples[n]]
            ch.line(rec, c, n, r.deltas, var, _color(n))
            ch.points(rec, c, f"{n}_points", r.deltas, var, _color(n), size=2.5)
        for k, (n, e) in enumerate(sorted(hidden.items())):
            ch.note(rec, b, f"off_scale_{n}", f"▲▼ {_label(n)} off scale: |ĝ·d| up to {_sci(e)}",
                    row=k)
    return Path(out)


# -- variance against P (Fig. 4.13) ------------------------------------------------------------------


def _weighted(r: VarianceResult) -> list[str]:
    """The estimators whose k_LR the variance figure plots."""
    return [n for n in r.samples if _weighs_parts(n)]


def variance_figure(r: VarianceResult) -> tuple[ch.Figure, list[dict[str, np.ndarray]]]:
    """One log-log panel per Δ (tr Cov[ĝ] against P) and, for the estimators that weigh two parts,
    k_LR per step; per Δ, the estimators off scale."""
    names = list(r.samples)
    weighted = _weighted(r)
    P = np.asarray(r.particles, dtype=float)
    px = ch.Axis("number of particles P", P.min() / 1.4, P.max() * 1.4, log=True,
                 ticks=tuple(float(p) for p in P), tick_labels=tuple(str(int(p)) for p in P))
    charts, hidden = [], []
    for di, delta in enumerate(r.deltas):
        traces = {n: np.array([s.trace_variance for s in r.samples[n][di]]) for n in names}
        off = off_scale({n: float(np.nanmax(np.where(v > 0, v, np.nan))) if np.any(v > 0) else np.nan
                         for n, v in traces.items()}, 1e3)
        hidden.append({n: traces[n] for n in off})
        rng = ch.data_range([v for n, v in traces.items() if n not in off], log=True)
        letter = "ab"[di] if len(r.deltas) == 2 else str(di + 1)
        kind = " (smooth)" if delta == 0 else ""
        charts.append(ch.chart(f"variance/delta_{di}", f"({letter}) Δ = {delta:.3g}{kind}: tr Cov[ĝ] over {r.repeats} repeats",
                               px, ch.Axis("tr Cov[ĝ]", *rng, log=True), PANEL))
    if weighted:
        T = len(r.samples[weighted[0]][0][-1].k_lr)
        whose = f"{_label(weighted[0])}'s" if len(weighted) == 1 else "each weighted estimator's"
        charts.append(ch.chart("variance/k_lr", f"({'c' if len(r.deltas) == 2 else 'k'}) {whose} k_LR per step, P = {int(P[-1])}",
                               ch.Axis("time step t", 0.5, T + 0.5), ch.Axis("k_LR: weight of the LR estimate", -0.04, 1.04),
                               PANEL))
    keys = [*_estimator_keys(names), ch.Key(f"∝ 1/P (through {_label(_one_over_p(r))}'s first point)", ch.GREY, "dash")]
    keys += [ch.Key(f"{_label(n)} k_LR, Δ = {d:.3g}", _color(n), "line" if i == 0 else "dash")
             for n in weighted for i, d in enumerate(r.deltas)]
    return ch.figure(charts, len(charts), keys), hidden


def _one_over_p(r: VarianceResult) -> str:
    """The series the ∝ 1/P guide goes through: the first weighted estimator's, else the first's."""
    return (_weighted(r) or list(r.samples))[0]


def record_variance(r: VarianceResult, out: str | Path) -> Path:
    """Recording of :func:`variance_figure` (log-log: equal ratios of P and of the variance are equal distances)."""
    fig, hidden = variance_figure(r)
    P = np.asarray(r.particles, dtype=float)
    with ch.recording(out, "pipps-variance", fig) as rec:
        ch.draw(rec, fig)
        for di, c in enumerate(fig.charts[: len(r.deltas)]):
            for n, grid in r.samples.items():
                v = np.array([s.trace_variance for s in grid[di]])
                ch.line(rec, c, n, P, v, _color(n))
                ch.points(rec, c, f"{n}_points", P, v, _color(n), size=3.0)
            v0 = r.samples[_one_over_p(r)][di][0].trace_variance
            ch.line(rec, c, "one_over_P", P, v0 * P[0] / P, ch.GREY, width=0.9, dash=True, order=3.0)
            for k, (n, v) in enumerate(sorted(hidden[di].items())):
                ch.note(rec, c, f"off_scale_{n}", f"{_label(n)} off scale: {_sci(np.nanmin(v))} to {_sci(np.nanmax(v))}",
                        row=k)
        if _weighted(r):
            c = fig.charts[-1]
            for n in _weighted(r):
                for di in range(len(r.deltas)):
                    k = r.samples[n][di][-1].k_lr
                    ch.line(rec, c, f"{n}_delta_{di}", np.arange(1, len(k) + 1), k, _color(n), width=1.3, dash=di > 0)
    return Path(out)


# -- run time against error (pipps bench) --------------------------------------------------------------


def bench_figure(r) -> tuple[ch.Figure, list[dict[str, np.ndarray]]]:
    """One log-log panel per Δ: MSE to the reference against seconds per estimate; per Δ, the estimators off scale."""
    names = list(dict.fromkeys(e.series for es in r.entries for e in es))
    seconds = [e.seconds for es in r.entries for e in es] + [r.mm_seconds]
    sx = ch.Axis("seconds per value-and-gradient (median)", *ch.data_range([seconds], log=True), log=True)
    charts, hidden = [], []
    for di, delta in enumerate(r.deltas):
        mse = {n: np.array([e.mse for e in r.entries[di] if e.series == n]) for n in names}
        off = off_scale({n: float(np.nanmax(v)) if np.any(np.isfinite(v)) else np.nan for n, v in mse.items()}, 1e3)
        hidden.append({n: mse[n] for n in off})
        rng = ch.data_range([v for n, v in mse.items() if n not in off], log=True,
                            include=[r.reference_error[di], r.mm_distance[di]])
        charts.append(ch.chart(f"bench/delta_{di}", f"({'ab'[di] if len(r.deltas) == 2 else di + 1}) Δ = {delta:.3g}: "
                               "error against run time", sx, ch.Axis("MSE ‖ĝ − g_ref‖²", *rng, log=True), PANEL))
    keys = [*_estimator_keys(names), *[ch.Key(f"P = {p}", ch.GREY, "point", s) for p, s in _marker_sizes(r).items()],
            ch.Key("PILCO's exact MM gradient (its ‖∇J_MM − g_ref‖²)", MM_COLOR, "diamond"),
            ch.Key(f"tr Cov[g_ref]: the reference's own error ({_label(r.reference_name)}, P = {r.reference_particles})",
                   ch.GREY, "dash")]
    return ch.figure(charts, len(charts), keys), hidden


def _marker_sizes(r) -> dict[int, float]:
    """Marker radius per number of particles: larger P, larger marker."""
    ps = sorted({e.particles for es in r.entries for e in es})
    return {p: 2.0 + 1.5 * i for i, p in enumerate(ps)}


def record_bench(r, out: str | Path) -> Path:
    """Recording of :func:`bench_figure`: per estimator a line through its P values, each point labelled with P."""
    fig, hidden = bench_figure(r)
    names = list(dict.fromkeys(e.series for es in r.entries for e in es))
    sizes = _marker_sizes(r)
    with ch.recording(out, "pipps-bench", fig) as rec:
        ch.draw(rec, fig)
        for di, c in enumerate(fig.charts):
            for n in names:
                es = sorted((e for e in r.entries[di] if e.series == n), key=lambda e: e.particles)
                x, y = [e.seconds for e in es], [e.mse for e in es]
                ch.line(rec, c, n, x, y, _color(n), dash=" (" in n)  # dashed: a low-rank variance
                for e in es:
                    ch.points(rec, c, f"{n}_points/P_{e.particles}", [e.seconds], [e.mse], _color(n), size=sizes[e.particles])
            ch.markers(rec, c, "pilco_mm", [r.mm_seconds], [r.mm_distance[di]], MM_COLOR)
            ch.line(rec, c, "reference_error", [c.x.lo, c.x.hi], [r.reference_error[di]] * 2, ch.GREY, width=0.9, dash=True,
                    order=3.0)
            for k, (n, v) in enumerate(sorted(hidden[di].items())):
                ch.note(rec, c, f"off_scale_{n}", f"{_label(n)} off scale: MSE {_sci(np.nanmin(v))} to {_sci(np.nanmax(v))}",
                        row=k)
    return Path(out)
