"""The kinds of piece an estimator is composed of, as types, and the data that passes between them.

An estimator (:class:`~pipps.propagation.estimators.Estimator`) is cost terms, one or two gradient
parts and a combiner, run by a sweep schedule. Every piece is a strategy (a frozen dataclass that is
a pytree, :mod:`~pipps.propagation.strategy`) with an ``(init, step)`` pair that owns its state, as
an optax transformation owns its state: ``init(context)`` gives the piece's state before the first
estimate, and its step method takes the state first and returns ``(next_state, output)``. The
composition threads the pieces' states as one tuple, :class:`EstimatorState`, in the pieces' order;
no piece reads another's state.

**A piece's state is per step.** Every leaf has a leading axis of T steps. The reverse sweep hands
step t's slice to the piece's step method and stacks the slices it returns into the next state, so
a memory across optimizer iterations ("the previous iteration's mean return at t", "the previous
iteration's k_LR at t") is a piece's own state. A piece without memory has the state ``()``.

The kinds, each a :class:`typing.Protocol` that every built-in piece satisfies
(tests/test_estimator_pieces.py checks their methods' signatures):

=================  ==================================================================================
:class:`CostTerms`  what a particle adds to the returns ``G`` and to the pathwise chain at a step
:class:`GradientPart`  one step's ζ-cotangent ``γ_{i,t}``, of kind pathwise or likelihood ratio
:class:`Combiner`  the weight ``k_LR`` on the LR part and the mix of the parts' gradients and messages
:class:`WeightSource`  inside a two-part combiner: where ``k_LR`` comes from
:class:`Schedule`  how many sweeps over which particles make one estimate
=================  ==================================================================================

Every piece also says whether its state after ``init`` is a *cold start* (``cold_start``): then the
first estimate falls back on its own batch (the "previous" ``k_LR`` uses this batch's weight), and
only the state an estimate leaves is what later optimizer iterations read. A piece that fits a
Gaussian to the particles at every step (DEL's cost terms and LR part) says so with
``fits_density = True``: the estimator then needs more particles than the model state has
dimensions, and the CLI's checks ask the composed estimator (``Estimator.fits_density``), not its
name. A piece without the attribute fits nothing.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Protocol, runtime_checkable

import jax
import jax.numpy as jnp

from pipps.propagation.lr import ZetaGrad

PATHWISE = "pathwise"
LIKELIHOOD_RATIO = "likelihood_ratio"

State = Any  # a piece's state: a pytree whose leaves have a leading axis of T steps, or ()


class InitContext(NamedTuple):
    """What a piece's ``init`` may read."""

    steps: int  # T, the length of every state leaf's leading axis
    num_actions: int  # the action dimension (a weight per action coordinate needs it)
    mean_returns: Callable[[], jax.Array]  # (T,) mean return-to-go of one extra independent rollout


class EstimatorState(NamedTuple):
    """What an estimator carries between optimizer iterations: each piece's own state."""

    costs: State
    parts: tuple  # one state per gradient part, in the parts' order
    combiner: State


class MeanReturn(NamedTuple):
    """The state of a piece with the "previous" baseline (BIW-LR, DEL)."""

    mean_return: jax.Array  # (T,) mean_i G_{i,t} of the previous iteration (first: of the extra rollout)


class PreviousBaseline:
    """What a piece with a ``baseline`` setting shares (BIW-LR, both DELs): with "previous", its state
    is the previous iteration's mean return per step (first: of the extra rollout); otherwise ``()``."""

    cold_start = False  # the first iteration's baseline comes from the extra rollout

    def init(self, context: InitContext) -> MeanReturn | tuple:
        return MeanReturn(context.mean_returns()) if self.baseline == "previous" else ()

    def previous_baseline(self, state, returns: jax.Array) -> tuple[jax.Array | float, MeanReturn | tuple]:
        """(``b_t``, the next state): the stored mean return and this batch's, or (0, ``()``)."""
        if self.baseline != "previous":
            return 0.0, state
        return state.mean_return, MeanReturn(jnp.mean(returns))


class Stateless:
    """What a piece without memory shares: the state ``()``."""

    cold_start = False

    def init(self, context: InitContext) -> tuple:
        del context
        return ()


class StepCosts(NamedTuple):
    """One step's cost terms, per particle."""

    cost: jax.Array  # c_i, added to the returns G_i, (P,)
    gradient: jax.Array | None  # ∂c_i/∂x_i started down the pathwise chain, (P, D); None if not asked for
    objective: jax.Array  # the step's term of the objective being differentiated


class StepInputs(NamedTuple):
    """What a gradient part reads at step t of the sweep, per particle.

    The sample is the step's sampled node: the next state ``x_{i,t}`` (the thesis; D components) or,
    with noise on the actions, the action ``u_{i,t}`` (F components), whose ζ is ``(π(x̃[P]), σ_u)``."""

    x: jax.Array  # the sample x_{i,t}, (P, D)
    mean: jax.Array  # its mean μ_{i,t}, (P, D)
    std: jax.Array  # its standard deviation s_{i,t}, (P, D)
    eps: jax.Array  # its standardised noise ε_{i,t}, (P, D)
    returns: jax.Array  # G_{i,t}, (P,)
    carried: jax.Array  # ∂G_i/∂(sample) passed back from step t+1, (P, D)
    cost_gradient: jax.Array | None  # the cost terms' ∂c_i/∂(sample), (P, D)
    total_returns: jax.Array | None = None  # V_i = Σ_t c_{i,t}, (P,), where a part reads it (``reads``)
    nominal_returns: jax.Array | None = None  # the zero-noise rollout's return-to-go from t, (P,), where read
    nominal_total_returns: jax.Array | None = None  # the zero-noise rollout's whole return, (P,), where read


class PartCotangents(NamedTuple):
    """One step's gradient parts as the combiner receives them (in the parts' order)."""

    zeta: tuple  # each part's ζ-cotangent γ_{i,t} (ZetaGrad of (P, D) arrays)
    z: jax.Array  # (K, P, Dz) each part's cotangent on the GP input z = [x̃[I]; u], u last
    num_actions: int  # the last num_actions entries of z are the action u_{t−1} (static)
    pull_back: Callable  # (K', P, Dz) z-cotangents → (θ-cotangents (K', P, n_θ), x-cotangents (K', P, D) or None)
    direct: jax.Array | None = None  # (P, D) the message's path that bypasses ζ, the same for every part; None: γ_μ

    def message(self, i: int, cx: jax.Array) -> jax.Array:
        """Part ``i``'s message to the previous state from its pulled-back x-cotangent ``cx``: plus the
        path that bypasses ζ — at the thesis' node ``γ_μ`` (``μ = x + m_Δ`` holds the state itself), at
        the action node the simulator's direct path ``(∂x'/∂x)ᵀ ∂G/∂x'`` (``direct``)."""
        return cx + (self.zeta[i].mean if self.direct is None else self.direct)

    def gradients_and_messages(self):
        """Every part pulled back at once: θ-gradients (K, P, n_θ) and, where a pathwise part reads
        them, the messages ``∂G/∂x_{i,t−1} = (∂z/∂x)ᵀ c_z + γ_μ`` of each part (else None; at the action
        node the direct path in place of γ_μ, :meth:`message`)."""
        g, cx = self.pull_back(self.z)
        messages = None if cx is None else [self.message(i, cx[i]) for i in range(len(self.zeta))]
        return g, messages


class Combined(NamedTuple):
    """One step's combination of the gradient parts."""

    k: jax.Array  # the weight used on the LR part (its mean over particles for a per-particle weight)
    k_batch: jax.Array  # the weight this batch's statistics give
    variances: tuple  # σ² = trace Var_i[g_{i,t}] of each part, in the parts' order
    gradient: jax.Array  # (P, n_θ) each particle's contribution at this step
    message: jax.Array | None  # (P, D) ∂G_i/∂x_{i,t−1} passed back; None where no part reads it


class StepDiagnostics(NamedTuple):
    """Per-step diagnostics of one estimate, each (T,), step t = 1..T in order."""

    k_lr: jax.Array  # the weight used on the LR part (0 for RP, 1 for LR)
    k_lr_batch: jax.Array  # the weight this batch's variances give
    var_rp: jax.Array  # σ²_RP = trace Var_i[g^RP_{i,t}] (NaN if the RP part is off)
    var_lr: jax.Array  # σ²_LR (NaN if the LR part is off)
    mean_return: jax.Array  # mean_i G_{i,t}
    objective: jax.Array  # the step's objective term: mean_i c_{i,t}, or Ē_t under shaping
    nonfinite: jax.Array  # bool: a per-particle gradient at this step was not finite


class SweepOutput(NamedTuple):
    contributions: jax.Array  # (P, n_θ) each particle's total contribution Σ_t g_{i,t}
    diagnostics: StepDiagnostics


@runtime_checkable
class CostTerms(Protocol):
    """What each particle contributes at a step: its cost for the returns and its cost gradient."""

    feeds_likelihood_ratio: bool  # its costs may be weighed by an LR part (DEL's may not)
    cold_start: bool

    def init(self, context: InitContext) -> State: ...

    def returns(self, cost, x: jax.Array, c: jax.Array) -> jax.Array:
        """``c_i`` alone, (P,): what the particle adds to the returns (for the extra rollout's mean)."""

    def step(self, state: State, cost, x: jax.Array, c: jax.Array, returns_next: jax.Array, *,
             gradient: bool) -> tuple[State, StepCosts]: ...


@runtime_checkable
class GradientPart(Protocol):
    """One step's particles → a ζ-cotangent γ_{i,t}; ``kind`` is :data:`PATHWISE` or :data:`LIKELIHOOD_RATIO`."""

    kind: str
    cold_start: bool

    def init(self, context: InitContext) -> State: ...

    def zeta(self, state: State, inputs: StepInputs, config) -> tuple[State, ZetaGrad]: ...


@runtime_checkable
class Combiner(Protocol):
    """One step's parts → the weight on the LR part, the step's contributions and the message λ."""

    name: str
    num_parts: int  # how many parts it weighs: 1 (single) or 2 (a pathwise and an LR part)
    k_lr: str | float | None  # its weight source's setting ("previous", 0.3, ...); None for one part
    cold_start: bool

    def init(self, context: InitContext) -> State: ...

    def combine(self, state: State, kinds: tuple[str, ...], parts: PartCotangents) -> tuple[State, Combined]: ...


@runtime_checkable
class WeighsTwoParts(Combiner, Protocol):
    """A combiner of a pathwise and an LR part whose weights come from a :class:`WeightSource`; its
    state is its source's state (so a schedule can run it with a source of its own choosing)."""

    source: WeightSource

    def with_source(self, source: WeightSource) -> WeighsTwoParts: ...


@runtime_checkable
class WeightSource(Protocol):
    """Where a two-part combiner's ``k_LR`` comes from, given this batch's statistics.

    ``init(context, weight_shape)``: ``weight_shape`` is the shape of one step's weight, ``()`` for
    one weight per step or ``(1 + num_actions,)`` at the action nodes. ``weight`` returns one weight
    (scalar) or one per particle ((P,)), and takes ``rule.batch_weight`` only through ``k_batch``
    or, for a weight from the other particles, by calling it on their statistics.
    """

    k_lr: str | float  # its setting: a name of :data:`~pipps.propagation.weights.WEIGHT_SOURCES`, or the number
    cold_start: bool

    def init(self, context: InitContext, weight_shape: tuple) -> State: ...

    def weight(self, state: State, rule, g_rp: jax.Array, g_lr: jax.Array,
               k_batch: jax.Array) -> tuple[State, jax.Array]: ...


@runtime_checkable
class Schedule(Protocol):
    """How an estimate sweeps the particle record: one reverse sweep, or several over subsets."""

    name: str

    def problem(self, estimator) -> str | None:
        """Why this schedule cannot run ``estimator``, or None."""

    def sweep(self, problem, policy, record, config, estimator, state: EstimatorState) -> tuple[EstimatorState, SweepOutput]: ...
