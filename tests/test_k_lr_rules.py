"""Total propagation's k_LR rules: leave-one-out, split, cross-fit and guarded (docs/estimators.md,
"Choosing k_LR"; numbers in docs/estimator-variance.md).

Exact identities first:

* the O(P·n) leave-one-out and split statistics equal a direct computation over the other
  particles, also where one particle's gradient is 10¹² times the others' (the downdate of the
  sum of squares would cancel there);
* a per-particle weight that is the same for every particle gives bit for bit the scalar weight's
  combination (the (P, 1) path of ``mix`` is the scalar path);
* leave-one-out and split weights through the whole sweep (gradients and messages λ) equal a
  direct loop of thesis Alg. 5 with NumPy variances over the other particles (the batch weight
  misses that loop by 4 %, so the comparison can fail);
* the guarded source is "previous" below its threshold and LR at or above it;
* the cross-fit is what it says: each half's contributions equal a separate sweep of that half with
  the weights read from a separate pilot sweep of the other half.

Then statistics against an exact gradient (linear-Gaussian reference system, as in
tests/test_estimators_unbiased.py): the cross-fit, which is exactly unbiased by construction,
passes the Bonferroni z-test, and the same test with the same R detects the thesis' bias (power).

On the chaotic kicked rotor (``slow``; P = 100, R = 400, the bounds of test_estimators_variance.py):
leave-one-out is significantly below "previous"; the exact cross-fit is significantly above BIW-LR
(it cannot see an exploding particle); leave-one-out not significantly above BIW-LR is a strict
xfail (measured 1.5×); neither shows a bias against BIW-LR on the same particles. In the smooth
setting, TP with "previous" weights on the contributions and pathwise messages
(``inverse_variance(messages="pathwise")``) is significantly below RP; paired against "previous" on
the linear-Gaussian system it shows no bias.
"""

import functools

import direct_sweep
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from pipps.particles.forward import ParticleRecord, RolloutConfig, particle_rollout, sample_noise
from pipps.propagation.backward import backward_sweep
from pipps.propagation.combine import InverseVariance, _total_propagation, inverse_variance
from pipps.propagation.cost_terms import plain_costs
from pipps.propagation.estimate import estimate, init_estimator_state
from pipps.propagation.estimators import compose, estimator, thesis_estimator
from pipps.propagation.parts import biw_lr, pathwise
from pipps.propagation.schedules import CrossFitted, cross_fitted
from pipps.propagation.weights import (
    FixedWeight,
    GuardedWeight,
    PreviousBatchWeight,
    leave_one_out_statistics,
    split_statistics,
)
from pipps.stats import log_variance_ratio, paired_replicate_gradients, replicate_gradients, z_bound
from pipps.systems import exact_objective, reference_system
from pipps.systems.chaotic import kicked_rotor_system


def _gradients(scale_top: float) -> np.ndarray:
    rng = np.random.default_rng(4)
    g = rng.normal(size=(12, 5)) * np.array([1.0, 3.0, 0.1, 2.0, 5.0])
    g[7] *= scale_top
    return g


def _direct_others(g: np.ndarray, others) -> tuple[float, np.ndarray]:
    sub = g[others]
    return float(np.sum(np.var(sub, axis=0, ddof=1))), sub.mean(axis=0)


@pytest.mark.parametrize("scale_top", [1.0, 1e6, 1e12])
def test_leave_one_out_statistics_equal_a_direct_computation(scale_top):
    g = _gradients(scale_top)
    st = leave_one_out_statistics(jnp.asarray(g))
    assert st.count == g.shape[0] - 1
    for i in range(g.shape[0]):
        var, mean = _direct_others(g, np.arange(g.shape[0]) != i)
        np.testing.assert_allclose(float(st.var[i]), var, rtol=1e-9)
        np.testing.assert_allclose(np.asarray(st.mean[i]), mean, rtol=1e-9, atol=1e-12 * np.abs(mean).max())


def test_split_statistics_are_the_other_halfs():
    g = _gradients(1e6)
    st = split_statistics(jnp.asarray(g))
    half = np.arange(g.shape[0]) % 2
    for i in range(g.shape[0]):
        var, mean = _direct_others(g, half != half[i])
        np.testing.assert_allclose(float(st.var[i]), var, rtol=1e-12)
        np.testing.assert_allclose(np.asarray(st.mean[i]), mean, rtol=1e-12)


class _SameForEveryParticle:
    """A per-particle source whose weights are all ``k`` (for the (P, 1) path of the combination)."""

    cold_start = False
    k_lr = "same_for_every_particle"

    def __init__(self, k):
        self.k = k

    def init(self, context, weight_shape):
        return ()

    def weight(self, state, rule, g_rp, g_lr, k_batch):
        return state, jnp.full(g_rp.shape[0], self.k, g_rp.dtype)


def test_a_per_particle_weight_equal_for_all_is_the_scalar_weight_bit_for_bit():
    rng = np.random.default_rng(1)
    g = jnp.asarray(rng.normal(size=(2, 9, 4)))
    messages = [jnp.asarray(rng.normal(size=(9, 3))) for _ in range(2)]
    _, scalar = _total_propagation(InverseVariance(FixedWeight(0.3)), (), g, messages)
    _, per_particle = _total_propagation(InverseVariance(_SameForEveryParticle(0.3)), (), g, messages)
    for name in ("gradient", "message", "k_batch", "variances"):
        for x, y in zip(jax.tree.leaves(getattr(scalar, name)), jax.tree.leaves(getattr(per_particle, name))):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=name)
    assert float(per_particle.k) == pytest.approx(0.3, rel=1e-15)  # the reported mean of nine 0.3s


def test_guarded_is_previous_below_its_threshold_and_lr_above():
    src = GuardedWeight(0.99)

    def k(kb, kp, has):
        state, used = src.weight(PreviousBatchWeight(jnp.asarray(kp), jnp.asarray(has)), None, None, None, jnp.asarray(kb))
        assert float(state.k_batch) == kb and bool(state.has_previous)  # it remembers this batch's weight
        return float(used)

    assert k(0.5, 0.2, True) == 0.2
    assert k(0.989, 0.2, True) == 0.2
    assert k(0.99, 0.2, True) == 1.0 and k(0.999999, 0.0, True) == 1.0
    assert k(0.5, 0.2, False) == 0.5  # first iteration: this batch's, as "previous"
    assert estimator("tp", k_lr="guarded").cold_start and not estimator("tp", k_lr="leave_one_out").cold_start


# -- a weight per particle, through the whole sweep: a direct loop of Alg. 5 ------------------


def _inverse_variance(v_rp, v_lr):
    return v_rp / (v_rp + v_lr)


def _others_loo(g):
    P = g.shape[0]
    return [np.arange(P) != i for i in range(P)]


def _others_split(g):
    half = np.arange(g.shape[0]) % 2
    return [half != half[i] for i in range(g.shape[0])]


def _direct_tp_per_particle(task, model, policy, noise, others, baseline, pathwise_messages=False):
    """Alg. 5 with BIW-LR as plain loops over t and i, particle i's k_LR the inverse-variance weight
    of the particles ``others(g)[i]`` (NumPy variances, ddof 1, trace over θ); with
    ``pathwise_messages`` the message passed back is γ^RP instead of the mixed λ."""
    f = direct_sweep.forward(task, model, policy, noise)
    dzeta_dx, dzeta_dth, dcost = direct_sweep.through_policy(task, f)
    P, T, D = noise.x0.shape[0], noise.eps.shape[0], task.model_dim
    lam, grad = np.zeros((P, 2 * D)), np.zeros(f.theta.size)
    for t, x, mu, sd, G in direct_sweep.backward_steps(task, f):
        w = direct_sweep.biw_weights(x, mu, sd)
        gam_rp, gam_lr, jac = [], [], []
        for i in range(P):
            a = np.asarray(dcost(x[i]))
            if t < T:
                a = a + lam[i] @ np.asarray(dzeta_dx(x[i], f.theta))
            gam_rp.append(np.concatenate([a, a * np.asarray(noise.eps[t - 1][i])]))
            gam_lr.append(direct_sweep.lr_zeta(i, w, G, baseline[t - 1], x, mu, sd))
            jac.append(np.asarray(dzeta_dth(f.xs[t - 1][i], f.theta)))
        g_rp = np.stack([gam_rp[i] @ jac[i] for i in range(P)])
        g_lr = np.stack([gam_lr[i] @ jac[i] for i in range(P)])
        sets = others(g_rp)
        k = [_inverse_variance(np.var(g_rp[o], axis=0, ddof=1).sum(), np.var(g_lr[o], axis=0, ddof=1).sum()) for o in sets]
        lam = np.stack([gam_rp[i] if pathwise_messages else k[i] * gam_lr[i] + (1 - k[i]) * gam_rp[i] for i in range(P)])
        grad = grad + np.mean([k[i] * g_lr[i] + (1 - k[i]) * g_rp[i] for i in range(P)], axis=0)
    return grad


@pytest.mark.parametrize(
    "rule, others, messages",
    [("leave_one_out", _others_loo, "mixed"), ("split", _others_split, "mixed"), ("leave_one_out", _others_loo, "pathwise")],
)
def test_a_weight_per_particle_matches_a_direct_loop_through_the_messages(rule, others, messages):
    """Particle i's weight enters its gradient and the message λ_i it passes back (Alg. 5's
    last two steps), or only its gradient with ``messages="pathwise"``; the sweep equals plain loops with
    NumPy variances over the other particles."""
    task, model, policy = kicked_rotor_system("chaotic", horizon=4)
    cfg = RolloutConfig(num_particles=6, model_variance=False)
    est = compose(plain_costs(), pathwise(), biw_lr(), combiner=inverse_variance(rule, messages))
    assert messages == "pathwise" or est == estimator("tp", k_lr=rule)
    state = init_estimator_state(jax.random.PRNGKey(9), policy, model, problem=task, config=cfg, estimator=est)
    _, e = estimate(jax.random.PRNGKey(3), state, policy, model, problem=task, config=cfg, estimator=est)
    noise = sample_noise(jax.random.PRNGKey(3), task, cfg)
    ref = _direct_tp_per_particle(task, model, policy, noise, others, np.asarray(state.parts[1].mean_return), messages == "pathwise")
    got = np.asarray(ravel_pytree(e.grad)[0])
    assert np.linalg.norm(ref) > 1e-3
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max())
    k = np.asarray(e.diagnostics.k_lr)
    assert np.all((k > 0.0) & (k < 1.0))  # an intermediate weight: both parts and the messages matter


# -- the cross-fit is two pilot and two final half sweeps ----------------------------------------------


def _half(record: ParticleRecord, h: int) -> ParticleRecord:
    P = record.x.shape[1]
    sl = slice(0, P // 2) if h == 0 else slice(P // 2, P)
    return ParticleRecord(*(None if a is None else a[:, sl] for a in record))


def test_cross_fit_is_each_half_swept_with_the_other_halfs_pilot_weights():
    task, model, policy = reference_system(0.3, "saturating")
    cfg = RolloutConfig(num_particles=16)
    est = estimator("tp", k_lr="cross_fit")
    assert est == cross_fitted(estimator("tp", k_lr="batch")) and est.schedule == CrossFitted("leave_one_out")
    assert not est.cold_start
    state = init_estimator_state(jax.random.PRNGKey(2), policy, model, problem=task, config=cfg, estimator=est)
    record = particle_rollout(task, policy, model, sample_noise(jax.random.PRNGKey(5), task, cfg), cfg, jacobian=True)
    next_state, out = est.schedule.sweep(task, policy, record, cfg, est, state)
    got = np.asarray(out.contributions)

    pilot_est, final_est = estimator("tp", k_lr="leave_one_out"), estimator("tp", k_lr="previous")
    k_pilot = [backward_sweep(task, policy, _half(record, h), cfg, pilot_est, state)[1].diagnostics.k_lr_batch for h in (0, 1)]
    baselines = []
    for h in (0, 1):
        other = state._replace(combiner=PreviousBatchWeight(k_pilot[1 - h], jnp.ones(k_pilot[1 - h].shape, bool)))
        half_state, half = backward_sweep(task, policy, _half(record, h), cfg, final_est, other)
        want = np.asarray(half.contributions)
        np.testing.assert_allclose(got[h * 8 : (h + 1) * 8], want, rtol=1e-12, atol=1e-14 * np.abs(want).max())
        baselines.append(np.asarray(half_state.parts[1].mean_return))
    # the next "previous" baseline is the mean return over all particles: the halves' average
    np.testing.assert_allclose(np.asarray(next_state.parts[1].mean_return), np.mean(baselines, axis=0), rtol=1e-14)
    k0, k1 = (np.asarray(k) for k in k_pilot)
    assert np.all((k0 > 0) & (k0 < 1)) and not np.allclose(k0, k1)  # the halves' weights really differ

    _, e = estimate(jax.random.PRNGKey(5), state, policy, model, problem=task, config=cfg, estimator=est)
    np.testing.assert_allclose(np.asarray(ravel_pytree(e.grad)[0]), got.mean(0), rtol=1e-12)


def test_cross_fit_refuses_what_it_cannot_split():
    task, model, policy = reference_system(0.3, "saturating")
    cfg = RolloutConfig(num_particles=9)
    est = estimator("tp", k_lr="cross_fit")
    state = init_estimator_state(jax.random.PRNGKey(2), policy, model, problem=task, config=cfg, estimator=est)
    with pytest.raises(ValueError, match="P must be even"):
        estimate(jax.random.PRNGKey(5), state, policy, model, problem=task, config=cfg, estimator=est)
    with pytest.raises(ValueError, match="total propagation"):
        cross_fitted(estimator("lr"))
    with pytest.raises(ValueError, match="pilot must be one of"):
        cross_fitted(estimator("tp"), "previous")


# -- unbiasedness against the exact gradient (linear-Gaussian reference system) --------------------------

ALPHA = 1e-3  # family-wise false-alarm probability
N_THETA = 4  # the reference policy's parameters
R_UNBIASED = 2000
# the comparisons of this family: (name, estimator, P); each must pass, with every coordinate's |z|
UNBIASED = [
    ("cross_fit", estimator("tp", k_lr="cross_fit"), 30),
    ("cross_fit_batch_pilot", cross_fitted(estimator("tp", k_lr="batch"), "batch"), 30),
]
Z_BOUND = z_bound(N_THETA * (len(UNBIASED) + 2), ALPHA)  # + the paired cross-fit and RP-message comparisons below
RP_MESSAGES = compose(plain_costs(), pathwise(), biw_lr(), combiner=inverse_variance("previous", "pathwise"))


def _z_against_exact(est, P: int, R: int, seed: int):
    task, model, policy = reference_system(0.3, "saturating")
    exact = np.asarray(ravel_pytree(jax.grad(exact_objective, argnums=2)(task, model, policy))[0])
    g = replicate_gradients(jax.random.PRNGKey(seed), task, model, policy, RolloutConfig(num_particles=P), est, R)
    mean, se = g.mean(0), g.std(0, ddof=1) / np.sqrt(R)
    assert np.linalg.norm(exact) > 1e-2 and np.all(se > 0)
    return (mean - exact) / se, mean, exact, se


@pytest.mark.parametrize("name, est, P", UNBIASED, ids=[u[0] for u in UNBIASED])
def test_the_cross_fit_is_unbiased(name, est, P):
    z, mean, exact, se = _z_against_exact(est, P, R_UNBIASED, seed=101)
    print(f"{name} P={P}: R = {R_UNBIASED}, bound {Z_BOUND:.2f}, z = {np.round(z, 2)}, rel. SE {np.linalg.norm(se) / np.linalg.norm(exact):.4f}")
    assert np.max(np.abs(z)) < Z_BOUND, f"{name}: z = {z}, mean {mean}, exact {exact}, se {se}"


R_PAIRED = 10000


@functools.lru_cache(maxsize=None)
def _paired_lg(P: int):
    task, model, policy = reference_system(0.3, "saturating")
    ests = {n: estimator("tp", k_lr=n) for n in ("previous", "batch", "leave_one_out", "cross_fit")}
    ests["rp_messages"] = RP_MESSAGES
    run = jax.jit(functools.partial(
        paired_replicate_gradients, problem=task, model=model, policy=policy, config=RolloutConfig(num_particles=P),
        estimators=ests, num_replicates=R_PAIRED, batch_size=200,
    ))
    g = {n: np.asarray(v) for n, v in run(jax.random.PRNGKey(303)).grad.items()}
    exact = np.asarray(ravel_pytree(jax.grad(exact_objective, argnums=2)(task, model, policy))[0])
    out = {}
    for n in ("batch", "leave_one_out", "cross_fit", "rp_messages"):
        d = g[n] - g["previous"]  # paired on the same particles against an exactly unbiased rule
        out[n] = (d.mean(0), d.mean(0) / (d.std(0, ddof=1) / np.sqrt(R_PAIRED)), np.linalg.norm(exact))
    return out


def test_paired_against_previous_the_cross_fit_shows_no_bias_and_leave_one_out_its_bias():
    """The paired difference against "previous" (exact) on the same particles cancels their common
    sampling error, which makes the test sharp (docs/estimator-variance.md: leave-one-out's bias is
    1.0 % of ‖∇J‖ at P = 30, z = 17.5 at R = 40,000; the thesis rule's 3.1 %). The cross-fit passes;
    leave-one-out, which is not exact (docs/estimators.md), is detected, and its bias is below the
    thesis rule's on the same particles."""
    res = _paired_lg(30)
    for n, (b, z, norm) in res.items():
        print(f"{n} − previous: rel {np.linalg.norm(b) / norm:.4f}, z = {np.round(z, 1)} (bound {Z_BOUND:.2f})")
    assert np.max(np.abs(res["cross_fit"][1])) < Z_BOUND
    assert np.max(np.abs(res["rp_messages"][1])) < Z_BOUND  # "previous" weights, pathwise messages: exact too
    assert np.max(np.abs(res["leave_one_out"][1])) > Z_BOUND
    assert np.max(np.abs(res["batch"][1])) > Z_BOUND
    assert np.linalg.norm(res["leave_one_out"][0]) < np.linalg.norm(res["batch"][0])


def test_the_same_test_detects_the_thesis_bias():
    """Power: the thesis' TP (eq. 4.3 baseline and batch k_LR) fails the test above at the same R
    (expected max |z| ≈ 7.7, tests/test_estimators_unbiased.py)."""
    z, *_ = _z_against_exact(thesis_estimator("tp"), 30, R_UNBIASED, seed=101)
    assert np.max(np.abs(z)) > Z_BOUND, f"z = {z}"


# -- the chaotic kicked rotor: what the weights from this batch buy, and what the exact rule cannot ----------

CHAOS_P, CHAOS_R = 100, 400
CHAOS_FAMILY = 4 + 2 * N_THETA  # four variance comparisons (one smooth) and two rules' bias coordinates below
Z_CHAOS = z_bound(CHAOS_FAMILY, 0.01, two_sided=False)  # one-sided, family-wise 1 %, as in test_estimators_variance.py


@functools.lru_cache(maxsize=None)
def _chaos():
    task, model, policy = kicked_rotor_system("chaotic")
    ests = {
        "lr": estimator("lr"),
        "previous": estimator("tp", k_lr="previous"),
        "leave_one_out": estimator("tp", k_lr="leave_one_out"),
        "cross_fit": estimator("tp", k_lr="cross_fit"),
    }
    run = jax.jit(functools.partial(
        paired_replicate_gradients, problem=task, model=model, policy=policy,
        config=RolloutConfig(num_particles=CHAOS_P, model_variance=False), estimators=ests, num_replicates=CHAOS_R,
    ))
    return {n: np.asarray(g) for n, g in run(jax.random.PRNGKey(77)).grad.items()}


def _ratio(a, b):
    log_ratio, se = log_variance_ratio(_chaos()[a], _chaos()[b])
    print(f"{a}/{b}: {np.exp(log_ratio):.3g}, one-sided bound factor {np.exp(Z_CHAOS * se):.3g}")
    return log_ratio, se


@pytest.mark.slow
def test_leave_one_out_is_far_below_previous_in_chaos():
    log_ratio, se = _ratio("leave_one_out", "previous")
    assert log_ratio + Z_CHAOS * se < 0.0


@pytest.mark.slow
def test_the_exact_cross_fit_keeps_the_heavy_tail_in_chaos():
    """An exactly unbiased weight cannot depend on the exploding particle's own future
    (docs/estimators.md, "Choosing k_LR"): the cross-fit is significantly above BIW-LR."""
    log_ratio, se = _ratio("cross_fit", "lr")
    assert log_ratio - Z_CHAOS * se > 0.0


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="measured: leave-one-out is 1.5× BIW-LR's variance in chaos (P = 30 and 100), docs/estimator-variance.md")
def test_leave_one_out_is_not_significantly_above_lr_in_chaos():
    log_ratio, se = _ratio("leave_one_out", "lr")
    assert log_ratio <= Z_CHAOS * se


@pytest.mark.slow
@pytest.mark.parametrize("rule", ["leave_one_out", "cross_fit"])
def test_no_bias_against_lr_is_detected_in_chaos(rule):
    """Paired against BIW-LR on the same particles (both would be unbiased): no coordinate beyond the
    family's two-sided bound. (Leave-one-out's bias is detected only on the linear-Gaussian system at
    R = 40,000, docs/estimator-variance.md; the heavy-tailed cross-fit has little power here.)"""
    d = _chaos()[rule] - _chaos()["lr"]
    z = d.mean(0) / (d.std(0, ddof=1) / np.sqrt(CHAOS_R))
    bound = z_bound(CHAOS_FAMILY, 0.01)
    print(f"{rule} − lr: z = {np.round(z, 2)}, bound {bound:.2f}")
    assert np.max(np.abs(z)) < bound


@pytest.mark.slow
def test_pathwise_messages_bring_tp_below_rp_in_the_smooth_setting():
    """The smooth setting's obstacle is λ-mixing (docs/estimator-variance.md): with the weight on the
    contributions only and the pathwise message passed back, TP ("previous" weights, exactly unbiased)
    is significantly below RP (measured 0.88–0.92×). Same bound as the chaos comparisons."""
    task, model, policy = kicked_rotor_system("smooth")
    ests = {"rp": estimator("rp"), "rp_messages": RP_MESSAGES}
    run = jax.jit(functools.partial(
        paired_replicate_gradients, problem=task, model=model, policy=policy,
        config=RolloutConfig(num_particles=30, model_variance=False), estimators=ests, num_replicates=1000,
    ))
    g = {n: np.asarray(v) for n, v in run(jax.random.PRNGKey(78)).grad.items()}
    log_ratio, se = log_variance_ratio(g["rp_messages"], g["rp"])
    print(f"rp_messages/rp: {np.exp(log_ratio):.3g}, upper bound {np.exp(log_ratio + Z_CHAOS * se):.3g}")
    assert log_ratio + Z_CHAOS * se < 0.0
