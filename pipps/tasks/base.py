"""The planning problem, the true system, and the task that pairs them.

Two frozen dataclasses of numbers and pure JAX functions, never pytrees (jitted code closes
over them):

* :class:`Problem` — what the learner and PILCO plan on: the model state, the control, the
  horizon, the planning start distribution, the cost and the input maps. Everything that only
  plans (:mod:`pipps.particles`, :mod:`pipps.propagation`, :mod:`pipps.pilco`,
  :mod:`pipps.systems`, :mod:`pipps.studies`, :mod:`pipps.stats`) takes a Problem.
* :class:`Simulator` — the true system that produces data: the ODE, its integration, the
  simulator start distribution, the observation noise, the random actions, the fall condition,
  and ``sim_to_model``, the map from its state into the problem's model state. A true system
  that JAX cannot trace (a gymnasium environment, a robot) is a :class:`HostSimulator`: the
  learning loop steps it from Python (:func:`pipps.rollout.host_rollout`).

A :class:`Task` is one of each (``task.problem``, ``task.simulator``) with the same control
interval ``dt``: what ``make_task`` builds, and what the true-system code (:mod:`pipps.rollout`,
:mod:`pipps.tasks.envs`, the experiment programs) takes, since a rollout on the true system needs
the problem's cost and policy input too. For reading, ``task.<field>`` forwards to the half that
has the field (``task.horizon`` is ``task.problem.horizon``, ``task.step`` is
``task.simulator.step``). A planning problem without a true system (the reference systems of
:mod:`pipps.systems`, whose dynamics are their model) is a Problem only.

**Checked at construction.** Each record checks its own fields in ``__post_init__`` and raises
one ``ValueError`` naming the field: index sets in range and without duplicates, covariances
symmetric positive semi-definite, arrays of the right shape and finite, sizes that agree; a Task
also checks that its halves fit each other and the cost (``dt`` equal, the ODE, ``sim_to_model``,
``fallen`` and the cost evaluated on shapes alone, :func:`jax.eval_shape`). Arrays are stored as
read-only float64 copies and index sets as tuples of ``int``, so a record is never changed after
it was checked.

The state has four representations (as in PILCO):

* the simulator state ``s`` that the ODE integrates (``Simulator.sim_dim`` components);
* the model state ``x = sim_to_model(s)`` that the GP predicts and the cost is defined on
  (``Problem.model_dim``);
* the augmented model state ``x̃ = [x; sin x_a, cos x_a (a in angle_idx)]``;
* the control ``u = u_max ⊙ sat(ũ)``.

All index sets here are 0-based (PILCO's MATLAB code writes them 1-based).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Protocol

import jax
import jax.numpy as jnp
import numpy as np


class Cost(Protocol):
    """A per-state cost on the model state with its closed-form Gaussian expectation."""

    def __call__(self, x: jax.Array) -> jax.Array:  # c(x) for one model state
        ...

    def expected(self, mean: jax.Array, cov: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(E[c], Var[c]) for x ~ N(mean, cov), moment-matched as PILCO does (docs/costs.md)."""
        ...


# -- checks: each raises one ValueError naming ``owner.field`` ------------------------------------------


def _fail(owner: str, name: str, msg: str):
    raise ValueError(f"{owner}.{name}: {msg}")


def _set(obj, name: str, value) -> None:
    object.__setattr__(obj, name, value)


def _count(owner: str, name: str, value, lowest: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < lowest:
        _fail(owner, name, f"must be an integer >= {lowest}, got {value!r}")
    return int(value)


def _positive(owner: str, name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        _fail(owner, name, f"must be a finite number > 0, got {value!r}")
    if not (math.isfinite(v) and v > 0):
        _fail(owner, name, f"must be a finite number > 0, got {value!r}")
    return v


def _array(owner: str, name: str, value, shape: tuple[int, ...]) -> np.ndarray:
    """A read-only float64 copy of ``value`` of ``shape``, every entry finite."""
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        _fail(owner, name, f"must be an array of numbers of shape {shape}, got {value!r}")
    if arr.shape != shape:
        _fail(owner, name, f"must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        _fail(owner, name, f"must be finite, got {arr.tolist()}")
    arr.setflags(write=False)
    return arr


def _covariance(owner: str, name: str, value, dim: int) -> np.ndarray:
    c = _array(owner, name, value, (dim, dim))
    if not np.allclose(c, c.T, rtol=0.0, atol=1e-12):
        _fail(owner, name, "must be symmetric")
    if dim and np.linalg.eigvalsh(c).min() < -1e-12:
        _fail(owner, name, f"must be positive semi-definite (smallest eigenvalue {np.linalg.eigvalsh(c).min():.3g})")
    return c


def _indices(owner: str, name: str, value, size: int, what: str) -> tuple[int, ...]:
    """An index set into ``size`` components (``what`` names them): integers in range, no duplicates."""
    try:
        idx = tuple(value)
    except TypeError:
        _fail(owner, name, f"must be a sequence of integers, got {value!r}")
    for i in idx:
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)):
            _fail(owner, name, f"must hold integers, got {i!r}")
        if not 0 <= i < size:
            _fail(owner, name, f"index {int(i)} out of range [0, {size}) ({what} has {size} components)")
    idx = tuple(int(i) for i in idx)
    if len(set(idx)) != len(idx):
        _fail(owner, name, f"holds duplicates: {idx}")
    return idx


def _callable(owner: str, name: str, value, optional: bool = False) -> None:
    if value is None and optional:
        return
    if not callable(value):
        _fail(owner, name, f"must be callable, got {value!r}")


def _shape_of(owner: str, name: str, fn, *args: tuple[int, ...]) -> tuple[int, ...]:
    """The output shape of ``fn`` on float arrays of the given shapes, found by tracing alone."""
    specs = [jax.ShapeDtypeStruct(shape, jnp.result_type(float)) for shape in args]
    try:
        out = jax.eval_shape(fn, *specs)
    except Exception as err:  # noqa: BLE001 - any failure of the user's function is this field's error
        shapes = " and ".join(str(s) for s in args)
        _fail(owner, name, f"fails on inputs of shape {shapes}: {type(err).__name__}: {str(err).splitlines()[0]}")
    if not hasattr(out, "shape"):
        _fail(owner, name, f"must return one array, got {out!r}")
    return tuple(out.shape)


# -- the planning problem ---------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """The planning problem: model state, control, horizon, start, cost and input maps.

    ``model_dim`` and ``action_dim`` default to the sizes of ``model_init_mean`` and ``u_max``;
    ``gp_input_idx`` and ``policy_input_idx`` default to the whole augmented state ``x̃``.
    ``pilco_budget`` is PILCO's policy-search budget on this problem, ``(length, evaluations per
    line search)`` as minimize.m counts them (:func:`pipps.pilco.pilco_budget`; None: its default).

    Raises:
      ValueError: a field out of shape or range, naming it (module docstring).
    """

    name: str
    dt: float
    horizon: int
    u_max: np.ndarray  # (action_dim,) control limits ū
    model_init_mean: np.ndarray  # (model_dim,) planning start mean μ0^x
    model_init_cov: np.ndarray  # (model_dim, model_dim) planning start covariance Σ0^x
    cost: Cost
    model_dim: int | None = None
    action_dim: int | None = None
    angle_idx: tuple[int, ...] = ()  # model-state components augmented with (sin, cos)
    gp_input_idx: tuple[int, ...] | None = None  # indices into x̃ fed to the GP (the control is appended)
    policy_input_idx: tuple[int, ...] | None = None  # indices into x̃ fed to the policy
    pilco_budget: tuple[int, int] | None = None

    def __post_init__(self):
        own = "Problem"
        if not isinstance(self.name, str) or not self.name:
            _fail(own, "name", f"must be a non-empty string, got {self.name!r}")
        _set(self, "dt", _positive(own, "dt", self.dt))
        _set(self, "horizon", _count(own, "horizon", self.horizon))
        action_dim, model_dim = self.action_dim, self.model_dim
        if action_dim is None:
            if np.ndim(self.u_max) != 1:
                _fail(own, "u_max", f"must be a 1-d array (one limit per control), got shape {np.shape(self.u_max)}")
            action_dim = np.shape(self.u_max)[0]
        if model_dim is None:
            if np.ndim(self.model_init_mean) != 1:
                _fail(own, "model_init_mean", f"must be a 1-d array, got shape {np.shape(self.model_init_mean)}")
            model_dim = np.shape(self.model_init_mean)[0]
        _set(self, "action_dim", _count(own, "action_dim", action_dim))
        _set(self, "model_dim", _count(own, "model_dim", model_dim))
        _set(self, "u_max", _array(own, "u_max", self.u_max, (self.action_dim,)))
        if not np.all(self.u_max > 0):
            _fail(own, "u_max", f"must be > 0, got {self.u_max.tolist()}")
        _set(self, "model_init_mean", _array(own, "model_init_mean", self.model_init_mean, (self.model_dim,)))
        _set(self, "model_init_cov", _covariance(own, "model_init_cov", self.model_init_cov, self.model_dim))
        _set(self, "angle_idx", _indices(own, "angle_idx", self.angle_idx, self.model_dim, "the model state"))
        for name in ("gp_input_idx", "policy_input_idx"):
            value = getattr(self, name)
            value = range(self.augmented_dim) if value is None else value
            _set(self, name, _indices(own, name, value, self.augmented_dim, "the augmented model state x̃"))
        if self.pilco_budget is not None:
            budget = tuple(self.pilco_budget)
            if len(budget) != 2 or any(isinstance(b, bool) or not isinstance(b, (int, np.integer)) for b in budget) \
                    or budget[0] == 0 or budget[1] < 1:
                _fail(own, "pilco_budget", f"must be (length != 0, evaluations per line search >= 1), got {budget!r}")
            _set(self, "pilco_budget", tuple(int(b) for b in budget))
        _callable(own, "cost", self.cost)
        shape = _shape_of(own, "cost", self.cost, (self.model_dim,))
        if shape != ():
            _fail(own, "cost", f"must return a scalar for a model state of shape ({self.model_dim},), got shape {shape}")

    def augment(self, x: jax.Array) -> jax.Array:
        """x̃ = [x; sin x_a, cos x_a] with each angle's pair in (sin, cos) order."""
        if not self.angle_idx:
            return x
        a = x[..., jnp.asarray(self.angle_idx)]
        trig = jnp.stack([jnp.sin(a), jnp.cos(a)], axis=-1).reshape(*a.shape[:-1], 2 * a.shape[-1])
        return jnp.concatenate([x, trig], axis=-1)

    @property
    def augmented_dim(self) -> int:
        return self.model_dim + 2 * len(self.angle_idx)

    @property
    def gp_input_dim(self) -> int:
        return len(self.gp_input_idx) + self.action_dim

    @property
    def policy_input_dim(self) -> int:
        return len(self.policy_input_idx)

    def gp_input(self, x: jax.Array, u: jax.Array) -> jax.Array:
        """z = [x̃[I]; u], the GP input for model state x and control u."""
        xa = self.augment(x)
        return jnp.concatenate([xa[..., jnp.asarray(self.gp_input_idx)], u], axis=-1)

    def policy_input(self, x: jax.Array) -> jax.Array:
        """x̃[P], the policy input for model state x."""
        return self.augment(x)[..., jnp.asarray(self.policy_input_idx)]


# -- the true system ----------------------------------------------------------------------------------


def identity(s: jax.Array) -> jax.Array:
    """``sim_to_model`` of a system whose model state is its simulator state."""
    return s


def _noise(owner: str, value, sim_dim: int) -> np.ndarray:
    """Observation-noise standard deviations: one per component, or one number for all, >= 0."""
    value = np.zeros(sim_dim) if value is None else value
    if np.ndim(value) == 0:
        value = np.full(sim_dim, value, dtype=np.float64)
    std = _array(owner, "obs_noise_std", value, (sim_dim,))
    if not np.all(std >= 0):
        _fail(owner, "obs_noise_std", f"must be >= 0, got {std.tolist()}")
    return std


def _random_actions(owner: str, value) -> np.ndarray | None:
    """``u_rand``: None (the Task takes the problem's ``u_max``) or a 1-d array >= 0."""
    if value is None:
        return None
    if np.ndim(value) != 1:
        _fail(owner, "u_rand", f"must be a 1-d array (one bound per control), got shape {np.shape(value)}")
    u = _array(owner, "u_rand", value, np.shape(value))
    if not np.all(u >= 0):
        _fail(owner, "u_rand", f"must be >= 0, got {u.tolist()}")
    return u


def _noise_multiplier(owner: str, value) -> float:
    try:
        k = float(value)
    except (TypeError, ValueError):
        _fail(owner, "noise_multiplier", f"must be a finite number >= 0, got {value!r}")
    if not (math.isfinite(k) and k >= 0):
        _fail(owner, "noise_multiplier", f"must be a finite number >= 0, got {value!r}")
    return k


def _check_system_fields(sim, own: str) -> None:
    """Validate and normalise the fields both kinds of true system share (name, dt, the start
    distribution, the observation noise, random actions, wrapped components, ``sim_to_model``)."""
    if not isinstance(sim.name, str) or not sim.name:
        _fail(own, "name", f"must be a non-empty string, got {sim.name!r}")
    _set(sim, "dt", _positive(own, "dt", sim.dt))
    sim_dim = sim.sim_dim
    if sim_dim is None:
        if np.ndim(sim.init_mean) != 1:
            _fail(own, "init_mean", f"must be a 1-d array, got shape {np.shape(sim.init_mean)}")
        sim_dim = np.shape(sim.init_mean)[0]
    _set(sim, "sim_dim", _count(own, "sim_dim", sim_dim))
    _set(sim, "init_mean", _array(own, "init_mean", sim.init_mean, (sim.sim_dim,)))
    _set(sim, "init_cov", _covariance(own, "init_cov", sim.init_cov, sim.sim_dim))
    _set(sim, "obs_noise_std", _noise(own, sim.obs_noise_std, sim.sim_dim))
    _set(sim, "u_rand", _random_actions(own, sim.u_rand))
    _set(sim, "noise_multiplier", _noise_multiplier(own, sim.noise_multiplier))
    _set(sim, "periodic", tuple(sim.periodic))
    _callable(own, "sim_to_model", sim.sim_to_model)


@dataclasses.dataclass(frozen=True, eq=False)
class Simulator:
    """The true system: what a rollout integrates, observes and maps into the model state.

    ``sim_dim`` defaults to the size of ``init_mean``; ``obs_noise_std`` to no noise (one number
    is the same std on every component); ``u_rand`` to the problem's ``u_max`` (set by the
    :class:`Task`); ``sim_to_model`` to the identity. ``periodic`` lists model-state components
    that ``sim_to_model`` returns wrapped (an angle read from an observation, in (−π, π]): their
    one-step differences, the GP's targets, are wrapped as well (:func:`pipps.rollout.training_pairs`).

    Raises:
      ValueError: a field out of shape or range, naming it (module docstring).
    """

    name: str
    dt: float  # the control interval; a Task's problem has the same
    ode: Callable[[jax.Array, jax.Array], jax.Array]  # ṡ = ode(s, u)
    init_mean: np.ndarray  # (sim_dim,) simulator start mean μ0
    init_cov: np.ndarray  # (sim_dim, sim_dim) simulator start covariance Σ0
    obs_noise_std: np.ndarray | float | None = None  # (sim_dim,) observation noise std, already scaled by √k
    u_rand: np.ndarray | None = None  # (action_dim,) random actions are U[-u_rand, u_rand], unsquashed
    sim_to_model: Callable[[jax.Array], jax.Array] = identity  # x = sim_to_model(s), into the problem's model state
    fallen: Callable[[jax.Array], jax.Array] | None = None  # True where s violates the constraint
    substeps: int = 100  # integrator sub-steps per control interval (see integrate.py)
    noise_multiplier: float = 1.0  # k: observation noise variance is k·σ_base²
    sim_dim: int | None = None
    periodic: tuple[int, ...] = ()  # model-state components sim_to_model returns wrapped into (−π, π]

    def __post_init__(self):
        own = "Simulator"
        _check_system_fields(self, own)
        _set(self, "substeps", _count(own, "substeps", self.substeps))
        _callable(own, "ode", self.ode)
        _callable(own, "fallen", self.fallen, optional=True)

    def step(self, s: jax.Array, u: jax.Array) -> jax.Array:
        """One control interval of the true system: integrate ṡ = ode(s, u) over dt, u held."""
        from pipps.tasks.integrate import integrate_interval

        return integrate_interval(self.ode, s, u, self.dt, self.substeps)


class HostSystem(Protocol):
    """A true system stepped from Python: what a :class:`HostSimulator`'s ``make_system`` returns."""

    def reset(self, seed: int) -> np.ndarray:
        """Start an episode from the system's own start distribution, seeded; the first state (sim_dim,)."""
        ...

    def step(self, u: np.ndarray) -> tuple[np.ndarray, bool]:
        """Apply the control for one control interval: the next state and whether the episode ended there
        (a fall: the transition is not valid, and the system is not stepped again before a reset)."""
        ...


@dataclasses.dataclass(frozen=True, eq=False)
class HostSimulator:
    """A true system that JAX cannot trace (a gymnasium environment, a robot): the learning loop
    steps it from Python (:func:`pipps.rollout.host_rollout`), one episode at a time, seed by seed.

    ``make_system()`` builds the :class:`HostSystem` in the process that steps it (a sweep's worker
    builds its own; nothing unpicklable travels). Its state is what ``reset`` and ``step`` return:
    an environment's observation. The fields shared with :class:`Simulator` mean the same: the
    observation noise pipps adds on top (the learner sees ``s + ε``), the random-action range of
    the random trials, the map into the model state (a JAX function) and its ``periodic``
    components. ``init_mean`` and ``init_cov`` describe the system's own start distribution (for
    reading; ``reset`` draws from it).

    Raises:
      ValueError: a field out of shape or range, naming it.
    """

    name: str
    dt: float
    make_system: Callable[[], HostSystem]
    init_mean: np.ndarray
    init_cov: np.ndarray
    obs_noise_std: np.ndarray | float | None = None
    u_rand: np.ndarray | None = None
    sim_to_model: Callable[[jax.Array], jax.Array] = identity
    noise_multiplier: float = 1.0
    sim_dim: int | None = None
    periodic: tuple[int, ...] = ()
    fallen = None  # the system reports a fall itself (HostSystem.step)

    def __post_init__(self):
        own = "HostSimulator"
        _check_system_fields(self, own)
        _callable(own, "make_system", self.make_system)

    def system(self) -> HostSystem:
        """This process's system, built on first use."""
        built = self.__dict__.get("_system")
        if built is None:
            built = self.make_system()
            _set(self, "_system", built)
        return built

    def __getstate__(self) -> dict[str, Any]:  # a sweep's worker builds its own system
        return {k: v for k, v in self.__dict__.items() if k != "_system"}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)


# -- the pair -----------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class Task:
    """A planning problem and the true system it describes, under one preset.

    ``task.<field>`` reads the field (or method) of whichever half has it, the problem first
    (``name`` and ``dt``, which both have, agree); code that needs only one half takes that half.
    A simulator without ``u_rand`` takes the problem's ``u_max``.

    Raises:
      ValueError: the two halves disagree on ``dt``, on the number of controls, or on the model
        state (``sim_to_model``'s output against ``model_dim``); the ODE, ``sim_to_model`` or
        ``fallen`` fail on the simulator state, or ``periodic`` is out of range.
    """

    problem: Problem
    simulator: Simulator | HostSimulator
    preset: str = "thesis"

    def __post_init__(self):
        p, sim = self.problem, self.simulator
        if not isinstance(p, Problem):
            _fail("Task", "problem", f"must be a Problem, got {type(p).__name__}")
        if not isinstance(sim, (Simulator, HostSimulator)):
            _fail("Task", "simulator", f"must be a Simulator or HostSimulator, got {type(sim).__name__}")
        if p.dt != sim.dt:
            raise ValueError(f"problem and simulator differ in dt: {p.dt} and {sim.dt}")
        if sim.u_rand is None:
            _set(self, "simulator", dataclasses.replace(sim, u_rand=p.u_max))
            sim = self.simulator
        if np.shape(sim.u_rand) != (p.action_dim,):
            raise ValueError(f"simulator.u_rand must have shape ({p.action_dim},) (the problem's "
                             f"action_dim), got {np.shape(sim.u_rand)}")
        _indices("Simulator", "periodic", sim.periodic, p.model_dim, "the model state")
        shape = _shape_of("Simulator", "sim_to_model", sim.sim_to_model, (sim.sim_dim,))
        if shape != (p.model_dim,):
            _fail("Simulator", "sim_to_model", f"maps a simulator state of shape ({sim.sim_dim},) to shape {shape}, "
                                               f"the problem's model state has ({p.model_dim},)")
        if isinstance(sim, Simulator):
            shape = _shape_of("Simulator", "ode", sim.ode, (sim.sim_dim,), (p.action_dim,))
            if shape != (sim.sim_dim,):
                _fail("Simulator", "ode", f"returns shape {shape} for a state of shape ({sim.sim_dim},) and a control "
                                          f"of shape ({p.action_dim},); it must return ṡ of the state's shape")
            if sim.fallen is not None:
                shape = _shape_of("Simulator", "fallen", sim.fallen, (sim.sim_dim,))
                if shape != ():
                    _fail("Simulator", "fallen", f"must return one boolean per state, got shape {shape}")

    @property
    def host_stepped(self) -> bool:
        """Whether the true system is stepped from Python (a :class:`HostSimulator`), not traced by JAX."""
        return isinstance(self.simulator, HostSimulator)

    def __getattr__(self, attr: str):
        # Only called when ordinary lookup fails: forward reads to the half that has the field.
        if attr.startswith("__"):
            raise AttributeError(attr)
        for half in ("problem", "simulator"):
            part = self.__dict__.get(half)
            if part is not None and hasattr(part, attr):
                return getattr(part, attr)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {attr!r} (neither its problem nor its "
                             "simulator has it)")
