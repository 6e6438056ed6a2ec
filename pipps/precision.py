"""Float64 is the caller's choice: importing pipps changes no global setting.

The task physics, GP training and every numerical check of this project are specified in float64,
so a program that uses pipps (the ``pipps`` command, the test session, a script)
switches on JAX's 64-bit mode once, before it builds any array::

    import pipps
    pipps.enable_float64()        # the same as jax.config.update("jax_enable_x64", True)

The entry points whose results depend on it — GP fitting (:func:`pipps.gp.make_data`,
:func:`~pipps.gp.fit`, :func:`~pipps.gp.fit_many`), true-system rollouts (:func:`pipps.rollout.rollout`,
the gymnasium environments), gradient estimates (:func:`pipps.propagation.estimate`,
:func:`~pipps.propagation.init_estimator_state`), PILCO's moment propagation
(:func:`pipps.pilco.objective`, :func:`~pipps.pilco.trajectory`) and experiments — call
:func:`require_float64` and raise :class:`Float64Required` when it is off, instead of computing
silently in float32. A caller that wants float32 somewhere (fast particle rollouts) casts its
arrays explicitly with 64-bit mode on.

JAX is imported only when one of these functions runs, so ``import pipps`` stays cheap.
"""

from __future__ import annotations

_ENABLE = 'pipps.enable_float64() (or jax.config.update("jax_enable_x64", True))'


class Float64Required(RuntimeError):
    """A float64 entry point was called while JAX's 64-bit mode is off."""


def enable_float64() -> None:
    """Switch on JAX's 64-bit mode for this process; call it before any array is built."""
    import jax

    jax.config.update("jax_enable_x64", True)


def float64_enabled() -> bool:
    """Whether JAX's 64-bit mode is on (in this thread: a ``jax.enable_x64(True)`` scope counts)."""
    import jax

    return bool(jax.config.jax_enable_x64)


def require_float64(what: str) -> None:
    """Raise :class:`Float64Required`, naming ``what`` and the remedy, unless 64-bit mode is on."""
    if not float64_enabled():
        raise Float64Required(
            f"{what} computes in float64, but JAX's 64-bit mode is off; call {_ENABLE} once at the start "
            "of the program, before any array is built"
        )
