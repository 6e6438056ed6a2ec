"""Tasks: physics against reference values from PILCO's code, integrator accuracy, presets, and the gymnasium envs.

Reference vectors are checked to 1e-9 max abs error (docs/task-cartpole.md, "Integrator and measured accuracy").
Statistical checks use a fixed seed and a tolerance of ``b`` standard errors, ``b`` the
two-sided normal quantile at a family-wise level of 1e-3, Bonferroni-corrected over the
comparisons a test makes; each has a companion showing it rejects a plausible mistake.
"""

from __future__ import annotations

import warnings

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from scipy.integrate import solve_ivp

import pipps.tasks as T
from pipps.stats import z_bound
from pipps.tasks.cartpole import CartPoleParams, cartpole_energy, cartpole_ode
from pipps.tasks.integrate import integrate_interval
from pipps.tasks.presets import make_task
from pipps.tasks.unicycle import (
    unicycle_derived,
    unicycle_fallen,
    unicycle_full_state,
    unicycle_ode,
    unicycle_sim_to_model,
)

T.register_envs()

TOL = 1e-9  # any integrator that reproduces the reference steps to about 1e-9 is accepted
FAMILY_ALPHA = 1e-3

# -- reference values (PILCO's code, scipy DOP853) -------------------------------------------------
CP_S = np.array([0.3, -0.5, 1.2, 2.0])
CP_U = np.array([4.0])
CP_DS = np.array([-0.5, 3.016080716629, -23.022504847296, 1.2])
CP_STEP = np.array([0.264274219842, -0.215736532085, -1.079456114396, 2.006003341609])
CP_STEP_FROM_ZERO_U10 = np.array([0.077955405886, 1.515299393311, -4.29564437995, -0.227706657241])

UC_S = np.array([0.1, -0.2, 0.3, 0.05, -0.4, 0.2, -0.1, 0.05, 0.3, 1.0, -0.08, 0.7])
UC_U = np.array([1.5, -3.0])
UC_DS = np.array(
    [0.36594600351, -3.291973559398, 3.483290800029, -2.270776571079, 10.752885216948,
     0.064485213016, 0.01994761395, 0.1, -0.2, 0.3, 0.05, -0.4]
)  # fmt: skip
UC_STEP = np.array(
    [0.15795985371, -0.697305986855, 0.948345139991, -0.365155514002, 1.210162286038, 0.218937472929,
     -0.09482938717, 0.069429720359, 0.232793692538, 1.087264368583, -0.100436889228, 0.760865890783]
)  # fmt: skip
UC_DERIVED = np.array([0.0644852130, 0.0199476139, -0.0984275380, -0.0323030554, -0.1615152772, 0.1546376902])


def max_err(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))))


def dop853_step(ode, s, u, dt):
    """The reference integrator: scipy DOP853 with rtol = atol = 1e-12."""
    f = jax.jit(lambda y: ode(y, jnp.asarray(u)))
    sol = solve_ivp(lambda t, y: np.asarray(f(jnp.asarray(y))), (0.0, dt), np.asarray(s, float),
                    method="DOP853", rtol=1e-12, atol=1e-12)  # fmt: skip
    assert sol.success
    return sol.y[:, -1]


def quiet_make(env_id, **kwargs):
    return gymnasium.make(env_id, disable_env_checker=True, **kwargs)


# == physics: cart-pole ========================================================================
def test_cartpole_derivative_matches_reference():
    assert max_err(cartpole_ode(jnp.asarray(CP_S), jnp.asarray(CP_U)), CP_DS) < TOL


@pytest.mark.parametrize("preset", T.PRESETS)
def test_cartpole_one_step_matches_reference(preset):
    task = make_task("cartpole_swingup", preset=preset)
    assert task.dt == 0.1
    assert max_err(task.step(jnp.asarray(CP_S), jnp.asarray(CP_U)), CP_STEP) < TOL
    assert max_err(task.step(jnp.zeros(4), jnp.array([10.0])), CP_STEP_FROM_ZERO_U10) < TOL


def test_cartpole_step_matches_dop853():
    task = make_task("cartpole_swingup")
    s = np.array([-0.4, 1.5, 6.0, 3.5])  # a fast state, away from the reference ones
    u = np.array([-7.0])
    assert max_err(task.step(jnp.asarray(s), jnp.asarray(u)), dop853_step(cartpole_ode, s, u, task.dt)) < TOL


def test_cartpole_energy_conserved_without_friction():
    """Energy conservation: drift < 1e-9 over 5 s for b = 0, u = 0, from a nontrivial state."""
    params = CartPoleParams(b=0.0)
    s0 = jnp.array([0.2, 1.0, 3.0, 2.5])
    u = jnp.zeros(1)

    def run(p):
        ode = lambda s, u: cartpole_ode(s, u, p)  # noqa: E731
        step = lambda s, _: (integrate_interval(ode, s, u, 0.1, 100),) * 2  # noqa: E731
        _, traj = jax.lax.scan(step, s0, None, length=50)  # 50 × 0.1 s = 5 s
        return cartpole_energy(traj, p) - cartpole_energy(s0, p), traj

    drift, traj = run(params)
    assert np.ptp(np.asarray(traj[:, 3])) > 1.0  # the pole really swings
    assert float(jnp.max(jnp.abs(drift))) < 1e-9
    # power: the default friction b = 0.1 dissipates energy far beyond the tolerance
    drift_friction, _ = run(CartPoleParams())
    assert float(jnp.max(jnp.abs(drift_friction))) > 1e-3


def test_cartpole_hanging_and_upright_are_equilibria():
    assert max_err(cartpole_ode(jnp.zeros(4), jnp.zeros(1)), np.zeros(4)) == 0.0
    assert max_err(cartpole_ode(jnp.array([0.0, 0.0, 0.0, np.pi]), jnp.zeros(1)), np.zeros(4)) < 1e-14


# == physics: unicycle =========================================================================
def test_unicycle_derivative_matches_reference():
    assert max_err(unicycle_ode(jnp.asarray(UC_S), jnp.asarray(UC_U)), UC_DS) < TOL


def test_unicycle_one_step_matches_reference():
    task = make_task("unicycle", preset="pilco")
    assert task.dt == 0.15
    assert max_err(task.step(jnp.asarray(UC_S), jnp.asarray(UC_U)), UC_STEP) < TOL


def test_unicycle_thesis_step_matches_dop853():
    task = make_task("unicycle", preset="thesis")
    assert task.dt == 0.1
    expected = dop853_step(unicycle_ode, UC_S, UC_U, task.dt)
    assert max_err(task.step(jnp.asarray(UC_S), jnp.asarray(UC_U)), expected) < TOL


def test_unicycle_derived_quantities_match_reference():
    assert max_err(unicycle_derived(jnp.asarray(UC_S)), UC_DERIVED) < TOL


def test_unicycle_derived_velocity_is_time_derivative_of_position():
    """(ẋ_c, ẏ_c) is d/dt (x_c, y_c) along the ODE (checked by the chain rule with jvp)."""
    s = jnp.asarray(UC_S)
    ds = unicycle_ode(s, jnp.asarray(UC_U))
    _, dpos = jax.jvp(lambda y: unicycle_derived(y)[4:6], (s,), (ds,))
    assert max_err(unicycle_derived(s)[2:4], dpos) < 1e-12


def test_unicycle_state_layouts():
    """18-dim full state: ODE variables at 1-based {5–11, 14–18}, model state at {5,6,7,8,9,12,13,14,15,17}."""
    s = jnp.asarray(UC_S)
    full = np.asarray(unicycle_full_state(s))
    ode_idx = np.r_[4:11, 13:18]
    model_idx = np.array([5, 6, 7, 8, 9, 12, 13, 14, 15, 17]) - 1
    assert np.array_equal(full[ode_idx], UC_S)
    assert np.array_equal(full[model_idx], np.asarray(unicycle_sim_to_model(s)))
    x = np.asarray(unicycle_sim_to_model(s))
    assert np.array_equal(x[[0, 1, 2, 3, 4, 7, 8, 9]], UC_S[[0, 1, 2, 3, 4, 7, 8, 10]])
    assert max_err(x[5:7], UC_DERIVED[4:6]) < TOL


def test_unicycle_zero_state_is_equilibrium():
    task = make_task("unicycle")
    zero, no_torque = jnp.zeros(12), jnp.zeros(2)
    assert np.array_equal(np.asarray(unicycle_ode(zero, no_torque)), np.zeros(12))
    assert np.array_equal(np.asarray(task.step(zero, no_torque)), np.zeros(12))
    # power: a turntable torque alone moves it
    assert np.max(np.abs(np.asarray(unicycle_ode(zero, jnp.array([1.0, 0.0]))))) > 0.1


def test_unicycle_fall_condition():
    s = np.zeros(12)
    assert not bool(unicycle_fallen(jnp.asarray(s)))
    for idx in (7, 10):  # θ (roll), ψ_f (pitch)
        for sign in (1.0, -1.0):
            t = s.copy()
            t[idx] = sign * (np.pi / 2 + 1e-6)
            assert bool(unicycle_fallen(jnp.asarray(t)))
            t[idx] = sign * (np.pi / 2 - 1e-6)
            assert not bool(unicycle_fallen(jnp.asarray(t)))
    t = s.copy()
    t[[8, 9, 11]] = 3.0  # yaw, wheel and turntable angles never count
    assert not bool(unicycle_fallen(jnp.asarray(t)))


def test_unicycle_model_start_distribution_is_the_moments_of_x_of_s0():
    """The unicycle's planning start: analytic mean/covariance of x(s0) against 40 000 samples of s0."""
    task = make_task("unicycle")
    n = 40_000
    rng = np.random.default_rng(0)
    s0 = rng.multivariate_normal(task.init_mean, task.init_cov, size=n)
    x0 = np.asarray(unicycle_sim_to_model(jnp.asarray(s0)))
    d = x0 - x0.mean(0)
    iu = np.triu_indices(10)
    prods = (d[:, :, None] * d[:, None, :])[:, iu[0], iu[1]]  # (n, 55)
    cov_hat, cov_se = prods.mean(0), prods.std(0) / np.sqrt(n)
    mean_se = x0.std(0) / np.sqrt(n)
    b = z_bound(10 + 55, FAMILY_ALPHA)
    assert np.all(np.abs(x0.mean(0) - task.model_init_mean) < b * mean_se)
    assert np.all(np.abs(cov_hat - task.model_init_cov[iu]) < b * cov_se)
    # power: the same check rejects the (x, y) variance left unrotated at 0.02², a plausible mistake
    wrong = task.model_init_cov.copy()
    wrong[5, 5] = wrong[6, 6] = 0.02**2
    assert not np.all(np.abs(cov_hat - wrong[iu]) < b * cov_se)


# == integrator ================================================================================
def test_integrator_is_vmappable_and_jittable():
    task = make_task("cartpole_swingup")
    rng = np.random.default_rng(1)
    s = jnp.asarray(rng.normal(size=(5, 4)))
    u = jnp.asarray(rng.uniform(-10, 10, size=(5, 1)))
    batched = jax.jit(jax.vmap(task.step))(s, u)
    for i in range(5):
        assert max_err(batched[i], task.step(s[i], u[i])) < 1e-14


def test_integrator_error_falls_with_substeps():
    """RK4: error ∝ substeps⁻⁴ against the reference vector (ratio ≈ 16 per doubling)."""
    errs = [max_err(integrate_interval(unicycle_ode, jnp.asarray(UC_S), jnp.asarray(UC_U), 0.15, n), UC_STEP)
            for n in (10, 20)]  # fmt: skip
    assert 10.0 < errs[0] / errs[1] < 20.0
    with pytest.raises(ValueError, match="substeps"):
        integrate_interval(unicycle_ode, jnp.asarray(UC_S), jnp.asarray(UC_U), 0.15, 0)


# == presets ===================================================================================
def test_presets_match_spec():
    t = make_task("cartpole_swingup", "thesis")
    assert (t.dt, t.horizon, t.substeps, t.angle_idx) == (0.1, 30, 100, ())
    assert t.gp_input_idx == t.policy_input_idx == (0, 1, 2, 3) and t.gp_input_dim == 5
    assert np.allclose(t.obs_noise_std, [0.01, 0.1, 10 * np.pi / 180, np.pi / 180], rtol=0, atol=1e-15)
    assert np.array_equal(t.init_mean, np.zeros(4)) and np.allclose(t.init_cov, 0.01 * np.eye(4), rtol=1e-15, atol=0)
    assert np.array_equal(t.model_init_cov, t.init_cov) and t.fallen is None

    p = make_task("cartpole_swingup", "pilco")
    assert (p.dt, p.horizon, p.angle_idx, p.gp_input_idx, p.policy_input_idx) == (0.1, 40, (3,), (0, 1, 2, 4, 5), (0, 1, 2, 4, 5))
    assert p.gp_input_dim == 6 and np.allclose(p.obs_noise_std, 0.01, rtol=0, atol=1e-15)
    xa = np.asarray(p.gp_input(jnp.array([1.0, 2.0, 3.0, 0.5]), jnp.array([7.0])))
    assert np.allclose(xa, [1.0, 2.0, 3.0, np.sin(0.5), np.cos(0.5), 7.0], rtol=0, atol=1e-15)

    b = make_task("cartpole_balance")
    assert np.array_equal(b.init_mean, [0.0, 0.0, 0.0, np.pi]) and np.array_equal(b.model_init_mean, b.init_mean)

    for preset, dt, horizon, substeps in (("thesis", 0.1, 20, 134), ("pilco", 0.15, 67, 200)):
        u = make_task("unicycle", preset)
        assert (u.dt, u.horizon, u.substeps, u.angle_idx) == (dt, horizon, substeps, ())
        assert u.gp_input_idx == (0, 1, 2, 3, 4, 5, 6, 7, 9) and u.gp_input_dim == 11
        assert u.policy_input_idx == tuple(range(10))
        assert np.array_equal(u.u_max, [10.0, 50.0]) and np.array_equal(u.u_rand, [2.0, 10.0])
        assert np.allclose(u.obs_noise_std, [0.01] * 5 + [0.003] * 7, rtol=0, atol=1e-15)
        assert np.allclose(np.diag(u.init_cov), [0.02**2] * 5 + [0.01] * 2 + [0.02**2] * 5, rtol=0, atol=1e-15)
        assert np.allclose(u.model_init_cov, np.diag([0.02**2] * 5 + [0.01] * 2 + [0.02**2] * 3), rtol=0, atol=1e-15)


@pytest.mark.parametrize("k", [0.0, 0.01, 4.0, 16])
def test_noise_std_scales_with_sqrt_k(k):
    for name in T.TASK_NAMES:
        base = make_task(name, k=1.0).obs_noise_std
        task = make_task(name, k=k)
        assert np.allclose(task.obs_noise_std, np.sqrt(k) * base, rtol=1e-15, atol=0)
        assert task.noise_multiplier == k


def test_overrides():
    t = make_task("unicycle", horizon=10, substeps=50)
    assert (t.horizon, t.substeps) == (10, 50)
    t = make_task("cartpole_swingup", dt=0.05)  # substeps follow dt (1 ms sub-step)
    assert (t.dt, t.substeps) == (0.05, 50)
    t = make_task("cartpole_swingup", u_max=[5.0])
    assert t.u_max.dtype == np.float64 and np.array_equal(t.u_max, [5.0]) and not t.u_max.flags.writeable


def test_a_task_is_a_problem_and_a_simulator():
    """make_task splits the fields between the planning problem and the true system; the pair
    reads them through, refuses halves that disagree, and a field on neither is an error."""
    import dataclasses

    task = make_task("unicycle", "pilco", k=4.0, horizon=10)
    p, sim = task.problem, task.simulator
    assert isinstance(p, T.Problem) and isinstance(sim, T.Simulator) and task.preset == "pilco"
    assert not any(hasattr(p, f) for f in ("sim_dim", "ode", "init_mean", "obs_noise_std", "u_rand", "step"))
    assert not any(hasattr(sim, f) for f in ("model_dim", "horizon", "cost", "gp_input_idx", "policy_input"))
    assert (p.horizon, p.model_dim, sim.sim_dim, sim.substeps, sim.noise_multiplier) == (10, 10, 12, 200, 4.0)
    assert p.dt == sim.dt == task.dt == 0.15 and task.name == p.name == sim.name == "unicycle"
    assert task.horizon is p.horizon and task.init_cov is sim.init_cov and task.cost is p.cost
    assert task.step.__self__ is sim and task.gp_input.__self__ is p
    with pytest.raises(AttributeError, match="neither its problem nor its simulator"):
        task.horizn
    with pytest.raises(ValueError, match="differ in dt"):
        T.Task(p, dataclasses.replace(sim, dt=0.1))
    with pytest.raises(ValueError, match="u_rand must have shape"):
        T.Task(p, dataclasses.replace(sim, u_rand=np.ones(3)))
    cp = make_task("cartpole_swingup", dt=0.05)
    assert cp.problem.dt == cp.simulator.dt == 0.05


def test_costs_wired_and_match_reference():
    """Reference cost values through make_task (tip cost by name; pilco default), unicycle cost, angle cost."""
    tip_cost = make_task("cartpole_swingup", "pilco").cost
    assert make_task("cartpole_swingup", cost="tip").cost.name == "tip" == tip_cost.name
    tip = jax.jit(tip_cost)
    assert abs(float(tip(jnp.array([0.2, 0.0, 0.0, 2.5]))) - 0.874189814022) < TOL
    assert abs(float(tip(jnp.zeros(4))) - 0.999664537372) < TOL
    assert abs(float(tip(jnp.array([0.0, 0.0, 0.0, np.pi])))) < TOL
    mu = jnp.array([0.1, 0.3, -0.2, np.pi - 0.2])
    cov = jnp.diag(jnp.array([0.03, 0.04, 0.06, 0.05])).at[0, 3].set(-0.01).at[3, 0].set(-0.01)
    ec, vc = jax.jit(tip_cost.expected)(mu, cov)
    assert abs(float(ec) - 0.379042594224) < TOL and abs(float(vc) - 0.095031140975) < TOL

    uni = jax.jit(make_task("unicycle").cost)
    assert abs(float(uni(jnp.array([0, 0, 0, 0, 0, 0.1, -0.05, 0.05, 0.3, -0.08]))) - 0.009656629969) < TOL

    angle = jax.jit(make_task("cartpole_swingup").cost)  # thesis default
    x = jnp.array([0.2, 0.0, 0.0, 2.5])
    assert abs(float(angle(x)) - (1 - np.exp(-(0.2**2 + (2.5 - np.pi) ** 2)))) < 1e-12
    assert float(angle(jnp.array([0.0, 1.0, 1.0, np.pi]))) == 0.0


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(name="cartpole"), "unknown task 'cartpole'.*cartpole_swingup, cartpole_balance, unicycle"),
        (dict(name="unicycle", preset="paper"), "unknown preset 'paper'.*thesis, pilco"),
        (dict(name="unicycle", cost="tip"), "'tip'.*valid choices: unicycle"),
        (dict(name="cartpole_swingup", cost="distance"), "'distance'.*angle, tip"),
        (dict(name="cartpole_swingup", k=-1.0), "k must be.*-1.0"),
        (dict(name="cartpole_swingup", k=float("nan")), "k must be.*nan"),
        (dict(name="cartpole_swingup", k=float("inf")), "k must be.*inf"),
        (dict(name="cartpole_swingup", k="1"), "k must be"),
        (dict(name="cartpole_swingup", horizn=10), "unknown Task field 'horizn'.*horizon"),
        (dict(name="cartpole_swingup", noise_multiplier=2.0), "'k' argument"),
        (dict(name="cartpole_swingup", horizon=0), "horizon must be >= 1"),
        (dict(name="cartpole_swingup", dt=-0.1), "dt must be"),
        (dict(name="unicycle", u_max=[1.0]), "u_max must have shape"),
    ],
)
def test_make_task_rejects_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        make_task(**kwargs)


# == gymnasium environments ====================================================================
@pytest.mark.parametrize("preset", T.PRESETS)
@pytest.mark.parametrize("env_id", sorted(T.ENV_IDS))
def test_check_env(env_id, preset):
    env = gymnasium.make(env_id, preset=preset, k=0.01)
    assert env.unwrapped.task.preset == preset and env.unwrapped.task.name == T.ENV_IDS[env_id]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # advisory: unbounded observation box, unnormalised actions
        check_env(env.unwrapped, skip_render_check=True)


@pytest.mark.parametrize("env_id", ["pipps/CartPoleSwingUp-v0", "pipps/Unicycle-v0"])
def test_k0_observation_is_state_and_reward_is_noise_free_cost(env_id):
    env = quiet_make(env_id, k=0.0)
    task = env.unwrapped.task
    step, cost_of = jax.jit(task.step), jax.jit(lambda s: task.cost(task.sim_to_model(s)))
    obs, info = env.reset(seed=3)
    assert np.array_equal(obs, env.unwrapped.state)
    assert env.unwrapped.state.dtype == np.float64 and obs.dtype == np.float64
    for _ in range(3):
        s_prev = env.unwrapped.state.copy()
        u = env.action_space.sample() * 0.2
        obs, reward, terminated, truncated, info = env.step(u)
        assert np.array_equal(obs, env.unwrapped.state)
        assert np.array_equal(info["model_state"], info["obs_model_state"])
        expected_next = np.asarray(step(jnp.asarray(s_prev), jnp.asarray(u)))
        assert max_err(env.unwrapped.state, expected_next) < 1e-14
        cost = float(cost_of(jnp.asarray(expected_next)))
        assert abs(reward + cost) < 1e-14 and info["cost"] == -reward


def test_reward_uses_noise_free_next_state_when_noisy():
    env = quiet_make("pipps/CartPoleSwingUp-v0", k=100.0)
    cost = jax.jit(env.unwrapped.task.cost)
    env.reset(seed=0)
    obs, reward, _, _, info = env.step(np.array([1.0]))
    assert abs(reward + float(cost(jnp.asarray(info["model_state"])))) < 1e-14
    assert np.array_equal(info["model_state"], env.unwrapped.state)  # cart-pole: x = s
    assert np.array_equal(info["obs_model_state"], obs) and not np.allclose(obs, env.unwrapped.state)
    assert abs(reward + float(cost(jnp.asarray(info["obs_model_state"])))) > 1e-6


@pytest.mark.parametrize("env_id, k", [("pipps/CartPoleSwingUp-v0", 4.0), ("pipps/Unicycle-v0", 0.25)])
def test_observation_noise_has_the_right_std(env_id, k):
    """o − s ~ N(0, k·diag(σ_base²)): sample mean and std per component within the bound.

    Samples are the reset observations of 4000 episodes (``step`` draws its noise with the
    same code; the k = 0 and k = 100 tests cover the step path). The std's standard error
    is estimated as σ̂/√(2n) (normal data); n = 4000 gives ≈ 1.1 %.
    """
    env = quiet_make(env_id, k=k)
    expected_std = np.sqrt(k) * make_task(T.ENV_IDS[env_id], k=1.0).obs_noise_std
    env.reset(seed=123)
    eps = []
    for _ in range(4000):
        obs, _ = env.reset()
        eps.append(obs - env.unwrapped.state)
    eps = np.asarray(eps)
    n, d = eps.shape
    b = z_bound(2 * d, FAMILY_ALPHA)
    std_hat = eps.std(axis=0, ddof=1)
    assert np.all(np.abs(eps.mean(0)) < b * std_hat / np.sqrt(n))
    assert np.all(np.abs(std_hat - expected_std) < b * std_hat / np.sqrt(2 * n))
    # power: the check rejects std = k·σ_base (variance k²σ²), the easy √k mistake
    assert not np.all(np.abs(std_hat - k * expected_std / np.sqrt(k)) < b * std_hat / np.sqrt(2 * n))


def test_reset_samples_start_distribution_and_is_seeded():
    env = quiet_make("pipps/CartPoleBalance-v0", k=0.0)
    o1, _ = env.reset(seed=7)
    o2, _ = env.reset(seed=7)
    o3, _ = env.reset(seed=8)
    assert np.array_equal(o1, o2) and not np.array_equal(o1, o3)
    s0 = np.array([env.reset()[0] for _ in range(2000)])
    b = z_bound(8, FAMILY_ALPHA)
    assert np.all(np.abs(s0.mean(0) - [0, 0, 0, np.pi]) < b * 0.1 / np.sqrt(2000))
    assert np.all(np.abs(s0.std(0, ddof=1) - 0.1) < b * 0.1 / np.sqrt(2 * 2000))


def test_unicycle_fall_terminates_episode():
    env = quiet_make("pipps/Unicycle-v0", preset="pilco", k=0.0)
    env.reset(seed=0)
    push = np.array([10.0, 50.0])  # full torque on both motors tips it over
    for t in range(env.unwrapped.task.horizon):
        before = env.unwrapped.state.copy()
        _, _, terminated, truncated, info = env.step(push)
        if terminated:
            break
        assert not info["fallen"] and not truncated
    assert terminated and not truncated and info["fallen"] and t < env.unwrapped.task.horizon - 1
    assert not bool(unicycle_fallen(jnp.asarray(before)))
    s = env.unwrapped.state
    assert abs(s[7]) > np.pi / 2 or abs(s[10]) > np.pi / 2
    with pytest.raises(gymnasium.error.ResetNeeded):
        env.step(np.zeros(2))


def test_truncation_at_horizon_and_no_recompilation():
    env = quiet_make("pipps/CartPoleSwingUp-v0", horizon=5)
    env.reset(seed=0)
    for t in range(5):
        _, _, terminated, truncated, _ = env.step(np.array([0.5]))
        assert not terminated and truncated == (t == 4)
    with pytest.raises(gymnasium.error.ResetNeeded):
        env.step(np.array([0.5]))
    env.reset(seed=1)
    env.step(np.array([-3.0]))
    assert env.unwrapped._transition._cache_size() == 1  # one compile per env, not per step


@pytest.mark.parametrize(
    "action, match",
    [
        (np.array([np.nan]), "finite"),
        (np.array([np.inf]), "finite"),
        (np.array([1.0, 2.0]), r"shape \(2,\), expected \(1,\)"),
        (np.float64(1.0), r"shape \(\), expected \(1,\)"),
        (np.array([10.5]), "outside the control limits"),
        ("push", "numeric"),
    ],
)
def test_env_rejects_bad_actions(action, match):
    env = quiet_make("pipps/CartPoleSwingUp-v0")
    env.reset(seed=0)
    state = env.unwrapped.state.copy()
    with pytest.raises(ValueError, match=match):
        env.step(action)
    assert np.array_equal(env.unwrapped.state, state)  # nothing happened


def test_env_construction_errors():
    with pytest.raises(gymnasium.error.Error):
        gymnasium.make("pipps/CartPoleSwingDown-v0")
    with pytest.raises(ValueError, match="unknown preset 'paper'"):
        gymnasium.make("pipps/Unicycle-v0", preset="paper")
    with pytest.raises(ValueError, match="unknown cost .*'tip'"):
        gymnasium.make("pipps/Unicycle-v0", cost="tip")
    with pytest.raises(ValueError, match="k must be"):
        gymnasium.make("pipps/CartPoleSwingUp-v0", k=-0.5)
    with pytest.raises(ValueError, match="only when the task is given by name"):
        T.PippsEnv(make_task("cartpole_swingup"), k=4.0)
    env = T.PippsEnv(make_task("cartpole_swingup"))
    with pytest.raises(gymnasium.error.ResetNeeded):
        env.step(np.zeros(1))


def test_reference_systems_name_their_bad_parameters():
    from pipps.systems import make_linear_gaussian_task
    from pipps.systems.chaotic import make_kicked_rotor_task

    with pytest.raises(ValueError, match=r"init_mean must have shape \(2,\), got \(3,\)"):
        make_kicked_rotor_task(init_mean=(0.5, 0.0, 0.0))
    with pytest.raises(ValueError, match="init_std must be finite"):
        make_kicked_rotor_task(init_std=(0.05, float("nan")))
    with pytest.raises(ValueError, match=r"init_cov must have shape \(3, 3\), got \(2, 2\)"):
        make_linear_gaussian_task(3, 1, init_cov=np.eye(2))
    with pytest.raises(ValueError, match="u_max must be finite"):
        make_linear_gaussian_task(3, 1, u_max=float("inf"))
