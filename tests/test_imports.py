"""Importing pipps has no side effect on the process (docs/architecture.md, "Layers and imports").

Each check runs in a fresh interpreter, without this session's conftest, so JAX's 64-bit mode is
off there unless the code under test switches it on: ``import pipps`` must not import JAX or
gymnasium, the library's modules must not switch on float64 or register environments, the
float64 entry points must refuse to run in float32 and say what to do, and the gymnasium ids must
register through :func:`pipps.tasks.register_envs` or an id that names :mod:`pipps.tasks.envs`.
A last check reads the source: every module imports only from its own layer or a lower one
(docs/architecture.md, "Layers and imports").
"""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

ENV_IDS = ["pipps/CartPoleBalance-v0", "pipps/CartPoleSwingUp-v0", "pipps/Unicycle-v0"]
PACKAGE = Path(__file__).resolve().parents[1] / "pipps"

#: docs/architecture.md's layers; a module belongs to the longest prefix listed
LAYERS = {
    "pipps": 0, "pipps.precision": 0,
    "pipps.gaussian": 1, "pipps.costs": 1, "pipps.policies": 1,
    "pipps.tasks": 2, "pipps.gp": 2, "pipps.optimizers": 2,
    "pipps.rollout": 3, "pipps.particles": 3, "pipps.pilco": 3,
    "pipps.propagation": 4, "pipps.systems": 4,
    "pipps.stats": 5,
    "pipps.experiments": 6, "pipps.studies": 6, "pipps.charts": 6, "pipps.reporting": 6,
    "pipps.cli": 7, "pipps.cli_options": 7, "pipps.cli_report": 7, "pipps.demo": 7, "pipps.tasks.envs": 7,
    "pipps.tasks.gym_task": 7,
}
#: imports against the layering, each made on request inside a function
UPWARD = {("pipps.tasks", "pipps.tasks.envs"),  # register_envs() and the lazy ENV_IDS, PippsEnv
          ("pipps.tasks", "pipps.tasks.gym_task")}  # the lazy from_gymnasium


def fresh(code: str) -> dict:
    """Run ``code`` in a new interpreter and return the JSON object its last output line holds."""
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                          env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_import_pipps_loads_neither_jax_nor_gymnasium():
    out = fresh("""
        import json, sys
        import pipps
        print(json.dumps({"jax": "jax" in sys.modules, "gymnasium": "gymnasium" in sys.modules}))
    """)
    assert out == {"jax": False, "gymnasium": False}


def test_library_imports_change_no_global_state():
    out = fresh("""
        import json, sys
        import pipps.experiments, pipps.gp, pipps.particles, pipps.pilco, pipps.propagation, pipps.rollout
        import pipps.stats, pipps.studies, pipps.systems, pipps.tasks
        import jax
        seen = {"gymnasium": "gymnasium" in sys.modules, "x64": bool(jax.config.jax_enable_x64)}
        import gymnasium
        seen["before"] = sorted(i for i in gymnasium.registry if i.startswith("pipps/"))
        pipps.tasks.register_envs()
        pipps.tasks.register_envs()
        seen["after"] = sorted(i for i in gymnasium.registry if i.startswith("pipps/"))
        print(json.dumps(seen))
    """)
    assert out == {"gymnasium": False, "x64": False, "before": [], "after": ENV_IDS}


def test_float64_entry_points_refuse_float32_and_say_what_to_do():
    out = fresh("""
        import json
        import jax
        import numpy as np
        import pipps
        from pipps.gp import make_data
        from pipps.particles import RolloutConfig
        from pipps.pilco import objective
        from pipps.propagation import estimate, estimator, init_estimator_state
        from pipps.rollout import rollout
        from pipps.systems import reference_system
        from pipps.tasks import PippsEnv, make_task

        task, model, policy = reference_system()
        key, cfg, rp = jax.random.PRNGKey(0), RolloutConfig(num_particles=4), estimator("rp")
        calls = {
            "pipps.gp.make_data": lambda: make_data(np.zeros((3, 2)), np.zeros((3, 1))),
            "pipps.propagation.init_estimator_state":
                lambda: init_estimator_state(key, policy, model, problem=task, config=cfg, estimator=rp),
            "pipps.propagation.estimate":
                lambda: estimate(key, None, policy, model, problem=task, config=cfg, estimator=rp),
            "pipps.pilco.objective": lambda: objective(task, policy, model),
            "pipps.rollout.rollout": lambda: rollout(key, make_task("cartpole_swingup")),
            "PippsEnv": lambda: PippsEnv("cartpole_swingup"),
        }
        messages = {}
        for name, call in calls.items():
            try:
                call()
                messages[name] = None
            except pipps.Float64Required as err:
                messages[name] = str(err)
        pipps.enable_float64()
        data = make_data(np.zeros((3, 2)), np.arange(3.0)[:, None])
        print(json.dumps({"messages": messages, "dtype": str(data.inputs.dtype)}))
    """)
    for name, message in out["messages"].items():
        assert message is not None, f"{name} ran in float32"
        assert message.startswith(name) and "pipps.enable_float64()" in message and "jax_enable_x64" in message
    assert out["dtype"] == "float64"


def test_gymnasium_registers_the_envs_when_an_id_names_the_module():
    out = fresh("""
        import json
        import gymnasium
        import pipps
        pipps.enable_float64()
        env = gymnasium.make("pipps.tasks.envs:pipps/Unicycle-v0", disable_env_checker=True)
        ids = sorted(i for i in gymnasium.registry if i.startswith("pipps/"))
        print(json.dumps({"task": env.unwrapped.task.name, "ids": ids}))
    """)
    assert out == {"task": "unicycle", "ids": ENV_IDS}


def layer(module: str) -> int:
    parts = module.split(".")
    return next(LAYERS[".".join(parts[:i])] for i in range(len(parts), 0, -1) if ".".join(parts[:i]) in LAYERS)


def imported_modules(node: ast.AST) -> list[str]:
    """The pipps modules an import statement loads (``from pipps.a import b`` loads pipps.a.b if it is one)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names if a.name.split(".")[0] == "pipps"]
    if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "pipps":
        base = PACKAGE.parent / node.module.replace(".", "/")
        return [f"{node.module}.{a.name}" if (base / a.name).is_dir() or (base / f"{a.name}.py").exists()
                else node.module for a in node.names]
    return []


def test_modules_import_only_their_layer_and_below():
    upward = set()
    for path in sorted(PACKAGE.rglob("*.py")):
        module = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts).removesuffix(".__init__")
        for node in ast.walk(ast.parse(path.read_text())):
            upward |= {(module, target) for target in imported_modules(node) if layer(target) > layer(module)}
    assert upward == UPWARD
