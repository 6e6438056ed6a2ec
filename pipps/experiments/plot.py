"""Rerun recordings of experiment results (rerun-sdk; no matplotlib).

:func:`record` writes one ``.rrd`` with a blueprint of four panels:

* **learning curves** — evaluated return per trial for each (task, method, k, cost) group:
  the mean over seeds and the mean ± one standard deviation (timeline ``trial``), with the
  success threshold (x: trial);
* **predictions** — for one experiment per group, the final trial's predicted particle
  trajectories of the pole angle (or the PILCO Gaussian's mean ± 2 std) against the real
  rollout, in the (time, angle) plane;
* **k_LR per step** and **gradient variances per step** (log₁₀ σ²_RP, σ²_LR), averaged over the
  final trial's optimizer iterations (x: time step). All panels share one sequence timeline,
  ``index``, because a rerun time-series view follows the viewer's single active timeline.

:func:`render_png` renders a recording with rerun's own viewer under ``xvfb-run``.
"""

from __future__ import annotations

import shutil
import subprocess
from collections import defaultdict
from pathlib import Path

import numpy as np

from pipps.experiments.loop import ExperimentResult

#: which model-state component is drawn in the predictions panel, and its label
ANGLE_INDEX = {"cartpole_swingup": (3, "θ (rad)"), "cartpole_balance": (3, "θ (rad)"), "unicycle": (9, "pitch ψ_f (rad)")}
#: one sequence timeline for every panel: the trial index in the learning curves, the time step in
#: the k_LR and variance profiles (a time-series view follows the viewer's one active timeline)
TIMELINE = "index"
_PALETTE = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
            (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]


def group_name(r: ExperimentResult) -> str:
    from pipps.tasks.presets import DEFAULT_COST

    c = r.config
    cost = c.cost or DEFAULT_COST[(c.task, c.preset)]
    if c.centre_std is None and c.policy == "rbf" and c.policy_init == "start":
        cost += "_startcentres"
    return f"{c.task}_{cost}_k{c.k:g}_{c.method}".replace("+", "plus").replace(".", "p")


def _blueprint():
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Grid(
            rrb.TimeSeriesView(origin="/curves", name="Evaluated return per trial (mean ± std over seeds)"),
            rrb.Spatial2DView(origin="/predictions", name="Final-trial predictions vs real rollout (time, angle)"),
            rrb.TimeSeriesView(origin="/diagnostics/k_lr", name="k_LR per time step (final trial)"),
            rrb.TimeSeriesView(origin="/diagnostics/log10_variance", name="log10 gradient variance per time step"),
        ),
        collapse_panels=True,
    )


def record(results: list[ExperimentResult], out: str | Path) -> Path:
    """Write the recording of ``results`` to ``out`` (.rrd) and return its path."""
    import rerun as rr

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream("pipps")
    rr.save(out, default_blueprint=_blueprint(), recording=rec)
    groups: dict[str, list[ExperimentResult]] = defaultdict(list)
    for r in results:
        groups[group_name(r)].append(r)
    for gi, (name, rs) in enumerate(sorted(groups.items())):
        color = _PALETTE[gi % len(_PALETTE)]
        _log_curves(rec, name, rs, color)
        _log_predictions(rec, name, rs[0], color, offset=gi)
        _log_diagnostics(rec, name, rs[0], color)
    rec.flush()
    rec.disconnect()
    return out


def curve(rs: list[ExperimentResult]) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation over seeds of the evaluated return per trial (the trials all have)."""
    n = min(len(r.trials) for r in rs)
    returns = np.array([[t.eval_return for t in r.trials[:n]] for r in rs])
    return returns.mean(0), returns.std(0)


def _log_curves(rec, name: str, rs: list[ExperimentResult], color) -> None:
    import rerun as rr

    mean, std = curve(rs)
    n = len(mean)
    light = tuple(int(0.5 * c + 127) for c in color)
    rec.log(f"curves/{name}/mean", rr.SeriesLines(colors=[color], widths=[2.0], names=[f"{name} (n={len(rs)})"]),
            static=True)
    for part in ("lo", "hi"):
        rec.log(f"curves/{name}/{part}", rr.SeriesLines(colors=[light], widths=[1.0], names=[f"{name} ± std"]),
                static=True)
    threshold = rs[0].config.success_threshold if rs[0].config.task != "unicycle" else None
    for i in range(n):
        rec.set_time(TIMELINE, sequence=i)
        rec.log(f"curves/{name}/mean", rr.Scalars([mean[i]]))
        rec.log(f"curves/{name}/lo", rr.Scalars([mean[i] - std[i]]))
        rec.log(f"curves/{name}/hi", rr.Scalars([mean[i] + std[i]]))
        if threshold is not None:
            rec.log("curves/success_threshold", rr.Scalars([threshold]))


def _log_predictions(rec, name: str, r: ExperimentResult, color, offset: int) -> None:
    """(time, angle) strips; groups are stacked vertically so they do not overlap."""
    import rerun as rr

    final = r.trials[-1]
    if final.predicted is None:
        return
    idx, _ = ANGLE_INDEX[r.config.task]
    dt = 0.1
    y0 = 8.0 * offset
    rec.set_time(TIMELINE, sequence=final.index)
    pred = final.predicted
    scale = 10.0  # time axis stretch so a 3 s episode is as wide as the angle range
    if "particles" in pred:
        x = pred["particles"][:, :, idx]  # (T+1, S)
        t = np.arange(x.shape[0]) * dt * scale
        strips = [np.stack([t, y0 - x[:, j]], axis=1) for j in range(x.shape[1])]
        light = tuple(int(0.4 * c + 150) for c in color)
        rec.log(f"predictions/{name}/particles", rr.LineStrips2D(strips, colors=[light], radii=[0.02]))
    else:
        m, s = pred["mean"][:, idx], np.sqrt(np.maximum(pred["cov"][:, idx, idx], 0.0))
        t = np.arange(m.shape[0]) * dt * scale
        rec.log(f"predictions/{name}/gaussian_mean", rr.LineStrips2D([np.stack([t, y0 - m], 1)], colors=[color], radii=[0.04]))
        band = [np.stack([t, y0 - (m + k * s)], 1) for k in (-2.0, 2.0)]
        rec.log(f"predictions/{name}/gaussian_2std", rr.LineStrips2D(band, colors=[color], radii=[0.02]))
    valid = np.concatenate([[True], final.valid.astype(bool)])
    real = final.states[valid][:, idx if r.config.task != "unicycle" else 10]
    t = np.arange(real.shape[0]) * dt * scale
    rec.log(f"predictions/{name}/real", rr.LineStrips2D([np.stack([t, y0 - real], 1)], colors=[(255, 255, 255)], radii=[0.05],
                                                          labels=[f"{name}: real rollout"]))


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
        for t in range(len(d["k_lr"])):
            rec.set_time(TIMELINE, sequence=t + 1)
            if np.isfinite(d["k_lr"][t]):
                rec.log(f"diagnostics/k_lr/{name}", rr.Scalars([d["k_lr"][t]]))
            for part in ("rp", "lr"):
                v = d[f"var_{part}"][t]
                if np.isfinite(v) and v > 0:
                    rec.log(f"diagnostics/log10_variance/{name}/{part}", rr.Scalars([np.log10(v)]))


def check_viewer() -> tuple[str, str]:
    """``(xvfb-run, rerun)`` on PATH, or a :class:`FileNotFoundError` that says what to install."""
    xvfb = shutil.which("xvfb-run")
    viewer = shutil.which("rerun")
    if xvfb is None or viewer is None:
        missing = " and ".join(n for n, p in (("xvfb-run", xvfb), ("the rerun viewer", viewer)) if p is None)
        raise FileNotFoundError(f"--png needs {missing} on PATH (Debian: apt-get install xvfb mesa-vulkan-drivers; "
                                "the viewer comes with rerun-sdk); the .rrd recording needs neither")
    return xvfb, viewer


def render_png(rrd: str | Path, png: str | Path, size: str = "1600x1000", timeout: float = 120.0) -> Path:
    """Render ``rrd`` to ``png`` with ``xvfb-run rerun REC --screenshot-to PNG --window-size WxH``."""
    xvfb, viewer = check_viewer()
    cmd = [xvfb, "-a", "-s", f"-screen 0 {size.replace('x', 'x')}x24", viewer, str(rrd),
           "--screenshot-to", str(png), "--window-size", size]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0 or not Path(png).exists():
        raise RuntimeError(f"rendering failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return Path(png)
