"""Fixed-seed (``_FS``, PEGASUS-style) policy optimization: RP_FS and GR_FS (thesis §4.5.1).

With the particle noise drawn once from a fixed key, ``J(θ)`` is a deterministic, smooth function
of the policy parameters, so it is minimised by the quasi-Newton method of
:mod:`pipps.optimizers.quasi_newton` on the exact gradient of that objective — the RP sweep
(:func:`~pipps.propagation.estimate.estimate` with the ``rp`` estimator), through the Gaussian
resampling too when ``config.resampling == "gaussian"`` (GR_FS).
"""

from __future__ import annotations

import jax

from pipps.optimizers.quasi_newton import QuasiNewtonConfig, QuasiNewtonTrace, minimize
from pipps.particles.forward import RolloutConfig
from pipps.propagation.estimators import estimator
from pipps.propagation.estimate import estimate, init_estimator_state
from pipps.tasks.base import Problem


def optimize_fixed_seed(
    key: jax.Array,
    policy,
    model,
    *,
    problem: Problem,
    config: RolloutConfig,
    qn_config: QuasiNewtonConfig = QuasiNewtonConfig(length=150, max_evals_per_linesearch=30),
):
    """Minimise the fixed-seed particle objective; returns ``(policy, QuasiNewtonTrace)``.

    The default budget is PILCO's cart-pole one (150 line searches, ≤ 30 evaluations each).
    Pure and jittable (static: ``problem``, ``config``, ``qn_config``).
    """
    est = estimator("rp")
    state = init_estimator_state(key, policy, model, problem=problem, config=config, estimator=est)

    def value_and_grad(p):
        _, e = estimate(key, state, p, model, problem=problem, config=config, estimator=est)
        return e.value, e.grad

    return minimize(None, policy, qn_config, value_and_grad=value_and_grad)


__all__ = ["QuasiNewtonTrace", "optimize_fixed_seed"]
