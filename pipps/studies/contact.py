"""First-, zeroth- and α-order gradients on contact: the measurements behind docs/contact.md.

Each study runs Suh et al.'s estimators — FoBG (``rp``), ZoBG (``zobg``), AoBG (``aobg``) — and the
thesis' total propagation with its inverse-variance weight from the batch (``tp_plain`` over the same
ZoBG part: ``TP`` below) on the systems of :mod:`pipps.systems.contact`, through the library's own
estimator pieces (:func:`pipps.propagation.estimate` with noise on the actions), and returns plain
arrays: a :class:`StudyResult` of named tables, written to JSON (:func:`write_study`).

**Replicates.** :func:`replicate_estimates` draws ``R`` independent batches of ``N`` samples per
estimator on common random numbers (every estimator sees the same noise in a replicate) and keeps,
per replicate, the batch's gradient (the estimate), its *empirical* variance — the across-sample
variance within the batch, ``P·V[g]``, what an estimator sees of itself and what TP's weight reads —
and the per-step weight on the LR part. The *expected* per-sample variance is ``N`` times the
variance of the R estimates. Bias is the mean of the R estimates less the exact gradient, with its
standard error; where no closed form exists the reference is ZoBG's mean over many more samples
(unbiased), whose standard error is reported beside it.
"""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from pipps.particles.forward import RolloutConfig
from pipps.propagation.estimate import estimate, estimate_on, init_estimator_state, rollout_for
from pipps.propagation.estimators import estimator

#: Suh et al.'s names for the estimators compared here, and the library's composition of each
SUH_NAMES = {"FoBG": "rp", "ZoBG": "zobg", "TP": "tp", "AoBG": "aobg"}


def estimators(gamma: float, z: float = 2.0) -> dict:
    """FoBG, ZoBG, TP (inverse-variance weight from the batch, over the ZoBG part) and AoBG with bound ``γ``."""
    zobg = dict(weighting="plain", baseline="zero_noise", returns="total")
    return {
        "FoBG": estimator("rp"),
        "ZoBG": estimator("zobg"),
        "TP": estimator("tp", **zobg, k_lr="batch"),
        "AoBG": estimator("aobg", robust_gamma=float(gamma), robust_z=float(z)),
    }


class Samples(NamedTuple):
    """R replicate estimates of one estimator."""

    grad: np.ndarray  # (R, n) the batch estimates
    empirical: np.ndarray  # (R, n) per-coordinate across-sample variance within each batch
    k_lr: np.ndarray  # (R, T) the weight on the LR part at each step
    value: np.ndarray  # (R,) the batch's objective


def replicate_estimates(example, ests: dict, num_samples: int, replicates: int, key, *, policy=None,
                        simulator=None, batch: int = 64) -> dict[str, Samples]:
    """``replicates`` independent batches of ``num_samples`` per estimator, common random numbers (module doc).

    Every estimator is swept on the same record in a replicate (:func:`pipps.propagation.rollout_for`).
    The compiled program is kept per (problem, estimators, sizes): a new policy or simulator of the
    same shapes (another θ, another stiffness) does not recompile."""
    policy = example.policy if policy is None else policy
    sim = example.simulator if simulator is None else simulator
    fn = _replicate_program(example.problem, tuple(ests.items()), int(num_samples), float(example.action_noise),
                            min(batch, replicates))
    res = fn(jax.random.split(key, replicates), policy, sim)
    return {n: Samples(*(np.asarray(a) for a in v)) for n, v in res.items()}


_PROGRAMS: dict = {}


def _replicate_program(problem, ests: tuple, P: int, sigma: float, batch: int):
    """The jitted replicate map for one problem, estimator set and batch size (cached; the problem by identity)."""
    cache_key = (id(problem), ests, P, sigma, batch)
    if cache_key in _PROGRAMS:
        return _PROGRAMS[cache_key][1]
    cfg = RolloutConfig(num_particles=P, action_noise=sigma)
    named = dict(ests)

    def run(keys, policy, sim):
        def one(k):
            ks, ke = jax.random.split(k)
            record = rollout_for(ke, policy, sim, problem=problem, config=cfg, estimators=tuple(named.values()))
            out = {}
            for name, est in named.items():
                state = init_estimator_state(ks, policy, sim, problem=problem, config=cfg, estimator=est)
                _, e = estimate_on(record, state, policy, problem=problem, config=cfg, estimator=est)
                out[name] = (ravel_pytree(e.grad)[0], ravel_pytree(e.grad_variance)[0] * P, e.diagnostics.k_lr, e.value)
            return out

        return jax.lax.map(one, keys, batch_size=batch)

    fn = jax.jit(run)
    _PROGRAMS[cache_key] = (problem, fn)  # the problem is held so that its id is not reused
    return fn


def summarise(s: Samples, exact: np.ndarray | None, num_samples: int) -> dict:
    """Mean, bias (with its standard error and max |z|), expected and empirical per-sample variance
    (traces), MSE of one estimate, the fraction of estimates exactly zero, the mean weight on LR."""
    R = s.grad.shape[0]
    mean = s.grad.mean(0)
    se = s.grad.std(0, ddof=1) / math.sqrt(R)
    out = dict(mean=mean.tolist(), se=se.tolist(),
               expected_variance=float(num_samples * np.sum(np.var(s.grad, axis=0, ddof=1))),
               empirical_variance=float(np.mean(np.sum(s.empirical, axis=1))),
               zero_fraction=float(np.mean(np.all(s.grad == 0.0, axis=1))),
               k_lr=float(np.mean(s.k_lr)))
    if exact is not None:
        err = s.grad - exact[None, :]
        bias = mean - exact
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(se > 0, np.abs(bias) / se, np.where(bias == 0, 0.0, np.inf))
        out.update(bias=bias.tolist(), bias_norm=float(np.linalg.norm(bias)), max_z=float(np.max(z)),
                   mse=float(np.mean(np.sum(err**2, axis=1))))
    return out


def reference_gradient(example, num_samples: int, replicates: int, key, *, policy=None, simulator=None):
    """ZoBG's mean over ``replicates × num_samples`` samples and its standard error: the unbiased
    reference where no closed form exists."""
    s = replicate_estimates(example, {"ZoBG": estimator("zobg")}, num_samples, replicates, key, policy=policy,
                            simulator=simulator)["ZoBG"]
    return s.grad.mean(0), s.grad.std(0, ddof=1) / math.sqrt(replicates)


def descend(example, est, *, iterations: int, num_samples: int, step: float, key, clip: float | None = None,
            evaluate=None, points: int = 11) -> np.ndarray:
    """Gradient descent ``θ ← θ − step · ĝ`` (ĝ's norm clipped at ``clip``; a non-finite ĝ is skipped)
    with a fresh batch per iteration; returns ``(iteration, evaluate(θ))`` rows at ``points`` evenly
    spaced iterations, the start and the end included (``evaluate`` defaults to the exact ``F``)."""
    update = _update_program(example.problem, est, int(num_samples), float(example.action_noise), float(step), clip)
    evaluate = evaluate or (lambda pol: example.exact(pol)[0])
    at = set(np.unique(np.linspace(0, iterations, points).round().astype(int)).tolist())
    policy, rows = example.policy, [(0, evaluate(example.policy))]
    for i in range(iterations):
        policy = update(jax.random.fold_in(key, i), policy, example.simulator)
        if i + 1 in at:
            rows.append((i + 1, evaluate(policy)))
    return np.asarray(rows, dtype=float)


def _update_program(problem, est, P: int, sigma: float, step: float, clip):
    cache_key = ("update", id(problem), est, P, sigma, step, clip)
    if cache_key in _PROGRAMS:
        return _PROGRAMS[cache_key][1]
    cfg = RolloutConfig(num_particles=P, action_noise=sigma)

    @jax.jit
    def update(k, policy, sim):
        ks, ke = jax.random.split(k)
        state = init_estimator_state(ks, policy, sim, problem=problem, config=cfg, estimator=est)
        _, e = estimate(ke, state, policy, sim, problem=problem, config=cfg, estimator=est)
        g, unravel = ravel_pytree(e.grad)
        g = jnp.where(jnp.all(jnp.isfinite(g)), g, 0.0)
        if clip is not None:
            g = g * jnp.minimum(1.0, clip / jnp.maximum(jnp.linalg.norm(g), 1e-300))
        return jax.tree.map(lambda p, d: p - step * d, policy, unravel(g))

    _PROGRAMS[cache_key] = (problem, update)
    return update


def batch_objective(example, num_samples: int, key, replicates: int = 1):
    """An evaluator ``policy -> mean objective`` over ``replicates × num_samples`` fresh rollouts with a
    fixed key (common random numbers across the policies it is asked about)."""
    from pipps.particles.forward import particle_rollout, sample_noise

    cfg = RolloutConfig(num_particles=int(num_samples), action_noise=example.action_noise)
    keys = jax.random.split(key, replicates)

    @jax.jit
    def value(policy):
        def one(k):
            rec = particle_rollout(example.problem, policy, example.simulator, sample_noise(k, example.problem, cfg), cfg,
                                   jacobian=False)
            return rec.objective
        return jnp.mean(jax.lax.map(one, keys))

    return lambda policy: float(value(policy))


@dataclasses.dataclass
class StudyResult:
    """A study's output: its name, settings and named tables (plain lists), and the versions that made it."""

    study: str
    settings: dict
    tables: dict = dataclasses.field(default_factory=dict)
    versions: dict = dataclasses.field(default_factory=dict)


def write_study(path, result: StudyResult) -> None:
    """Write ``result`` as JSON (a new file; the caller's :func:`pipps.experiments.storage.publish` names it)."""
    from pathlib import Path

    Path(path).write_text(json.dumps(dataclasses.asdict(result), indent=1, default=_plain) + "\n", encoding="utf-8")


def read_study(path) -> StudyResult:
    from pathlib import Path

    data = json.loads(Path(path).read_text(encoding="utf-8"))
    if not isinstance(data, dict) or data.get("kind") != "pipps-contact-study" and "study" not in data:
        raise ValueError(f"{path}: not a pipps contact study file")
    return StudyResult(data["study"], data.get("settings", {}), data.get("tables", {}), data.get("versions", {}))


def _plain(o: Any):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    raise TypeError(f"cannot store {type(o).__name__}")
