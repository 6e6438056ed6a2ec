"""Variance of the gradient estimators on a chaotic system (docs/estimator-variance.md).

System: the controlled kicked rotor (Chirikov standard map) of :mod:`pipps.systems.chaotic`,
``"chaotic"`` (K = 2, T = 30: RP's variance ~10¹⁰–10¹¹) and ``"smooth"`` (K = 0.1, T = 30).
For each P, R independent replicates of every estimator on common random numbers
(:func:`~pipps.stats.paired_replicate_gradients`; BIW-LR gets its "previous" baseline from an
independent extra rollout, TP its "previous" k_LR from an independent earlier estimate). The
variance of an estimator is the trace of the covariance of its R estimates.

Claims (thesis §4.4.1, Fig. 4.13, and that TP should do no worse than its parts):

* BIW-LR's variance is below plain LR's — asserted as *significantly* below;
* TP's variance is at most ``min(RP, BIW-LR)`` up to sampling error — asserted as *not
  significantly above* either. This fails for the library's TP (k_LR from the previous iteration)
  by orders of magnitude in the chaotic setting, and for every TP in the smooth setting; those
  cases are ``xfail(strict=True)`` with the measured numbers in docs/estimator-variance.md. The
  thesis' TP (k_LR from the same batch, biased) satisfies it in the chaotic setting.

The bound (no hand-tuned δ). The trace variance is a mean over replicates of the squared
deviations ``d_r = ‖g_r − ḡ‖²``, so ``log(V̂_a/V̂_b)`` is asymptotically normal with a standard
error estimated from the paired ``d``'s (delta method, :func:`~pipps.stats.log_variance_ratio`).
That SE uses the empirical fourth moments and the pairing of estimators on the same particles;
an F- or χ²-bound would instead assume Gaussian, independent estimates, and both assumptions are
false here (RP's and TP's gradients are heavy-tailed; the estimators share particles), which makes
the F-test badly anti-conservative (Box 1953). With ``z`` the one-sided normal quantile at a
family-wise level ``ALPHA`` Bonferroni-split over the ``FAMILY`` comparisons of this file,

* "a < b" passes iff ``log(V̂_a/V̂_b) + z·SE < 0`` (the upper confidence bound of the ratio is < 1);
* "a ≤ b (1 + δ)" passes iff ``V̂_a/V̂_b ≤ exp(z·SE) =: 1 + δ`` (no significant excess).

So a correct estimator fails a test with probability ≤ ALPHA over the whole file (asymptotically),
and :func:`test_the_comparison_has_power` shows that a 1.6× variance difference is detected.
Where a variance has effectively no finite fourth moment (RP in the chaotic setting) the SE is not
reliable, but those comparisons are decided by 8 or more orders of magnitude.
"""

import dataclasses
import functools

import direct_sweep
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from pipps.particles.forward import RolloutConfig, particle_rollout, sample_noise
from pipps.propagation.estimators import estimator
from pipps.propagation.estimate import estimate, init_estimator_state
from pipps.stats import log_variance_ratio, paired_replicate_gradients, trace_variance, z_bound
from pipps.systems.chaotic import finite_time_lyapunov, kicked_rotor_system

# Replicates per P: enough that a 1.5× variance ratio is resolved at the family-wise level
# (SE of a log variance ratio ≈ 1–1.8/√R here; P = 300 is slow, O(P²) BIW weights).
R = {30: 1000, 100: 400, 300: 400}
ALPHA = 0.01  # family-wise level of all variance comparisons below
FAMILY = 21  # 4 (setting, P) cells × (1 BIW-vs-plain + 2 TP + 2 thesis-TP comparisons) + the smooth RP contrast
Z = z_bound(FAMILY, ALPHA, two_sided=False)  # ≈ 3.30

ESTIMATORS = {
    "rp": estimator("rp"),
    "lr_plain": estimator("lr_plain"),
    "lr": estimator("lr"),  # BIW-LR, "previous" baseline
    "tp": estimator("tp", k_lr="previous"),  # the library default before leave-one-out
    "tp_batch": estimator("tp", k_lr="batch"),  # the thesis' k_LR (biased, docs/estimator-bias.md)
}

TP_XFAIL = (
    "measured: TP with k_LR from an independent earlier batch cannot down-weight a batch whose "
    "pathwise gradients explode (heavy tails): TP/BIW-LR is 10 to 10⁷ — docs/estimator-variance.md"
)
SMOOTH_XFAIL = (
    "measured: in the smooth setting TP's variance is 1.2–3× RP's (P = 10–300): per-step inverse-variance "
    "weights ignore that λ-mixing feeds LR noise into the earlier pathwise terms — docs/estimator-variance.md"
)


@functools.lru_cache(maxsize=None)
def replicates(setting: str, P: int):
    task, model, policy = kicked_rotor_system(setting)
    cfg = RolloutConfig(num_particles=P, model_variance=False)  # zero epistemic variance: skip it
    run = jax.jit(
        functools.partial(
            paired_replicate_gradients, problem=task, model=model, policy=policy, config=cfg,
            estimators=ESTIMATORS, num_replicates=R[P],
        )
    )
    out = run(jax.random.PRNGKey(2024 + P))
    return {name: np.asarray(g) for name, g in out.grad.items()}


def significantly_less(g_a, g_b) -> tuple[bool, float, float]:
    """(V_a < V_b at level ALPHA/FAMILY, ratio V̂_a/V̂_b, its upper confidence bound)."""
    log_ratio, se = log_variance_ratio(g_a, g_b)
    upper = np.exp(log_ratio + Z * se)
    return bool(upper < 1.0), float(np.exp(log_ratio)), float(upper)


def not_significantly_greater(g_a, g_b) -> tuple[bool, float, float]:
    """(V_a ≤ V_b (1 + δ), ratio V̂_a/V̂_b, 1 + δ = exp(z·SE))."""
    log_ratio, se = log_variance_ratio(g_a, g_b)
    bound = np.exp(Z * se)
    return bool(np.exp(log_ratio) <= bound), float(np.exp(log_ratio)), float(bound)


def assert_tp_at_most_min(g, name):
    for other in ("rp", "lr"):
        ok, ratio, bound = not_significantly_greater(g[name], g[other])
        assert ok, (
            f"Var[{name}]/Var[{other}] = {ratio:.4g} > 1 + δ = {bound:.4g} "
            f"(Var {name} {trace_variance(g[name]):.4g}, {other} {trace_variance(g[other]):.4g})"
        )


CELLS = [
    pytest.param("chaotic", 30, id="chaotic-P30"),
    pytest.param("chaotic", 100, id="chaotic-P100"),
    pytest.param("chaotic", 300, id="chaotic-P300", marks=pytest.mark.slow),
    pytest.param("smooth", 30, id="smooth-P30"),
]


def test_kicked_rotor_rollout_is_the_controlled_standard_map():
    """Without noise the particle rollout is p' = p + K sin θ + u, θ' = θ + p' (NumPy loop)."""
    task, model, policy = kicked_rotor_system("chaotic", horizon=6)
    model = dataclasses.replace(model, noise_var=jnp.zeros(2))
    cfg = RolloutConfig(num_particles=4, model_variance=False)
    noise = sample_noise(jax.random.PRNGKey(5), task, cfg)
    rec = particle_rollout(task, policy, model, noise, cfg, jacobian=False)
    W, b, u_max = np.asarray(policy.W)[0], float(policy.b[0]), policy.u_max[0]
    theta, p = np.asarray(noise.x0[:, 0]), np.asarray(noise.x0[:, 1])
    for t in range(6):
        w = W @ np.stack([p, np.sin(theta), np.cos(theta)]) + b
        u = u_max * (9 * np.sin(w) + np.sin(3 * w)) / 8
        p = p + 2.0 * np.sin(theta) + u
        theta = theta + p
        np.testing.assert_allclose(np.asarray(rec.x_next[t]), np.stack([theta, p], axis=-1), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.asarray(rec.cost[t]), 1 - np.exp(-(p**2 / 2 + 1 - np.cos(theta))), rtol=1e-12)


def _direct_tp(task, model, policy, noise, k, weighting, baseline):
    """Thesis Alg. 5 written as plain loops over t and i, for a constant k_LR."""
    f = direct_sweep.forward(task, model, policy, noise)
    dzeta_dx, dzeta_dth, dcost = direct_sweep.through_policy(task, f)
    P, T, D = noise.x0.shape[0], noise.eps.shape[0], task.model_dim
    lam, grad = np.zeros((P, 2 * D)), np.zeros(f.theta.size)
    for t, x, mu, sd, G in direct_sweep.backward_steps(task, f):
        w = direct_sweep.biw_weights(x, mu, sd) if weighting == "biw" else np.eye(P)
        new_lam, g = np.zeros((P, 2 * D)), np.zeros(f.theta.size)
        for i in range(P):
            a = np.asarray(dcost(x[i]))
            if t < T:
                a = a + lam[i] @ np.asarray(dzeta_dx(x[i], f.theta))
            gam_rp = np.concatenate([a, a * np.asarray(noise.eps[t - 1][i])])
            b = (G.sum() - G[i]) / (P - 1) if weighting == "plain" else baseline[t - 1]
            gam_lr = direct_sweep.lr_zeta(i, w, G, b, x, mu, sd)
            dzeta_dtheta = np.asarray(dzeta_dth(f.xs[t - 1][i], f.theta))
            g += (k * gam_lr + (1 - k) * gam_rp) @ dzeta_dtheta / P
            new_lam[i] = k * gam_lr + (1 - k) * gam_rp
        grad, lam = grad + g, new_lam
    return grad


@pytest.mark.parametrize("weighting", ["plain", "biw"])
def test_tp_with_an_intermediate_constant_k_matches_a_direct_loop(weighting):
    """The variance findings are about Alg. 5 itself, not the sweep: for 0 < k < 1 (which the
    exactness tests do not cover) the sweep equals a direct loop of Alg. 5."""
    task, model, policy = kicked_rotor_system("chaotic", horizon=4)
    cfg = RolloutConfig(num_particles=5, model_variance=False)
    est = estimator("tp", weighting=weighting, k_lr=0.3)
    state = init_estimator_state(jax.random.PRNGKey(9), policy, model, problem=task, config=cfg, estimator=est)
    _, e = estimate(jax.random.PRNGKey(3), state, policy, model, problem=task, config=cfg, estimator=est)
    noise = sample_noise(jax.random.PRNGKey(3), task, cfg)
    # plain LR uses the leave-one-out baseline (no memory: its state is ()); BIW the previous mean return
    baseline = None if weighting == "plain" else np.asarray(state.parts[1].mean_return)
    ref = _direct_tp(task, model, policy, noise, 0.3, weighting, baseline)
    got = np.asarray(ravel_pytree(e.grad)[0])
    assert np.linalg.norm(ref) > 1e-3
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max())


def test_lyapunov_exponents_separate_the_settings():
    """The chaotic setting stretches almost every particle's tangent; the smooth one does not."""
    lam = {}
    for setting in ("chaotic", "smooth"):
        task, model, policy = kicked_rotor_system(setting)
        lam[setting] = np.asarray(finite_time_lyapunov(jax.random.PRNGKey(0), task, model, policy, num_particles=500))
    assert np.median(lam["chaotic"]) > 0.05 and np.quantile(lam["chaotic"], 0.1) > 0.0
    assert abs(np.median(lam["smooth"])) < 0.02
    assert np.median(lam["chaotic"]) > 5 * abs(np.median(lam["smooth"]))


def test_rp_variance_explodes_only_in_the_chaotic_setting():
    chaotic, smooth = replicates("chaotic", 30), replicates("smooth", 30)
    # chaos: RP's variance is many orders of magnitude above both LR estimators'
    assert trace_variance(chaotic["rp"]) > 1e6 * trace_variance(chaotic["lr_plain"])
    # contrast: without chaos RP is the lowest-variance estimator
    ok, ratio, upper = significantly_less(smooth["rp"], smooth["lr"])
    assert ok, f"smooth: Var[rp]/Var[lr] = {ratio:.3g}, upper bound {upper:.3g}"


@pytest.mark.parametrize("setting, P", CELLS)
def test_biw_lr_variance_below_plain_lr(setting, P):
    g = replicates(setting, P)
    ok, ratio, upper = significantly_less(g["lr"], g["lr_plain"])
    assert ok, f"Var[BIW-LR]/Var[plain LR] = {ratio:.3g}, upper confidence bound {upper:.3g} (not < 1)"


def _xfail_cells(reason_chaotic, reason_smooth):
    marks = {"chaotic": reason_chaotic, "smooth": reason_smooth}
    cells = []
    for cell in CELLS:
        setting = cell.values[0]
        extra = [pytest.mark.xfail(strict=True, reason=marks[setting])] if marks[setting] else []
        cells.append(pytest.param(*cell.values, id=cell.id, marks=[*cell.marks, *extra]))
    return cells


@pytest.mark.parametrize("setting, P", _xfail_cells(TP_XFAIL, SMOOTH_XFAIL))
def test_tp_variance_at_most_min_of_rp_and_biw_lr(setting, P):
    """The library's TP (k_LR from the previous iteration): the claim above."""
    assert_tp_at_most_min(replicates(setting, P), "tp")


@pytest.mark.parametrize("setting, P", _xfail_cells(None, SMOOTH_XFAIL))
def test_thesis_tp_variance_at_most_min_of_rp_and_biw_lr(setting, P):
    """The thesis' TP (k_LR from the same batch) meets the claim in the chaotic setting."""
    assert_tp_at_most_min(replicates(setting, P), "tp_batch")


def test_the_comparison_has_power():
    """The same bound rejects a claim that is false by a factor of ~1.6."""
    g = replicates("chaotic", 30)
    ok, ratio, bound = not_significantly_greater(g["lr_plain"], g["lr"])
    assert ratio > 1.3 and not ok, (ratio, bound)
