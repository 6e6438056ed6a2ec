"""Re-running stored policies on the true system (docs/results-analyses.md "The physical criterion").

A result file stores, per evaluation rollout, whether it met its task's success criterion
(``eval_balanced``; :mod:`pipps.reporting.verdicts`). Files written before it was stored, and
studies of the criterion's bounds, need those rollouts again: :class:`Resimulator` re-runs a
trial's policy with the trial's own evaluation keys (the returns must equal the stored ones to
rounding, the true system being deterministic given them) or with fresh ones, and judges each
rollout with the task's rule, under the experiment's bounds or others.
"""

from __future__ import annotations

import numpy as np

from pipps.experiments.config import COMPUTATIONAL


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


# Settings that steer only the learning (which policy gets found), never the true system, the
# policy's structure or the success rule a stored policy is judged by: re-simulation programs are
# shared across them. Every other setting keys a program (the initial policy's too, which could
# change its structure), so a task whose factory reads a setting this module does not know of (a
# user task's ``success`` reading ``success_threshold``, say) gets a program of its own.
LEARNING_ONLY = frozenset(COMPUTATIONAL) | {
    "method", "seed", "num_random", "num_learned", "eval_rollouts", "num_particles", "policy_evals",
    "learning_rate", "momentum", "estimator_choices", "noise_boost_tp", "noise_boost_gtp",
    "variance_tol", "pilco_linesearches", "pilco_policy_noise", "gp_max_iters", "fitc_threshold",
    "num_inducing", "fitc_iters", "fitc_first_iters", "store_particles",
}


def program_key(cfg) -> tuple:
    """What a compiled re-simulation program depends on: every setting of ``cfg`` (a frozen, hashable
    configuration) outside :data:`LEARNING_ONLY`, with the cost by name (``None`` and the preset's
    default cost are one)."""
    import dataclasses

    return tuple((f.name, cfg.cost_name if f.name == "cost" else getattr(cfg, f.name))
                 for f in dataclasses.fields(cfg) if f.name not in LEARNING_ONLY)


class Resimulator:
    """Re-runs stored policies on the true system: a trial's own evaluation rollouts (same keys, so
    the returns must match the stored ones to rounding) or ``fresh`` independent ones. One compiled
    program per configuration shape, reused across files."""

    def __init__(self):
        self._programs: dict = {}

    def _program(self, cfg, balance=None, k=None):
        import jax

        from pipps.experiments.programs import evaluate_rollouts, success_rule
        from pipps.experiments.state import make_experiment_task

        if k is not None:  # the same true system observed at another noise level
            cfg = cfg.replace(k=k)
        if balance is not None:  # the cart-pole's criterion under other bounds
            steps, angle, position = balance
            cfg = cfg.replace(balance_steps=steps, balance_angle=angle, balance_position=position)
        key = program_key(cfg)
        if key not in self._programs:
            task = make_experiment_task(cfg)
            unravel = policy_unraveler(cfg, task.problem)
            rule = success_rule(cfg)
            run = lambda keys, flat: evaluate_rollouts(keys, task, unravel(flat), rule)  # noqa: E731
            self._programs[key] = run if task.host_stepped else jax.jit(run)
        return self._programs[key]

    def trial(self, result, index: int, *, fresh: int | None = None, seed: int = 0, balance=None,
              k: float | None = None):
        """``(returns, upright, criterion)`` (numpy) of trial ``index``'s policy: its own evaluation
        rollouts, or ``fresh`` rollouts with keys from ``seed`` (independent of the experiment's);
        ``criterion`` is the task's rule per rollout. ``balance = (steps, angle, position)`` judges
        the cart-pole with other bounds than the configuration's; ``k`` observes the true system at
        another observation-noise multiplier than the experiment's (``k = 0``: the policy sees the
        state). With ``fresh``, rollouts with the same ``seed`` share their keys across ``k`` (and
        across policies), so differences between them are paired."""
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
        out = self._program(cfg, balance, k)(keys, jnp.asarray(trial.policy))
        return tuple(np.asarray(a) for a in jax.device_get(out))
