"""A task is one record: what it owns, where it is found, what it refuses (pipps.tasks.spec, registry, base).

* Outside ``pipps/tasks/`` no module or script (``experiments/``, ``benchmarks/``) branches on a
  built-in task's name: the source is read for comparisons with the names, prefix tests and lookup
  tables keyed by them (and the reader is shown to find each kind).
* The built-in records reproduce what the library decided by name before (experiment settings,
  criteria, thresholds, PILCO budgets) — the bit-for-bit identity of configurations and results is
  checked by ``benchmarks/loop_reference.py`` and the committed result files (docs/architecture.md).
* Construction is validated: each bad field raises one ``ValueError`` naming it.
* Tasks are found by registration, ``module:attribute`` and entry points (a temporary dist-info on
  ``sys.path``), and a task that cannot be found says so in one line.
"""

from __future__ import annotations

import ast
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

import pipps.tasks as T
from pipps.costs import SaturatingCost
from pipps.experiments import resolve_config
from pipps.experiments.config import ConfigError, config_hash, stored_dict
from pipps.tasks import registry

PACKAGE = Path(__file__).resolve().parents[1] / "pipps"
NAMES = ("cartpole_swingup", "cartpole_balance", "unicycle")


# == no name branches outside pipps/tasks/ =====================================================


def _is_name(node) -> bool:
    """A string constant naming a built-in task, or a prefix of one (``"cartpole"``)."""
    return (isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value
            and any(n.startswith(node.value) for n in NAMES))


def _names_in(node) -> bool:
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return any(_names_in(e) for e in node.elts)
    return _is_name(node)


def name_branches(source: str) -> list[tuple[int, str]]:
    """Where ``source`` decodes a built-in task's name: a comparison with one (``==``, ``in (…)``), a
    prefix or suffix test against one, a ``match`` case on one, or a lookup table keyed by one."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Compare) and any(_names_in(n) for n in [node.left, *node.comparators]):
            found.append((node.lineno, "comparison"))
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
              and node.func.attr in ("startswith", "endswith", "removeprefix") and any(_names_in(a) for a in node.args)):
            found.append((node.lineno, f".{node.func.attr}()"))
        elif isinstance(node, ast.Dict) and any(k is not None and _names_in(k) for k in node.keys):
            found.append((node.lineno, "table keyed by name"))
        elif isinstance(node, ast.MatchValue) and _is_name(node.value):
            found.append((node.lineno, "match case"))
    return found


def test_the_reader_finds_every_kind_of_name_branch():
    """The check has power: each way the library used to decode a name is found."""
    cases = {
        'if cfg.task == "unicycle": pass': "comparison",
        'ok = task_name.startswith("cartpole")': ".startswith()",
        'x = "unicycle" != name': "comparison",
        'y = name in ("cartpole_swingup", "cartpole_balance")': "comparison",
        'ANGLE = {"unicycle": (9, 10), "other": 1}': "table keyed by name",
        'B = {("cartpole_swingup", "thesis"): 1}': "table keyed by name",
        'match name:\n    case "unicycle":\n        pass': "match case",
    }
    for code, kind in cases.items():
        assert [k for _, k in name_branches(code)] == [kind], code
    for code in ('run(task="cartpole_swingup")', 'DEFAULTS = {"task": "unicycle"}', 'if cfg.task == other: pass',
                 'if method == "tp": pass'):
        assert name_branches(code) == [], code


def test_no_module_outside_tasks_branches_on_a_task_name():
    """Neither a module of ``pipps/`` outside ``tasks/`` nor a script of ``experiments/`` or
    ``benchmarks/``: a script specific to one task compares the file's record with that task's
    (``cfg.task_spec is get_task(…)``) or asks the record what it needs, never the name."""
    root = PACKAGE.parent
    paths = [p for p in sorted(PACKAGE.rglob("*.py")) if p.relative_to(PACKAGE).parts[0] != "tasks"]
    paths += sorted((root / "experiments").rglob("*.py")) + sorted((root / "benchmarks").rglob("*.py"))
    branches = []
    for path in paths:
        name = path.relative_to(root).as_posix()
        branches += [f"{name}:{line} ({kind})" for line, kind in name_branches(path.read_text(encoding="utf-8"))]
    assert branches == [], "ask the task's record (pipps.tasks.TaskSpec) instead:\n" + "\n".join(branches)


# == the built-in records =====================================================================


def test_builtin_records_own_what_the_library_decided_by_name():
    cp, uni = T.get_task("cartpole_swingup"), T.get_task("unicycle")
    c = resolve_config("thesis", "cartpole_swingup")
    u = resolve_config("thesis", "unicycle")
    s_cp, s_uni = cp.success_for(c), uni.success_for(u)
    assert (s_cp.name, s_cp.fraction, s_cp.threshold) == ("balanced", 0.5, 15.0)
    assert (s_uni.name, s_uni.fraction, s_uni.threshold) == ("upright", 0.95, None)
    assert s_uni.rule is T.never_fell
    assert (cp.plot.panel, cp.plot.panel_true, cp.plot.label(3)) == (3, 3, "pole angle θ (rad)")
    assert (uni.plot.panel, uni.plot.panel_true, uni.plot.label(9)) == (9, 10, "wheel pitch ψ_f (rad)")
    assert uni.plot.log_returns and not cp.plot.log_returns
    assert cp.costs == ("angle", "tip") and uni.costs == ("unicycle",)
    assert cp.default_cost("thesis") == "angle" and cp.default_cost("pilco") == "tip"
    assert cp.centre_box is not None and uni.centre_box is None
    assert cp.make().problem.pilco_budget == (150, 30) and uni.make("pilco").problem.pilco_budget == (-150, 20)
    assert cp.label == "cart-pole"
    # the rule under other bounds follows the experiment's settings
    states = np.zeros((31, 4))
    states[:, 3] = np.pi
    states[-1, 0] = 0.4
    assert bool(s_cp.rule(states, np.ones(30, bool)))
    assert not bool(cp.success_for(c.replace(balance_position=0.3)).rule(states, np.ones(30, bool)))


def test_a_built_in_configuration_is_stored_as_before():
    """No ``task_source`` key in a built-in task's stored configuration (its files stay byte for byte as
    they were), and the source is not part of the identity."""
    c = resolve_config("thesis", "unicycle", seed=3)
    assert c.task_source is None and "task_source" not in stored_dict(c)
    assert config_hash(c) == config_hash(dataclasses.replace(c, task_source="somewhere:else"))


# == validation at construction ===============================================================


def _pendulum(**problem):
    cost = SaturatingCost(W=np.diag([0.0, 0.0, 4.0, 4.0]), target=[0.0, np.pi, 0.0, -1.0], angle_idx=(1,))
    fields = dict(name="pend", dt=0.1, horizon=10, u_max=[2.0], model_init_mean=[0.0, 0.0],
                  model_init_cov=np.eye(2) * 0.01, cost=cost, angle_idx=(1,), gp_input_idx=(0, 2, 3),
                  policy_input_idx=(0, 2, 3))
    fields.update(problem)
    return T.Problem(**fields)


def _ode(s, u):
    import jax.numpy as jnp

    return jnp.stack([u[0] - 9.81 * jnp.sin(s[1]), s[0]])


def _simulator(**fields):
    base = dict(name="pend", dt=0.1, ode=_ode, init_mean=[0.0, 0.0], init_cov=np.eye(2) * 0.01, obs_noise_std=0.01)
    base.update(fields)
    return T.Simulator(**base)


def test_defaults_fill_in_what_the_arrays_say():
    p, sim = _pendulum(), _simulator()
    task = T.Task(p, sim)
    assert (p.model_dim, p.action_dim, sim.sim_dim) == (2, 1, 2)
    assert np.array_equal(task.simulator.u_rand, [2.0])  # the problem's u_max
    assert np.array_equal(sim.obs_noise_std, [0.01, 0.01]) and not sim.obs_noise_std.flags.writeable
    assert _pendulum(gp_input_idx=None).gp_input_idx == (0, 1, 2, 3)  # the whole augmented state


@pytest.mark.parametrize("fields, match", [
    (dict(gp_input_idx=(0, 2, 4)), r"Problem.gp_input_idx: index 4 out of range \[0, 4\)"),
    (dict(policy_input_idx=(0, 2, 2)), r"Problem.policy_input_idx: holds duplicates"),
    (dict(angle_idx=(2,)), r"Problem.angle_idx: index 2 out of range \[0, 2\)"),
    (dict(model_init_cov=[[0.01, 0.0], [0.0, -0.01]]), r"Problem.model_init_cov: must be positive semi-definite"),
    (dict(model_init_cov=[[0.01, 0.005], [0.0, 0.01]]), r"Problem.model_init_cov: must be symmetric"),
    (dict(model_init_cov=np.eye(3)), r"Problem.model_init_cov: must have shape \(2, 2\)"),
    (dict(model_init_mean=[0.0, np.nan]), r"Problem.model_init_mean: must be finite"),
    (dict(u_max=[2.0, -1.0]), r"Problem.u_max: must be > 0"),
    (dict(u_max=[[2.0]]), r"Problem.u_max: must be a 1-d array"),
    (dict(action_dim=2), r"Problem.u_max: must have shape \(2,\)"),
    (dict(dt=0.0), r"Problem.dt: must be a finite number > 0"),
    (dict(horizon=0), r"Problem.horizon: must be an integer >= 1"),
    (dict(name=""), r"Problem.name: must be a non-empty string"),
    (dict(cost=lambda x: x), r"Problem.cost: must return a scalar"),
    (dict(cost=lambda x: x @ np.ones(3)), r"Problem.cost: fails on inputs of shape \(2,\)"),
    (dict(pilco_budget=(0, 10)), r"Problem.pilco_budget"),
])
def test_a_bad_problem_field_is_named(fields, match):
    with pytest.raises(ValueError, match=match):
        _pendulum(**fields)


@pytest.mark.parametrize("fields, match", [
    (dict(init_cov=[[0.01, 0.0], [0.0, -1e-6]]), r"Simulator.init_cov: must be positive semi-definite"),
    (dict(init_mean=[0.0, math.inf]), r"Simulator.init_mean: must be finite"),
    (dict(obs_noise_std=[0.01, -0.01]), r"Simulator.obs_noise_std: must be >= 0"),
    (dict(obs_noise_std=[0.01, 0.01, 0.01]), r"Simulator.obs_noise_std: must have shape \(2,\)"),
    (dict(u_rand=[-1.0]), r"Simulator.u_rand: must be >= 0"),
    (dict(substeps=0), r"Simulator.substeps: must be an integer >= 1"),
    (dict(noise_multiplier=-1.0), r"Simulator.noise_multiplier"),
    (dict(ode=None), r"Simulator.ode: must be callable"),
    (dict(sim_dim=3), r"Simulator.init_mean: must have shape \(3,\)"),
])
def test_a_bad_simulator_field_is_named(fields, match):
    with pytest.raises(ValueError, match=match):
        _simulator(**fields)


@pytest.mark.parametrize("sim, match", [
    (dict(dt=0.05), "problem and simulator differ in dt: 0.1 and 0.05"),
    (dict(u_rand=[1.0, 1.0]), r"u_rand must have shape \(1,\)"),
    (dict(sim_to_model=lambda s: s[:1]), r"Simulator.sim_to_model: maps a simulator state of shape \(2,\) to shape \(1,\)"),
    (dict(ode=lambda s, u: s[:1]), r"Simulator.ode: returns shape \(1,\)"),
    (dict(ode=lambda s, u: s + u @ np.ones((2, 2))), r"Simulator.ode: fails on inputs of shape \(2,\) and \(1,\)"),
    (dict(fallen=lambda s: s > 0), r"Simulator.fallen: must return one boolean per state"),
    (dict(periodic=(2,)), r"Simulator.periodic: index 2 out of range"),
])
def test_halves_that_do_not_fit_are_refused_by_the_task(sim, match):
    with pytest.raises(ValueError, match=match):
        T.Task(_pendulum(), _simulator(**sim))


def test_records_refuse_what_they_cannot_use():
    ok = T.Success("upright", lambda s, v: v.all(-1), 0.5)
    with pytest.raises(ValueError, match=r"Success.fraction: must lie in \(0, 1\]"):
        T.Success("upright", ok.rule, 1.5)
    with pytest.raises(ValueError, match="Success.threshold"):
        T.Success("upright", ok.rule, 0.5, threshold=math.nan)
    with pytest.raises(ValueError, match="Success.rule: must be callable"):
        T.Success("upright", None, 0.5)
    task = T.Task(_pendulum(), _simulator())
    with pytest.raises(ValueError, match="TaskSpec.name: must be a non-empty name without ':'"):
        T.TaskSpec(task, ok, name="my:task")
    with pytest.raises(ValueError, match=r"TaskSpec.centre_box"):
        T.TaskSpec(task, ok, centre_box=((0.0, 1.0), (1.0, 0.0)))
    with pytest.raises(ValueError, match=r"TaskSpec.settings\['quick'\]: task preset 'thesis'"):
        T.TaskSpec(task, ok, settings={"quick": {"preset": "thesis"}})
    spec = T.TaskSpec(task, ok)
    assert spec.name == "pend" and spec.presets == ("default",) and spec.costs == ("default",)
    assert spec.make() is task  # k = 1 and no override: the same object (its compiled programs are reused)
    assert np.allclose(spec.make(k=4.0).simulator.obs_noise_std, 0.02) and spec.make(horizon=5).problem.horizon == 5
    with pytest.raises(ValueError, match="takes no scale"):
        spec.make(cost_scale=0.5)
    with pytest.raises(ValueError, match="unknown Task field 'horizn'"):
        spec.make(horizn=5)


def test_a_record_refuses_policy_settings_that_do_not_fit_the_problem():
    """The pendulum's policy sees 3 components (ω, sin θ, cos θ): a 4-component centre box or 2
    length-scales are refused at construction, naming the field and both sizes."""
    task, ok = T.Task(_pendulum(), _simulator()), T.Success("upright", lambda s, v: v.all(-1), 0.5)
    with pytest.raises(ValueError, match=r"TaskSpec.centre_box: has 4 components per side, expected 3 "
                                         r"\(the problem's policy_input_dim\)"):
        T.TaskSpec(task, ok, centre_box=((-1.0,) * 4, (1.0,) * 4))
    with pytest.raises(ValueError, match=r"TaskSpec.settings\['quick'\]: log_lambda_init has 2 values, expected 1 or 3"):
        T.TaskSpec(task, ok, settings={"quick": {"log_lambda_init": (0.0, 1.0)}})
    spec = T.TaskSpec(task, ok, centre_box=((-1.0,) * 3, (1.0,) * 3), settings={"quick": {"log_lambda_init": (0.0,) * 3}})
    assert spec.centre_box == ((-1.0,) * 3, (1.0,) * 3)


def _policies(d: int, f: int):
    import jax

    from pipps.policies import init_linear_policy, init_pilco_rbf_policy, init_rbf_policy

    key, u = jax.random.PRNGKey(0), [2.0] * f
    return {"rbf": init_rbf_policy(key, 5, np.zeros(d), np.eye(d), u),
            "pilco_rbf": init_pilco_rbf_policy(key, 5, np.zeros(d), np.eye(d), u),
            "linear": init_linear_policy(key, d, u)}


@pytest.mark.parametrize("kind, field", [("rbf", "centres"), ("pilco_rbf", "centres"), ("linear", "W")])
def test_a_policy_that_does_not_fit_the_problem_is_refused(kind, field):
    """Where a policy meets a problem (the true-system rollout, the particle rollout every estimator
    and the loop run, PILCO's prediction), one that does not fit it is refused by name, before JAX
    broadcasts a 1-component policy over a 3-component input and runs (or fails deep in a trace)."""
    import jax
    import jax.numpy as jnp

    import pipps.pilco
    from pipps.gp import GPConfig, full_posterior, initial_hyper, make_data
    from pipps.particles import RolloutConfig, particle_rollout, sample_noise
    from pipps.policies import check_policy
    from pipps.rollout import rollout

    task, key, config = T.Task(_pendulum(), _simulator()), jax.random.PRNGKey(1), RolloutConfig(num_particles=3)
    data = make_data(np.arange(16.0).reshape(4, 4) / 16, np.arange(8.0).reshape(4, 2) / 80)
    model = full_posterior(initial_hyper(data, GPConfig())[0], data, GPConfig())[0]
    noise = sample_noise(key, task.problem, config)
    calls = {"rollout": lambda p: rollout(key, task, p),
             "particle_rollout": lambda p: particle_rollout(task.problem, p, model, noise, config),
             "pilco": lambda p: pipps.pilco.objective(task.problem, p, model)}
    fits, narrow, two_controls = _policies(3, 1)[kind], _policies(1, 1)[kind], _policies(3, 2)[kind]
    check_policy(fits, task.problem.policy_input_dim, task.problem.action_dim)  # the one that fits passes
    for name, call in calls.items():
        with pytest.raises(ValueError, match=rf"policy.{field}: axis 1 has size 1, expected 3 "
                                             r"\(the problem's policy_input_dim\)"):
            call(narrow)
        with pytest.raises(ValueError, match=r"expected 1 \(the problem's action_dim\)"):
            call(two_controls)
    with pytest.raises(ValueError, match=r"policy: returns shape \(2,\), expected \(1,\)"):
        rollout(key, task, lambda v: jnp.zeros(2))


# == finding tasks ============================================================================


SOURCE = '''
import numpy as np
from pipps.costs import SaturatingCost
from pipps.tasks import Problem, Simulator, Success, Task, TaskSpec
import jax.numpy as jnp

def ode(s, u):
    return jnp.stack([u[0] - 9.81 * jnp.sin(s[1]), s[0]])

def make():
    cost = SaturatingCost(W=np.diag([0.0, 0.0, 4.0, 4.0]), target=[0.0, np.pi, 0.0, -1.0], angle_idx=(1,))
    problem = Problem(name="{name}", dt=0.1, horizon=10, u_max=[2.0], model_init_mean=[0.0, 0.0],
                      model_init_cov=np.eye(2) * 0.01, cost=cost, angle_idx=(1,), gp_input_idx=(0, 2, 3),
                      policy_input_idx=(0, 2, 3))
    simulator = Simulator(name="{name}", dt=0.1, ode=ode, init_mean=[0.0, 0.0], init_cov=np.eye(2) * 0.01)
    return TaskSpec(Task(problem, simulator), Success("upright", lambda s, v: jnp.cos(s[..., -1, 1]) < -0.9, 0.5))

{attribute} = make()
'''


@pytest.fixture
def clean_registry():
    before = dict(registry._REGISTERED)
    yield
    registry._REGISTERED.clear()
    registry._REGISTERED.update(before)


def test_module_attribute_and_register(tmp_path, monkeypatch, clean_registry):
    (tmp_path / "rec_tasks.py").write_text(SOURCE.format(name="rec_pend", attribute="pendulum"))
    monkeypatch.syspath_prepend(str(tmp_path))
    spec = T.get_task("rec_tasks:pendulum")
    assert spec.name == "rec_pend" and T.task_source("rec_pend") == "rec_tasks:pendulum"
    assert T.get_task("rec_pend") is spec and "rec_pend" in T.task_names()
    cfg = resolve_config("quick", "rec_tasks:pendulum", seed=2)
    assert (cfg.task, cfg.task_source) == ("rec_pend", "rec_tasks:pendulum")
    assert stored_dict(cfg)["task_source"] == "rec_tasks:pendulum"
    # by name, once known; by the record itself; the factory's own path is its source
    assert resolve_config("quick", "rec_pend").task_source == "rec_tasks:pendulum"
    import rec_tasks

    other = T.register("rec_made", lambda: dataclasses.replace(rec_tasks.make(), name="rec_made"))
    assert T.get_task("rec_made") is other and T.task_source("rec_made") is None  # a lambda: no importable path
    T.register("rec_pend2", _factory_for_test)
    assert T.task_source("rec_pend2") == f"{__name__}:_factory_for_test"
    assert resolve_config("quick", other).task == "rec_made"
    with pytest.raises(ValueError, match="built-in task"):
        T.register(dataclasses.replace(other, name="unicycle"))


def _factory_for_test():
    import rec_tasks

    return dataclasses.replace(rec_tasks.make(), name="rec_pend2")


def test_an_unavailable_task_says_so_in_one_line(tmp_path, monkeypatch, clean_registry):
    for ref, match in [("no_such_task", "unknown task 'no_such_task'; choose one of cartpole_swingup"),
                       ("no_such_module_xyz:task", "cannot import no_such_module_xyz"),
                       ("pipps.tasks:make_task_nope", "has no attribute 'make_task_nope'"),
                       ("pipps.tasks:PRESETS", "is a tuple, not a pipps.tasks.TaskSpec"),
                       ("no_colon_attr:", "is not MODULE:ATTRIBUTE")]:
        with pytest.raises(T.TaskUnavailable, match=match) as err:
            T.get_task(ref)
        assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="task: task 'gone': its source gone_mod:gone cannot be loaded here"):
        resolve_config("quick", "cartpole_swingup").replace(task="gone", task_source="gone_mod:gone")


def test_entry_points_of_installed_packages(tmp_path, monkeypatch, clean_registry):
    """A temporary dist-info on sys.path declares two tasks in the ``pipps.tasks`` group: one loads, by
    name and only when asked; the other's module is missing, which is said in one line."""
    (tmp_path / "ep_tasks.py").write_text(SOURCE.format(name="ep_pend", attribute="pendulum"))
    dist = tmp_path / "ep_tasks_pkg-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: ep-tasks-pkg\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[pipps.tasks]\nep_pend = ep_tasks:pendulum\nep_gone = ep_missing:task\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert {"ep_pend", "ep_gone"} <= set(T.task_names())
    assert "ep_tasks" not in __import__("sys").modules  # listed, not loaded
    spec = T.get_task("ep_pend")
    assert spec.name == "ep_pend" and T.task_source("ep_pend") == "ep_tasks:pendulum"
    cfg = resolve_config("quick", "ep_pend")
    assert cfg.task_source == "ep_tasks:pendulum"
    with pytest.raises(T.TaskUnavailable, match=r"the entry point 'ep_gone' \(ep_missing:task\): cannot import ep_missing"):
        T.get_task("ep_gone")
