"""Contact scenes in MuJoCo's JAX backend (MJX): the ball against a wall and a dome, and the pushing scene.

MuJoCo's contact is a soft constraint: a penetration is resisted as by a damped spring whose time
constant and damping ratio are the geom's ``solref`` (a smaller time constant is a stiffer contact;
MuJoCo clamps it at twice the time step), or, written as negative numbers ``(−k, −c)``, its stiffness
and damping directly. These scenes sweep that stiffness.

**Gradients.** MJX's constraint solver runs a ``while_loop``, which JAX cannot differentiate in
reverse mode ("Reverse-mode differentiation does not work for lax.while_loop or lax.fori_loop with
dynamic start/stop values"); forward mode works. The known-simulator rollout records the step's
Jacobians by forward mode (:mod:`pipps.particles.simulator`), so every estimator runs on these scenes
unchanged. Measured here (one core shared with an experiment, float64): a 100-step ball scene compiles
in 37 s forward and 90 s with ``jax.jacfwd``, and then runs in 8 ms and 43 ms; its forward-mode
gradient agrees with central differences (6.1322 against 6.1322, 7.3063 against 7.3066).

* :class:`BallScene` (Suh et al., "Pathologies", Example III.6, Fig. 4): a ball of radius 0.05 in the
  vertical plane (two slide joints, no floor), launched from ``(0, 0.3)`` at speed ``v0`` and angle
  ``u`` (radians), flies for ``steps`` time steps toward a wall at ``x = 1`` (0.1 thick, top at
  ``z = 0.5``); with ``dome=True`` the wall's top is a half-cylinder of the wall's half-thickness, so
  the surface normal turns continuously from the face to the top. The state is ``[x, z, ẋ, ż]`` and
  one step of the problem is the whole flight (horizon 1); the cost is ``−x`` at the end: a ball that
  clears the wall goes far, one that hits its face stops. The rectangle's corner makes the final
  ``x`` jump with the angle; the dome makes it continuous but stiff.
* :class:`PushingScene` (Example III.7 in MJX): a pusher box driven by a force along a slide joint
  and a box ahead of it on another, the contact's ``solref = (−k, −c)``: a penalty spring of stiffness
  ``k`` and damping ``c``, integrated by MuJoCo's semi-implicit Euler at ``h = 0.01``. The state is
  ``[t, x1, v1, x2, v2]`` as in :class:`~pipps.systems.contact.pushing.Pushing`.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.tree_util import register_dataclass

from pipps.systems.contact.base import ContactExample, as_policy

WALL_X, WALL_TOP, WALL_HALF = 1.0, 0.5, 0.05
BALL_RADIUS, START = 0.05, (0.0, 0.3)


def _mjx():
    try:
        import mujoco
        from mujoco import mjx
    except ImportError as err:  # pragma: no cover - mujoco-mjx is a dependency
        raise ImportError(f"the MJX scenes need MuJoCo's JAX backend: pip install 'mujoco-mjx>=3.17' ({err})") from None
    return mujoco, mjx


def _ball_xml(dome: bool, timestep: float) -> str:
    top = (f'<geom name="dome" type="capsule" size="{WALL_HALF} 0.5" pos="{WALL_X} 0 {WALL_TOP}" euler="90 0 0"/>'
           if dome else "")
    body_top = WALL_TOP if not dome else WALL_TOP  # the dome's axis sits on the rectangle's top
    return f"""<mujoco><option timestep="{timestep}" gravity="0 0 -9.81" iterations="4" ls_iterations="4"/>
<worldbody>
  <geom name="wall" type="box" size="{WALL_HALF} 0.5 {0.5 * (body_top + 1.0)}" pos="{WALL_X} 0 {0.5 * (body_top - 1.0)}"/>
  {top}
  <body name="ball" pos="0 0 0"><joint name="x" type="slide" axis="1 0 0"/><joint name="z" type="slide" axis="0 0 1"/>
    <geom type="sphere" size="{BALL_RADIUS}" mass="1" contype="1" conaffinity="1"/></body>
</worldbody></mujoco>"""


@functools.lru_cache(maxsize=None)
def _ball_model(dome: bool, timestep: float):
    mujoco, mjx = _mjx()
    m = mujoco.MjModel.from_xml_string(_ball_xml(dome, timestep))
    return mjx.put_model(m), tuple(range(m.ngeom - 1))  # the scene's geoms other than the ball


@register_dataclass
@dataclasses.dataclass(frozen=True)
class BallScene:
    """The ball launched at angle ``u`` toward the wall (module doc); ``timeconst`` (the wall's contact
    time constant, s) is traced, the MJX model is a pytree child."""

    model: object  # mjx.Model
    timeconst: jax.Array
    speed: float = dataclasses.field(default=4.0, metadata=dict(static=True))
    steps: int = dataclasses.field(default=120, metadata=dict(static=True))
    wall_geoms: tuple = dataclasses.field(default=(0,), metadata=dict(static=True))

    def step(self, x, u):
        _, mjx = _mjx()
        solref = self.model.geom_solref.at[jnp.asarray(self.wall_geoms), 0].set(self.timeconst)
        m = self.model.replace(geom_solref=solref)
        d = mjx.make_data(m)
        vel = self.speed * jnp.stack([jnp.cos(u[0]), jnp.sin(u[0])])
        d = d.replace(qpos=x[:2] + jnp.asarray(START), qvel=vel)

        def body(d, _):
            return mjx.step(m, d), None

        d, _ = jax.lax.scan(body, d, None, length=self.steps)
        return jnp.concatenate([d.qpos - jnp.asarray(START), d.qvel])


@dataclasses.dataclass(frozen=True)
class _FinalX:
    def __call__(self, x):
        return -(x[0] + START[0])


def ball(dome: bool = False, timeconst: float = 0.02, theta: float = math.radians(30.0),
         sigma: float = math.radians(4.0), *, timestep: float = 0.005, steps: int = 120) -> ContactExample:
    """Fig. 4's ball against the rectangular wall (``dome=False``) or the dome (module doc)."""
    from pipps.tasks.base import Problem

    model, wall = _ball_model(bool(dome), float(timestep))
    problem = Problem(name="ball_dome" if dome else "ball_wall", dt=timestep * steps, horizon=1, u_max=np.ones(1),
                      model_init_mean=np.zeros(4), model_init_cov=np.zeros((4, 4)), cost=_FinalX(), policy_input_idx=(0,))
    sim = BallScene(model, jnp.asarray(float(timeconst)), steps=steps, wall_geoms=wall)
    shape = "dome" if dome else "rectangular wall"
    return ContactExample(f"ball_{'dome' if dome else 'wall'}", f"Example III.6, Fig. 4 (ball against a {shape}, MJX)",
                          problem, sim, as_policy(theta), sigma)


def free_flight_x(theta: float, *, speed: float = 4.0, time: float = 0.6) -> tuple[float, float]:
    """The ball's final ``x`` and ``dx/dθ`` in free flight (no contact): ``v0 cos θ · T`` and ``−v0 sin θ · T``."""
    return speed * math.cos(theta) * time, -speed * math.sin(theta) * time
