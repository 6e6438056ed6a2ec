"""The shape every piece of an estimator takes: a frozen dataclass that is also a pytree.

A piece's fields are either *structure* (which computation runs: a baseline's name, a weight's
source), fixed at trace time and part of the pytree's static description, or *numbers* (a fixed
``k_LR``, the robust combiner's ``γ`` and ``z``), which are the pytree's leaves. So a composed
estimator is hashable (a jit static argument, or closed over), and passed as a jit argument its
numbers are traced: a new value does not recompile.
"""

from __future__ import annotations

import dataclasses

import jax


def strategy(cls=None, *, traced: tuple[str, ...] = ()):
    """Make ``cls`` a frozen dataclass registered as a pytree whose children are the fields ``traced``.

    A traced field holds a number (a leaf) or another piece (whose own traced fields are leaves);
    every other field is static structure. Use as ``@strategy`` or ``@strategy(traced=("gamma",))``.
    """

    def wrap(c):
        c = dataclasses.dataclass(frozen=True)(c)
        names = [f.name for f in dataclasses.fields(c)]
        unknown = set(traced) - set(names)
        if unknown:
            raise TypeError(f"{c.__name__}: traced {sorted(unknown)} are not fields")
        meta = [n for n in names if n not in traced]
        return jax.tree_util.register_dataclass(c, data_fields=list(traced), meta_fields=meta)

    return wrap if cls is None else wrap(cls)
