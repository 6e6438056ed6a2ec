"""Rerun recordings of experiment results (rerun-sdk; no matplotlib).

:func:`record` writes the *overview*, the recording ``pipps plot`` makes by default, to explore
interactively: a blueprint of four panels,

* **learning curves** — evaluated return per trial for each (task, method, k, cost) group:
  the mean over seeds and the mean ± one standard deviation, with the success threshold (x: trial);
* **predictions** — for one experiment per group (a tab each), a chart of the final trial's predicted
  trajectories of the task's panel component (the pole angle; particles, or the PILCO Gaussian's
  mean ± 2 sd) against the real rollout, with time (s) and angle (rad) axes
  (:func:`pipps.reporting.figures.draw_prediction`);
* **k_LR per step** and **gradient variances per step** (log₁₀ σ²_RP, σ²_LR), averaged over the
  final trial's optimizer iterations (x: time step).

The time-series panels share one sequence timeline, ``index``, because a rerun time-series view
follows the viewer's single active timeline; their legends sit in the corner the data leave free.
The figures for a paper (no viewer chrome, labelled axes, log scales) are in
:mod:`pipps.reporting.figures` and :mod:`pipps.studies.figures`.

:func:`render_png` renders a recording with rerun's own viewer under ``xvfb-run``.
"""

from __future__ import annotations

import shutil
import subprocess
from collections import defaultdict
from pathlib import Path

import numpy as np

from pipps.experiments.loop import ExperimentResult

#: one sequence timeline for every panel: the trial index in the learning curves, the time step in
#: the k_LR and variance profiles (a time-series view follows the viewer's one active timeline)
TIMELINE = "index"
_PALETTE = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
            (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]


def group_name(r: ExperimentResult) -> str:
    c = r.config
    cost = c.cost_name
    if c.centre_std is None and c.policy == "rbf" and c.policy_init == "start":
        cost += "_startcentres"
    return f"{c.task}_{cost}_k{c.k:g}_{c.method}".replace("+", "plus").replace(".", "p")


def _blueprint(predictions, top: float):
    import rerun.blueprint as rrb

    from pipps import charts as ch

    return rrb.Blueprint(
        rrb.Grid(
            rrb.TimeSeriesView(origin="/curves", name="Evaluated return per trial (mean ± std over seeds)",
                               plot_legend=rrb.PlotLegend(corner="RightTop"), axis_y=rrb.ScalarAxis(range=(0.0, top))),
            rrb.Tabs(*[ch.view(c, titlebar=True) for c in predictions], name="Final-trial predictions vs real rollout (a tab per group)"),
            rrb.TimeSeriesView(origin="/diagnostics/k_lr", name="k_LR per time step (final trial)",
                               plot_legend=rrb.PlotLegend(corner="RightTop"), axis_y=rrb.ScalarAxis(range=(0.0, 1.0))),
            rrb.TimeSeriesView(origin="/diagnostics/log10_variance", name="log10 gradient variance per time step",
                               plot_legend=rrb.PlotLegend(corner="LeftBottom")),
        ),
        collapse_panels=True,
    )


def record(results: list[ExperimentResult], out: str | Path) -> Path:
    """Write the recording of ``results`` to ``out`` (.rrd) and return its path."""
    from pipps import charts as ch
    from pipps.reporting.figures import draw_prediction, prediction_chart

    groups: dict[str, list[ExperimentResult]] = defaultdict(list)
    for r in results:
        groups[group_name(r)].append(r)
    groups = dict(sorted(groups.items()))
    predictions = [prediction_chart(f"predictions/{name}", f"{name}, seed {rs[0].config.seed}: final trial", rs[0], (700.0, 400.0))
                   for name, rs in groups.items()]
    top = 1.05 * max(max(t.eval_return for t in r.trials) for r in results)
    with ch.recording(out, "pipps", _blueprint(predictions, top)) as rec:
        for gi, ((name, rs), c) in enumerate(zip(groups.items(), predictions)):
            color = _PALETTE[gi % len(_PALETTE)]
            _log_curves(rec, name, rs, color)
            ch.draw_axes(rec, c)
            draw_prediction(rec, c, rs[0], color)
            _log_diagnostics(rec, name, rs[0], color)
    return Path(out)


def curve(rs: list[ExperimentResult]) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation over seeds of the evaluated return per trial (the trials all have)."""
    n = min(len(r.trials) for r in rs)
    returns = np.array([[t.eval_return for t in r.trials[:n]] for r in rs])
    return returns.mean(0), returns.std(0)


def _log_curves(rec, name: str, rs: list[ExperimentResult], color) -> None:
    import rerun as rr

    from pipps.reporting.verdicts import criterion

    mean, std = curve(rs)
    n = len(mean)
    light = tuple(int(0.5 * c + 127) for c in color)
    rec.log(f"curves/{name}/mean", rr.SeriesLines(colors=[color], widths=[2.0], names=[f"{name} (n={len(rs)})"]),
            static=True)
    for part in ("lo", "hi"):
        rec.log(f"curves/{name}/{part}", rr.SeriesLines(colors=[light], widths=[1.0], names=[f"{name} ± std"]),
                static=True)
    threshold = criterion(rs[0].config).threshold  # None: the task is judged by its criterion alone
    for i in range(n):
        rec.set_time(TIMELINE, sequence=i)
        rec.log(f"curves/{name}/mean", rr.Scalars([mean[i]]))
        rec.log(f"curves/{name}/lo", rr.Scalars([mean[i] - std[i]]))
        rec.log(f"curves/{name}/hi", rr.Scalars([mean[i] + std[i]]))
        if threshold is not None:
            rec.log("curves/success_threshold", rr.Scalars([threshold]))


def _log_diagnostics(rec, name: str, r: ExperimentResult, color) -> None:
    import rerun as rr

    final = r.trials[-1]
    d = final.diagnostics
    if d is None:
        return
    rec.log(f"diagnostics/k_lr/{name}", rr.SeriesLines(colors=[color], names=[name]), static=True)
    for part, c in (("rp", color), ("lr", tuple(int(0.5 * v) for v in color))):
        rec.log(f"diagnostics/log10_variance/{name}/{part}", rr.SeriesLines(colors=[c], names=[f"{name} σ²_{part.upper()}"]),
                static=True)
    with np.errstate(all="ignore"):
        for t in range(len(d.k_lr)):
            rec.set_time(TIMELINE, sequence=t + 1)
            if np.isfinite(d.k_lr[t]):
                rec.log(f"diagnostics/k_lr/{name}", rr.Scalars([d.k_lr[t]]))
            for part in ("rp", "lr"):
                v = getattr(d, f"var_{part}")[t]
                if np.isfinite(v) and v > 0:
                    rec.log(f"diagnostics/log10_variance/{name}/{part}", rr.Scalars([np.log10(v)]))


#: what --png needs, as one install line (Debian/Ubuntu package names)
PNG_INSTALL = "apt-get install xvfb mesa-vulkan-drivers (Debian/Ubuntu); the viewer comes with pip install rerun-sdk"

#: where Vulkan drivers announce themselves (the Khronos loader's search path) and where Mesa's
#: software OpenGL lives: the viewer draws through one of them on the virtual screen
_VULKAN_ICDS = ("/usr/share/vulkan/icd.d", "/etc/vulkan/icd.d", "/usr/local/share/vulkan/icd.d")
_MESA_GL = ("/usr/lib/*/dri/swrast_dri.so", "/usr/lib64/dri/swrast_dri.so", "/usr/lib/dri/swrast_dri.so",
            "/usr/lib/*/dri/llvmpipe_dri.so", "/usr/lib64/dri/llvmpipe_dri.so")


def graphics_driver() -> str | None:
    """A driver the rerun viewer can draw with under Xvfb: a Vulkan driver (``*.json`` in the loader's
    folders, or named by ``VK_ICD_FILENAMES``/``VK_DRIVER_FILES``) or Mesa's software OpenGL; None if
    neither is installed. Not Linux: assumed present (the check is the Linux packages')."""
    import glob
    import os
    import sys

    if not sys.platform.startswith("linux"):
        return "the system's"
    for var in ("VK_ICD_FILENAMES", "VK_DRIVER_FILES"):
        named = [p for p in os.environ.get(var, "").split(os.pathsep) if p and os.path.exists(p)]
        if named:
            return named[0]
    for folder in _VULKAN_ICDS:
        found = sorted(glob.glob(os.path.join(folder, "*.json")))
        if found:
            return found[0]
    for pattern in _MESA_GL:
        found = sorted(glob.glob(pattern))
        if found:
            return found[0]
    return None


def check_viewer() -> tuple[str, str]:
    """``(xvfb-run, rerun)`` on PATH and a graphics driver for them (:func:`graphics_driver`), or a
    :class:`FileNotFoundError` that names what is missing and the line that installs it."""
    xvfb = shutil.which("xvfb-run")
    viewer = shutil.which("rerun")
    driver = graphics_driver()
    missing = [n for n, p in (("xvfb-run", xvfb), ("the rerun viewer", viewer),
                              ("a Vulkan or Mesa OpenGL driver", driver)) if p is None]
    if missing:
        raise FileNotFoundError(f"--png needs {' and '.join(missing)}: {PNG_INSTALL}; the .rrd recording needs none "
                                "of them (drop --png)")
    return xvfb, viewer


def render_png(rrd: str | Path, png: str | Path, size: str = "1600x1000", timeout: float = 120.0) -> Path:
    """Render ``rrd`` to ``png`` with ``xvfb-run rerun REC --screenshot-to PNG --window-size WxH``.

    The viewer draws at twice the window size; the virtual screen is made four times as large so that
    its pointer, which rests at the screen's centre, hovers over nothing (a hover draws a tooltip), and
    ``RUST_LOG=error`` keeps the viewer's startup warnings out of the picture (they show as toasts). The
    PNG is then stored with a 256-colour palette (figures are flat colours: a few times smaller)."""
    import os

    xvfb, viewer = check_viewer()
    try:
        w, h = (int(v) for v in size.lower().split("x"))
    except ValueError:
        raise ValueError(f"size must be WIDTHxHEIGHT in pixels, got {size!r}") from None
    cmd = [xvfb, "-a", "-s", f"-screen 0 {4 * w + 4}x{4 * h + 4}x24", viewer, str(rrd),
           "--screenshot-to", str(png), "--window-size", f"{w}x{h}"]
    env = {**os.environ, "RUST_LOG": "error"}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    if proc.returncode != 0 or not Path(png).exists():
        raise RuntimeError(f"rendering failed ({proc.returncode}): {proc.stderr[-2000:]}")
    _palette_png(png)
    return Path(png)


def _palette_png(png: str | Path) -> None:
    try:
        from PIL import Image  # comes with rerun-sdk
    except ImportError:  # pragma: no cover
        return
    with Image.open(png) as im:
        small = im.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    small.save(png, optimize=True)
