"""Estimators as compositions of pieces (pipps.propagation.estimators; docs/estimators.md).

* every named estimator, thesis variant and override is the one-line composition it claims to be;
* each piece owns its state: the estimator's state is the tuple of its pieces' states, and only the
  pieces with a memory (a "previous" baseline, a "previous" k_LR) hold one;
* a combination that means nothing is refused, and the error names the problem;
* structure is static (hashable, a jit static argument) and numbers are traced leaves: a new
  k_LR, γ or z does not recompile, and the traced number gives the closed-over estimate;
* the robust combiner is exact at its ends: γ = 0 is LR, γ = ∞ is the inverse-variance weight.
"""

import jax
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from pipps.particles.forward import RolloutConfig
from pipps.propagation.combine import inverse_variance, robust, single
from pipps.propagation.estimators import ESTIMATORS, NAMED, compose, estimator, thesis_estimator
from pipps.propagation.pieces import EstimatorState, MeanReturn
from pipps.propagation.weights import PreviousBatchWeight
from pipps.propagation.cost_terms import density_estimation_costs, plain_costs, shaped_costs
from pipps.propagation.estimate import estimate, init_estimator_state
from pipps.propagation.parts import biw_lr, density_lr, pathwise, plain_lr
from pipps.systems.linear_gaussian import reference_system

CFG = RolloutConfig(num_particles=16)


@pytest.fixture(scope="module")
def system():
    return reference_system(noise_std=0.3, cost="saturating")


def flat(tree):
    return np.asarray(ravel_pytree(tree)[0])


def one(system, est, key=3):
    task, model, policy = system
    st = init_estimator_state(jax.random.PRNGKey(9), policy, model, problem=task, config=CFG, estimator=est)
    return estimate(jax.random.PRNGKey(key), st, policy, model, problem=task, config=CFG, estimator=est)[1]


@pytest.mark.parametrize(
    "built, composed",
    [
        (estimator("rp"), compose(plain_costs(), pathwise())),
        (estimator("lr"), compose(plain_costs(), biw_lr("previous"))),
        (estimator("lr_plain"), compose(plain_costs(), plain_lr())),
        (estimator("tp"), compose(plain_costs(), biw_lr(), pathwise(), combiner=inverse_variance("leave_one_out"))),
        (estimator("tp", k_lr="previous"), compose(plain_costs(), biw_lr(), pathwise(), combiner=inverse_variance("previous"))),
        (estimator("gtp"), compose(shaped_costs(), pathwise(), biw_lr(), combiner=inverse_variance())),
        (estimator("glr"), compose(shaped_costs(), biw_lr())),
        (estimator("del"), compose(plain_costs(), density_lr("previous"), combiner=single())),
        (thesis_estimator("lr"), compose(plain_costs(), biw_lr("thesis"))),
        (thesis_estimator("tp"), compose(plain_costs(), pathwise(), biw_lr("thesis"), combiner=inverse_variance("batch"))),
        (thesis_estimator("gtp"), compose(shaped_costs(), pathwise(), biw_lr("thesis"), combiner=inverse_variance("batch"))),
        (thesis_estimator("glr"), compose(shaped_costs(), biw_lr("thesis"))),
        (thesis_estimator("rp"), estimator("rp")),
        (thesis_estimator("del"), compose(density_estimation_costs("previous"), pathwise())),
        (estimator("tp", weighting="plain", k_lr=0.3), compose(plain_costs(), pathwise(), plain_lr(), combiner=inverse_variance(0.3))),
        (estimator("lr_plain", weighting="biw"), estimator("lr")),
        (estimator("tp", baseline="none", k_lr="batch"), compose(plain_costs(), pathwise(), biw_lr("none"), combiner=inverse_variance("batch"))),
        (estimator("del", baseline="none"), compose(plain_costs(), density_lr("none"))),
        (thesis_estimator("del", baseline="none"), compose(density_estimation_costs("none"), pathwise())),
        (estimator("tp", combiner="robust", robust_gamma=0.5), compose(plain_costs(), pathwise(), biw_lr(), combiner=robust(0.5))),
        (thesis_estimator("tp", combiner="robust", robust_z=1.0), compose(plain_costs(), pathwise(), biw_lr("thesis"), combiner=robust(z=1.0, k_lr="batch"))),
        (thesis_estimator("tp", k_lr=0.0), compose(plain_costs(), pathwise(), biw_lr("thesis"), combiner=inverse_variance(0.0))),
        (estimator("tp", messages="pathwise"), compose(plain_costs(), pathwise(), biw_lr(), combiner=inverse_variance("leave_one_out", "pathwise"))),
        (thesis_estimator("tp", messages="pathwise"), compose(plain_costs(), pathwise(), biw_lr("thesis"), combiner=inverse_variance("batch", "pathwise"))),
        (estimator("tp", combiner="robust", messages="pathwise"), compose(plain_costs(), pathwise(), biw_lr(), combiner=robust(messages="pathwise"))),
    ],
)
def test_names_and_settings_are_the_compositions_they_claim(built, composed):
    assert built == composed and hash(built) == hash(composed)


def test_the_descriptive_views_follow_the_pieces():
    assert NAMED == tuple(ESTIMATORS) and all(e.name == n for n, e in ESTIMATORS.items())
    tp, rp, lr = estimator("tp"), estimator("rp"), estimator("lr")
    assert tp.pathwise and tp.likelihood_ratio and tp.kinds == ("pathwise", "likelihood_ratio")
    assert tp.combiner.k_lr == "leave_one_out" and rp.combiner.k_lr is None
    assert rp.pathwise and not rp.likelihood_ratio and lr.likelihood_ratio and not lr.pathwise
    assert estimator("tp", k_lr=0.25).combiner.k_lr == 0.25 and thesis_estimator("gtp").combiner.k_lr == "batch"
    assert tp.pieces == (tp.costs, *tp.parts, tp.combiner)


def _state_shapes(system, est):
    task, model, policy = system
    state = init_estimator_state(jax.random.PRNGKey(9), policy, model, problem=task, config=CFG, estimator=est)
    return jax.tree.map(lambda a: a.shape, state)


@pytest.mark.parametrize(
    "est, costs, parts, combiner, cold",
    [
        (estimator("rp"), (), ((),), (), False),
        (estimator("lr_plain"), (), ((),), (), False),
        (estimator("lr"), (), (MeanReturn((10,)),), (), False),
        (thesis_estimator("lr"), (), ((),), (), False),
        (estimator("tp"), (), ((), MeanReturn((10,))), (), False),
        (thesis_estimator("tp"), (), ((), ()), (), False),
        (estimator("tp", k_lr="previous"), (), ((), MeanReturn((10,))), PreviousBatchWeight((10,), (10,)), True),
        (estimator("tp", k_lr="guarded", baseline="none"), (), ((), ()), PreviousBatchWeight((10,), (10,)), True),
        (estimator("tp", k_lr="cross_fit"), (), ((), MeanReturn((10,))), (), False),
        (estimator("del"), (), (MeanReturn((10,)),), (), False),
        (estimator("del", baseline="none"), (), ((),), (), False),
        (thesis_estimator("del"), MeanReturn((10,)), ((),), (), False),
        (estimator("glr"), (), (MeanReturn((10,)),), (), False),
    ],
)
def test_each_piece_owns_its_state(system, est, costs, parts, combiner, cold):
    """The state is one entry per piece, each per step (T = 10); a piece without memory holds ()."""
    assert _state_shapes(system, est) == EstimatorState(costs, parts, combiner)
    assert est.cold_start == cold


def test_the_extra_rollout_is_made_only_for_a_piece_that_asks(system):
    """Only a "previous" baseline reads the extra rollout; an estimator without one traces no rollout."""
    task, model, policy = system

    def rollouts(est):
        jaxpr = jax.make_jaxpr(lambda k: init_estimator_state(k, policy, model, problem=task, config=CFG, estimator=est))(
            jax.random.PRNGKey(0))
        return str(jaxpr).count("scan")

    assert rollouts(estimator("rp")) == 0 and rollouts(thesis_estimator("tp")) == 0
    assert rollouts(estimator("lr")) == 1


@pytest.mark.parametrize(
    "build, match",
    [
        (lambda: estimator("rp", k_lr=0.5), "only apply to total propagation"),
        (lambda: estimator("lr", combiner="robust"), "only apply to total propagation"),
        (lambda: estimator("tp", robust_gamma=0.1), "belong to the robust combiner"),
        (lambda: estimator("tp", combiner="median"), "combiner must be one of"),
        (lambda: estimator("lr_plain", baseline="previous"), "plain LR's baseline must be one of"),
        (lambda: estimator("lr", returns="total"), "weighs a plain LR part"),
        (lambda: estimator("glr", weighting="plain", returns="total"), "shaped or density-estimation cost terms"),
        (lambda: estimator("rp", baseline="none"), "baseline applies to BIW-LR or DEL"),
        (lambda: estimator("del", baseline="thesis"), "DEL's baseline"),
        (lambda: estimator("rp", weighting="plain"), "weighting applies to a likelihood-ratio part"),
        (lambda: estimator("tp", weighting="uniform"), "weighting must be one of"),
        (lambda: estimator("tp", shaping=True), "unknown estimator settings"),
        (lambda: estimator("tp", k_lr="soon"), "k_lr must be one of"),
        (lambda: estimator("tp", messages="lr"), "messages must be one of"),
        (lambda: estimator("tp", combiner="robust", messages="lr"), "messages must be one of"),
        (lambda: estimator("rp", messages="pathwise"), "only apply to total propagation"),
        (lambda: estimator("tp", combiner="robust", robust_gamma=-1.0), "robust_gamma"),
        (lambda: thesis_estimator("nope"), "unknown estimator"),
        (lambda: compose(plain_costs()), "needs a gradient part"),
        (lambda: compose(plain_costs(), pathwise(), biw_lr()), "need a combiner"),
        (lambda: compose(plain_costs(), pathwise(), biw_lr(), combiner=single()), "not 'single'"),
        (lambda: compose(plain_costs(), biw_lr(), combiner=robust()), "a lone likelihood_ratio part takes single"),
        (lambda: compose(plain_costs(), biw_lr(), plain_lr(), combiner=inverse_variance()), "one of each"),
        (lambda: compose(density_estimation_costs(), pathwise(), biw_lr(), combiner=inverse_variance()), "lone pathwise part"),
        (lambda: compose(density_estimation_costs(), biw_lr()), "lone pathwise part"),
        (lambda: compose(plain_costs(), pathwise(), density_lr(), combiner=inverse_variance()), "compose it alone"),
        (lambda: estimator("del", weighting="plain"), "has no batch weighting"),
        (lambda: thesis_estimator("del", baseline="thesis"), "DEL's baseline"),
    ],
)
def test_a_meaningless_combination_is_refused_by_name(build, match):
    with pytest.raises(ValueError, match=match):
        build()


def test_numbers_are_traced_and_do_not_recompile(system):
    task, model, policy = system
    st = init_estimator_state(jax.random.PRNGKey(9), policy, model, problem=task, config=CFG, estimator=estimator("tp"))

    @jax.jit
    def grad(est, key):
        return ravel_pytree(estimate(key, st, policy, model, problem=task, config=CFG, estimator=est)[1].grad)[0]

    key = jax.random.PRNGKey(3)
    g3, g7 = grad(estimator("tp", k_lr=0.3), key), grad(estimator("tp", k_lr=0.7), key)
    assert grad._cache_size() == 1
    assert not np.allclose(g3, g7)
    closed = estimate(key, st, policy, model, problem=task, config=CFG, estimator=estimator("tp", k_lr=0.7))[1].grad
    np.testing.assert_allclose(np.asarray(g7), flat(closed), rtol=1e-12, atol=1e-15)
    grad(estimator("tp", combiner="robust", robust_gamma=0.1), key)
    grad(estimator("tp", combiner="robust", robust_gamma=3.0, robust_z=0.5), key)
    assert grad._cache_size() == 2  # one more program for the new structure, none for the new numbers


def test_structure_is_a_static_argument():
    calls = []

    def f(x, est):
        calls.append(est)
        return x * (2.0 if est.combiner.num_parts == 2 else 1.0)

    fj = jax.jit(f, static_argnames="est")
    fj(1.0, est=estimator("tp", k_lr=0.3))
    fj(1.0, est=estimator("tp", k_lr=0.3))  # a separately built, equal estimator
    assert len(calls) == 1 and fj._cache_size() == 1


def test_robust_combiner_is_lr_at_zero_tolerance_and_inverse_variance_at_infinite(system):
    lr_e = one(system, estimator("lr"))
    at_zero = one(system, estimator("tp", combiner="robust", robust_gamma=0.0, k_lr="batch"))
    np.testing.assert_array_equal(np.asarray(at_zero.diagnostics.k_lr), 1.0)
    np.testing.assert_allclose(flat(at_zero.grad), flat(lr_e.grad), rtol=1e-11, atol=1e-15)
    iv = one(system, estimator("tp", k_lr="batch"))
    at_inf = one(system, estimator("tp", combiner="robust", k_lr="batch"))
    np.testing.assert_allclose(np.asarray(at_inf.diagnostics.k_lr), np.asarray(iv.diagnostics.k_lr), rtol=1e-12)
    np.testing.assert_allclose(flat(at_inf.grad), flat(iv.grad), rtol=1e-10, atol=1e-15)
    k_iv = np.asarray(iv.diagnostics.k_lr)
    assert np.all((k_iv > 0.0) & (k_iv < 1.0))  # the two ends really differ


def test_tp_plain_is_total_propagation_of_rp_and_plain_lr(system):
    assert estimator("tp_plain") == estimator("tp", weighting="plain") == compose(
        plain_costs(), pathwise(), plain_lr(), combiner=inverse_variance()
    )
    rp, lr_plain = one(system, estimator("rp")), one(system, estimator("lr_plain"))
    np.testing.assert_allclose(flat(one(system, estimator("tp_plain", k_lr=0.0)).grad), flat(rp.grad), rtol=1e-11, atol=1e-15)
    np.testing.assert_allclose(flat(one(system, estimator("tp_plain", k_lr=1.0)).grad), flat(lr_plain.grad), rtol=1e-11, atol=1e-15)
    mixed = one(system, estimator("tp_plain", k_lr="batch"))
    k = np.asarray(mixed.diagnostics.k_lr)
    assert np.all((k > 0.0) & (k < 1.0)) and np.all(np.isfinite(flat(mixed.grad)))
