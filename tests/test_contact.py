"""Suh et al.'s contact examples (pipps.systems.contact) and the estimators on them, against closed forms.

* **The closed forms are right.** The Heaviside's and the relaxation's ``F`` and ``∇F`` against the
  quadrature of :func:`~pipps.systems.contact.base.smoothed`, ``∇F`` against central differences of
  ``F``, and ``F`` against a 10⁶-sample Monte Carlo mean of ``f``.
* **Estimators against them.** On the Heaviside every FoBG estimate and its within-batch variance are
  exactly 0 while ∇F is not; ZoBG's mean is within ``|z| < 4`` of the exact gradient on the Heaviside,
  the relaxation and the throw; FoBG's bias at the throw's wall is detected at family-wise α = 10⁻³;
  the relaxation's FoBG, Lipschitz, is unbiased.
* **AoBG's bound (000 Lemma 4.3).** Where the ZoBG's confidence radius is within γ, AoBG's error is
  within γ in at least the fraction δ = 1 − 1/z² of batches (less three binomial standard errors).
* **The contact models.** The implicit step never lets the pusher through the box, the barrier keeps
  a positive gap and tends to the implicit step as κ grows; Fig. 6's closed forms; the penalty model's
  pathwise gradient equals central differences of its fixed-noise objective.
* **MJX.** The ball scene's forward-mode gradient in free flight equals the analytic one and central
  differences (its reverse mode is refused by MJX's solver loop, which the docs quote).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from pipps.particles.forward import RolloutConfig, reparameterized_objective, sample_noise
from pipps.stats import z_bound
from pipps.studies.contact import estimators, replicate_estimates, summarise
from pipps.systems.contact import base, fig1, heaviside, pushing


def test_heaviside_closed_form_against_quadrature_and_monte_carlo():
    for th in (-1.0, 0.3, 2.0):
        F, dF = heaviside.heaviside_exact(th, 0.7)
        Fq, dFq, err = base.smoothed(lambda v: float(v >= 0), th, 0.7, breaks=(0.0,))
        assert abs(F - Fq) < 1e-9 and abs(dF - dFq) < 1e-9 and err < 1e-9
    w = np.random.default_rng(0).standard_normal(1_000_000)
    F, _ = heaviside.heaviside_exact(0.3, 0.7)
    assert abs(np.mean(0.3 + 0.7 * w >= 0) - F) < 4 * 0.5 / 1000


@pytest.mark.parametrize("nu, theta", [(0.1, 0.05), (1.0, -0.4), (0.01, 0.3)])
def test_relaxed_closed_form(nu, theta):
    sigma = 0.8
    F, dF = heaviside.relaxed_exact(theta, sigma, nu)
    f = heaviside.Relaxed(jnp.asarray(nu))
    fn = lambda v: float(np.asarray(f.step(None, jnp.asarray([v])))[0])  # noqa: E731
    Fq, dFq, _ = base.smoothed(fn, theta, sigma, breaks=(-0.5 * nu, 0.5 * nu))
    assert abs(F - Fq) < 1e-9 and abs(dF - dFq) < 1e-8
    h = 1e-5
    fd = (heaviside.relaxed_exact(theta + h, sigma, nu)[0] - heaviside.relaxed_exact(theta - h, sigma, nu)[0]) / (2 * h)
    assert abs(fd - dF) < 1e-7


def _z(reps, name, exact):
    s = reps[name]
    return np.abs(s.grad.mean(0) - exact) / (s.grad.std(0, ddof=1) / math.sqrt(s.grad.shape[0]))


def test_heaviside_fobg_is_exactly_zero_and_zobg_unbiased():
    ex = heaviside.heaviside(0.5, 1.0)
    dF = heaviside.heaviside_exact(0.5, 1.0)[1]
    reps = replicate_estimates(ex, estimators(0.2), 50, 400, jax.random.PRNGKey(0))
    assert dF > 0.3
    assert np.all(reps["FoBG"].grad == 0.0) and np.all(reps["FoBG"].empirical == 0.0)
    assert np.all(reps["TP"].grad == 0.0)  # the inverse-variance weight puts everything on the zero-variance FoBG
    assert np.all(reps["TP"].k_lr == 0.0)
    assert _z(reps, "ZoBG", dF).max() < 4.0


def test_fobg_bias_at_the_throws_wall_is_detected_and_zobg_is_not_biased():
    ex = fig1.throw()
    _, dF, err = ex.exact(ex.policy)
    assert err < 1e-7 * abs(dF[0]) and abs(dF[0]) > 1.0
    reps = replicate_estimates(ex, estimators(0.5), 50, 200, jax.random.PRNGKey(1))
    assert _z(reps, "FoBG", dF).max() > z_bound(1, 1e-3)
    assert _z(reps, "ZoBG", dF).max() < 4.0


def test_relaxed_fobg_is_unbiased():
    ex = heaviside.relaxed(0.5, theta=0.1, sigma=1.0)
    dF = heaviside.relaxed_exact(0.1, 1.0, 0.5)[1]
    reps = replicate_estimates(ex, estimators(0.2), 100, 400, jax.random.PRNGKey(2))
    assert _z(reps, "FoBG", dF).max() < 4.0 and _z(reps, "ZoBG", dF).max() < 4.0


def test_aobg_error_within_gamma_with_probability_delta():
    gamma, z, N = 0.2, 2.0, 100
    ex = heaviside.heaviside(0.5, 1.0)
    dF = np.array([heaviside.heaviside_exact(0.5, 1.0)[1]])
    reps = replicate_estimates(ex, estimators(gamma, z), N, 400, jax.random.PRNGKey(3))
    eps = z * np.sqrt(np.sum(reps["ZoBG"].empirical, axis=1) / N)
    feasible = eps <= gamma
    assert feasible.sum() > 300
    covered = np.mean(np.linalg.norm(reps["AoBG"].grad - dF, axis=1)[feasible] <= gamma)
    delta = 1 - 1 / z**2
    assert covered >= delta - 3 * math.sqrt(delta * (1 - delta) / feasible.sum())
    # and the bound binds: AoBG is neither ZoBG nor FoBG (its weight on LR is strictly inside (0, 1))
    assert 0.0 < float(np.mean(reps["AoBG"].k_lr)) < 1.0
    assert summarise(reps["AoBG"], dF, N)["bias_norm"] < summarise(reps["FoBG"], dF, N)["bias_norm"]


def test_implicit_and_barrier_steps_keep_the_bodies_apart():
    rng = np.random.default_rng(4)
    for model in ("implicit", "barrier"):
        sim = pushing.Pushing(model=model, kappa=jnp.asarray(1e3))
        x = jnp.array([0.0, 0.0, 0.0, 0.02, 0.0])
        for u in rng.uniform(-20.0, 40.0, 60):
            x = sim.step(x, jnp.array([u]))
            gap = float(x[3] - x[1])
            assert gap > 0 if model == "barrier" else gap >= -1e-12
    u = jnp.linspace(-2, 2, 9)
    implicit = pushing.wall_step("implicit", u)
    assert np.allclose(implicit, np.maximum(0.1 * np.asarray(u), 0.0))
    assert np.allclose(pushing.wall_step("barrier", u, kappa=1e8), implicit, atol=1e-4)
    assert np.all(np.asarray(pushing.wall_step("barrier", u, kappa=10.0)) > implicit)
    assert np.all(np.asarray(pushing.wall_step("penalty", u))[:4] < 0)  # the penalty step lets the mass into the wall


def test_penalty_pushing_pathwise_gradient_equals_finite_differences():
    ex = pushing.pushing("penalty", stiffness=300.0)
    cfg = RolloutConfig(num_particles=4, action_noise=ex.action_noise)
    noise = sample_noise(jax.random.PRNGKey(5), ex.problem, cfg)
    J = jax.jit(lambda p: reparameterized_objective(ex.problem, p, ex.simulator, noise, cfg))
    g = np.asarray(ravel_pytree(jax.grad(J)(ex.policy))[0])
    flat, unravel = ravel_pytree(ex.policy)
    h = 1e-6
    for i in (0, 10, 25, 39):
        e = jnp.zeros_like(flat).at[i].set(h)
        fd = (float(J(unravel(flat + e))) - float(J(unravel(flat - e)))) / (2 * h)
        assert abs(fd - g[i]) < 1e-6 * max(1.0, abs(g[i])) + 1e-8


def test_mjx_ball_gradient_in_free_flight_equals_analytic_and_finite_differences():
    from pipps.systems.contact import mjx_scenes

    theta = math.radians(60.0)
    ex = mjx_scenes.ball(False, steps=60, timestep=0.01)  # 0.6 s: the ball clears the wall without touching it
    x0 = jnp.zeros(4)
    final_x = jax.jit(lambda u: ex.simulator.step(x0, u)[0])
    grad = jax.jit(jax.jacfwd(lambda u: ex.simulator.step(x0, u)[0]))
    x, dx = mjx_scenes.free_flight_x(theta, time=0.6)
    u = jnp.array([theta])
    assert float(final_x(u)) == pytest.approx(x, abs=1e-9)
    assert float(grad(u)[0]) == pytest.approx(dx, rel=1e-9)
    h = 1e-6
    fd = (float(final_x(u + h)) - float(final_x(u - h))) / (2 * h)
    assert fd == pytest.approx(dx, rel=1e-6)


def test_a_study_writes_its_verdicts_and_figure_and_never_replaces_a_file(tmp_path, capsys):
    from pipps.cli import main
    from pipps.studies import contact, contact_figures, contact_studies

    r = contact_studies.run_study("heaviside", thetas=3, samples=10, replicates=8)
    claims = [v["verdict"] for v in r.tables["verdicts"]]
    assert len(claims) == 5 and set(claims) <= {"supported", "contradicted", "cannot tell"}
    assert claims[0] == "supported"  # FoBG is exactly 0: true at any size
    out = tmp_path / "h.json"
    contact.write_study(out, r)
    back = contact.read_study(out)
    assert back.tables["verdicts"] == r.tables["verdicts"] and back.versions["code"]
    svg = contact_figures.record(back, tmp_path / "h.svg").read_text()
    assert "ZoBG (plain LR, whole return)" in svg and "AoBG (robust, bound γ)" in svg
    assert "| FoBG ≡ 0" in contact_figures.verdict_table(back)
    # the command refuses an existing output before any work
    assert main(["study", "contact", "heaviside", "--out", str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err
