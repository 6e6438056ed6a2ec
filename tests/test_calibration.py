"""The unicycle's return-threshold calibration (pipps.reporting.calibration)."""

import numpy as np
import pytest

from pipps.reporting.calibration import fit_return_threshold


def _errors(returns, success, tau):
    return int(np.sum((np.asarray(returns) < tau) != np.asarray(success)))


def test_separable_policies_give_the_gap_between_them():
    fit = fit_return_threshold([3.0, 1.0, 4.0, 2.0], [False, True, False, True])
    assert (fit.low, fit.high, fit.errors, fit.n) == (2.0, 3.0, 0, 4)
    assert fit.agreement == 1.0


def test_ties_in_errors_go_to_fewer_false_passes():
    # τ ∈ (1, 2] misclassifies the success at 3 (a false fail); τ ∈ (3, 4] the failure at 2 (a false pass).
    fit = fit_return_threshold([1, 2, 3, 4, 5], [True, False, True, False, False])
    assert (fit.low, fit.high, fit.false_pass, fit.false_fail) == (1.0, 2.0, 0, 1)


def test_all_successful_or_all_failing():
    fit = fit_return_threshold([1.0, 2.0], [True, True])
    assert (fit.low, fit.high, fit.errors) == (2.0, np.inf, 0)
    fit = fit_return_threshold([1.0, 2.0], [False, False])
    assert (fit.low, fit.high, fit.errors) == (-np.inf, 1.0, 0)


def test_equal_returns_cannot_be_split():
    fit = fit_return_threshold([1.0, 1.0, 2.0], [True, False, True])
    assert fit.errors == 1 and _errors([1.0, 1.0, 2.0], [True, False, True], fit.high) == 1


@pytest.mark.parametrize("seed", range(5))
def test_the_fit_is_the_minimum_over_every_threshold(seed):
    rng = np.random.default_rng(seed)
    returns = np.round(rng.uniform(0, 10, 40), 1)  # rounded so that ties occur
    success = rng.uniform(size=40) < 1 / (1 + np.exp(returns - 4))
    fit = fit_return_threshold(returns, success)
    grid = np.linspace(-1, 11, 2401)
    brute = min(_errors(returns, success, t) for t in grid)
    assert fit.errors == brute
    lo = fit.low if np.isfinite(fit.low) else fit.high - 1
    hi = fit.high if np.isfinite(fit.high) else fit.low + 1
    for tau in np.linspace(lo, hi, 7)[1:]:  # every τ in (low, high] gives the same classification
        assert _errors(returns, success, tau) == fit.errors
        assert int(np.sum((returns < tau) & ~success)) == fit.false_pass


@pytest.mark.parametrize("returns, success, match", [
    ([1.0, np.nan], [True, False], "finite"),
    ([1.0, 2.0], [True], "one length"),
    ([], [], "no policies"),
])
def test_bad_input_is_named(returns, success, match):
    with pytest.raises(ValueError, match=match):
        fit_return_threshold(returns, success)
