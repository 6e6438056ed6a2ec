"""The readings of a success rate (pipps.reporting.readings): each against a direct computation, the
seed-level interval's coverage on simulated clustered data, the permutation test against enumeration,
and the committed Table 4.1 files re-tabulated to the numbers docs/results.md quotes."""

from __future__ import annotations

import dataclasses
import itertools
import math
from pathlib import Path

import h5py
import numpy as np
import pytest

from pipps.reporting import readings as rd
from pipps.reporting.readings import (CHI2_95, clustered_interval, compare, newcombe_interval, permutation_p, rates,
                                      seed_values, wilson_interval)

ROOT = Path(__file__).resolve().parents[1]
THESIS = ROOT / "results" / "thesis"


def test_seed_values_count_each_reading_from_the_rollouts():
    returns = np.array([10.0, 15.0, 14.999, 20.0, 15.002])  # a return equal to the threshold is not below it
    flags = np.array([True, True, False, False, False])
    v = seed_values(3, returns, flags, 14.0, 15.0, 0.5)
    assert v.seed == 3 and v.rollouts == 5
    assert v.get("trial_return") == 2 / 5
    assert v.get("seed_return") == 0.0  # mean 15.0002: not below
    assert v.get("system_trial") == 1.0
    assert v.get("trial_physical") == 2 / 5 and v.get("seed_physical") == 0.0  # 0.4 < 0.5
    at = seed_values(0, np.full(30, 15.0), np.ones(30, bool), 15.0, 15.0, 0.5)  # every rollout at the threshold
    assert (at.get("trial_return"), at.get("seed_return"), at.get("system_trial")) == (0.0, 0.0, 0.0)
    assert at.get("seed_physical") == 1.0
    edge = seed_values(0, np.ones(30), np.arange(30) < 15, None, 15.0, 0.5)  # exactly half balanced passes 0.5
    assert edge.get("seed_physical") == 1.0 and edge.get("system_trial") is None
    uni = seed_values(0, np.ones(4), np.array([1, 1, 1, 0], bool), None, None, 0.95)  # unicycle: no threshold
    assert set(k for k, x in uni.values.items() if x is not None) == {"trial_physical", "seed_physical"}
    assert seed_values(0, np.ones(4), np.ones(4, bool), None, None, 0.95, False).get("system_physical") == 0.0
    with pytest.raises(ValueError, match="seed 2"):
        seed_values(2, np.ones(3), np.ones(4, bool), None, 15.0, 0.5)


def test_rates_are_the_means_over_seeds_with_seed_level_intervals():
    per_seed = [seed_values(s, np.where(np.arange(10) < p, 10.0, 20.0), np.arange(10) < b, 10.0 + 4 * s, 15.0, 0.5)
                for s, (p, b) in enumerate([(10, 9), (7, 2), (0, 0), (10, 10)])]
    got = rates(per_seed)
    assert list(got) == [r.name for r in rd.READINGS if r.name != "system_physical"]  # not given: not counted
    assert got["trial_return"].rate == pytest.approx(27 / 40)
    assert got["trial_return"].interval == clustered_interval([10, 7, 0, 10], [10] * 4)
    assert got["trial_physical"].rate == pytest.approx(21 / 40)
    assert got["seed_return"].successes == 3 and got["seed_return"].interval == wilson_interval(3, 4)  # means 10, 13, 20, 10
    assert got["system_trial"].successes == 2  # system returns 10, 14, 18, 22
    assert got["seed_physical"].successes == 2 and got["seed_physical"].seeds == (0, 1, 2, 3)
    assert got["seed_return"].text() == f"3/4 = 0.75 [{wilson_interval(3, 4)[0]:.2f}, {wilson_interval(3, 4)[1]:.2f}]"


def test_clustered_interval_at_the_boundary_is_the_likelihood_bound_of_one_trial_per_seed():
    """Every seed at 0: at any μ the beta-binomial likelihood is maximal at ρ → 1 (each seed
    all-or-nothing), so n_eff = n and the statistic is 2n·KL(0 ‖ μ) = 2n·log(1/(1 − μ)): the upper
    end solves it = χ², μ = 1 − exp(−χ²/(2n)), the likelihood-ratio bound of n Bernoulli seeds."""
    for n in (5, 10, 20):
        lo, hi = clustered_interval([0] * n, [30] * n)
        assert lo == 0.0
        assert hi == pytest.approx(1 - math.exp(-CHI2_95 / (2 * n)), rel=1e-4)
        lo, hi = clustered_interval([30] * n, [30] * n)
        assert hi == 1.0 and lo == pytest.approx(math.exp(-CHI2_95 / (2 * n)), rel=1e-4)


def test_clustered_interval_narrows_to_the_binomial_one_when_seeds_agree():
    """Seeds drawn from one rate (ρ̂ → 0) carry as much as independent rollouts: the interval then
    approaches the likelihood-ratio interval of the pooled binomial, far narrower than the seed count alone allows."""
    rng = np.random.default_rng(0)
    x = rng.binomial(30, 0.5, 20)
    lo, hi = clustered_interval(x, [30] * 20)
    p = x.sum() / 600
    assert lo < p < hi and hi - lo < 1.5 * 2 * 1.96 * math.sqrt(p * (1 - p) / 600)
    assert hi - lo < (wilson_interval(10, 20)[1] - wilson_interval(10, 20)[0]) / 2


#: seed sets on which a beta-binomial fit is poor, so its maximum-likelihood rate lies far from the mean
#: of the per-seed fractions: (passes, rollouts) per seed. The first three put the mean outside the
#: beta-binomial's own profile-likelihood interval (18 seeds at 1/30 and 2 at 30/30: mean 0.13,
#: that interval [0.14, 0.41]); the last two mix rollout counts.
ADVERSARIAL = [([1] * 18 + [30] * 2, [30] * 20), ([29] * 18 + [0] * 2, [30] * 20), ([2] * 18 + [30] * 2, [30] * 20),
               ([0] * 9 + [30], [30] * 10), ([15] * 19 + [0], [30] * 20), ([1] * 3 + [30], [30] * 4),
               ([0] * 15 + [1] * 5, [100] * 15 + [1] * 5), ([4, 24], [4, 28])]


def _per_trial_rate(passes, rollouts):
    per_seed = [seed_values(s, np.where(np.arange(m) < x, 10.0, 20.0), np.ones(m, bool), None, 15.0, 0.5)
                for s, (x, m) in enumerate(zip(passes, rollouts))]
    return rd.rate("trial_return", per_seed)


def test_the_printed_per_trial_rate_lies_inside_its_interval_on_adversarial_seed_sets():
    rng = np.random.default_rng(7)
    cases = list(ADVERSARIAL)
    for _ in range(40):  # mixtures: most seeds near one rate, a few at the other end
        n = int(rng.integers(3, 21))
        near, far = int(rng.integers(0, 31)), int(rng.choice([0, 30]))
        cases.append((np.where(rng.random(n) < 0.85, near, far).tolist(), [30] * n))
    for passes, rollouts in cases:
        got = _per_trial_rate(passes, rollouts)
        assert got.rate == pytest.approx(np.mean(np.divide(passes, rollouts)))
        lo, hi = got.interval
        assert lo <= got.rate <= hi, (passes, rollouts, got.rate, got.interval)
        point, ends = got.text().split(" [")
        assert float(ends.split(", ")[0]) <= float(point) <= float(ends.rstrip("]").split(", ")[1])  # as printed


def test_clustered_interval_is_the_binomial_likelihood_ratio_interval_on_the_effective_rollouts():
    """At each end μ the statistic 2 n_eff KL(p̄ ‖ μ) reaches χ², n_eff from the ρ profiled at μ."""
    x, m = np.array([1] * 18 + [30] * 2), np.full(20, 30.0)
    p_bar = float(np.mean(x / m))
    for end in clustered_interval(x, m):
        rho = rd._profile(end, x, m)[1]
        kl = p_bar * math.log(p_bar / end) + (1 - p_bar) * math.log((1 - p_bar) / (1 - end))
        assert 2 * rd.effective_rollouts(rho, m) * kl == pytest.approx(CHI2_95, rel=1e-5)
    assert rd.effective_rollouts(0.0, m) == 600 and rd.effective_rollouts(1.0, m) == 20


def _coverage(p, icc, seeds, reps, rng, interval):
    s = 1 / icc - 1
    hits = 0
    for _ in range(reps):
        x = rng.binomial(30, rng.beta(p * s, (1 - p) * s, seeds))
        lo, hi = interval(x)
        hits += lo <= p <= hi
    return hits / reps


#: the simulated cells: (rate, intra-seed correlation ρ, seeds); ρ spans seeds that barely differ to
#: seeds that are nearly all-or-nothing, as the stored runs are (k = 9 TP: spread fractions; k = 1: 0 or 1)
COVERAGE_CASES = [(0.1, 0.2, 10), (0.5, 0.5, 10), (0.9, 0.8, 10), (0.4, 0.05, 20), (0.97, 0.5, 20), (0.03, 0.8, 20)]


def _check_coverage(cases, reps):
    """Coverage within the accepted band: the nominal 95 % ± 5 points (the approximation a
    likelihood-ratio interval with an estimated ρ makes at 10–20 seeds, docs/results.md), widened by
    3 Monte Carlo standard errors."""
    rng = np.random.default_rng(20261126)
    se = math.sqrt(0.95 * 0.05 / reps)
    for p, icc, n in cases:
        cov = _coverage(p, icc, n, reps, rng, lambda x, n=n: clustered_interval(x, [30] * n))
        assert 0.90 - 3 * se <= cov <= 1.0, (p, icc, n, cov)
        assert cov <= 0.995 + 3 * se or p in (0.03, 0.97), (p, icc, n, cov)  # not vacuous away from the edges


def test_clustered_interval_covers_a_known_rate_on_clustered_data():
    _check_coverage(COVERAGE_CASES[:3], reps=150)


@pytest.mark.slow
def test_clustered_interval_covers_a_known_rate_on_clustered_data_full_grid():
    _check_coverage(COVERAGE_CASES, reps=600)


def test_treating_rollouts_as_independent_fails_the_same_coverage_check():
    """The check has power: the pooled Wilson interval (every rollout independent) misses a clustered rate."""
    rng = np.random.default_rng(1)
    cov = _coverage(0.5, 0.5, 10, 150, rng, lambda x: wilson_interval(int(x.sum()), 300))
    assert cov < 0.6


def test_permutation_p_enumerates_the_splits_of_the_pooled_seeds():
    # [1, 1] against [0, 0]: of the C(4, 2) = 6 splits, 2 are as extreme (|difference| = 1)
    assert permutation_p([1, 1], [0, 0]) == pytest.approx(2 / 6)
    assert permutation_p([0.5, 0.5], [0.5, 0.5]) == 1.0
    a, b = [0.9, 0.8, 1.0, 0.7, 0.95], [0.6, 0.8, 0.5, 0.75, 0.4, 0.65]
    exact = permutation_p(a, b)
    sums = [sum(c) for c in itertools.combinations(a + b, 5)]
    total, obs = sum(a + b), abs(np.mean(a) - np.mean(b))
    assert exact == pytest.approx(np.mean([abs(x / 5 - (total - x) / 6) >= obs - 1e-12 for x in sums]))
    drawn = permutation_p(a, b, exact_limit=0, draws=20_000)  # the random splits estimate the same p
    assert abs(drawn - exact) < 4 * math.sqrt(exact * (1 - exact) / 20_000) + 1e-4


def test_compare_differences_two_cells_with_newcombes_interval_and_the_permutation_p():
    a = rates([seed_values(s, np.where(np.arange(10) < 9, 1.0, 20.0), np.ones(10, bool), None, 15.0, 0.5)
               for s in range(6)])["trial_return"]
    b = rates([seed_values(s, np.where(np.arange(10) < 3 + s % 2, 1.0, 20.0), np.ones(10, bool), None, 15.0, 0.5)
               for s in range(6)])["trial_return"]
    d = compare(a, b)
    assert d.difference == pytest.approx(0.9 - 0.35)
    assert d.interval == newcombe_interval(a.rate, a.interval, b.rate, b.interval)
    assert d.interval[0] > 0 and d.p == pytest.approx(2 / math.comb(12, 6))
    other = rates([seed_values(0, np.ones(2), np.ones(2, bool), None, 15.0, 0.5)])["seed_return"]
    with pytest.raises(ValueError, match="cannot compare"):
        compare(a, other)


# -- committed results ----------------------------------------------------------------------------------


def _stored_readings(path):
    """The readings of one file computed straight from HDF5 (no pipps reading code)."""
    with h5py.File(path, "r") as f:
        last = f["trials"][sorted(f["trials"].keys())[-1]]
        returns = last["eval_returns"][()]
        end = last["states"][()][-10:]  # the final second of the system trial: pole within 0.3 rad of upright, cart within 0.5 m
        balanced = np.all(np.abs(np.mod(end[:, 3], 2 * np.pi) - np.pi) <= 0.3) and np.all(np.abs(end[:, 0]) <= 0.5)
        rollouts_balanced = last["eval_balanced"][()].astype(bool)  # the stored per-rollout physical verdicts
        return {"trial_return": float(np.mean(returns < 15.0)), "seed_return": float(np.mean(returns) < 15.0),
                "system_trial": float(np.sum(last["costs"][()]) < 15.0), "system_physical": float(balanced),
                "trial_physical": float(np.mean(rollouts_balanced)),
                "seed_physical": float(np.mean(rollouts_balanced) >= 0.5)}  # the cart-pole asks half the rollouts


def test_a_hand_made_result_set_tabulates_as_computed_by_hand(tmp_path, capsys):
    """Real files through the command line: one as stored, one whose every final rollout sits exactly
    at the threshold (counted as failing), one unfinished (not counted)."""
    from pipps.cli import main
    from pipps.experiments.results import read_result, write_result

    sources = sorted(THESIS.glob("cartpole_swingup_angle_k9_tp_thesis_s1[0-1].h5"))
    assert len(sources) == 2
    stored = read_result(sources[0])
    write_result(tmp_path / "a.h5", stored)
    at = read_result(sources[1])
    last = dataclasses.replace(at.trials[-1], eval_returns=np.full_like(at.trials[-1].eval_returns, 15.0))
    write_result(tmp_path / "b.h5", dataclasses.replace(at, trials=at.trials[:-1] + [last]))
    other = read_result(sorted(THESIS.glob("cartpole_swingup_angle_k9_tp_thesis_s12.h5"))[0])
    write_result(tmp_path / "c.h5", dataclasses.replace(other, trials=other.trials[:-2], status="running"))
    by_hand = [_stored_readings(tmp_path / "a.h5"), _stored_readings(tmp_path / "b.h5")]
    assert (by_hand[1]["trial_return"], by_hand[1]["seed_return"]) == (0.0, 0.0)

    from pipps.reporting.tables import TABLES, collect, judge_counted
    from pipps.experiments.results import read_summary

    from pipps.experiments.results import ResultError

    with pytest.raises(ResultError):  # the unfinished file has no summary to count
        read_summary(tmp_path / "c.h5")
    judged, errors = judge_counted([read_summary(tmp_path / n) for n in ("a.h5", "b.h5")])
    assert not errors
    cell = next(r for r in collect(TABLES["4.1"], judged) if r.n)
    got = cell.by_reading
    assert set(got) == {rd.name for rd in rd.READINGS}
    for name in got:
        assert got[name].values == tuple(h[name] for h in by_hand), name
        assert got[name].rate == pytest.approx(np.mean([h[name] for h in by_hand])), name
    assert cell.rate == np.mean([h["trial_return"] for h in by_hand])
    # the command line over the folder counts a and b and names c as not counted
    assert main(["table", str(tmp_path), "--table", "4.1"]) == 0
    out = capsys.readouterr().out
    assert ("2 complete results of the thesis preset counted; 0 complete results of other settings and 1 incomplete "
            "or corrupt files not counted") in out
    (left_out,) = [line for line in out.splitlines() if line.startswith("  not counted:")]
    assert str(tmp_path / "c.h5") in left_out
    row = next(line for line in out.splitlines() if line.startswith("| k = 9 | TP | 2 |"))  # every reading, 2 seeds
    assert got["trial_physical"].text() in row and got["seed_physical"].text() in row


#: docs/results.md's Table 4.1 block, on the seeds it was first counted over: (k, method, seeds) ->
#: (per trial by return, per seed by mean return, final system trial successes)
ISSUE_TABLE = {
    (1.0, "tp", range(9)): (0.97, 9, 9),
    (1.0, "pilco", range(8)): (0.86, 8, 7),
    (9.0, "tp", range(20)): (0.80, 19, 15),
    (9.0, "pilco", range(20)): (0.24, 0, 6),
    (16.0, "tp", range(20)): (0.42, 2, 7),
    (16.0, "pilco", range(20)): (0.10, 0, 1),
}


def test_the_committed_table_4_1_files_tabulate_to_the_documented_readings():
    from pipps.experiments.results import read_summary
    from pipps.reporting.tables import TABLES, collect, judge_counted

    paths = [THESIS / f"cartpole_swingup_angle_k{k:g}_{m}_thesis_s{s}.h5"
             for (k, m, seeds) in ISSUE_TABLE for s in seeds]
    judged, errors = judge_counted([read_summary(p) for p in paths])
    assert not errors and len(judged) == len(paths)
    cells = {(r.cell.values[1][1], r.cell.method): r for r in collect(TABLES["4.1"], judged) if r.n}
    for (k, m, seeds), (per_trial, per_seed, system) in ISSUE_TABLE.items():
        got = cells[(k, m)].by_reading
        assert got["trial_return"].seeds == tuple(seeds)
        assert round(got["trial_return"].rate, 2) == per_trial, (k, m)
        assert (got["seed_return"].successes, got["system_trial"].successes) == (per_seed, system), (k, m)
