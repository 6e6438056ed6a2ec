"""GP dynamics models (docs/gp.md): one independent SE-ARD GP per output, full or FITC.

Typical use, once per episode::

    data = pad_to_capacity(make_data(inputs, targets), chunk=100)
    post, state, info = fit(key, data, prev=state)        # jitted training + posterior
    mean, var = predict(post, z, variance=True)            # (P, E) each
    noise_var = post.noise_variance                        # (E,) σ_n² for particle sampling

See docs/gp.md for the model, objective, optimiser, FITC and the numerical guards.
"""

from pipps.gp.data import capacity_for, make_data, num_real, pad_to_capacity
from pipps.gp.fit import FitInfo, GPNumericsWarning, fit, fit_many
from pipps.gp.fitc import fitc_objective, fitc_posterior, initial_inducing
from pipps.gp.kernel import se_ard, se_ard_batched
from pipps.gp.objective import hyper_objective, hyper_to_rows, neg_log_marginal, penalty, rows_to_hyper
from pipps.gp.posterior import full_posterior, predict
from pipps.gp.train import fit_hyper, fit_inducing, initial_hyper
from pipps.gp.types import FitcFitInfo, FitState, GPConfig, GPData, GPHyper, GPPosterior, HyperFitInfo

__all__ = [
    "FitInfo", "FitState", "FitcFitInfo", "GPConfig", "GPData", "GPHyper", "GPNumericsWarning",
    "GPPosterior", "HyperFitInfo", "capacity_for", "fit", "fit_hyper", "fit_inducing", "fit_many",
    "fitc_objective", "fitc_posterior", "full_posterior", "hyper_objective", "hyper_to_rows",
    "initial_hyper", "initial_inducing", "make_data", "neg_log_marginal", "num_real",
    "pad_to_capacity", "penalty", "predict", "rows_to_hyper", "se_ard", "se_ard_batched",
]
