"""Training sets: host-side validation, padding to a capacity, masked statistics (docs/gp.md).

Growing data sets are padded with ``mask=False`` rows to a capacity (a multiple of a chunk
size), so jitted training and prediction compile once per capacity, not once per episode.
Validation (NaN/Inf, shapes, lengths) runs on the host, outside jit, and raises
``ValueError`` naming the problem.
"""

from __future__ import annotations

import math
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np

from pipps.gp.types import GPData, GPHyper
from pipps.precision import require_float64


def _as_host(name: str, a) -> np.ndarray:
    if isinstance(a, jax.core.Tracer):
        raise ValueError(f"{name} is a traced value; GP data must be validated on the host, outside jit")
    return np.asarray(a)


def make_data(inputs, targets, mask=None) -> GPData:
    """Validate training pairs on the host and return them as a float64 :class:`GPData`.

    Args:
      inputs: (N, Dz) GP inputs.
      targets: (N, E) or (N,) GP targets (a 1-D array means E = 1).
      mask: optional (N,) bool; default all True. Masked-out rows may hold anything finite.

    Raises:
      ValueError: wrong rank, mismatched lengths, NaN/Inf anywhere, fewer than 2 real rows.
      Float64Required: JAX's 64-bit mode is off (:func:`pipps.enable_float64`).
    """
    require_float64("pipps.gp.make_data")
    x = _as_host("inputs", inputs)
    y = _as_host("targets", targets)
    if x.ndim != 2:
        raise ValueError(f"inputs must be 2-D (N, Dz), got shape {x.shape}")
    if y.ndim == 1:
        y = y[:, None]
    if y.ndim != 2:
        raise ValueError(f"targets must be 2-D (N, E) or 1-D (N,), got shape {y.shape}")
    if x.shape[0] != y.shape[0]:
        raise ValueError(f"inputs and targets have different lengths: {x.shape[0]} inputs vs {y.shape[0]} targets")
    if x.shape[1] < 1 or y.shape[1] < 1:
        raise ValueError(f"inputs and targets need ≥ 1 column, got shapes {x.shape} and {y.shape}")
    if mask is None:
        m = np.ones(x.shape[0], dtype=bool)
    else:
        m = _as_host("mask", mask)
        if m.shape != (x.shape[0],):
            raise ValueError(f"mask must have shape ({x.shape[0]},) to match inputs, got {m.shape}")
        if m.dtype != np.bool_:
            raise ValueError(f"mask must be boolean, got dtype {m.dtype}")
    for name, a in (("inputs", x), ("targets", y)):
        if not np.issubdtype(a.dtype, np.number) or np.iscomplexobj(a):
            raise ValueError(f"{name} must be real numbers, got dtype {a.dtype}")
        bad = ~np.isfinite(a.astype(np.float64))
        if bad.any():
            rows = np.unique(np.nonzero(bad)[0])
            kind = "NaN" if np.isnan(a[bad]).any() else "Inf"
            raise ValueError(f"{name} contain {kind} (non-finite values) in rows {rows[:10].tolist()}"
                             + (" ..." if rows.size > 10 else ""))
    if int(m.sum()) < 2:
        raise ValueError(f"need at least 2 real (unmasked) training points, got {int(m.sum())}")
    # Training squares differences and sums over the rows (the SE kernel's ((x − x')/ℓ)², the
    # standard deviations that initialise ℓ and σ_f, yᵀβ): with N rows that stays finite in float64
    # while every |value| < sqrt(max / (4N)) (the 4: a difference can double a value). Beyond it the
    # fit would return infinite length-scales or NaN without a word, so the data are refused.
    limit = math.sqrt(np.finfo(np.float64).max / (4.0 * x.shape[0]))
    for name, a in (("inputs", x), ("targets", y)):
        big = np.abs(a.astype(np.float64)[m]).max(initial=0.0)
        if big >= limit:
            raise ValueError(f"{name} reach |value| = {big:.3g}: with {x.shape[0]} rows, squared differences and "
                             f"sums overflow float64 beyond {limit:.3g}; rescale the {name}")
    return GPData(jnp.asarray(x, jnp.float64), jnp.asarray(y, jnp.float64), jnp.asarray(m))


def capacity_for(n: int, chunk: int = 100) -> int:
    """The capacity a set of n rows is padded to: the next multiple of ``chunk`` (≥ n, ≥ chunk)."""
    if chunk < 1:
        raise ValueError(f"chunk must be ≥ 1, got {chunk}")
    return max(chunk, chunk * math.ceil(n / chunk))


def pad_to_capacity(data: GPData, capacity: Optional[int] = None, *, chunk: int = 100) -> GPData:
    """Append ``mask=False`` rows (zeros) up to ``capacity`` (default: :func:`capacity_for`).

    Raises:
      ValueError: the data already has more rows than ``capacity``.
    """
    n = data.inputs.shape[0]
    cap = capacity_for(n, chunk) if capacity is None else int(capacity)
    if cap < n:
        raise ValueError(f"capacity {cap} is smaller than the number of rows {n}")
    pad = cap - n
    return GPData(
        jnp.concatenate([data.inputs, jnp.zeros((pad, data.inputs.shape[1]), data.inputs.dtype)]),
        jnp.concatenate([data.targets, jnp.zeros((pad, data.targets.shape[1]), data.targets.dtype)]),
        jnp.concatenate([data.mask, jnp.zeros((pad,), bool)]),
    )


def num_real(data: GPData) -> int:
    """Number of real (unmasked) rows, on the host."""
    return int(np.asarray(data.mask).sum())


def check_hyper(hyper: GPHyper, data: GPData) -> None:
    """Host check that warm-start hyperparameters match the data's (E, Dz) and are finite."""
    e, dz = data.targets.shape[1], data.inputs.shape[1]
    shapes = {"log_lengthscale": (e, dz), "log_signal": (e,), "log_noise": (e,)}
    for name, shape in shapes.items():
        a = _as_host(f"hyper.{name}", getattr(hyper, name))
        if a.shape != shape:
            raise ValueError(f"hyper.{name} has shape {a.shape} but the data needs {shape} (E={e}, Dz={dz})")
        if not np.isfinite(a).all():
            raise ValueError(f"hyper.{name} contains NaN/Inf")


def clean(data: GPData) -> GPData:
    """Zero the padded rows (traceable), so that their content can never leak into a result."""
    m = data.mask
    return GPData(jnp.where(m[:, None], data.inputs, 0.0), jnp.where(m[:, None], data.targets, 0.0), m)


def masked_std(a: jax.Array, mask: jax.Array) -> jax.Array:
    """Column sample standard deviation (n−1 normaliser) over the real rows: (N, C) → (C,)."""
    w = mask.astype(a.dtype)[:, None]
    n = jnp.sum(w)
    mean = jnp.sum(w * a, 0) / n
    return jnp.sqrt(jnp.sum(w * (a - mean) ** 2, 0) / (n - 1.0))


def masked_rms(a: jax.Array, mask: jax.Array) -> jax.Array:
    """Column root mean square over the real rows: (N, C) → (C,)."""
    w = mask.astype(a.dtype)[:, None]
    return jnp.sqrt(jnp.sum(w * a * a, 0) / jnp.sum(w))
