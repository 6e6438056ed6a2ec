"""A policy snapshot taken during a real training run, with the model it was optimised on.

A result file stores, per trial, the true trajectories, the trained GP hyperparameters and the
policy the trial ran. :func:`load_snapshot` rebuilds, for a learned trial ``k``, exactly what
that trial's policy optimisation saw at its start: the GP posterior from the data of trials
``0..k−1`` with trial ``k``'s hyperparameters (padded like the loop pads), and the policy it
started from (the one trial ``k − 1`` ran). FITC trials are rebuilt from their stored inducing
inputs; result files written before those were stored cannot rebuild them, and
:func:`load_snapshot` says so.
"""

from __future__ import annotations

import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from pipps.experiments.config import ExperimentConfig
from pipps.gp import GPHyper, GPPosterior, full_posterior
from pipps.gp.fitc import fitc_posterior
from pipps.tasks.base import Problem


@dataclasses.dataclass
class Snapshot:
    """Everything a gradient study needs about one trial of one experiment."""

    source: str  # the result file
    trial: int  # the learned trial whose optimisation start this is
    config: ExperimentConfig
    task: Problem  # the experiment's planning problem (the studies never simulate)
    policy: object  # policy pytree at the start of the trial's optimisation
    model: GPPosterior  # the trial's model
    num_points: int  # real GP training points
    data: object = None  # the padded GPData the model was built from
    jitter: object = None  # (E,) what the posterior's Cholesky added (to K_y, or to K_mm for FITC)
    sparse: bool = False  # the model is FITC
    programs: dict = dataclasses.field(default_factory=dict, repr=False)  # compiled study programs, reused

    def program(self, key, build):
        """The compiled program ``key``, built by ``build()`` on first use (studies reuse them)."""
        if key not in self.programs:
            self.programs[key] = build()
        return self.programs[key]

    @property
    def theta(self) -> jax.Array:
        return ravel_pytree(self.policy)[0]

    def unravel(self, flat: jax.Array):
        return ravel_pytree(self.policy)[1](flat)

    def mm_value_and_grad(self):
        """The jitted ``θ (flat) → (J_MM, ∇J_MM)`` of PILCO's moment matching on this model, compiled once."""
        from pipps.pilco.propagate import objective

        return self.program("mm", lambda: jax.jit(jax.value_and_grad(
            lambda th: objective(self.task, self.unravel(th), self.model))))


def load_snapshot(path: str | os.PathLike, trial: int, *, gp_chunk: int | None = None) -> Snapshot:
    """The policy and model at the start of learned trial ``trial``'s optimisation (module doc): the
    loop's state at that trial (:func:`pipps.experiments.state.restore`) with the trial's own GP.
    ``gp_chunk``: pad the data to multiples of this instead of the file's setting (1: no padding).

    Raises:
      ValueError: ``trial`` is not a learned trial of the file, or its FITC model cannot be rebuilt.
    """
    from pipps.experiments.results import read_result
    from pipps.experiments.state import gp_config, make_experiment_task, rebuildable_trials, restore

    result = read_result(path)
    cfg = result.config
    learned = [t.index for t in result.trials if t.kind == "learned"]
    if trial not in learned:
        raise ValueError(f"trial {trial} is not a learned trial of {path} (learned trials: {learned})")
    gp = result.trials[trial].gp
    if trial not in rebuildable_trials(result):
        raise ValueError(f"trial {trial} of {path} used a FITC model whose inducing inputs this (older) file does "
                         f"not store; pick a trial with at most fitc_threshold={cfg.fitc_threshold} points")
    task = make_experiment_task(cfg)
    state = restore(result, trial, task=task)
    data = state.data(chunk=cfg.gp_chunk if gp_chunk is None else gp_chunk)
    hyper = GPHyper(*(jnp.asarray(getattr(gp, n)) for n in GPHyper._fields))
    if gp.sparse:
        model, jitter, ok = fitc_posterior(hyper, data, jnp.asarray(gp.inducing), gp_config(cfg))
    else:
        model, jitter, ok = full_posterior(hyper, data, gp_config(cfg))
    if not bool(np.all(np.asarray(ok))):
        raise FloatingPointError(f"the posterior Cholesky of trial {trial} failed on rebuilding")
    return Snapshot(str(path), trial, cfg, task.problem, state.policy, model, state.num_points, data,
                    np.asarray(jitter), gp.sparse)


def pilco_direction(snap: Snapshot) -> jax.Array:
    """The unit descent direction of PILCO's moment-matching objective at the snapshot, ``−∇J/‖∇J‖``
    (flat, like :attr:`Snapshot.theta`): the thesis' choice of direction for the landscape."""
    _, g = snap.mm_value_and_grad()(snap.theta)
    norm = jnp.linalg.norm(g)
    if not bool(jnp.isfinite(norm)) or float(norm) == 0.0:
        raise FloatingPointError(f"the moment-matching gradient at the snapshot is {float(norm)}; pick another direction")
    return -g / norm
