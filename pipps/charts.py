"""Paper-style charts drawn in rerun 2-D views (no matplotlib).

A rerun time-series view puts a timeline on its x axis, labels no axis and draws the time cursor;
a figure needs labelled axes with units, log scales and legends off the data. So every figure is
drawn here as geometry in a :class:`rerun.blueprint.Spatial2DView`: a plot box, ticks and tick
labels, axis labels, a title, and the data as line strips and points, all logged ``static`` (no
timeline, hence no cursor). A figure's legend is a strip of its own below the panels.

Geometry. A chart is laid out in *nominal pixels*: the panel it is meant for is ``size`` =
(width, height) logical pixels, and the plot box is that minus margins for tick labels, axis labels
and the title. Text in rerun has a fixed size in pixels, so the margins are computed from the label
lengths; rendered at its nominal size (:func:`figure_size`) a figure is laid out exactly. View
coordinates have y growing downwards, so a data point lands at ``(left + x·w, −(bottom + y·h))``
with x, y its fractions of the axis ranges. Everything outside the plot box is clipped.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from pathlib import Path
from typing import Iterable, Iterator, NamedTuple, Sequence

import numpy as np

#: text metrics of the viewer's labels (logical pixels), measured on rendered ones: a label's box is
#: centred horizontally on its point and hangs below it, its top LABEL_DROP under the point
CHAR_WIDTH = 7.0
TEXT_HEIGHT = 23.0
LABEL_DROP = 1.0
BLACK = (0, 0, 0)
GREY = (130, 130, 130)
LIGHT_GREY = (225, 225, 225)
WHITE = (255, 255, 255)
_SUPERSCRIPT = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")


def lighter(color, amount: float = 0.6) -> tuple[int, int, int]:
    """``color`` mixed with white (``amount`` of white); opaque, so overlapping strokes do not darken."""
    return tuple(int(round(c + amount * (255 - c))) for c in color[:3])


def power_of_ten(exponent: int) -> str:
    """"1", "10", "10²", "10⁻³" …"""
    if exponent == 0:
        return "1"
    if exponent == 1:
        return "10"
    return "10" + str(exponent).translate(_SUPERSCRIPT)


def _nice_step(span: float, target: int) -> float:
    raw = span / max(target, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    for m in (1.0, 2.0, 2.5, 5.0, 10.0):
        if m * mag >= raw * (1 - 1e-9):
            return m * mag
    return 10.0 * mag


def _format(v: float, step: float) -> str:
    decimals = max(0, -int(math.floor(math.log10(step) + 1e-9))) if step < 1 else 0
    if step < 1 and not math.isclose(round(step, decimals), step, rel_tol=1e-6):
        decimals += 1
    text = f"{v:.{decimals}f}"
    return "0" if float(text) == 0.0 else text.replace("-", "−")


@dataclasses.dataclass(frozen=True)
class Axis:
    """One axis: its label (with units), the data range shown, linear or log₁₀, and optionally the
    ticks (data values) and their labels; a categorical axis gives both and the range ±0.5 around."""

    label: str
    lo: float
    hi: float
    log: bool = False
    ticks: tuple[float, ...] | None = None
    tick_labels: tuple[str, ...] | None = None

    def __post_init__(self):
        if not (np.isfinite(self.lo) and np.isfinite(self.hi) and self.hi > self.lo):
            raise ValueError(f"axis {self.label!r}: need finite lo < hi, got [{self.lo}, {self.hi}]")
        if self.log and self.lo <= 0:
            raise ValueError(f"axis {self.label!r}: a log axis needs lo > 0, got {self.lo}")

    def fraction(self, v) -> np.ndarray:
        """Position of data values along the axis, 0 at ``lo`` and 1 at ``hi`` (NaN where undefined)."""
        v = np.asarray(v, dtype=float)
        if self.log:
            with np.errstate(all="ignore"):
                v = np.where(v > 0, np.log10(np.where(v > 0, v, 1.0)), np.nan)
            lo, hi = math.log10(self.lo), math.log10(self.hi)
        else:
            lo, hi = self.lo, self.hi
        return (v - lo) / (hi - lo)

    def tick_marks(self) -> tuple[list[float], list[str], list[float]]:
        """(major tick values, their labels, minor tick values) inside the range."""
        if self.ticks is not None:
            labels = self.tick_labels or tuple(f"{t:g}".replace("-", "−") for t in self.ticks)
            keep = [(t, s) for t, s in zip(self.ticks, labels) if self.lo <= t <= self.hi]
            return [t for t, _ in keep], [s for _, s in keep], []
        if self.log:
            a, b = math.ceil(math.log10(self.lo) - 1e-9), math.floor(math.log10(self.hi) + 1e-9)
            if b - a < 2:  # fewer than three decades: label 1, 2 and 5 times the powers of ten
                e0 = math.floor(math.log10(self.lo))
                cands = [m * 10.0**e for e in range(e0, b + 1) for m in (1, 2, 5)]
                major = [v for v in cands if self.lo <= v <= self.hi]
                minor = [m * 10.0**e for e in range(e0, b + 1) for m in (3, 4, 6, 7, 8, 9) if self.lo <= m * 10.0**e <= self.hi]
                return major, [f"{v:.10g}" for v in major], minor
            every = next(s for s in (1, 2, 3, 4, 5, 10, 20, 50, 100) if (b - a) // s + 1 <= 7)
            exps = list(range(a - (a % every), b + 1, every))
            exps = [e for e in exps if a <= e <= b]
            minor = []
            if every == 1 and b - a <= 4:
                for e in range(a - 1, b + 1):
                    minor += [m * 10.0**e for m in range(2, 10) if self.lo <= m * 10.0**e <= self.hi]
            elif every > 1:
                minor = [10.0**e for e in range(a, b + 1) if e not in exps]
            return [10.0**e for e in exps], [power_of_ten(e) for e in exps], minor
        step = _nice_step(self.hi - self.lo, 5)
        first = math.ceil(self.lo / step - 1e-9)
        values = [k * step for k in range(first, int(math.floor(self.hi / step + 1e-9)) + 1)]
        return values, [_format(v, step) for v in values], []


def data_range(values: Iterable, *, log: bool = False, pad: float = 0.05, include: Iterable[float] = ()) -> tuple[float, float]:
    """A range that shows ``values`` (finite ones; positive ones on a log axis) and ``include``,
    padded by ``pad`` of the span (on a log axis, of the span of the logarithms)."""
    v = np.concatenate([np.ravel(np.asarray(x, dtype=float)) for x in [*values, list(include)] if np.size(x)] or [[]])
    v = v[np.isfinite(v)]
    if log:
        v = v[v > 0]
        if not v.size:
            return 0.1, 10.0
        lo, hi = math.log10(v.min()), math.log10(v.max())
        span = max(hi - lo, 1.0)
        return 10.0 ** (lo - pad * span), 10.0 ** (hi + pad * span)
    if not v.size:
        return 0.0, 1.0
    lo, hi = float(v.min()), float(v.max())
    span = hi - lo if hi > lo else max(abs(hi), 1.0)
    return lo - pad * span, hi + pad * span


def categorical(label: str, names: Sequence[str]) -> Axis:
    """An axis of named categories at 0, 1, …"""
    return Axis(label, -0.5, len(names) - 0.5, ticks=tuple(float(i) for i in range(len(names))), tick_labels=tuple(names))


@dataclasses.dataclass(frozen=True)
class Chart:
    """A panel: entity path, title, axes, its nominal size in pixels and the margins around its plot box."""

    path: str
    title: str
    x: Axis
    y: Axis
    size: tuple[float, float]
    margins: tuple[float, float, float, float]  # left, right, bottom, top

    @property
    def box(self) -> tuple[float, float]:
        """Width and height of the plot box."""
        left, right, bottom, top = self.margins
        return self.size[0] - left - right, self.size[1] - bottom - top

    def xy(self, x, y) -> np.ndarray:
        """View coordinates (n, 2) of data points; NaN where a coordinate is undefined (e.g. ≤ 0 on a log axis)."""
        w, h = self.box
        fx, fy = self.x.fraction(x), self.y.fraction(y)
        fx, fy = np.broadcast_arrays(fx, fy)
        return np.stack([self.margins[0] + fx * w, -(self.margins[2] + fy * h)], axis=-1)

    def inside(self, points: np.ndarray) -> np.ndarray:
        """Which view points lie in the plot box (with a little tolerance)."""
        left, _, bottom, _ = self.margins
        w, h = self.box
        px, py = points[..., 0] - left, -points[..., 1] - bottom
        tol = 1e-6 * max(w, h)
        return np.isfinite(px) & np.isfinite(py) & (px >= -tol) & (px <= w + tol) & (py >= -tol) & (py <= h + tol)


def chart(path: str, title: str, x: Axis, y: Axis, size: tuple[float, float] = (520.0, 380.0)) -> Chart:
    """A chart whose margins fit its tick labels, axis labels and title."""
    _, ylabels, _ = y.tick_marks()
    left = 16.0 + CHAR_WIDTH * max([len(s) for s in ylabels] + [2]) + 8.0
    right = 10.0 + 0.5 * CHAR_WIDTH * max([len(s) for s in x.tick_marks()[1][-1:]] + [1])
    bottom = 12.0 + 2 * TEXT_HEIGHT
    top = 26.0 + 2 * TEXT_HEIGHT  # title, then the y axis' label above the axis, clear of the top tick label
    c = Chart(path, title, x, y, tuple(map(float, size)), (left, right, bottom, top))
    if min(c.box) < 40:
        raise ValueError(f"chart {path!r}: size {size} leaves no room for the plot box")
    return c


# -- drawing ----------------------------------------------------------------------------------------


def _text(rec, path: str, positions, labels, color=BLACK, *, left: bool = False) -> None:
    """Labels centred on ``positions`` (view coordinates); with ``left``, ``positions`` are where the
    labels begin (a legend's text after its sample: an SVG anchors it there, the viewer, which only
    centres labels, at the estimated centre)."""
    positions = np.asarray(positions, dtype=float).reshape(-1, 2)
    if isinstance(rec, SvgCanvas):
        rec.text(path, positions, labels, color, anchor="start" if left else "middle")
        return
    import rerun as rr

    if left:
        positions = positions + np.array([[CHAR_WIDTH * len(str(t)) / 2, 0.0] for t in labels])

    positions = positions - [0.0, TEXT_HEIGHT / 2 + LABEL_DROP]  # a viewer label hangs below its point
    rec.log(path, rr.Points2D(positions, radii=[0.0], labels=list(labels), colors=[color], show_labels=True,
                              draw_order=[100.0]), static=True)


def _strips(rec, path: str, strips, color, radius: float, order: float = 20.0) -> None:
    """Line strips (view coordinates); ``radius`` < 0 is in UI points, > 0 in view units."""
    if isinstance(rec, SvgCanvas):
        rec.strips(path, strips, color, radius, order)
        return
    import rerun as rr

    rec.log(path, rr.LineStrips2D(strips, colors=[color], radii=[radius], draw_order=[order]), static=True)


def _dots(rec, path: str, positions, color, radius: float, order: float = 30.0) -> None:
    """Filled discs of ``radius`` (as :func:`_strips`) at ``positions`` (view coordinates)."""
    if isinstance(rec, SvgCanvas):
        rec.dots(path, positions, color, radius, order)
        return
    import rerun as rr

    rec.log(path, rr.Points2D(positions, colors=[color], radii=[radius], draw_order=[order]), static=True)


def draw_axes(rec, c: Chart, *, grid: bool = True) -> None:
    """The plot box, ticks with labels, light grid lines, the axis labels and the title."""
    left, _, bottom, _ = c.margins
    w, h = c.box
    x0, x1, y0, y1 = left, left + w, -bottom, -(bottom + h)
    _strips(rec, f"{c.path}/axes/box", [[[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]], BLACK, -0.6, 20.0)
    for name, axis in (("x", c.x), ("y", c.y)):
        values, labels, minor = axis.tick_marks()
        if name == "x":
            pos, mpos = c.xy(values, c.y.lo)[:, 0], c.xy(minor, c.y.lo)[:, 0]
        else:
            pos, mpos = c.xy(c.x.lo, values)[:, 1], c.xy(c.x.lo, minor)[:, 1]

        def tick(p, length):
            return [[p, y0], [p, y0 + length]] if name == "x" else [[x0, p], [x0 - length, p]]

        _strips(rec, f"{c.path}/axes/{name}ticks", [tick(p, 5.0) for p in pos] + [tick(p, 3.0) for p in mpos], BLACK,
                -0.5, 20.0)
        if grid and len(pos):
            lines = [[[p, y0], [p, y1]] for p in pos] if name == "x" else [[[x0, p], [x1, p]] for p in pos]
            _strips(rec, f"{c.path}/axes/{name}grid", lines, LIGHT_GREY, -0.4, 1.0)
        if name == "x":
            at = [[p, y0 + 8.0 + TEXT_HEIGHT / 2] for p in pos]
        else:
            at = [[x0 - 10.0 - CHAR_WIDTH * len(s) / 2 - 4.0, p] for p, s in zip(pos, labels)]
        if labels:
            _text(rec, f"{c.path}/axes/{name}tick_labels", at, labels)
    if c.x.label:
        _text(rec, f"{c.path}/axes/xlabel", [[x0 + w / 2, y0 + 10.0 + 1.5 * TEXT_HEIGHT]], [c.x.label])
    _text(rec, f"{c.path}/axes/ylabel", [[x0 - 10.0 + CHAR_WIDTH * len(c.y.label) / 2, y1 - 16.0 - TEXT_HEIGHT / 2]],
          [c.y.label])
    _text(rec, f"{c.path}/title", [[c.size[0] / 2, -c.size[1] + 6.0 + TEXT_HEIGHT / 2]], [c.title])


def clip(c: Chart, points: np.ndarray) -> list[np.ndarray]:
    """Split a polyline (n, 2) in view coordinates into the pieces inside the plot box: segments are cut
    where they cross its edges (Liang–Barsky) and where a point is undefined (NaN)."""
    left, _, bottom, _ = c.margins
    w, h = c.box
    lo, hi = np.array([left, -(bottom + h)]), np.array([left + w, -bottom])
    pieces: list[list[np.ndarray]] = []
    current: list[np.ndarray] = []
    for a, b in zip(points[:-1], points[1:]):
        seg = _clip_segment(a, b, lo, hi) if np.all(np.isfinite(a)) and np.all(np.isfinite(b)) else None
        if seg is None:
            if current:
                pieces.append(current)
            current = []
            continue
        p, q = seg
        if current and np.allclose(current[-1], p):
            current.append(q)
        else:
            if current:
                pieces.append(current)
            current = [p, q]
    if current:
        pieces.append(current)
    if len(points) == 1 and c.inside(points).all():
        pieces.append([points[0]])
    return [np.array(p) for p in pieces]


def _clip_segment(a, b, lo, hi):
    d = b - a
    t0, t1 = 0.0, 1.0
    for k in range(2):
        for p, q in ((-d[k], a[k] - lo[k]), (d[k], hi[k] - a[k])):
            if p == 0:
                if q < 0:
                    return None
                continue
            t = q / p
            if p < 0:
                t0 = max(t0, t)
            else:
                t1 = min(t1, t)
            if t0 > t1:
                return None
    return a + t0 * d, a + t1 * d


def line(rec, c: Chart, name: str, x, y, color, *, width: float = 1.2, dash: bool = False, order: float = 10.0,
         partial: bool = True) -> None:
    """A polyline through the data points, clipped to the plot box; ``dash`` draws it dashed; without
    ``partial`` a segment with an end outside the box is left out rather than cut (for a series that is
    mostly off scale). ``width`` is in UI points (the stroke's radius)."""
    p = c.xy(x, y)
    if not partial:
        p = np.where(c.inside(p)[:, None], p, np.nan)
    pieces = clip(c, p)
    if dash:
        pieces = [d for p in pieces for d in _dashes(p, 7.0, 5.0)]
    _strips(rec, f"{c.path}/data/{name}", pieces, color, -width, order)


def _dashes(strip: np.ndarray, on: float, off: float) -> list[np.ndarray]:
    seg = np.linalg.norm(np.diff(strip, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    out = []
    start = 0.0
    while start < s[-1]:
        stop = min(start + on, s[-1])
        ts = np.concatenate([[start], s[(s > start) & (s < stop)], [stop]])
        out.append(np.stack([np.interp(ts, s, strip[:, 0]), np.interp(ts, s, strip[:, 1])], axis=1))
        start = stop + off
    return out


def points(rec, c: Chart, name: str, x, y, color, *, size: float = 3.5, order: float = 30.0) -> None:
    """Markers (radius ``size`` UI points) at the data points inside the plot box."""
    p = c.xy(x, y).reshape(-1, 2)
    _dots(rec, f"{c.path}/data/{name}", p[c.inside(p)], color, -size, order)


def off_range(rec, c: Chart, name: str, x, y, color) -> None:
    """Triangles on the plot box's top (bottom) edge where a value lies above (below) the y range."""
    x, y = np.ravel(np.asarray(x, dtype=float)), np.ravel(np.asarray(y, dtype=float))
    fy = c.y.fraction(y)
    tris = []
    for xi, f in zip(x, fy):
        if not np.isfinite(f) or 0.0 <= f <= 1.0:
            continue
        at = c.xy(xi, c.y.hi if f > 1 else c.y.lo)
        if not c.inside(at[None]).all():
            continue
        dy = 9.0 if f > 1 else -9.0  # apex on the edge, base inside the box (view y grows downwards)
        tris.append(at + np.array([[-5.0, dy], [5.0, dy], [0.0, 0.0], [-5.0, dy]]))
    _strips(rec, f"{c.path}/data/{name}", tris, color, -1.2, 35.0)


def markers(rec, c: Chart, name: str, x, y, color, shape: str = "diamond", *, size: float = 7.0) -> None:
    """Hollow markers at the data points inside the plot box: ``diamond`` (half-diagonal ``size``
    pixels), ``bar`` (a short horizontal stroke ``2·size`` wide), or ``square``, ``triangle``,
    ``cross``, ``plus`` (half-width ``size``)."""
    p = c.xy(x, y).reshape(-1, 2)
    p = p[c.inside(p)]
    _strips(rec, f"{c.path}/data/{name}", [q + d for q in p for d in _shape(shape, size)], color,
            -1.1 if shape == "diamond" else -1.6, 40.0)


#: the hollow marker shapes :func:`markers` and legend keys draw (as line strips)
SHAPES = ("diamond", "bar", "square", "triangle", "cross", "plus")


def _shape(shape: str, size: float) -> list[np.ndarray]:
    if shape == "diamond":
        return [np.array([[0, -size], [size, 0], [0, size], [-size, 0], [0, -size]], dtype=float)]
    if shape == "bar":
        return [np.array([[-size, 0], [size, 0]], dtype=float)]
    if shape == "square":
        return [np.array([[-size, -size], [size, -size], [size, size], [-size, size], [-size, -size]], dtype=float)]
    if shape == "triangle":  # apex up (view y grows downwards)
        return [np.array([[0, -size], [size, size], [-size, size], [0, -size]], dtype=float)]
    if shape == "cross":
        return [np.array([[-size, -size], [size, size]], dtype=float), np.array([[-size, size], [size, -size]], dtype=float)]
    if shape == "plus":
        return [np.array([[-size, 0], [size, 0]], dtype=float), np.array([[0, -size], [0, size]], dtype=float)]
    raise ValueError(f"marker shape {shape!r}; one of {SHAPES}")


def text(rec, c: Chart, name: str, x, y, labels: Sequence[str], *, above: bool = False) -> None:
    """Labels at data points inside the plot box (centred on them, or just above them)."""
    p = c.xy(x, y).reshape(-1, 2)
    keep = c.inside(p)
    if above:
        p = p - [0.0, 6.0 + TEXT_HEIGHT / 2]
    _text(rec, f"{c.path}/data/{name}", p[keep], [s for s, k in zip(labels, keep) if k])


def intervals(rec, c: Chart, name: str, x, lo, hi, color, *, cap: float = 4.0, width: float = 1.0) -> None:
    """Vertical error bars from ``lo`` to ``hi`` with caps of half-width ``cap`` pixels, clipped."""
    strips = []
    for xi, a, b in zip(np.ravel(x), np.ravel(lo), np.ravel(hi)):
        pa, pb = c.xy(xi, a), c.xy(xi, b)
        strips += clip(c, np.stack([pa, pb]))
        for q in (pa, pb):
            if c.inside(q[None]).all():
                strips.append(np.array([q - [cap, 0.0], q + [cap, 0.0]]))
    _strips(rec, f"{c.path}/data/{name}", strips, color, -width, 25.0)


def band(rec, c: Chart, name: str, x, lo, hi, color) -> None:
    """The region between two curves, filled, linearly interpolated between the data points (2-d views
    draw no polygons: dense opaque vertical strokes; an SVG gets the outline of the same strokes)."""
    x, lo, hi = (np.asarray(v, dtype=float) for v in (x, lo, hi))
    ok = np.isfinite(x) & np.isfinite(lo) & np.isfinite(hi)
    if ok.sum() < 2:
        return
    x, lo, hi = x[ok], lo[ok], hi[ok]
    step = 1.0  # pixels between strokes; each stroke is 2 pixels wide, so neighbours overlap
    px = c.xy(x, c.y.lo)[:, 0]
    grid = np.arange(px.min(), px.max() + 1e-9, step)
    xs = np.interp(grid, px, np.arange(len(x)))  # fractional data index of each stroke
    idx = np.arange(len(x))
    strips = []
    for g, k in zip(grid, xs):
        a, b = c.xy(np.interp(k, idx, x), np.interp(k, idx, lo))[..., 1], c.xy(np.interp(k, idx, x), np.interp(k, idx, hi))[..., 1]
        strips += clip(c, np.array([[g, float(a)], [g, float(b)]]))
    if isinstance(rec, SvgCanvas):  # each run of neighbouring strokes is one polygon: their tops, then their bottoms
        runs: list[list[np.ndarray]] = []
        for st in (st for st in strips if len(st) == 2):
            if runs and st[0, 0] - runs[-1][-1][0, 0] <= 1.5 * step:
                runs[-1].append(st)
            else:
                runs.append([st])
        for run in runs:
            top = [st[np.argmin(st[:, 1])] for st in run]
            bottom = [st[np.argmax(st[:, 1])] for st in run]
            rec.polygon(f"{c.path}/data/{name}", np.array(top + bottom[::-1]), color, 5.0)
        return
    _strips(rec, f"{c.path}/data/{name}", strips, color, 1.0, 5.0)


def note(rec, c: Chart, name: str, text: str, *, row: int = 0) -> None:
    """A line of text above the plot box's right end, level with the y axis' label (``row`` 1: just
    under the box's top edge, inside): what the axes cannot show, e.g. an off-scale series."""
    left, _, bottom, _ = c.margins
    w, h = c.box
    x = left + w - CHAR_WIDTH * len(text) / 2 - 6.0
    y = -(bottom + h) - 16.0 - TEXT_HEIGHT / 2 if row == 0 else -(bottom + h) + TEXT_HEIGHT / 2 + 4.0
    _text(rec, f"{c.path}/notes/{name}", [[x, y]], [text])


# -- legends, views and the figure ------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Key:
    """One legend entry: its text, colour and how the series is drawn (line, dash, point, band, interval, or a
    marker shape of :data:`SHAPES`)."""

    label: str
    color: tuple[int, ...]
    style: str = "line"
    size: float = 3.5  # a point's radius, a marker's half-width (UI points; diamond and bar keys: 7)


def legend_chart(path: str, keys: Sequence[Key], width: float) -> Chart:
    """A strip holding the figure's legend, one row of entries (wrapped onto more rows when needed)."""
    rows = _legend_rows(keys, width)
    return Chart(path, "", Axis("", 0.0, 1.0), Axis("", 0.0, 1.0), (float(width), 10.0 + 26.0 * len(rows)), (0.0, 0.0, 0.0, 0.0))


def _entry_width(k: Key) -> float:
    return 34.0 + CHAR_WIDTH * len(k.label) + 24.0


def legend_width(keys: Sequence[Key]) -> float:
    """The narrowest legend strip that holds each of ``keys`` on a row of its own (0 without keys)."""
    return max(_entry_width(k) for k in keys) + 20.0 if keys else 0.0


def _legend_rows(keys: Sequence[Key], width: float) -> list[list[Key]]:
    rows: list[list[Key]] = [[]]
    used = 0.0
    for k in keys:
        if rows[-1] and used + _entry_width(k) > width - 20:
            rows.append([])
            used = 0.0
        rows[-1].append(k)
        used += _entry_width(k)
    return rows


def draw_legend(rec, c: Chart, keys: Sequence[Key]) -> None:
    """The entries of a :func:`legend_chart`, each row centred: a sample of the stroke, then its text."""
    for r, row in enumerate(_legend_rows(keys, c.size[0])):
        y = -c.size[1] + 18.0 + 26.0 * r
        x = (c.size[0] - sum(_entry_width(k) for k in row)) / 2
        for i, k in enumerate(row):
            path = f"{c.path}/legend/{r}_{i}"
            sample = np.array([[x, y], [x + 26.0, y]])
            mid = sample.mean(0)
            if k.style in ("line", "dash"):
                strips = _dashes(sample, 7.0, 5.0) if k.style == "dash" else [sample]
                _strips(rec, path, strips, k.color, -1.4)
            elif k.style == "band":
                _strips(rec, path, [sample], k.color, 6.0)
            elif k.style == "point":
                _dots(rec, path, [mid], k.color, -k.size)
            elif k.style in SHAPES:
                size = 7.0 if k.style in ("diamond", "bar") else k.size
                _strips(rec, path, [mid + d for d in _shape(k.style, size)], k.color, -1.1 if k.style == "diamond" else -1.6)
            elif k.style == "interval":
                _strips(rec, path, [[mid - [0, 8], mid + [0, 8]], [mid - [4, 8], mid + [4, -8]], [mid - [4, -8], mid + [4, 8]]],
                        k.color, -1.0)
                _dots(rec, f"{path}_point", [mid], k.color, -3.5)
            else:
                raise ValueError(f"legend style {k.style!r}")
            _text(rec, f"{path}_label", [[x + 34.0, y]], [k.label], left=True)
            x += _entry_width(k)


def view(c: Chart, *, titlebar: bool = False):
    """The 2-d view of a chart: white, no title bar by default (the title is drawn), bounds = the nominal panel."""
    import rerun.blueprint as rrb

    return rrb.Spatial2DView(origin=f"/{c.path}", name=c.title or c.path, titlebar=titlebar, background=WHITE,
                             visual_bounds=rrb.VisualBounds2D(x_range=[0.0, c.size[0]], y_range=[-c.size[1], 0.0]))


class Figure(NamedTuple):
    """Panels in a grid of ``columns`` (row-major) and the legend strip below them."""

    charts: list[Chart]
    columns: int
    legend: Chart | None
    keys: list[Key]


def figure(charts: Sequence[Chart], columns: int, keys: Sequence[Key] = (), legend_path: str | None = None) -> Figure:
    """A figure of ``charts``; with ``keys``, a legend strip as wide as the grid (at ``legend_path``),
    or wider where one entry is wider than the grid (the grid is then centred above it)."""
    charts = list(charts)
    if not charts:
        raise ValueError("a figure needs at least one chart")
    legend = None
    if keys:
        path = legend_path or f"{charts[0].path.split('/')[0]}/legend"
        legend = legend_chart(path, keys, max(columns * charts[0].size[0], legend_width(keys)))
    return Figure(charts, columns, legend, list(keys))


def _blanks(fig: Figure) -> int:
    return math.ceil(len(fig.charts) / fig.columns) * fig.columns - len(fig.charts)


def draw(rec, fig: Figure) -> None:
    """Every chart's axes, and the legend."""
    for c in fig.charts:
        draw_axes(rec, c)
    if not isinstance(rec, SvgCanvas):
        for i in range(_blanks(fig)):  # an empty view would say "No data available"
            _dots(rec, f"blank_{i}", [[0.0, 0.0]], WHITE, 0.0)
    if fig.legend is not None:
        draw_legend(rec, fig.legend, fig.keys)


def blueprint(fig: Figure):
    """The figure's panels with every viewer panel (menu bar, blueprint tree, selection, timeline)
    hidden: the window shows the figure only."""
    import rerun.blueprint as rrb

    blank = [rrb.Spatial2DView(origin=f"/blank_{i}", name=" ", titlebar=False, background=WHITE)  # fill the last row
             for i in range(_blanks(fig))]
    body = rrb.Grid(*[view(c) for c in fig.charts], *blank, grid_columns=fig.columns)
    if fig.legend is not None:
        body = rrb.Vertical(body, view(fig.legend), row_shares=[math.ceil(len(fig.charts) / fig.columns) * fig.charts[0].size[1], fig.legend.size[1]])
    return rrb.Blueprint(body, rrb.TopPanel(state="hidden"), rrb.BlueprintPanel(state="hidden"),
                         rrb.SelectionPanel(state="hidden"), rrb.TimePanel(state="hidden"), auto_views=False)


def size(fig: Figure) -> str:
    """The window size ``WxH`` at which the figure renders at its nominal layout."""
    rows = math.ceil(len(fig.charts) / fig.columns)
    w = max(fig.columns * fig.charts[0].size[0], fig.legend.size[0] if fig.legend is not None else 0.0)
    h = rows * fig.charts[0].size[1] + (fig.legend.size[1] if fig.legend is not None else 0.0)
    return f"{int(round(w))}x{int(round(h))}"


# -- SVG -----------------------------------------------------------------------------------------------


class SvgCanvas:
    """A figure drawn as one SVG document instead of a rerun recording: the same geometry (the
    functions above draw on either), each panel at its place in the figure's grid and the legend
    below, text as plain text (a viewer label sits in a box). A vector figure for a paper, written
    without a viewer or a display."""

    def __init__(self, fig: Figure):
        w, h = fig.charts[0].size
        self.width = max(fig.columns * w, fig.legend.size[0] if fig.legend is not None else 0.0)
        left = (self.width - fig.columns * w) / 2  # a grid narrower than its legend sits centred above it
        self.places = {c.path: (left + i % fig.columns * w, i // fig.columns * h, c.size[1])
                       for i, c in enumerate(fig.charts)}
        rows = math.ceil(len(fig.charts) / fig.columns)
        if fig.legend is not None:
            self.places[fig.legend.path] = (0.0, rows * h, fig.legend.size[1])
        self.height = rows * h + (fig.legend.size[1] if fig.legend is not None else 0.0)
        self._items: list[tuple[float, int, str]] = []

    def _place(self, path: str, points) -> np.ndarray:
        """Document coordinates of view points logged under ``path`` (the panel whose path prefixes it)."""
        owner = max((p for p in self.places if path == p or path.startswith(p + "/")),
                    key=len, default=None)
        if owner is None:
            raise ValueError(f"{path!r} belongs to no panel of the figure")
        x0, y0, h = self.places[owner]
        return np.asarray(points, dtype=float).reshape(-1, 2) + [x0, y0 + h]

    def _add(self, order: float, item: str) -> None:
        self._items.append((order, len(self._items), item))

    def strips(self, path: str, strips, color, radius: float, order: float) -> None:
        for strip in strips:
            p = self._place(path, strip)
            p = p[np.all(np.isfinite(p), axis=1)]
            if len(p) < 2:
                continue
            self._add(order, f'<polyline points="{_svg_points(p)}" fill="none" stroke="{_svg_color(color)}" '
                             f'stroke-width="{2 * abs(radius):.2f}" stroke-linecap="round" stroke-linejoin="round"/>')

    def polygon(self, path: str, outline, color, order: float) -> None:
        p = self._place(path, outline)
        if len(p) >= 3:
            self._add(order, f'<polygon points="{_svg_points(p)}" fill="{_svg_color(color)}" stroke="{_svg_color(color)}" '
                             'stroke-width="0.5" stroke-linejoin="round"/>')

    def dots(self, path: str, positions, color, radius: float, order: float) -> None:
        if radius == 0:
            return
        for x, y in self._place(path, positions):
            if np.isfinite(x) and np.isfinite(y):
                self._add(order, f'<circle cx="{x:.2f}" cy="{y:.2f}" r="{abs(radius):.2f}" fill="{_svg_color(color)}"/>')

    def text(self, path: str, positions, labels, color, anchor: str = "middle") -> None:
        from xml.sax.saxutils import escape

        where = "" if anchor == "middle" else f' text-anchor="{anchor}"'  # the group's default is middle
        for (x, y), label in zip(self._place(path, positions), labels):
            self._add(100.0, f'<text x="{x:.2f}" y="{y:.2f}"{where} fill="{_svg_color(color)}">{escape(str(label))}</text>')

    def write(self, out: str | Path) -> Path:
        body = "\n".join(item for _, _, item in sorted(self._items))
        Path(out).write_text(
            f'<svg xmlns="http://www.w3.org/2000/svg" width="{self.width:.0f}" height="{self.height:.0f}" '
            f'viewBox="0 0 {self.width:.2f} {self.height:.2f}">\n'
            f'<rect width="100%" height="100%" fill="white"/>\n'
            f'<g font-family="DejaVu Sans, Helvetica, Arial, sans-serif" font-size="{SVG_FONT_SIZE}" '
            f'text-anchor="middle" dominant-baseline="central">\n{body}\n</g>\n</svg>\n', encoding="utf-8")
        return Path(out)


#: the SVG text size (px) whose average glyph is about :data:`CHAR_WIDTH` wide, as the viewer's labels
SVG_FONT_SIZE = 11.5


def _svg_color(color) -> str:
    return "#" + "".join(f"{int(v):02x}" for v in color[:3])


def _svg_points(p: np.ndarray) -> str:
    return " ".join(f"{x:.2f},{y:.2f}" for x, y in p)


@contextlib.contextmanager
def recording(out: str | Path, application_id: str, layout) -> Iterator:
    """What to draw on, written to ``out`` on exit: for an ``.svg`` name, an :class:`SvgCanvas` of the
    figure ``layout``; otherwise a rerun recording stream saving to ``out`` (``.rrd``) with
    ``layout``'s blueprint (a :class:`Figure`'s, or a blueprint given as is), flushed and closed."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.suffix.lower() == ".svg":
        if not isinstance(layout, Figure):
            raise ValueError(f"{out}: only a figure is written as SVG (the interactive overview is a recording)")
        canvas = SvgCanvas(layout)
        yield canvas
        canvas.write(out)
        return
    import rerun as rr

    rec = rr.RecordingStream(application_id)
    rr.save(out, default_blueprint=blueprint(layout) if isinstance(layout, Figure) else layout, recording=rec)
    try:
        yield rec
    finally:
        rec.flush()
        rec.disconnect()
