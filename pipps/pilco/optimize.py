"""PILCO's policy search: quasi-Newton on the moment-matching objective (minimize.m's semantics).

``optimize_policy(task, model, policy)`` minimises ``J(θ) = Σ_{t=1..H} E[c(x_t)]`` over the
policy's parameters (its pytree leaves; ``u_max`` is static) with :func:`pipps.optimizers.minimize`,
warm-started from the given policy. The budget is the problem's own (``Problem.pilco_budget``,
set by its task); the built-in tasks carry PILCO's (``settings_cp.m``, ``settings_unicycle.m``):

| task | budget | evaluations per line search |
|---|---|---|
| cart-pole (swing-up, balance) | 150 line searches | 30 |
| unicycle | 150 evaluations (``length = −150``) | 20 |
| a problem without a budget | 100 line searches | 10 (minimize.m's default) |

The whole optimisation is one jitted program (compiled once per task object, policy structure
and model shapes).
"""

from __future__ import annotations

import dataclasses
import functools

import jax

from pipps.optimizers.quasi_newton import QuasiNewtonConfig, QuasiNewtonTrace, minimize
from pipps.pilco.propagate import objective
from pipps.tasks.base import Problem

#: minimize.m's default budget, for a problem that sets none: 100 line searches of at most 10 evaluations
DEFAULT_BUDGET = (100, 10)


@dataclasses.dataclass(frozen=True)
class PolicySearchConfig:
    """Static settings of :func:`optimize_policy` (hashable).

    Attributes:
      optimizer: the quasi-Newton settings (budgets, line search); None → :func:`pilco_budget`.
      model_uncertainty: keep the GP's ``E_z[var_f]`` (model-uncertainty) term in the propagation.
      horizon: planning horizon (None → ``task.horizon``).
      checkpoint: rematerialise each step in the backward pass (``jax.checkpoint``): H× less
        memory for the stored (E², n, n) intermediates and, measured on the cart-pole benchmark
        (docs/pilco.md), no slower — the default here. Same value and gradient.
      policy_noise: the policy sees the state distribution plus the model's noise variances
        halved, as PILCO's release V0.9 did (:func:`pipps.pilco.propagate.objective`); False
        (default): the latent state, as the later code (``a0b48b7``).
    """

    optimizer: QuasiNewtonConfig | None = None
    model_uncertainty: bool = True
    horizon: int | None = None
    checkpoint: bool = True
    policy_noise: bool = False


def pilco_budget(task: Problem, **overrides) -> QuasiNewtonConfig:
    """PILCO's policy-search budget for ``task``: its ``pilco_budget`` or :data:`DEFAULT_BUDGET` (see
    the module table), with optional overrides."""
    length, per_ls = task.pilco_budget or DEFAULT_BUDGET
    settings = dict(length=length, max_evals_per_linesearch=per_ls)
    settings.update(overrides)
    return QuasiNewtonConfig(**settings)


@functools.partial(jax.jit, static_argnames=("task", "opt", "config"))
def _search(task: Problem, opt: QuasiNewtonConfig, config: PolicySearchConfig, policy, model):
    def J(p):
        return objective(
            task, p, model, horizon=config.horizon, model_uncertainty=config.model_uncertainty,
            checkpoint=config.checkpoint, policy_noise=config.policy_noise,
        )

    return minimize(J, policy, opt)


def optimize_policy(
    task: Problem, model, policy, config: PolicySearchConfig | None = None
) -> tuple[object, QuasiNewtonTrace]:
    """Minimise PILCO's moment-matching objective over the policy parameters.

    Args:
      task: the task (static; the compiled program is cached per task object).
      model: a :class:`~pipps.gp.GPPosterior` (full or FITC) or a model with ``moments``.
      policy: the start policy (warm start).
      config: :class:`PolicySearchConfig`; None → PILCO's budgets for the task.

    Returns:
      ``(policy, trace)``: the best policy evaluated and the optimiser's trace (objective per
      line search, evaluations, failed line searches).
    """
    config = PolicySearchConfig() if config is None else config
    opt = pilco_budget(task) if config.optimizer is None else config.optimizer
    return _search(task, opt, config, policy, model)
