"""Pytrees and configuration of the GP dynamics model (docs/gp.md).

* :class:`GPHyper` — unconstrained hyperparameters ψ_a = [log ℓ_a, log σ_f,a, log σ_n,a]
  of the E independent SE-ARD GPs, stored output-major.
* :class:`GPData` — a (possibly padded) training set; rows with ``mask=False`` are padding
  and have exactly no effect on training or prediction.
* :class:`GPPosterior` — what prediction and moment matching need, computed once per
  training: ``beta`` and ``inv`` for the full GP, or their FITC counterparts.
* :class:`FitState` — what the next training warm-starts from (hyperparameters, inducing inputs).
* :class:`GPConfig` — settings; a pytree whose numbers are traced and whose structural
  settings are static metadata.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp


class GPHyper(NamedTuple):
    """Unconstrained SE-ARD hyperparameters of E independent GPs.

    Attributes:
      log_lengthscale: (E, Dz) log ℓ_{a,d}.
      log_signal: (E,) log σ_f,a.
      log_noise: (E,) log σ_n,a.
    """

    log_lengthscale: jax.Array
    log_signal: jax.Array
    log_noise: jax.Array

    @property
    def lengthscale(self) -> jax.Array:
        """(E, Dz) ℓ_{a,d}."""
        return jnp.exp(self.log_lengthscale)

    @property
    def signal_variance(self) -> jax.Array:
        """(E,) σ_f,a²."""
        return jnp.exp(2.0 * self.log_signal)

    @property
    def noise_variance(self) -> jax.Array:
        """(E,) σ_n,a², the learned observation-noise variance used for particle sampling."""
        return jnp.exp(2.0 * self.log_noise)

    @property
    def num_outputs(self) -> int:
        return self.log_lengthscale.shape[-2]

    @property
    def input_dim(self) -> int:
        return self.log_lengthscale.shape[-1]


class GPData(NamedTuple):
    """Training pairs, padded to a capacity (rows with ``mask=False`` are ignored).

    Attributes:
      inputs: (N, Dz) z_i = [x̃_i[I]; u_i].
      targets: (N, E) Δ_i (state differences; not normalised, as in PILCO).
      mask: (N,) bool, True for real rows.
    """

    inputs: jax.Array
    targets: jax.Array
    mask: jax.Array


class GPPosterior(NamedTuple):
    """The GP posterior in the form moment matching consumes, identical for the full GP and FITC.

    Attributes:
      hyper: the hyperparameters (noise already at or above the noise floor).
      inputs: (M, Dz) training inputs (full GP; padded rows included) or inducing inputs (FITC).
      beta: (E, M) full: (K_a + σ_n²I)⁻¹ y_a; FITC: B_a⁻¹ K_mn Λ_a⁻¹ y_a. Zero on padded rows.
      inv: (E, M, M) full: (K_a + σ_n²I)⁻¹; FITC: K_mm⁻¹ − B_a⁻¹. Zero on padded rows/columns.
    """

    hyper: GPHyper
    inputs: jax.Array
    beta: jax.Array
    inv: jax.Array

    @property
    def noise_variance(self) -> jax.Array:
        """(E,) σ_n,a² for particle sampling."""
        return self.hyper.noise_variance


class FitState(NamedTuple):
    """What the next training warm-starts from."""

    hyper: GPHyper
    inducing: Optional[jax.Array] = None  # (M, Dz) FITC inducing inputs once FITC has been used


class HyperFitInfo(NamedTuple):
    """Diagnostics of the marginal-likelihood training (per output unless noted)."""

    objective_init: jax.Array  # (E,) penalised objective at the start point
    objective: jax.Array  # (E,) penalised objective at the returned point
    iterations: jax.Array  # (E,) accepted + failed line searches
    failed_linesearches: jax.Array  # (E,) line searches that did not decrease the objective
    grad_norm: jax.Array  # (E,) ‖∇ψ‖∞ at the returned point
    jitter: jax.Array  # (E,) jitter added to K_y during training (adaptive at the start point)
    noise_floored: jax.Array  # (E,) bool: σ_n hit the noise floor and was clamped
    input_std_floored: jax.Array  # (Dz,) bool: input column std below the floor (penalty centre)
    target_std_floored: jax.Array  # (E,) bool: first-time init used the target-std floor


class FitcFitInfo(NamedTuple):
    """Diagnostics of the inducing-input optimisation (sum over outputs)."""

    objective_init: jax.Array  # () FITC NLL at the start X_u
    objective: jax.Array  # () FITC NLL at the returned X_u
    iterations: jax.Array  # ()
    failed_linesearches: jax.Array  # ()
    jitter: jax.Array  # (E,) jitter on K_mm actually used (≥ config.fitc_jitter)


# Settings that change the program (shapes, loop structure, Python branches) are static pytree
# metadata; settings that only change a number are leaves, traced under jit, so that e.g. a new
# noise floor or budget does not recompile (docs/gp.md, "Configuration: traced numbers, static structure").
_STATIC_FIELDS = ("max_linesearch_steps", "memory_size", "penalty_power", "max_jitter_tries",
                  "fitc_threshold", "num_inducing", "fitc_memory_size", "output_batching")


@dataclasses.dataclass(frozen=True)
class GPConfig:
    """Settings of GP training (docs/gp.md); a pytree (numbers are leaves, see _STATIC_FIELDS).

    Defaults follow PILCO where PILCO fixes them. ``fitc_iters``/``fitc_first_iters`` are
    deliberately smaller than PILCO's 500/1500 line searches (see docs/gp.md, "Optimiser and budgets").
    """

    # full-GP hyperparameter training (PILCO: 300 line searches, ≤10 evaluations each)
    max_iters: int = 300
    max_linesearch_steps: int = 20  # PILCO: 10, but optax's zoom search halves its bracket (docs/gp.md)
    memory_size: int = 20  # L-BFGS memory; ≥ #params (Dz+2) makes it a full BFGS in practice
    grad_tol: float = 1e-7  # stop when ‖∇ψ‖∞ falls below this
    # penalty (hypCurb): ((log ℓ − log s)/log ls_curb)^p + ((log σ_f − log σ_n)/log snr_curb)^p
    penalty_power: int = 30
    ls_curb: float = 100.0
    snr_curb: float = 1000.0
    # numerical guards (all reported when they act)
    noise_floor: float = 1e-6  # minimum σ_n
    input_std_floor: float = 1e-6  # minimum input-column std s_d (penalty centre, init)
    target_std_floor: float = 1e-6  # minimum std(y_a) for the first-time init
    jitter: float = 0.0  # base jitter on K + σ_n²I; escalated ×10 while the Cholesky fails
    jitter_min: float = 1e-12  # first non-zero jitter, relative to σ_f² + σ_n² (or σ_f² for K_mm)
    max_jitter_tries: int = 12
    # sparse FITC
    fitc_threshold: int = 300  # FITC iff (real) N > fitc_threshold
    num_inducing: int = 300
    fitc_jitter: float = 1e-6  # on K_mm (PILCO's ridge)
    fitc_iters: int = 100  # warm-started line searches (PILCO: 500 cart-pole / 300 unicycle)
    fitc_first_iters: int = 300  # first time (PILCO: 3× the above)
    fitc_memory_size: int = 100
    fitc_grad_tol: float = 1e-7
    # how per-output work is batched: "auto" (lax.map on CPU, vmap elsewhere), "map", "vmap";
    # see pipps.gp.linalg.map_outputs for why CPU avoids batched LAPACK calls
    output_batching: str = "auto"

    def __post_init__(self):
        # Validate only concrete Python numbers: under jit the leaves are tracers.
        def concrete(name):
            v = getattr(self, name)
            return isinstance(v, (int, float)) and not isinstance(v, bool)

        if self.num_inducing > self.fitc_threshold:
            raise ValueError(
                f"GPConfig: num_inducing={self.num_inducing} exceeds fitc_threshold="
                f"{self.fitc_threshold}; FITC needs more training points than inducing inputs"
            )
        if self.penalty_power % 2:
            raise ValueError(f"GPConfig: penalty_power must be even, got {self.penalty_power}")
        for name in ("max_iters", "max_linesearch_steps", "memory_size", "num_inducing",
                     "fitc_iters", "fitc_first_iters", "fitc_memory_size"):
            if concrete(name) and getattr(self, name) < 1:
                raise ValueError(f"GPConfig: {name} must be ≥ 1, got {getattr(self, name)}")
        for name in ("noise_floor", "input_std_floor", "target_std_floor", "jitter", "fitc_jitter", "jitter_min"):
            if concrete(name) and not getattr(self, name) >= 0.0:
                raise ValueError(f"GPConfig: {name} must be ≥ 0, got {getattr(self, name)}")
        if self.output_batching not in ("auto", "map", "vmap"):
            raise ValueError(f"GPConfig: output_batching must be 'auto', 'map' or 'vmap', got {self.output_batching!r}")
        for name in ("ls_curb", "snr_curb"):
            if concrete(name) and not getattr(self, name) > 1.0:
                raise ValueError(f"GPConfig: {name} must exceed 1, got {getattr(self, name)}")


jax.tree_util.register_dataclass(
    GPConfig,
    data_fields=[f.name for f in dataclasses.fields(GPConfig) if f.name not in _STATIC_FIELDS],
    meta_fields=list(_STATIC_FIELDS),
)
