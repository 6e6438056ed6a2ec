"""Success judged on the true system (experiments.md "Success"; docs/results-analyses.md "The physical criterion").

The thesis judged a cart-pole experiment a success when "the pendulum was swung up and kept
balanced", checked by looking at the final trajectory distributions; its return threshold (15)
was calibrated to that. A return threshold alone passes a policy that swings the pole up and then
runs the cart away, so the project judges the physical statement itself:

* a cart-pole evaluation rollout is **balanced** when, over its last ``balance_steps`` states (the
  final second at dt = 0.1 s), the pole stays within ``balance_angle`` rad of upright (the angle
  wrapped, so either swing direction counts) and the cart within ``balance_position`` m of the
  centre;
* an experiment succeeds when at least ``balanced_fraction`` of its final trial's evaluation
  rollouts are balanced.

The unicycle's criterion is its own (``upright_fraction`` of rollouts never fall). The return
threshold is kept, calibrated against the physical verdict (:mod:`pipps.experiments.calibration`),
and reported beside it; the physical criterion decides where they differ.

:func:`flip_probability` says how sure a verdict is: the probability that a fresh evaluation of the
same policy (another 30 rollouts) lands on the other side of the criterion.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

#: The physical criterion's settings (ExperimentConfig fields of the same names); docs/results-analyses.md gives the reasons.
BALANCE_STEPS = 10
BALANCE_ANGLE = 0.3
BALANCE_POSITION = 0.5
BALANCED_FRACTION = 0.5


def is_cartpole(task_name: str) -> bool:
    return task_name.startswith("cartpole")


def balanced(states, steps: int = BALANCE_STEPS, angle: float = BALANCE_ANGLE, position: float = BALANCE_POSITION):
    """Per rollout: pole within ``angle`` of upright and cart within ``position`` of the centre in
    each of the last ``steps`` states. ``states``: (..., H+1, 4) cart-pole simulator states
    ``[x_c, v, ω, θ]`` with θ = π upright. Works on numpy and JAX arrays (pure)."""
    xp = jnp if isinstance(states, jnp.ndarray) and not isinstance(states, np.ndarray) else np
    last = states[..., -steps:, :]
    off_upright = xp.abs(xp.mod(last[..., 3], 2 * math.pi) - math.pi)  # distance to θ = π (mod 2π)
    ok = (off_upright <= angle) & (xp.abs(last[..., 0]) <= position)
    return xp.all(ok, axis=-1)


def flip_probability_fraction(successes: int, n: int, required: float) -> float:
    """The probability that a fresh evaluation with ``n`` rollouts crosses the fraction criterion the
    other way: the predictive (beta-binomial, Jeffreys prior) probability of the fresh count landing
    on the other side of ``ceil(required·n)`` than the observed ``successes``."""
    if n <= 0:
        return math.nan
    from scipy.stats import betabinom

    need = math.ceil(required * n - 1e-12)
    fresh = betabinom(n, successes + 0.5, n - successes + 0.5)
    return float(fresh.cdf(need - 1)) if successes >= need else float(fresh.sf(need - 1))


def flip_probability_return(returns, threshold: float) -> float:
    """The probability that a fresh mean of as many rollouts lands on the other side of ``threshold``:
    fresh − observed mean ~ N(0, 2·SE²) with SE the standard error of the stored mean."""
    r = np.asarray(returns, dtype=float)
    if r.size < 2:
        return math.nan
    se = float(np.std(r, ddof=1) / math.sqrt(r.size))
    gap = abs(float(np.mean(r)) - threshold)
    if se == 0.0:
        return 0.0 if gap > 0 else 0.5
    return 0.5 * math.erfc(gap / (2.0 * se))  # Φ(−gap/(√2·SE)) = ½ erfc(gap/(2·SE))


def standard_error(returns) -> float:
    r = np.asarray(returns, dtype=float)
    return float(np.std(r, ddof=1) / math.sqrt(r.size)) if r.size >= 2 else math.nan


def evaluation_keys(cfg, index: int):
    """The keys of trial ``index``'s evaluation rollouts, as the learning loop draws them
    (:func:`pipps.experiments.state.evaluation_keys`)."""
    from pipps.experiments.state import evaluation_keys as keys

    return keys(cfg, index)


def policy_unraveler(cfg, problem):
    """``flat -> policy``: the map from a stored flat policy vector (``TrialResult.policy``) back to the
    policy ``cfg`` learns on ``problem`` (its structure is that of the initial policy)."""
    import jax
    from jax.flatten_util import ravel_pytree

    from pipps.experiments.state import init_policy

    return ravel_pytree(init_policy(jax.random.PRNGKey(0), cfg, problem))[1]


class Resimulator:
    """Re-runs stored policies on the true system: a trial's own evaluation rollouts (same keys, so
    the returns must match the stored ones to rounding) or ``fresh`` independent ones. One compiled
    program per configuration shape, reused across files."""

    def __init__(self):
        self._programs: dict = {}

    def _program(self, cfg, balance=None):
        import jax

        from pipps.experiments.loop import balance_settings, evaluate_rollouts, make_experiment_task

        balance = balance_settings(cfg) if balance is None else tuple(balance)
        key = (cfg.task, cfg.preset, cfg.k, cfg.cost, cfg.cost_scale, cfg.horizon, cfg.policy, cfg.num_basis, balance)
        if key not in self._programs:
            task = make_experiment_task(cfg)
            unravel = policy_unraveler(cfg, task.problem)
            run = jax.jit(lambda keys, flat: evaluate_rollouts(keys, task, unravel(flat), balance))
            self._programs[key] = run
        return self._programs[key]

    def trial(self, result, index: int, *, fresh: int | None = None, seed: int = 0, balance=None):
        """``(returns, upright, balanced)`` (numpy) of trial ``index``'s policy: its own evaluation
        rollouts, or ``fresh`` rollouts with keys from ``seed`` (independent of the experiment's).
        ``balance = (steps, angle, position)`` judges with other bounds than the configuration's."""
        import jax
        import jax.numpy as jnp

        cfg = result.config
        trial = result.trials[index]
        if trial.kind != "learned":
            raise ValueError(f"trial {index} is a random trial; its evaluation used random actions")
        if fresh is None:
            keys = evaluation_keys(cfg, index)
        else:
            keys = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(seed), 1_000_003 + index), fresh)
        out = self._program(cfg, balance)(keys, jnp.asarray(trial.policy))
        return tuple(np.asarray(a) for a in jax.device_get(out))
