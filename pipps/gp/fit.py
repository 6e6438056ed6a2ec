"""Host-level GP training entry point: the first step of each learned trial (docs/gp.md).

:func:`fit` validates the data on the host, runs one jitted program (hyperparameters, then
FITC inducing inputs when N > threshold, then the posterior), and reports every numerical
guard that acted, both in the returned :class:`FitInfo` and as a :class:`GPNumericsWarning`.
The first-time initialisation and the first inducing subset are computed before that program,
so the first and every later training with the same capacity run the same compiled program.
"""

from __future__ import annotations

import functools
import warnings
from typing import NamedTuple, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from pipps.gp.data import check_hyper, make_data, num_real
from pipps.gp.fitc import fitc_posterior, initial_inducing
from pipps.gp.linalg import map_outputs, stack_trees
from pipps.gp.posterior import full_posterior
from pipps.gp.train import fit_hyper, fit_inducing, initial_hyper
from pipps.gp.types import FitcFitInfo, FitState, GPConfig, GPData, GPHyper, GPPosterior, HyperFitInfo
from pipps.precision import require_float64


class GPNumericsWarning(RuntimeWarning):
    """A numerical guard (noise floor, std floor, jitter) changed what the model computes, or the
    training inputs repeat exactly (a singular Gram matrix, see :func:`duplicate_inputs`)."""


class FitInfo(NamedTuple):
    """Everything :func:`fit` measured; arrays are on the host (numpy)."""

    hyper: HyperFitInfo
    fitc: Optional[FitcFitInfo]  # None when the full GP is used
    posterior_jitter: np.ndarray  # (E,) jitter on K_y (full) or K_mm (FITC) in the posterior
    sparse: bool
    num_points: int  # real training points
    messages: tuple[str, ...]  # the warnings emitted
    duplicate_inputs: tuple[int, int] = (0, 0)  # real rows repeating an earlier input (of them, with equal targets)


@jax.jit
def _initial(data: GPData, config: GPConfig):
    return initial_hyper(data, config)


@functools.partial(jax.jit, static_argnames=("num_inducing",))
def _initial_inducing(key, data: GPData, num_inducing: int):
    return initial_inducing(key, data, num_inducing)


@jax.jit
def _train_full(data: GPData, init: GPHyper, config: GPConfig):
    """Hyperparameters, then the full-GP posterior. One program per (capacity, E, Dz, statics)."""
    hyper, hinfo = fit_hyper(data, init, config)
    post, jitter, ok = full_posterior(hyper, data, config)
    return post, hinfo, jitter, ok


@jax.jit
def _train_sparse(data: GPData, init: GPHyper, xu0, fitc_iters, config: GPConfig):
    """Hyperparameters, then X_u, then the FITC posterior; first and later trainings share it."""
    hyper, hinfo = fit_hyper(data, init, config)
    xu, finfo = fit_inducing(data, hyper, xu0, config, fitc_iters)
    post, jitter, ok = fitc_posterior(hyper, data, xu, config)
    return post, hinfo, finfo, jitter, ok


def _check_prev(prev: Optional[FitState], data: GPData, config: GPConfig) -> None:
    if prev is None:
        return
    if not isinstance(prev, FitState):
        raise ValueError(f"prev must be a FitState or None, got {type(prev).__name__}")
    check_hyper(prev.hyper, data)
    if prev.inducing is not None:
        xu = np.asarray(prev.inducing)
        want = (config.num_inducing, data.inputs.shape[1])
        if xu.shape != want:
            raise ValueError(f"prev.inducing has shape {xu.shape} but config/data need {want}")
        if not np.isfinite(xu).all():
            raise ValueError("prev.inducing contains NaN/Inf")


def duplicate_inputs(data: GPData) -> tuple[int, int]:
    """(real rows whose input repeats an earlier real row's exactly, how many of those repeat its targets too).

    Repeated inputs make K singular, so only σ_n² keeps K + σ_n²I invertible; repeated
    (input, target) pairs are evidence of noise-free observations and pull the learned σ_n down
    (every cart-pole pair twice: σ_n 165–540× smaller, docs/stress.md). Host-side.
    """
    m = np.asarray(data.mask)
    x, y = np.asarray(data.inputs)[m], np.asarray(data.targets)[m]
    n = x.shape[0]
    return n - np.unique(x, axis=0).shape[0], n - np.unique(np.concatenate([x, y], 1), axis=0).shape[0]


def _messages(hinfo, finfo, jitter, ok, config: GPConfig, sparse: bool) -> list[str]:
    msgs = []
    outs = lambda b: np.nonzero(np.asarray(b))[0].tolist()  # noqa: E731
    if outs(hinfo.noise_floored):
        msgs.append(f"noise floor σ_n ≥ {config.noise_floor:g} acted for outputs {outs(hinfo.noise_floored)}")
    if outs(hinfo.input_std_floored):
        msgs.append(f"input std floor {config.input_std_floor:g} acted for (near-)constant input "
                    f"columns {outs(hinfo.input_std_floored)}")
    if outs(hinfo.target_std_floored):
        msgs.append(f"target std below {config.target_std_floor:g} for outputs {outs(hinfo.target_std_floored)}: "
                    "σ_f initialised from the targets' root mean square")
    train_j = np.asarray(hinfo.jitter)
    if (train_j > config.jitter).any():
        msgs.append(f"training jitter raised above {config.jitter:g} to {train_j.tolist()} (per output)")
    base = config.fitc_jitter if sparse else config.jitter
    if finfo is not None and (np.asarray(finfo.jitter) > base).any():
        msgs.append(f"FITC K_mm jitter raised above {base:g} to {np.asarray(finfo.jitter).tolist()} during training")
    if (np.asarray(jitter) > base).any():
        what = "K_mm" if sparse else "K + σ_n²I"
        msgs.append(f"posterior jitter on {what} raised above {base:g} to {np.asarray(jitter).tolist()} (per output)")
    return msgs


def fit(
    key: Optional[jax.Array],
    data: GPData,
    prev: Optional[FitState] = None,
    config: GPConfig = GPConfig(),
) -> tuple[GPPosterior, FitState, FitInfo]:
    """Train the GP dynamics model on all data and build its posterior (docs/gp.md).

    Args:
      key: PRNG key for the first FITC inducing-input subset (only needed when FITC is used
        for the first time; may be None otherwise).
      data: the (padded) training set; validated on the host.
      prev: the previous training's :class:`FitState` to warm-start from, or None for the
        first-time initialisation.
      config: settings (numbers are traced, so changing them does not recompile).

    Returns:
      (posterior, state, info): the posterior (full or FITC, same fields), the state to
      warm-start the next training from, and diagnostics.

    Raises:
      ValueError: bad data or warm-start state (shapes, NaN/Inf, too few points, missing key).
      FloatingPointError: a posterior Cholesky failed even with the largest jitter.
      Float64Required: JAX's 64-bit mode is off (:func:`pipps.enable_float64`).
    """
    require_float64("pipps.gp.fit")
    p = _prepare(key, data, prev, config)
    if p.sparse:
        out = _train_sparse(p.data, p.init, p.xu0, p.iters, config)
    else:
        post, hinfo, jitter, ok = _train_full(p.data, p.init, config)
        out = (post, hinfo, None, jitter, ok)
    return _finish(p, prev, out, config, stacklevel=3)


class _Prepared(NamedTuple):
    """One training's host-side preparation: what the compiled program takes, and what the report needs."""

    data: GPData
    num_points: int
    sparse: bool
    init: GPHyper
    target_floored: np.ndarray
    xu0: Optional[jax.Array]  # FITC start inducing inputs (sparse only)
    iters: int  # FITC line searches (sparse only)


def _prepare(key, data: GPData, prev: Optional[FitState], config: GPConfig) -> _Prepared:
    if not isinstance(data, GPData):
        raise ValueError(f"data must be a GPData, got {type(data).__name__}")
    data = make_data(data.inputs, data.targets, data.mask)
    _check_prev(prev, data, config)
    n = num_real(data)
    sparse = n > config.fitc_threshold
    if prev is None:
        init, target_floored = _initial(data, config)
    else:
        init = GPHyper(*(jnp.asarray(a, jnp.float64) for a in prev.hyper))
        target_floored = np.zeros(data.targets.shape[1], bool)
    xu0, iters = None, 0
    if sparse:
        first = prev is None or prev.inducing is None
        if first and key is None:
            raise ValueError("key is required to draw the first FITC inducing inputs (N > fitc_threshold)")
        xu0 = _initial_inducing(key, data, config.num_inducing) if first else jnp.asarray(prev.inducing, jnp.float64)
        iters = config.fitc_first_iters if first else config.fitc_iters
    return _Prepared(data, n, sparse, init, np.asarray(target_floored), xu0, iters)


def _finish(p: _Prepared, prev: Optional[FitState], out, config: GPConfig, stacklevel: int = 2):
    """The report of one training: guards that acted (FitInfo and warnings), the warm-start state."""
    post, hinfo, finfo, jitter, ok = out
    data, n, sparse = p.data, p.num_points, p.sparse
    if sparse:
        state = FitState(post.hyper, post.inputs)
    else:
        state = FitState(post.hyper, None if prev is None else prev.inducing)
    hinfo = HyperFitInfo(*jax.device_get(tuple(hinfo)))._replace(target_std_floored=p.target_floored)
    finfo = None if finfo is None else FitcFitInfo(*jax.device_get(tuple(finfo)))
    jitter, ok = np.asarray(jitter), np.asarray(ok)
    if not ok.all():
        raise FloatingPointError(f"posterior Cholesky failed for outputs {np.nonzero(~ok)[0].tolist()} "
                                 f"even with jitter {jitter.tolist()}")
    msgs = _messages(hinfo, finfo, jitter, ok, config, sparse)
    dup = duplicate_inputs(data)
    if dup[0]:
        pulled = (f"; repeated pairs read as noise-free and pull σ_n down "
                  f"(σ_n = {np.exp(np.asarray(post.hyper.log_noise)).tolist()})") if dup[1] else ""
        msgs.append(f"{dup[0]} training inputs repeat an earlier input exactly ({dup[1]} with equal targets): "
                    f"K is singular, only σ_n² keeps K + σ_n²I invertible{pulled}")
    for m in msgs:
        warnings.warn(m, GPNumericsWarning, stacklevel=stacklevel)
    return post, state, FitInfo(hinfo, finfo, jitter, sparse, n, tuple(msgs), dup)


@functools.partial(jax.jit, static_argnames="batching")
def _train_full_many(datas: GPData, inits: GPHyper, config: GPConfig, batching: str):
    return map_outputs(lambda a: _train_full(a[0], a[1], config), (datas, inits), batching)


@functools.partial(jax.jit, static_argnames="batching")
def _train_sparse_many(datas: GPData, inits: GPHyper, xu0s, iters, config: GPConfig, batching: str):
    return map_outputs(lambda a: _train_sparse(a[0], a[1], a[2], a[3], config), (datas, inits, xu0s, iters), batching)


def fit_many(
    keys: Sequence[Optional[jax.Array]],
    datas: Sequence[GPData],
    prevs: Sequence[Optional[FitState]],
    config: GPConfig = GPConfig(),
    *,
    batching: str = "auto",
) -> list[tuple[GPPosterior, FitState, FitInfo]]:
    """:func:`fit` for R independent data sets (the seeds of a batched experiment) at once.

    The data sets must share their padded capacity. Those on the same side of ``fitc_threshold``
    train in one compiled program with the data set as a leading batch axis (``batching``: "vmap",
    "map" = ``lax.map``, or "auto" = map on CPU, vmap elsewhere); each result is what :func:`fit`
    returns for that data set, warnings included. "vmap" is refused on CPU: jaxlib 0.10's batched
    LAPACK deadlocks there once XLA runs two threads (seen here with two data sets of 60 points;
    :func:`pipps.gp.linalg.map_outputs`).
    """
    require_float64("pipps.gp.fit_many")
    if batching == "vmap" and jax.default_backend() == "cpu":
        raise ValueError("fit_many: batching='vmap' on CPU can deadlock (jaxlib's batched LAPACK in loops); "
                         "use 'map' or 'auto'")
    if not (len(keys) == len(datas) == len(prevs)) or not datas:
        raise ValueError(f"fit_many needs equally many keys, data sets and states, got "
                         f"{len(keys)}, {len(datas)}, {len(prevs)}")
    preps = [_prepare(k, d, pv, config) for k, d, pv in zip(keys, datas, prevs)]
    shapes = {(p.data.inputs.shape, p.data.targets.shape) for p in preps}
    if len(shapes) > 1:
        raise ValueError(f"fit_many needs data sets of one padded capacity, got shapes {sorted(shapes)}")
    outs: list = [None] * len(preps)
    for sparse in (False, True):
        idx = [i for i, p in enumerate(preps) if p.sparse == sparse]
        if not idx:
            continue
        datas_b, inits_b = stack_trees([preps[i].data for i in idx]), stack_trees([preps[i].init for i in idx])
        if sparse:
            xu0s = stack_trees([preps[i].xu0 for i in idx])
            iters = jnp.asarray([preps[i].iters for i in idx])
            res = _train_sparse_many(datas_b, inits_b, xu0s, iters, config, batching)
        else:
            post, hinfo, jitter, ok = _train_full_many(datas_b, inits_b, config, batching)
            res = (post, hinfo, None, jitter, ok)
        for j, i in enumerate(idx):
            outs[i] = jax.tree_util.tree_map(lambda a: a[j], res)
    return [_finish(p, pv, out, config, stacklevel=3) for p, pv, out in zip(preps, prevs, outs)]
