"""Run time against gradient error (``pipps bench``).

At a smooth and a chaotic point of the line ``θ + Δ·d`` through a policy snapshot, for each
estimator and number of particles P:

* **time**: the median wall seconds of one jitted value-and-gradient call, after compilation,
  over ``time_repeats`` calls (``block_until_ready``), as an optimizer iteration pays for it
  (the estimator state, e.g. the "previous" baseline, comes from the previous iteration);
* **error**: the mean squared error ``mean_r ‖ĝ_r − g_ref‖²`` over ``repeats`` independent
  estimates, against a reference gradient ``g_ref``: the average of ``reference_repeats``
  estimates of an unbiased estimator (library TP by default) at the largest P. The reference has
  its own error, ``tr Cov[g_ref] = tr Cov[one estimate]/n``, which every MSE contains; it is
  reported next to the table so that no MSE is read below it.

The Pareto table lists, per point, the (estimator, P) pairs that no other pair beats in both
time and error, and for error targets (decades) the fastest pair that reaches each. PILCO's
moment-matching gradient is timed too; its "error" against the particle reference is the
gradient difference of the two objectives (moment matching is a different approximation of the
same expected cost), reported for information.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from pipps.propagation.estimate import estimate, init_estimator_state
from pipps.studies.gradients import LABELS, _check_estimators, _direction, estimator_program, estimator_setup
from pipps.studies.snapshot import Snapshot


@dataclasses.dataclass
class BenchEntry:
    estimator: str
    particles: int
    seconds: float  # median wall seconds per value-and-gradient
    mse: float  # mean_r ‖ĝ_r − g_ref‖²
    mse_se: float  # its standard error over the repeats
    nonfinite: int  # repeats with a non-finite gradient (excluded)
    variance_tol: float = 0.0  # 0: the exact GP variance; > 0: the certified low-rank form (pipps.gp.lowrank)
    exact_change: float = 0.0  # with variance_tol > 0: max_r ‖ĝ_r − ĝ_r(exact variance)‖, same random numbers
    exact_spread: float = 0.0  # the exact-variance estimates' Monte Carlo spread, sqrt(tr Cov) over the repeats

    @property
    def series(self) -> str:
        """The estimator's name, with the tolerance for a low-rank variance (one line per series in a figure)."""
        return self.estimator if self.variance_tol == 0 else f"{self.estimator} (variance tol {self.variance_tol:g})"

    @property
    def label(self) -> str:
        name = LABELS.get(self.estimator, self.estimator)
        return name if self.variance_tol == 0 else f"{name}, variance tol {self.variance_tol:g}"


@dataclasses.dataclass
class BenchResult:
    source: str
    trial: int
    deltas: np.ndarray
    direction: np.ndarray
    direction_kind: str
    reference: np.ndarray  # (nΔ, n_θ)
    reference_error: np.ndarray  # (nΔ,) tr Cov[g_ref]
    reference_name: str
    reference_particles: int
    entries: list[list[BenchEntry]]  # [Δ] → entries
    mm_seconds: float
    mm_distance: np.ndarray  # (nΔ,) ‖∇J_MM − g_ref‖²
    repeats: int
    seed: int
    seconds: float
    variance_bounds: dict = dataclasses.field(default_factory=dict)  # tol → (E,) certified bound (units of σ²)
    variance_ranks: dict = dataclasses.field(default_factory=dict)  # tol → (E,) kept directions


def _time(fn, arg, *, repeats: int) -> float:
    """Median wall seconds of ``fn(arg)`` after a first (compiling) call."""
    jax.block_until_ready(fn(arg))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(arg))
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _timing_program(snap: Snapshot, name: str, P: int):
    """``θ → (value, ĝ)`` as an optimizer iteration pays for it: the estimator state (the
    "previous" baseline) is computed once, outside, so its extra rollout is not timed."""
    def build():
        est, rcfg = estimator_setup(snap, name, P, "library")
        problem, model = snap.task, snap.model
        state = init_estimator_state(jax.random.PRNGKey(1), snap.policy, model, problem=problem, config=rcfg, estimator=est)
        key = jax.random.PRNGKey(2)

        @jax.jit
        def run(theta):
            _, e = estimate(key, state, snap.unravel(theta), model, problem=problem, config=rcfg, estimator=est)
            return e.value, e.grad

        return run

    return snap.program(("timing", name, P), build)


def _estimates(program, key, theta, n: int) -> np.ndarray:
    return np.stack([np.asarray(program(jax.random.fold_in(key, r), theta)[0]) for r in range(n)])


def bench(
    snap: Snapshot,
    *,
    deltas=(0.0, 1.5),
    particles=(30, 100, 300, 1000),
    estimators=("rp", "lr", "tp", "gtp"),
    repeats: int = 20,
    time_repeats: int = 5,
    reference: str = "tp",
    reference_repeats: int = 50,
    direction: str = "pilco",
    seed: int = 0,
    variance_tols=(0.0,),
    progress: Callable[[str], None] | None = None,
) -> BenchResult:
    """Time and error of every (estimator, P) at every Δ (module doc), for each GP variance in
    ``variance_tols`` (0: exact; > 0: the certified low-rank form at that tolerance, whose entries
    also report the change of each estimate from the exact-variance one with the same random
    numbers). The reference gradient is always computed on the exact variance."""
    names = _check_estimators(estimators)
    _check_estimators([reference])
    particles = sorted(int(p) for p in particles)
    if not particles or particles[0] < 2:
        raise ValueError(f"particles must be integers >= 2, got {particles}")
    for name, v in (("repeats", repeats), ("reference_repeats", reference_repeats)):
        if int(v) < 2:
            raise ValueError(f"{name} must be >= 2, got {v}")
    if int(time_repeats) < 1:
        raise ValueError(f"time_repeats must be >= 1, got {time_repeats}")
    tols = sorted({float(t) for t in variance_tols} | {0.0})
    if tols[0] < 0 or not all(np.isfinite(tols)):
        raise ValueError(f"variance_tols must be finite numbers >= 0, got {list(variance_tols)}")
    variants, bounds, ranks = {0.0: snap}, {}, {}
    for tol in tols[1:]:
        from pipps.gp.lowrank import low_rank_model

        model, kept = low_rank_model(snap.model, snap.data, tol, sparse=snap.sparse, jitter=snap.jitter)
        variants[tol] = dataclasses.replace(snap, model=model, programs={})
        bounds[tol], ranks[tol] = np.asarray(model.bound), np.asarray(kept)
    progress = progress or (lambda msg: None)
    start = time.perf_counter()
    deltas = np.asarray(deltas, float)
    d = _direction(snap, direction, seed)
    theta0 = np.asarray(snap.theta)
    points = [jnp.asarray(theta0 + delta * d) for delta in deltas]
    P_ref = particles[-1]
    ref_prog = estimator_program(snap, reference, P_ref, "library")
    refs, ref_err = [], []
    for di, p in enumerate(points):
        g = _estimates(ref_prog, jax.random.fold_in(jax.random.PRNGKey(seed + 7), di), p, reference_repeats)
        g = g[np.all(np.isfinite(g), axis=1)]
        refs.append(g.mean(0))
        ref_err.append(float(np.sum(np.var(g, axis=0, ddof=1)) / len(g)))
        progress(f"reference {LABELS.get(reference, reference)} P={P_ref} Δ={deltas[di]:.3g}")
    mm = snap.mm_value_and_grad()
    mm_seconds = _time(mm, points[0], repeats=time_repeats)
    mm_dist = np.array([float(np.sum((np.asarray(mm(p)[1]) - r) ** 2)) for p, r in zip(points, refs)])
    entries: list[list[BenchEntry]] = [[] for _ in deltas]
    for ei, name in enumerate(names):
        for P in particles:
            exact_g = {}
            for tol, variant in variants.items():
                prog = estimator_program(variant, name, P, "library")
                seconds = _time(_timing_program(variant, name, P), points[0], repeats=time_repeats)
                for di, p in enumerate(points):
                    key = jax.random.fold_in(jax.random.PRNGKey(seed + 13), 10_000 * ei + 10 * P + di)
                    g = _estimates(prog, key, p, repeats)  # the same keys for every tolerance: paired
                    finite = np.all(np.isfinite(g), axis=1)
                    sq = np.sum((g[finite] - refs[di]) ** 2, axis=1)
                    se = float(sq.std(ddof=1) / np.sqrt(len(sq))) if len(sq) > 1 else float("nan")
                    if tol == 0.0:
                        exact_g[di] = g
                    both = finite & np.all(np.isfinite(exact_g[di]), axis=1)
                    change = float(np.max(np.linalg.norm(g[both] - exact_g[di][both], axis=1))) if both.any() else float("nan")
                    spread = float(np.sqrt(np.sum(np.var(exact_g[di][both], axis=0, ddof=1)))) if both.sum() > 1 else float("nan")
                    entry = BenchEntry(name, P, seconds, float(sq.mean()) if len(sq) else float("nan"), se,
                                       int((~finite).sum()), tol, change, spread)
                    entries[di].append(entry)
                    progress(f"{entry.label} P={P} Δ={deltas[di]:.3g}: {seconds:.3g} s, MSE {entry.mse:.3g}")
    return BenchResult(snap.source, snap.trial, deltas, d, direction, np.stack(refs), np.array(ref_err), reference,
                       P_ref, entries, mm_seconds, mm_dist, repeats, seed, time.perf_counter() - start, bounds, ranks)


def pareto(entries: list[BenchEntry]) -> list[BenchEntry]:
    """The entries no other entry beats in both time and error, fastest first."""
    finite = [e for e in entries if np.isfinite(e.mse)]
    front = [e for e in finite
             if not any((o.seconds <= e.seconds and o.mse < e.mse) or (o.seconds < e.seconds and o.mse <= e.mse) for o in finite)]
    return sorted(front, key=lambda e: e.seconds)


def bench_table(r: BenchResult) -> str:
    """Markdown: every entry, the Pareto front and the fastest entry per error decade, per Δ."""
    lines = [f"Bench: {r.source} trial {r.trial}, direction {r.direction_kind}, {r.repeats} repeats per entry; "
             f"reference: {LABELS.get(r.reference_name, r.reference_name)} at P = {r.reference_particles}"]
    for di, delta in enumerate(r.deltas):
        es = r.entries[di]
        front = pareto(es)
        lines += ["", f"Δ = {delta:.3g} (reference error tr Cov[g_ref] = {r.reference_error[di]:.3g}; "
                      f"‖g_ref‖² = {float(np.sum(r.reference[di] ** 2)):.3g})", "",
                  "| estimator | P | s per value-and-gradient | MSE to g_ref | ± SE | Pareto |"
                  + (" max ‖ĝ − ĝ_exact‖ / MC spread |" if r.variance_bounds else ""),
                  "|---|---|---|---|---|---|" + ("---|" if r.variance_bounds else "")]
        for e in sorted(es, key=lambda e: (e.estimator, e.particles, e.variance_tol)):
            bad = f" ({e.nonfinite} non-finite)" if e.nonfinite else ""
            change = ""
            if r.variance_bounds:
                change = f" {e.exact_change:.3g} / {e.exact_spread:.3g} |" if e.variance_tol > 0 else " – |"
            lines.append(f"| {e.label} | {e.particles} | {e.seconds:.4f} | {e.mse:.3g}{bad} "
                         f"| {e.mse_se:.2g} | {'yes' if e in front else ''} |{change}")
        lines.append(f"| PILCO (exact MM gradient) | – | {r.mm_seconds:.4f} | {r.mm_distance[di]:.3g} (‖∇J_MM − g_ref‖²) | – | |")
        finite = [e for e in es if np.isfinite(e.mse)]
        if finite:
            # decades up to the worst Pareto entry: above it the fastest entry no longer changes
            lo, hi = np.floor(np.log10(min(e.mse for e in finite))), np.ceil(np.log10(max(e.mse for e in front)))
            targets = [10.0**k for k in range(int(lo), int(hi) + 1)]
            lines += ["", "| error target (MSE ≤) | fastest | its time s |", "|---|---|---|"]
            for t in targets:
                ok = [e for e in finite if e.mse <= t]
                if ok:
                    best = min(ok, key=lambda e: e.seconds)
                    lines.append(f"| {t:.0e} | {best.label}, P = {best.particles} | {best.seconds:.4f} |")
    for tol in sorted(r.variance_bounds):
        lines.append(f"\nvariance tol {tol:g}: ranks {np.asarray(r.variance_ranks[tol]).tolist()}, certified bounds "
                     f"{np.array2string(np.asarray(r.variance_bounds[tol]), precision=2)} (units of σ²)")
    return "\n".join(lines)


def write_bench(path: str | Path, r: BenchResult) -> Path:
    """HDF5 (atomic): attributes as the studies', ``reference`` (nΔ, n_θ), ``reference_error``,
    ``mm_distance``, and per Δ a table ``entries/delta_<i>`` with columns estimator, particles,
    seconds, mse, mse_se, nonfinite."""
    import os

    import h5py

    from pipps.experiments.results import versions

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with h5py.File(tmp, "w") as f:
        f.attrs.update(study="bench", source=r.source, trial=r.trial, direction_kind=r.direction_kind, repeats=r.repeats,
                       seed=r.seed, seconds=r.seconds, reference_estimator=r.reference_name,
                       reference_particles=r.reference_particles, mm_seconds=r.mm_seconds, schema_version=1)
        for k, v in versions().items():
            f.attrs[f"version_{k}"] = v
        for name in ("deltas", "direction", "reference", "reference_error", "mm_distance"):
            f.create_dataset(name, data=getattr(r, name))
        for di, es in enumerate(r.entries):
            g = f.create_group(f"entries/delta_{di:03d}")
            g.create_dataset("estimator", data=np.array([e.estimator for e in es], dtype="S"))
            for col in ("particles", "seconds", "mse", "mse_se", "nonfinite", "variance_tol", "exact_change",
                        "exact_spread"):
                g.create_dataset(col, data=np.array([getattr(e, col) for e in es]))
        for tol in sorted(r.variance_bounds):
            g = f.create_group(f"variance/tol_{tol:g}")
            g.attrs["tol"] = tol
            g.create_dataset("bound", data=np.asarray(r.variance_bounds[tol]))
            g.create_dataset("ranks", data=np.asarray(r.variance_ranks[tol]))
    with open(tmp, "rb+") as fh:
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    return path


def read_bench(path: str | Path) -> BenchResult:
    """Load a bench written by :func:`write_bench` (to re-print its table or re-draw its figure)."""
    import h5py

    with h5py.File(path, "r") as f:
        a = f.attrs
        entries = []
        for key in sorted(f["entries"]):
            g = f["entries"][key]
            n = len(g["estimator"])
            cols = {c: g[c][()] for c in ("particles", "seconds", "mse", "mse_se", "nonfinite")}
            for c in ("variance_tol", "exact_change", "exact_spread"):  # benches written before the tolerance axis lack them
                cols[c] = g[c][()] if c in g else np.zeros(n)
            entries.append([BenchEntry(e.decode(), int(cols["particles"][i]), float(cols["seconds"][i]), float(cols["mse"][i]),
                                       float(cols["mse_se"][i]), int(cols["nonfinite"][i]), float(cols["variance_tol"][i]),
                                       float(cols["exact_change"][i]), float(cols["exact_spread"][i]))
                            for i, e in enumerate(g["estimator"][()])])
        bounds, ranks = {}, {}
        for g in (f["variance"].values() if "variance" in f else []):
            bounds[float(g.attrs["tol"])], ranks[float(g.attrs["tol"])] = g["bound"][()], g["ranks"][()]
        return BenchResult(str(a["source"]), int(a["trial"]), f["deltas"][()], f["direction"][()], str(a["direction_kind"]),
                           f["reference"][()], f["reference_error"][()], str(a["reference_estimator"]),
                           int(a["reference_particles"]), entries, float(a["mm_seconds"]), f["mm_distance"][()],
                           int(a["repeats"]), int(a["seed"]), float(a["seconds"]), bounds, ranks)
