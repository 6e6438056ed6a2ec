"""What an experiment records: one :class:`TrialResult` per trial of thesis Algorithm 1, made of typed records.

A trial holds its true-system trajectory and evaluation (arrays), its :class:`Timings`, and for a
learned trial the :class:`GPRecord` it planned on, its optimiser's trace (:class:`StepTrace` for the
stochastic-gradient methods, :class:`SearchTrace` for the quasi-Newton ones), the particle methods'
:class:`Diagnostics`, and the stored prediction (:class:`ParticlePrediction` or PILCO's
:class:`MomentPrediction`).

Every field says how it is stored in a result file (:mod:`pipps.experiments.results` walks the
fields; docs/results-schema.md): :func:`attr` is an HDF5 attribute, :func:`array` a dataset, and a
field holding a record is a group of that name. A record's ``extra`` keeps whatever a file holds
beyond the fields (written back unchanged), so a file from another pipps version survives a resume.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

import numpy as np

from pipps.experiments.config import ExperimentConfig


def attr(convert: Callable[[Any], Any], **kw):
    """A scalar stored as an HDF5 attribute, read back through ``convert`` (``bool``, ``int``, ``float``, ``str``)."""
    return dataclasses.field(metadata={"h5": "attr", "convert": convert}, **kw)


def array(*, dtype=None, compress: bool = True, **kw):
    """An array stored as an HDF5 dataset (gzip above 256 elements if ``compress``), read back as numpy."""
    return dataclasses.field(metadata={"h5": "array", "dtype": dtype, "compress": compress}, **kw)


def group(*types: type, **kw):
    """A record stored as an HDF5 group named after the field; read back as the first of ``types``
    whose required fields the group holds."""
    return dataclasses.field(metadata={"h5": "group", "types": types}, **kw)


def extra():
    """Entries a file holds that the record has no field for: kept, and written back as they were read."""
    return dataclasses.field(default_factory=dict, metadata={"h5": "extra"})


@dataclasses.dataclass
class Timings:
    """Seconds per phase of a trial. In a batched run they are the batch's (the same for every seed)
    and ``batched_seeds`` is the batch size."""

    gp: float | None = attr(float, default=None)
    optimize: float | None = attr(float, default=None)
    trial: float | None = attr(float, default=None)
    evaluate: float | None = attr(float, default=None)
    total: float | None = attr(float, default=None)
    batched_seeds: float | None = attr(float, default=None)
    extra: dict[str, Any] = extra()


@dataclasses.dataclass
class GPRecord:
    """The GP a learned trial trained and planned on (E outputs, Dz inputs): its hyperparameters and
    training report; with the data of the trials before it they rebuild the model
    (:func:`pipps.experiments.state.restore`, :func:`pipps.studies.snapshot.load_snapshot`)."""

    log_lengthscale: np.ndarray = array()  # (E, Dz)
    log_signal: np.ndarray = array()  # (E,)
    log_noise: np.ndarray = array()  # (E,)
    sparse: bool = attr(bool)  # FITC
    num_points: int = attr(int)  # real training points
    objective: np.ndarray = array()  # (E,) the training objective per output
    messages: str = attr(str)  # the numerical guards that acted, one per line
    inducing: np.ndarray | None = array(default=None)  # (M, Dz) FITC's inducing inputs (older files lack them)
    capacity: int | None = attr(int, default=None)  # the padded size it trained and planned at (older files lack it)
    variance_ranks: np.ndarray | None = array(default=None)  # (E,) the low-rank variance's ranks (variance_tol > 0)
    variance_bound: np.ndarray | None = array(default=None)  # (E,) and its certified bound
    extra: dict[str, Any] = extra()

    @property
    def rebuildable(self) -> bool:
        """Whether the record with its training data rebuilds the model: a full GP, or FITC with its inducing inputs."""
        return not self.sparse or self.inducing is not None


@dataclasses.dataclass
class StepTrace:
    """The stochastic-gradient optimiser's values per policy step."""

    value: np.ndarray = array()  # the estimator's objective
    particle_objective: np.ndarray = array()  # the plain particle mean of the return
    grad_norm: np.ndarray = array()
    skipped: np.ndarray = array()  # bool: a non-finite step was refused
    extra: dict[str, Any] = extra()


@dataclasses.dataclass
class SearchTrace:
    """A quasi-Newton optimiser's values per line search (PILCO, the fixed-seed ``_FS`` methods)."""

    value: np.ndarray = array()
    evaluations: np.ndarray = array()
    failed: np.ndarray = array()
    stop_reason: np.ndarray = array()  # 0-d (files resumed by older versions stored it as an attribute)
    extra: dict[str, Any] = extra()


@dataclasses.dataclass
class Diagnostics:
    """The particle estimators' per-time-step diagnostics, averaged over a trial's policy steps
    (NaN where a part is off)."""

    k_lr: np.ndarray = array()  # (T,)
    var_rp: np.ndarray = array()  # (T,)
    var_lr: np.ndarray = array()  # (T,)
    k_lr_per_iteration: np.ndarray = array()  # (n,)
    nonfinite_steps: np.ndarray = array()  # (T,)
    extra: dict[str, Any] = extra()


@dataclasses.dataclass
class ParticlePrediction:
    """The first ``store_particles`` predicted trajectories of the optimised policy on the model."""

    particles: np.ndarray = array()  # (T+1, S_p, D)
    cost_mean: np.ndarray = array()  # (T,): steps 1..T, summing to the predicted return
    extra: dict[str, Any] = extra()


@dataclasses.dataclass
class MomentPrediction:
    """PILCO's moment-matched prediction of the optimised policy."""

    mean: np.ndarray = array()  # (T+1, D)
    cov: np.ndarray = array()  # (T+1, D, D)
    cost_mean: np.ndarray = array()  # (T+1,): steps 0..T; the predicted return is cost_mean[1:].sum()
    extra: dict[str, Any] = extra()


@dataclasses.dataclass
class TrialResult:
    """One trial: what was run on the true system, how the policy was found, how it evaluates.

    Array shapes: H steps, S simulator dims, F controls, R evaluation rollouts, n policy steps,
    T planning horizon, D model dims. Stored as the group ``/trials/NNN`` (NNN = ``index``).
    """

    index: int
    kind: str = attr(str)  # "random" or "learned"
    states: np.ndarray = array(compress=False)  # (H+1, S) the trial's true states
    observations: np.ndarray = array(compress=False)  # (H+1, S) what the learner saw
    actions: np.ndarray = array(compress=False)  # (H, F)
    costs: np.ndarray = array(compress=False)  # (H,) true cost of each transition (0 after a fall)
    valid: np.ndarray = array(compress=False)  # (H,) bool
    eval_returns: np.ndarray = array(compress=False)  # (R,) evaluation returns (fallen steps charged cost 1)
    eval_upright: np.ndarray = array(compress=False)  # (R,) bool: the rollout never fell (cart-pole: always)
    policy: np.ndarray = array(compress=False)  # (n_θ,) flattened policy the trial ran (random: the initial one)
    timings: Timings = group(Timings)
    gp: GPRecord | None = group(GPRecord, default=None)  # learned trials
    opt_trace: StepTrace | SearchTrace | None = group(StepTrace, SearchTrace, default=None)
    diagnostics: Diagnostics | None = group(Diagnostics, default=None)  # stochastic-gradient particle methods
    predicted: ParticlePrediction | MomentPrediction | None = group(ParticlePrediction, MomentPrediction, default=None)
    # (R,) bool: the task's success rule per evaluation rollout (pipps.tasks.Success; cart-pole: balanced
    # at the end, unicycle: upright); None in files written before it was stored
    eval_balanced: np.ndarray | None = array(dtype=bool, compress=False, default=None)

    @property
    def eval_return(self) -> float:
        return float(np.mean(self.eval_returns))

    @property
    def upright_fraction(self) -> float:
        return float(np.mean(self.eval_upright))

    @property
    def balanced_fraction(self) -> float:
        """Fraction of evaluation rollouts meeting the physical criterion (NaN where not stored)."""
        return float(np.mean(self.eval_balanced)) if self.eval_balanced is not None else math.nan


def required_fields(cls: type) -> set[str]:
    """The stored fields of a record class without a default: what a group must hold to be one."""
    missing = dataclasses.MISSING
    return {f.name for f in dataclasses.fields(cls)
            if f.metadata.get("h5") in ("attr", "array", "group") and f.default is missing
            and f.default_factory is missing}


@dataclasses.dataclass
class ExperimentResult:
    config: ExperimentConfig
    trials: list[TrialResult]
    status: str = "running"  # running | complete | failed | interrupted (Ctrl-C: resumable as it stands)
    error: str = ""
    wall_seconds: float = 0.0  # summed over the sessions that ran it (see resumed_at)
    resumed_at: list[int] = dataclasses.field(default_factory=list)  # trial indices a resumed session began at

    @property
    def final_return(self) -> float:
        return self.trials[-1].eval_return if self.trials else math.nan

    @property
    def success(self) -> bool:
        """The task's verdict on the final trial (:func:`pipps.reporting.verdicts.judge_trial`) of a complete run."""
        from pipps.reporting.verdicts import judge_trial

        return self.status == "complete" and judge_trial(self.config, self.trials[-1])
