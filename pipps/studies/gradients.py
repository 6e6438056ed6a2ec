"""The gradient landscape and the variance against particles (thesis Fig. 4.2/4.12 and 4.13).

Both studies evaluate estimators at points ``θ + Δ·d`` of a line through a policy snapshot
(:mod:`pipps.studies.snapshot`), ``d`` a unit direction (default: PILCO's moment-matching descent
direction). At each point every estimator is run ``repeats`` times with independent keys (each
repeat also draws its own "previous"-baseline rollout, i.e. each is an optimizer's first
iteration), and we keep the directional derivative ``ĝ·d`` of every repeat and the trace of the
estimate's per-parameter variance across repeats.

* :func:`landscape`: ``Δ`` on a grid in ``[0, Δ_max]`` at one P; also the particle objective
  with one fixed seed (common random numbers along the line, as the thesis plots it), the
  moment-matching objective and its exact directional derivative for reference.
* :func:`variance_study`: at a few ``Δ`` (smooth and chaotic) for several P; also the mean
  per-step ``k_LR`` of every estimator that weighs two parts.

An estimator is named as in the registry (:data:`pipps.propagation.estimators.ESTIMATORS`), with
settings if wanted: ``"tp:k_lr=previous"`` (:func:`pipps.propagation.estimators.from_spec`); its
label and colour are the registry's.

The 95 % interval of a mean directional derivative is ``± 1.96·sd/√R`` over the R repeats.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from pipps.particles.forward import RolloutConfig, reparameterized_objective, sample_noise
from pipps.propagation.estimators import ESTIMATORS, NAMED, from_spec, spec_label
from pipps.propagation.estimate import estimate, init_estimator_state
from pipps.studies.snapshot import Snapshot

#: the thesis' Fig. 4.2 set: RP, plain LR, BIW-LR, TP, GTP
DEFAULT_ESTIMATORS = ("rp", "lr_plain", "lr", "tp", "gtp")
#: each named estimator's label (the registry's)
LABELS = {name: entry.label for name, entry in ESTIMATORS.items()}


def label(spec: str) -> str:
    """An estimator's label: ``"tp"`` → ``"TP"``, ``"tp:k_lr=previous"`` → ``"TP (k_lr=previous)"``."""
    return spec_label(spec)


def _check_estimators(names) -> tuple[str, ...]:
    names = tuple(names)
    if not names:
        raise ValueError(f"estimators: empty list; choose from {NAMED}")
    for n in names:
        try:
            from_spec(n)
        except ValueError as err:
            raise ValueError(f"estimators: {err}") from None
    return names


def _check_positive(name: str, value: int, lowest: int = 1) -> None:
    if int(value) < lowest:
        raise ValueError(f"{name} must be >= {lowest}, got {value}")


def estimator_program(snap: Snapshot, name: str, P: int, choices: str):
    """A jitted ``(key, θ) → (ĝ flat, per-step k_LR)`` for one estimator at P particles (cached on the snapshot)."""
    return snap.program(("estimator", name, P, choices), lambda: _build_estimator_program(snap, name, P, choices))


def estimator_setup(snap: Snapshot, name: str, P: int, choices: str):
    """(Estimator, RolloutConfig) of a named estimator (with its settings, if any) at P particles on the
    snapshot's horizon."""
    est = from_spec(name, choices)
    return est, RolloutConfig(num_particles=P, horizon=snap.config.horizon)


def _build_estimator_program(snap: Snapshot, name: str, P: int, choices: str):
    est, rcfg = estimator_setup(snap, name, P, choices)
    problem, model = snap.task, snap.model

    @jax.jit
    def run(key, theta):
        policy = snap.unravel(theta)
        k_state, k_est = jax.random.split(key)
        state = init_estimator_state(k_state, policy, model, problem=problem, config=rcfg, estimator=est)
        _, e = estimate(k_est, state, policy, model, problem=problem, config=rcfg, estimator=est)
        return ravel_pytree(e.grad)[0], e.diagnostics.k_lr

    return run


@dataclasses.dataclass
class Samples:
    """Repeated estimates of one estimator at one point: (R,) directional derivatives and more."""

    directional: np.ndarray  # (R,) ĝ·d
    trace_variance: float  # Σ_j Var_r[ĝ_j] over the repeats
    k_lr: np.ndarray  # (T,) mean over repeats of the per-step k_LR used
    nonfinite: int  # repeats whose gradient had a non-finite entry (excluded above)


def _samples(program, key, theta, d, repeats: int) -> Samples:
    grads, klr = [], []
    for r in range(repeats):
        g, k = program(jax.random.fold_in(key, r), theta)
        grads.append(np.asarray(g))
        klr.append(np.asarray(k))
    grads, klr = np.stack(grads), np.stack(klr)
    finite = np.all(np.isfinite(grads), axis=1)
    g = grads[finite]
    dirs = g @ np.asarray(d)
    trace = float(np.sum(np.var(g, axis=0, ddof=1))) if len(g) > 1 else float("nan")
    return Samples(dirs, trace, np.nanmean(klr[finite], axis=0) if finite.any() else np.full(klr.shape[1], np.nan),
                   int((~finite).sum()))


def interval(x: np.ndarray) -> tuple[float, float]:
    """(mean, 95 % half-width 1.96·sd/√R) of repeated estimates."""
    x = np.asarray(x, float)
    if len(x) < 2:
        return (float(x.mean()) if len(x) else float("nan")), float("nan")
    return float(x.mean()), float(1.96 * x.std(ddof=1) / np.sqrt(len(x)))


@dataclasses.dataclass
class LandscapeResult:
    source: str
    trial: int
    deltas: np.ndarray  # (nΔ,)
    direction: np.ndarray  # (n_θ,) unit
    direction_kind: str
    particles: int
    repeats: int
    seed: int
    choices: str
    objective_fixed_seed: np.ndarray  # (nΔ,) particle objective with one fixed key
    objective_mm: np.ndarray  # (nΔ,) moment-matching objective
    directional_mm: np.ndarray  # (nΔ,) its exact derivative along d
    samples: dict[str, list[Samples]]  # estimator → per Δ
    seconds: float


@dataclasses.dataclass
class VarianceResult:
    source: str
    trial: int
    deltas: np.ndarray  # (nΔ,)
    particles: np.ndarray  # (nP,)
    direction: np.ndarray
    direction_kind: str
    repeats: int
    seed: int
    choices: str
    samples: dict[str, list[list[Samples]]]  # estimator → [Δ][P]
    seconds: float


def _direction(snap: Snapshot, kind: str, seed: int) -> np.ndarray:
    from pipps.studies.snapshot import pilco_direction

    if kind == "pilco":
        return np.asarray(pilco_direction(snap))
    if kind == "random":
        v = np.random.default_rng(seed).normal(size=snap.theta.shape[0])
        return v / np.linalg.norm(v)
    raise ValueError(f"direction must be 'pilco' or 'random', got {kind!r}")


def landscape(
    snap: Snapshot,
    *,
    deltas=np.linspace(0.0, 1.5, 16),
    particles: int = 1000,
    repeats: int = 10,
    estimators=DEFAULT_ESTIMATORS,
    direction: str = "pilco",
    seed: int = 0,
    choices: str = "library",
    progress: Callable[[str], None] | None = None,
) -> LandscapeResult:
    """The objective and each estimator's directional derivative along ``θ + Δ·d`` (module doc)."""
    names = _check_estimators(estimators)
    _check_positive("particles", particles, 2)
    _check_positive("repeats", repeats, 2)
    deltas = np.asarray(deltas, float)
    if deltas.ndim != 1 or deltas.size == 0 or not np.all(np.isfinite(deltas)):
        raise ValueError(f"deltas must be a non-empty 1-d array of finite numbers, got {deltas!r}")
    progress = progress or (lambda msg: None)
    start = time.perf_counter()
    d = _direction(snap, direction, seed)
    theta = np.asarray(snap.theta)
    task, model = snap.task, snap.model
    rcfg = RolloutConfig(num_particles=particles, horizon=snap.config.horizon)
    noise = sample_noise(jax.random.PRNGKey(seed), task, rcfg)
    fixed = jax.jit(lambda th: reparameterized_objective(task, snap.unravel(th), model, noise, rcfg))
    mm = snap.mm_value_and_grad()
    points = [jnp.asarray(theta + delta * d) for delta in deltas]
    obj_fixed = np.array([float(fixed(p)) for p in points])
    mm_vals = [mm(p) for p in points]
    obj_mm = np.array([float(v) for v, _ in mm_vals])
    dir_mm = np.array([float(np.asarray(g) @ d) for _, g in mm_vals])
    samples: dict[str, list[Samples]] = {}
    for ei, name in enumerate(names):
        program = estimator_program(snap, name, particles, choices)
        samples[name] = []
        for di, p in enumerate(points):
            key = jax.random.fold_in(jax.random.PRNGKey(seed + 1), 1000 * ei + di)
            samples[name].append(_samples(program, key, p, d, repeats))
            progress(f"{label(name)} Δ={deltas[di]:.3g} ({di + 1}/{len(points)})")
    return LandscapeResult(snap.source, snap.trial, deltas, d, direction, particles, repeats, seed, choices,
                           obj_fixed, obj_mm, dir_mm, samples, time.perf_counter() - start)


def variance_study(
    snap: Snapshot,
    *,
    deltas=(0.0, 1.5),
    particles=(10, 30, 100, 300, 1000),
    repeats: int = 30,
    estimators=("rp", "lr_plain", "lr", "tp"),
    direction: str = "pilco",
    seed: int = 0,
    choices: str = "library",
    progress: Callable[[str], None] | None = None,
) -> VarianceResult:
    """The variance of each estimator (trace and along d) against P at each Δ (module doc)."""
    names = _check_estimators(estimators)
    _check_positive("repeats", repeats, 2)
    particles = np.asarray(particles, int)
    if particles.ndim != 1 or particles.size == 0 or np.any(particles < 2):
        raise ValueError(f"particles must be a non-empty list of integers >= 2, got {particles.tolist()}")
    deltas = np.asarray(deltas, float)
    progress = progress or (lambda msg: None)
    start = time.perf_counter()
    d = _direction(snap, direction, seed)
    theta = np.asarray(snap.theta)
    samples: dict[str, list[list[Samples]]] = {n: [[None] * len(particles) for _ in deltas] for n in names}
    for ei, name in enumerate(names):
        for pi, P in enumerate(particles):
            program = estimator_program(snap, name, int(P), choices)
            for di, delta in enumerate(deltas):
                key = jax.random.fold_in(jax.random.PRNGKey(seed + 2), 10_000 * ei + 100 * pi + di)
                samples[name][di][pi] = _samples(program, key, jnp.asarray(theta + delta * d), d, repeats)
                progress(f"{label(name)} P={P} Δ={delta:.3g}")
    return VarianceResult(snap.source, snap.trial, deltas, particles, d, direction, repeats, seed, choices,
                          samples, time.perf_counter() - start)


# -- output ---------------------------------------------------------------------------------------


def _write_samples(g, s: Samples) -> None:
    g.create_dataset("directional", data=s.directional)
    g.create_dataset("k_lr", data=s.k_lr)
    g.attrs["trace_variance"] = s.trace_variance
    g.attrs["nonfinite_repeats"] = s.nonfinite


def _common_attrs(f, r, kind: str) -> None:
    from pipps.experiments.results import versions

    f.attrs.update(study=kind, source=r.source, trial=r.trial, direction_kind=r.direction_kind, repeats=r.repeats,
                   seed=r.seed, estimator_choices=r.choices, seconds=r.seconds, schema_version=1)
    f.attrs["estimators"] = ",".join(r.samples)  # their order (HDF5 lists groups by name)
    for k, v in versions().items():
        f.attrs[f"version_{k}"] = v
    f.create_dataset("direction", data=r.direction)


def write_study(path: str | Path, r: LandscapeResult | VarianceResult) -> Path:
    """Write a study's numbers to HDF5 atomically (tmp file + rename); schema in docs/gradients.md."""
    import os

    import h5py

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with h5py.File(tmp, "w") as f:
        if isinstance(r, LandscapeResult):
            _common_attrs(f, r, "landscape")
            f.attrs["particles"] = r.particles
            for name in ("deltas", "objective_fixed_seed", "objective_mm", "directional_mm"):
                f.create_dataset(name, data=getattr(r, name))
            for est, per in r.samples.items():
                for i, s in enumerate(per):
                    _write_samples(f.create_group(f"estimators/{est}/delta_{i:03d}"), s)
        else:
            _common_attrs(f, r, "variance")
            f.create_dataset("deltas", data=r.deltas)
            f.create_dataset("particles", data=r.particles)
            for est, grid in r.samples.items():
                for i, row in enumerate(grid):
                    for j, s in enumerate(row):
                        _write_samples(f.create_group(f"estimators/{est}/delta_{i:03d}/P_{int(r.particles[j])}"), s)
    with open(tmp, "rb+") as fh:
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    return path


def _read_samples(g) -> Samples:
    return Samples(g["directional"][()], float(g.attrs["trace_variance"]), g["k_lr"][()], int(g.attrs["nonfinite_repeats"]))


def read_study(path: str | Path) -> LandscapeResult | VarianceResult:
    """Load a study written by :func:`write_study` (to re-print its table or re-record it)."""
    import h5py

    with h5py.File(path, "r") as f:
        a = f.attrs
        common = dict(source=str(a["source"]), trial=int(a["trial"]), direction=f["direction"][()],
                      direction_kind=str(a["direction_kind"]), repeats=int(a["repeats"]), seed=int(a["seed"]),
                      choices=str(a["estimator_choices"]), seconds=float(a["seconds"]), deltas=f["deltas"][()])
        ests = f["estimators"]
        order = str(a["estimators"]).split(",") if "estimators" in a else sorted(ests)
        ests = {n: ests[n] for n in order}
        if a["study"] == "landscape":
            samples = {n: [_read_samples(ests[n][k]) for k in sorted(ests[n])] for n in ests}
            return LandscapeResult(particles=int(a["particles"]), objective_fixed_seed=f["objective_fixed_seed"][()],
                                   objective_mm=f["objective_mm"][()], directional_mm=f["directional_mm"][()],
                                   samples=samples, **common)
        particles = f["particles"][()]
        samples = {n: [[_read_samples(ests[n][dk][f"P_{int(P)}"]) for P in particles] for dk in sorted(ests[n])]
                   for n in ests}
        return VarianceResult(particles=particles, samples=samples, **common)


def landscape_table(r: LandscapeResult) -> str:
    """Markdown: per Δ the objectives and each estimator's ĝ·d mean ± 95 % half-width, and Var[ĝ·d]."""
    names = list(r.samples)
    head = "| Δ | J (fixed seed) | J_MM | ∇J_MM·d | " + " | ".join(f"{label(n)} ĝ·d" for n in names) + " | " \
        + " | ".join(f"Var {label(n)}" for n in names) + " |"
    lines = [f"Landscape: {r.source} trial {r.trial}, P = {r.particles}, {r.repeats} repeats, direction {r.direction_kind}",
             "", head, "|" + "---|" * (4 + 2 * len(names))]
    for i, delta in enumerate(r.deltas):
        cells = []
        for n in names:
            m, h = interval(r.samples[n][i].directional)
            cells.append(f"{m:.3g} ± {h:.2g}")
        var = [f"{np.var(r.samples[n][i].directional, ddof=1):.3g}" for n in names]
        lines.append(f"| {delta:.3g} | {r.objective_fixed_seed[i]:.4g} | {r.objective_mm[i]:.4g} | {r.directional_mm[i]:.3g} | "
                     + " | ".join(cells) + " | " + " | ".join(var) + " |")
    # the thesis' number (Fig. 4.2) is about RP itself, the one estimator named here, not a kind of estimator
    if "rp" in r.samples and len(r.deltas) > 1:
        v0 = np.var(r.samples["rp"][0].directional, ddof=1)
        v1 = np.var(r.samples["rp"][-1].directional, ddof=1)
        lines += ["", f"RP: Var[ĝ·d] at Δ = {r.deltas[-1]:.3g} is {v1 / v0:.3g}× that at Δ = {r.deltas[0]:.3g} "
                      f"(thesis: ~4·10⁵× at 1.5 against 0)."]
    return "\n".join(lines)


def variance_table(r: VarianceResult) -> str:
    """Markdown: per Δ and P, Var[ĝ·d] and the trace of the covariance for each estimator."""
    names = list(r.samples)
    lines = [f"Variance: {r.source} trial {r.trial}, {r.repeats} repeats, direction {r.direction_kind}"]
    for di, delta in enumerate(r.deltas):
        lines += ["", f"Δ = {delta:.3g}", "",
                  "| P | " + " | ".join(f"{label(n)} Var[ĝ·d] | {label(n)} tr Cov" for n in names) + " |",
                  "|" + "---|" * (1 + 2 * len(names))]
        for pi, P in enumerate(r.particles):
            cells = []
            for n in names:
                s = r.samples[n][di][pi]
                cells += [f"{np.var(s.directional, ddof=1):.3g}", f"{s.trace_variance:.3g}"]
            lines.append(f"| {int(P)} | " + " | ".join(cells) + " |")
    # the thesis' comparison (Fig. 4.13) is of these two named estimators, TP and BIW-LR, so the line
    # names them rather than asking the registry which estimators weigh two parts
    if "tp" in r.samples and "lr" in r.samples:
        lines += ["", "TP against BIW-LR, trace of the covariance (thesis: TP 10–50 % below BIW-LR at P ≤ 250, chaotic case):"]
        for di, delta in enumerate(r.deltas):
            ratios = [r.samples["tp"][di][pi].trace_variance / r.samples["lr"][di][pi].trace_variance
                      for pi in range(len(r.particles))]
            lines.append(f"- Δ = {delta:.3g}: TP/BIW-LR = " + ", ".join(f"{x:.3g} (P={int(P)})" for x, P in zip(ratios, r.particles)))
    return "\n".join(lines)
