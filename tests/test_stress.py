"""Numerical stress suite (the case list, commands and wall times: docs/stress.md).

Every case pushes one setting to an extreme on a small cart-pole GP model (2 random rollouts of
8 steps, 16 transitions; P = 32 particles), or pushes the GP fit itself, and asserts:

1. one jitted policy update leaves θ, the optimizer state and the estimator state finite;
2. the objective is finite;
3. the problem is *reported*, and the report agrees with what was applied: ``info.skipped`` for a
   refused step, ``diagnostics.nonfinite``, the per-step variances ``var_rp``/``var_lr`` and the
   weight ``k_lr`` that total propagation took from them, a ``GPNumericsWarning`` and its
   ``FitInfo`` field, or PILCO's optimizer trace.

The invariants every update must satisfy are in :func:`assert_contained`; each case adds what
its extreme must show. All cases are marked ``stress``; the ones that cost more than a few
compilations are also ``slow`` (out of the default run): ``pytest -m stress`` runs all of them.
Settings that change the compiled program are built once per module (``functools.lru_cache``),
so cases that share an estimator and a rollout configuration share one compiled update.
"""

import dataclasses
import functools
import math
import warnings
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from pipps.gp import GPConfig, GPNumericsWarning, fit, make_data, predict
from pipps.optimizers.normalized import normalized_momentum
from pipps.optimizers.quasi_newton import STOP_GRADIENT, QuasiNewtonConfig
from pipps.particles.forward import RolloutConfig, particle_rollout, sample_noise
from pipps.pilco import PolicySearchConfig, objective, optimize_policy
from pipps.policies import init_rbf_policy
from pipps.propagation.combine import inverse_variance_k
from pipps.propagation.estimators import estimator, thesis_estimator
from pipps.propagation.update import init_policy_opt_state, make_policy_update
from pipps.rollout import rollout, training_pairs
from pipps.tasks.presets import make_task

pytestmark = pytest.mark.stress

P = 32
TASK = make_task("cartpole_swingup", horizon=8)  # 8-step random rollouts for the data; T is set per case
ESTIMATORS = ("rp", "lr", "lr_plain", "tp", "tp_loo", "gtp", "glr", "del", "del_thesis", "del_cost", "gr")  # "gr": RP with Gaussian resampling
# The suite's TP and GTP weigh with k_LR "previous" (on a first iteration: this batch's weight), the
# rule the k_LR assertions below are about; "tp_loo" is the library's TP now
# (leave-one-out weights, one per particle), checked for containment and reporting.
_BUILT = {"gr": lambda: estimator("rp"), "tp": lambda: estimator("tp", k_lr="previous"),
          "gtp": lambda: estimator("gtp", k_lr="previous"), "tp_loo": lambda: estimator("tp"),
          "del_thesis": lambda: thesis_estimator("del")}


def built(name: str):
    """The suite's estimator called ``name``."""
    return _BUILT[name]() if name in _BUILT else estimator(name)


def flat(tree) -> np.ndarray:
    return np.asarray(ravel_pytree(tree)[0])


def all_finite(tree) -> bool:
    return all(np.all(np.isfinite(np.asarray(leaf))) for leaf in jax.tree.leaves(tree))


# -- the model, the policies -------------------------------------------------------------------


@functools.lru_cache(maxsize=None)
def transitions(k: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """GP training pairs of two random 8-step rollouts (observation-noise variance ×k)."""
    task = make_task("cartpole_swingup", horizon=8, k=k)
    pairs = [training_pairs(task, rollout(jax.random.PRNGKey(s), task)) for s in range(2)]
    return np.concatenate([p[0] for p in pairs]), np.concatenate([p[1] for p in pairs])


@functools.lru_cache(maxsize=None)
def base_model():
    """The reference GP: fitted without any guard acting (a warning here would fail every case)."""
    x, y = transitions()
    with warnings.catch_warnings():
        warnings.simplefilter("error", GPNumericsWarning)
        post, _, _ = fit(None, make_data(x, y))
    return post


@functools.lru_cache(maxsize=None)
def policy(variant: str = "base"):
    """8-centre thesis RBF policy with weights ~ 5·N(0, 1) (the thesis init: 0.1·N(0, 1)), so that the
    pendulum swings: with 0.1 the cost stays ≈ 1 and σ²_RP does not grow over 100 steps.

    ``centres_far``: every centre shifted by 100 (the policy input never gets near one);
    ``weights_huge``: weights ×10³ (the saturation sin(π̃) is driven far past its range);
    ``weights_extreme``: weights ×10⁶ (with T = 100, RP's gradient products overflow)."""
    pol = init_rbf_policy(jax.random.PRNGKey(1), 8, np.zeros(4), np.diag([0.1, 1.0, 4.0, 1.0]), TASK.u_max,
                          weight_scale=5.0)
    if variant == "centres_far":
        return dataclasses.replace(pol, centres=pol.centres + 100.0)
    if variant == "weights_huge":
        return dataclasses.replace(pol, weights=pol.weights * 1e3)
    if variant == "weights_extreme":
        return dataclasses.replace(pol, weights=pol.weights * 1e6)
    assert variant == "base"
    return pol


def config(T: int = 30, m: float = 1.0, resampling: str = "none", model_variance: bool = True) -> RolloutConfig:
    return RolloutConfig(num_particles=P, horizon=T, noise_multiplier=m, resampling=resampling,
                         model_variance=model_variance)


# -- one jitted update and what every update must satisfy --------------------------------------


class Outcome(NamedTuple):
    name: str
    old: Any  # PolicyOptState before
    new: Any  # after
    info: Any  # UpdateInfo, on the host


@functools.lru_cache(maxsize=None)
def _programs(name: str, cfg: RolloutConfig):
    """(estimator, jitted init, jitted step) per (estimator, rollout config): compiled once per shape."""
    est = built(name)
    opt = normalized_momentum(1e-2, 0.9)
    init = jax.jit(functools.partial(init_policy_opt_state, problem=TASK, config=cfg, estimator=est, optimizer=opt))
    return est, init, make_policy_update(TASK, cfg, est, opt)


R = 6  # independent keys per case: the chaotic statistics are heavy-tailed across keys (below)


def updates(name: str, cfg: RolloutConfig, pol, model, replicates: int = R) -> tuple[Outcome, ...]:
    """``replicates`` jitted updates from the same start on independent keys (one compiled program)."""
    est, init, step = _programs(name, cfg)
    out = []
    for r in range(replicates):
        old = init(jax.random.PRNGKey(100 + r), pol, model)
        new, info = step(jax.random.PRNGKey(200 + r), old, model)
        out.append(Outcome(name, old, new, jax.device_get(info)))
    return tuple(out)


@functools.lru_cache(maxsize=None)
def base_updates(name: str, T: int = 30, m: float = 1.0, model_variance: bool = True, variant: str = "base"):
    """Updates on the reference model, cached so that cases can compare with each other."""
    cfg = config(T, m, "gaussian" if name == "gr" else "none", model_variance)
    return updates(name, cfg, policy(variant), base_model())


def median(outs, statistic) -> float:
    """Median over replicates of a per-update statistic."""
    return float(np.median([statistic(o) for o in outs]))


def grad_norm(o: Outcome) -> float:
    return float(o.info.grad_norm)


def var_first_step(o: Outcome) -> float:
    """The reported variance of the active part at step 1 (σ²_RP if pathwise, else σ²_LR)."""
    d = o.info.diagnostics
    return float(d.var_rp[0] if np.isfinite(d.var_rp[0]) else d.var_lr[0])


def lr_over_rp(o: Outcome) -> float:
    """Median over steps of the reported σ²_LR/σ²_RP."""
    d = o.info.diagnostics
    return float(np.median(np.asarray(d.var_lr) / np.asarray(d.var_rp)))


def assert_contained(out: Outcome) -> None:
    """(1) finite state, (2) finite objective, (3) a report consistent with what was applied."""
    for path, leaf in jax.tree_util.tree_leaves_with_path(out.new):
        assert np.all(np.isfinite(np.asarray(leaf))), f"{out.name}: non-finite {jax.tree_util.keystr(path)} reached the state"
    info, d = out.info, out.info.diagnostics
    assert np.isfinite(info.value) and np.isfinite(info.particle_objective), f"{out.name}: objective {info.value}"
    est = built(out.name)
    k, var_rp, var_lr, flagged = (np.asarray(a) for a in (d.k_lr, d.var_rp, d.var_lr, d.nonfinite))
    assert np.all((k >= 0.0) & (k <= 1.0)), f"{out.name}: k_lr outside [0, 1]: {k}"
    # a part that is off reports NaN, never a number that could be mistaken for a measurement
    if not est.likelihood_ratio:
        assert np.all(k == 0.0) and np.all(np.isnan(var_lr))
    if not est.pathwise:
        assert np.all(k == 1.0) and np.all(np.isnan(var_rp))
    # a part that is on reports its variance at every step; where it is not finite, the step either
    # moved all weight to the other part (total propagation) or was flagged and the update refused
    for on, var, weight_elsewhere in ((est.pathwise, var_rp, 1.0), (est.likelihood_ratio, var_lr, 0.0)):
        if not on:
            continue
        bad = ~np.isfinite(var)
        if est.total_propagation:
            assert np.all((k[bad] == weight_elsewhere) | flagged[bad]), f"{out.name}: a non-finite part kept weight"
        else:
            assert not bad.any() or bool(info.skipped), f"{out.name}: non-finite variance at steps {np.nonzero(bad)[0]}, step applied"
    if flagged.any():
        assert bool(info.skipped), f"{out.name}: steps {np.nonzero(flagged)[0]} flagged non-finite, update applied"
    if bool(info.skipped):  # refused: the reason is visible, and nothing moved
        bad_var = (est.pathwise and not np.all(np.isfinite(var_rp))) or (est.likelihood_ratio and not np.all(np.isfinite(var_lr)))
        assert bad_var or flagged.any() or not np.isfinite(info.grad_norm), \
            f"{out.name}: update refused with no non-finite gradient, variance or flag reported"
        np.testing.assert_array_equal(flat(out.new.policy), flat(out.old.policy))
        np.testing.assert_array_equal(flat(out.new.opt_state), flat(out.old.opt_state))
    else:
        assert np.isfinite(info.grad_norm)


def contained(outs) -> tuple[Outcome, ...]:
    for o in outs:
        assert_contained(o)
    return outs


# -- noise multipliers 1e-4 … 100 (the −σ_f rollout, so that s² = σ_n²·m exactly) --------------


@pytest.mark.parametrize("m", [1e-4, pytest.param(1e-2, marks=pytest.mark.slow), pytest.param(1.0, marks=pytest.mark.slow),
                               pytest.param(100.0, marks=pytest.mark.slow)])
def test_noise_multiplier(m):
    """s = σ_n·√m from 10⁻² σ_n to 10 σ_n. LR's score (x − μ)/s² grows as s shrinks: its variance is
    reported, and TP's weight follows the reported variances (k_LR = σ²_RP/(σ²_RP + σ²_LR)).

    The ratio is heavy-tailed across keys (m = 10⁻⁴: from 11 to 7·10⁵ over six keys)."""
    outs = contained(base_updates("tp", 30, m, model_variance=False))
    for o in outs:
        d = o.info.diagnostics
        np.testing.assert_allclose(d.k_lr, inverse_variance_k(d.var_rp, d.var_lr), rtol=1e-12)  # 1st iteration: batch k
    ratio = median(outs, lr_over_rp)
    if m == 1e-4:
        k = median(outs, lambda o: np.median(o.info.diagnostics.k_lr))
        assert ratio > 100.0, f"median σ²_LR/σ²_RP = {ratio:.3g}: s = 10⁻² σ_n should make LR the noisy part"
        assert k < 0.05, f"median k_LR = {k:.3g}: the weight should be on RP"
    else:
        tiny = median(base_updates("tp", 30, 1e-4, model_variance=False), lr_over_rp)
        assert ratio < tiny / 10.0, f"median σ²_LR/σ²_RP = {ratio:.3g} at m = {m:g} vs {tiny:.3g} at m = 1e-4"


# -- long horizons: deep chaos ------------------------------------------------------------------


@pytest.mark.parametrize("T", [pytest.param(30, marks=pytest.mark.slow), pytest.param(60, marks=pytest.mark.slow), 100])
def test_horizon_rp_variance_growth_is_reported(T):
    """RP differentiates through T model Jacobians: its per-step variance σ²_RP at step 1 reports
    the growth (over the six keys, T = 30: 3.7 to 2.8·10⁴; T = 100: 6.8·10⁶ to 4·10¹⁶)."""
    outs = contained(base_updates("rp", T))
    v = median(outs, var_first_step)
    assert np.isfinite(v) and v > 0.0
    v30 = median(base_updates("rp", 30), var_first_step)
    if T > 30:
        assert v > 10.0 * v30, f"median σ²_RP(step 1) = {v:.3g} at T = {T}, {v30:.3g} at T = 30"
    if T == 100:
        assert v > 1e5 * v30, f"median σ²_RP(step 1) = {v:.3g} at T = 100, {v30:.3g} at T = 30: no deep chaos"


@pytest.mark.parametrize("name", [n if n == "tp" else pytest.param(n, marks=pytest.mark.slow) for n in ESTIMATORS if n != "rp"])
def test_every_estimator_at_horizon_100(name):
    """The same deep chaos for LR, plain LR, TP, GTP, GLR, the three DELs and GR: contained and reported.

    An LR part (the library's DEL is one; or GR's one Gaussian refit per step) keeps the gradient two
    or more orders of magnitude below RP's; the whole-chain DELs (the thesis preset's and DEL_c), whose
    density-gradient runs down the pathwise chain, explode like RP's and report it in their variance. TP: where σ²_RP ≫ σ²_LR nearly
    all weight went to LR."""
    outs = contained(base_updates(name, 100))
    if name in ("del_thesis", "del_cost"):
        v, v30 = median(outs, var_first_step), median(base_updates("rp", 30), var_first_step)
        assert v > 1e5 * v30, f"DEL: median σ²(step 1) = {v:.3g} vs RP's {v30:.3g} at T = 30"
    else:
        g, g_rp = median(outs, grad_norm), median(base_updates("rp", 100), grad_norm)
        assert g < 1e-2 * g_rp, f"{name}: median ‖g‖ = {g:.3g}, RP's {g_rp:.3g}"
    if name in ("tp", "gtp"):
        for o in outs:
            d = o.info.diagnostics
            rp_worse = np.asarray(d.var_rp) > 100.0 * np.asarray(d.var_lr)
            assert np.all(np.asarray(d.k_lr)[rp_worse] > 0.99)


@pytest.mark.slow
@pytest.mark.parametrize("name", ESTIMATORS)
def test_overflowing_pathwise_gradient_is_refused_and_reported(name):
    """Deep chaos (T = 100) with a policy gain ×10⁶: the pathwise chains of RP, GR and the thesis' DEL reach
    ‖g‖ ~ 10¹⁰⁵–10¹⁵⁰ or overflow; where their variance or gradient overflows the update is refused
    (``info.skipped``, θ kept) and σ²_RP reports the overflow. Every method with an LR part stays
    finite and is applied (TP and GTP restart RP's chain at every step)."""
    outs = contained(base_updates(name, 100, variant="weights_extreme"))
    skipped = [bool(o.info.skipped) for o in outs]
    est = built(name)
    if est.likelihood_ratio:
        assert not any(skipped), f"{name}: skipped {skipped}"
        assert all(np.isfinite(grad_norm(o)) for o in outs)
    else:
        assert any(skipped), f"{name}: no replicate overflowed; the case provokes nothing"  # the case bites
        for o in outs:
            if bool(o.info.skipped):
                d = o.info.diagnostics
                assert np.any(~np.isfinite(d.var_rp)) or np.any(d.nonfinite), f"{name}: refused without a report"


# -- float32 rollout against float64 ------------------------------------------------------------


@pytest.mark.parametrize("T", [30, pytest.param(100, marks=pytest.mark.slow)])
def test_float32_rollout_against_float64(T):
    """Model, policy and noise cast to float32: the rollout stays float32 and finite. The two do NOT
    agree beyond the objective: the RP-gradient difference is printed (-rP), not asserted (measured,
    T = 30 / 100: objective 7.5·10⁻⁴ / 1.1·10⁻³ relative, gradient 1.0 / 1.8 relative; the states
    differ by 1.2·10⁻³ after one step — the GP mean βᵀk cancels — and the chaos does the rest)."""
    cfg = config(T)
    f32 = lambda tree: jax.tree.map(lambda a: a.astype(jnp.float32), tree)  # noqa: E731
    noise, pol, model = sample_noise(jax.random.PRNGKey(3), TASK, cfg), policy(), base_model()

    def objective_and_record(p, mo, n):
        rec = particle_rollout(TASK, p, mo, n, cfg, jacobian=False)
        return rec.objective, rec

    vg = jax.jit(jax.value_and_grad(objective_and_record, has_aux=True))  # RP gradient (jax.grad of J)
    (J64, _), g64 = vg(pol, model, noise)
    (J32, rec), g32 = vg(f32(pol), f32(model), f32(noise))
    assert rec.x_next.dtype == jnp.float32 and rec.std.dtype == jnp.float32 and all_finite(rec)
    g64, g32 = flat(g64), flat(g32)
    assert g32.dtype == np.float32 and np.all(np.isfinite(g32)) and np.isfinite(float(J32))
    rel_J = abs(float(J32) - float(J64)) / abs(float(J64))
    rel_g = float(np.linalg.norm(g32 - g64) / np.linalg.norm(g64))
    print(f"float32 vs float64, T = {T}: objective rel {rel_J:.3g}, RP gradient rel {rel_g:.3g}")  # shown by -rP
    assert rel_J < 1e-2, f"objective float32 {float(J32)!r} vs float64 {float(J64)!r}: rel {rel_J:.3g} (gradient: rel {rel_g:.3g})"
    if T == 30:  # one jitted update from the float32-cast policy and model (estimate draws float64 noise)
        contained(updates("tp", cfg, f32(pol), f32(model), replicates=1))


# -- GP data: repeated inputs, near-zero noise, huge targets ------------------------------------


@pytest.mark.slow  # the fit's own repeated-inputs test (tests/test_gp.py) runs by default
def test_gp_repeated_inputs_are_reported():
    """Every transition twice: no guard acts, but σ_n collapses — fit must say so."""
    x, y = transitions()
    with pytest.warns(GPNumericsWarning, match="16 training inputs repeat an earlier input exactly"):
        post, _, info = fit(None, make_data(np.concatenate([x, x]), np.concatenate([y, y])))
    assert info.duplicate_inputs == (16, 16)
    assert all_finite(post)
    shrink = np.exp(np.asarray(base_model().hyper.log_noise - post.hyper.log_noise))
    assert np.all(shrink > 50.0), f"σ_n(base)/σ_n(repeated) = {shrink}"  # the problem the warning is about
    contained(updates("tp", config(30), policy(), post, replicates=2))


def test_gp_near_zero_noise_hits_the_noise_floor():
    """Noise-free observations (k = 0) of state changes 10⁴× smaller: σ_n wants to go below the 10⁻⁶
    floor; the floor acts and is reported per output."""
    x, y = transitions(0.0)
    with pytest.warns(GPNumericsWarning, match="noise floor"):
        post, _, info = fit(None, make_data(x, 1e-4 * y))
    assert info.hyper.noise_floored.tolist() == [True] * 4
    np.testing.assert_allclose(np.asarray(post.hyper.log_noise), math.log(GPConfig().noise_floor), atol=1e-12)
    assert all_finite(post)
    mean, var = predict(post, jnp.asarray(x), variance=True)
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(var))
    contained(updates("tp", config(30), policy(), post, replicates=2))


def test_gp_huge_targets_are_scale_equivariant():
    """Targets ×10⁶: the initialisation and the penalties are scale-free, so the fit is the base fit
    with σ_f, σ_n ×10⁶ (to the optimizer's rounding) — nothing to report, and nothing must be
    reported (a guard acting here would be a false alarm)."""
    x, y = transitions()
    with warnings.catch_warnings():
        warnings.simplefilter("error", GPNumericsWarning)
        post, _, info = fit(None, make_data(x, 1e6 * y))
    assert info.messages == ()
    base = base_model()
    np.testing.assert_allclose(post.hyper.log_lengthscale, base.hyper.log_lengthscale, atol=1e-5)
    np.testing.assert_allclose(post.hyper.log_signal - base.hyper.log_signal, math.log(1e6), atol=1e-5)
    np.testing.assert_allclose(post.hyper.log_noise - base.hyper.log_noise, math.log(1e6), atol=1e-5)
    assert all_finite(post)
    contained(updates("tp", config(30), policy(), post, replicates=2))


# -- policy parameters far outside the data -----------------------------------------------------


def test_policy_centres_far_outside_give_a_zero_gradient_reported():
    """Centres 100 away: every RBF is exp(−10⁴…) = 0, the control is 0 and so is the gradient —
    exactly. Reported as grad_norm = 0; the normalized step is 0/√(0 + 0) := 0 (θ unchanged, not
    skipped)."""
    for o in contained(base_updates("tp", 30, variant="centres_far")):
        assert not bool(o.info.skipped) and float(o.info.grad_norm) == 0.0
        np.testing.assert_array_equal(flat(o.new.policy), flat(o.old.policy))


@pytest.mark.slow
def test_policy_weights_huge():
    """Weights ×10³: sat(π̃) = (9 sin π̃ + sin 3π̃)/8 oscillates wildly across the particles; RP's
    per-particle gradients grow with the weights, which σ²_RP reports."""
    outs = contained(base_updates("tp", 30, variant="weights_huge"))
    v, v_base = median(outs, var_first_step), median(base_updates("tp", 30), var_first_step)
    assert v > 100.0 * v_base, f"median σ²_RP(step 1) = {v:.3g}, {v_base:.3g} with the base weights"


# -- PILCO --------------------------------------------------------------------------------------


PILCO_SEARCH = PolicySearchConfig(optimizer=QuasiNewtonConfig(length=-6, max_evals_per_linesearch=5), horizon=30)


@functools.lru_cache(maxsize=None)
def pilco_value_and_grad(H: int):
    return jax.jit(jax.value_and_grad(lambda p, mo: objective(TASK, p, mo, horizon=H)))


@pytest.mark.slow
@pytest.mark.parametrize("H", [30, 100])
def test_pilco_objective_and_gradient_at_long_horizons(H):
    J, g = pilco_value_and_grad(H)(policy(), base_model())
    assert np.isfinite(float(J)) and all_finite(g)
    assert 0.0 < float(J) <= H and np.linalg.norm(flat(g)) > 0.0


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["centres_far", "weights_huge"])
def test_pilco_dead_gradient_is_reported_by_the_optimizer(variant):
    """Centres far away: the controller is 0. Weights ×10³: the moment-matched E[sin π̃] carries
    exp(−Var[π̃]/2) = 0. Either way J is finite and ∇J is exactly 0; optimize_policy reports it as
    stop reason STOP_GRADIENT after its single evaluation and returns the start policy."""
    pol = policy(variant)
    J, g = pilco_value_and_grad(30)(pol, base_model())
    assert np.isfinite(float(J)) and np.all(flat(g) == 0.0)
    best, trace = optimize_policy(TASK, base_model(), pol, PILCO_SEARCH)
    assert int(trace.stop_reason) == STOP_GRADIENT and int(trace.num_evaluations) == 1
    assert float(trace.grad_norm) == 0.0
    np.testing.assert_array_equal(flat(best), flat(pol))


@pytest.mark.slow
def test_pilco_optimize_policy_small_budget():
    """Six evaluations of the quasi-Newton search from the swinging policy: finite, never worse, and
    the returned value is the objective at the returned policy."""
    best, trace = optimize_policy(TASK, base_model(), policy(), PILCO_SEARCH)
    assert all_finite(best)
    assert np.isfinite(float(trace.value)) and float(trace.value) <= float(trace.value_init)
    assert int(trace.num_evaluations) <= 6
    J, _ = pilco_value_and_grad(30)(best, base_model())
    assert float(J) == pytest.approx(float(trace.value), rel=1e-10)
