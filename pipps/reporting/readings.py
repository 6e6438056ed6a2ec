"""The ways a success rate can be counted from one table cell's experiments, with seed-level statistics.

The thesis (§4.5.3) describes its success rate in words that admit more than one counting:

    "Each experiment was repeated 100 times and averaged. Each trial was evaluated by running the
    policy 30 times, and averaging ... Success was determined by whether the return of the final
    trial passed below a threshold. The threshold was calibrated at a total cost of below 15 ...
    Trials were considered successful if the pendulum was swung up and kept balanced."

Every reading below is computed from the final learned trial of each experiment (seed) and
reported side by side (docs/results.md, "How a success rate is counted"); the value per seed:

- ``trial_return`` (per trial; the headline, "trials were considered successful"): the fraction of
  the final policy's evaluation rollouts whose return is below the threshold;
- ``seed_return`` (per seed): 1 if the mean of those rollouts' returns is below the threshold, else 0;
- ``system_trial`` (per seed): 1 if the final trial run on the system (the one the learner saw) is
  below it;
- ``trial_physical`` (per trial): the fraction of evaluation rollouts that meet the physical
  criterion (cart-pole: swung up and balanced at the end; unicycle: stayed upright);
- ``seed_physical`` (per seed): 1 if at least the configured fraction of rollouts meets it (0.5
  cart-pole, 0.95 unicycle);
- ``system_physical`` (per seed): 1 if the final trial run on the system meets it.

A cell's rate under a reading is the mean of the per-seed values. The unicycle has no return
threshold in the thesis, so its return readings are absent (``None``) and its physical readings
stand alone.

**Intervals respect the seeds.** The rollouts of one seed share a policy and are not independent,
so a per-trial rate's interval is computed over seeds: :func:`clustered_interval` is the
likelihood-ratio interval of the printed rate (the mean of the per-seed fractions) on the effective
number of independent rollouts, which follows from the intra-seed correlation, estimated from how
much the seeds differ (a beta-binomial profile likelihood); it always contains the printed rate. Its
coverage on simulated clustered data of known rate is measured in ``tests/test_readings.py`` and
docs/results.md. A per-seed reading is one Bernoulli verdict per
seed: the plain Wilson interval. A difference between two cells (:func:`compare`) gets Newcombe's
interval built from the two cells' intervals and a permutation test over seeds on the per-seed
values.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import Sequence

import numpy as np

#: the normal quantile of a two-sided 95 % interval
Z95 = 1.959963984540054


@dataclasses.dataclass(frozen=True)
class Reading:
    """One way of counting successes: its name, what it is per seed, and whether it is a fraction of
    rollouts (per trial) or one verdict per seed."""

    name: str
    label: str
    per_trial: bool
    description: str


READINGS: tuple[Reading, ...] = (
    Reading("trial_return", "per trial, return", True,
            "fraction of the final policy's evaluation rollouts with return below the threshold, averaged over seeds"),
    Reading("seed_return", "per seed, mean return", False,
            "seeds whose mean evaluation return is below the threshold"),
    Reading("system_trial", "final system trial, return", False,
            "seeds whose final trial on the system (the one the learner saw) has return below the threshold"),
    Reading("trial_physical", "per trial, physical", True,
            "fraction of evaluation rollouts meeting the physical criterion, averaged over seeds"),
    Reading("seed_physical", "per seed, physical", False,
            "seeds with at least the configured fraction of rollouts meeting the physical criterion"),
    Reading("system_physical", "final system trial, physical", False,
            "seeds whose final trial on the system meets the physical criterion"),
)
BY_NAME = {r.name: r for r in READINGS}
#: the reading the tables lead with, chosen from the thesis' words (module docstring; docs/results.md)
HEADLINE = "trial_return"


def reading(name: str) -> Reading:
    if name not in BY_NAME:
        raise ValueError(f"unknown reading {name!r}; choose one of {', '.join(BY_NAME)}")
    return BY_NAME[name]


@dataclasses.dataclass(frozen=True)
class SeedValues:
    """One experiment's values under every reading (``None`` where a reading does not apply)."""

    seed: int
    rollouts: int
    values: dict

    def get(self, name: str):
        return self.values.get(name)


def seed_values(seed: int, eval_returns, flags, system_return: float | None, threshold: float | None,
                required_fraction: float, system_flag: bool | None = None) -> SeedValues:
    """The per-seed values of every reading from the final trial of one experiment.

    ``eval_returns``: the (R,) evaluation returns; ``flags``: the (R,) physical verdicts per rollout
    (balanced or upright); ``system_return``: the return of the final trial run on the system (None
    where it has no return reading); ``threshold``: the return threshold (None: no return readings);
    ``required_fraction``: the fraction of rollouts the per-seed physical verdict asks for;
    ``system_flag``: whether the final system trial meets the physical criterion (None: not known)."""
    r = np.asarray(eval_returns, dtype=float)
    f = np.asarray(flags, dtype=bool)
    if r.ndim != 1 or r.size == 0 or f.shape != r.shape:
        raise ValueError(f"seed {seed}: eval_returns and flags must be 1-d of one nonzero length, "
                         f"got shapes {r.shape} and {f.shape}")
    frac = float(np.mean(f))
    values = {"trial_physical": frac, "seed_physical": float(frac >= required_fraction - 1e-12),
              "system_physical": None if system_flag is None else float(bool(system_flag))}
    if threshold is not None:
        values["trial_return"] = float(np.mean(r < threshold))
        values["seed_return"] = float(np.mean(r) < threshold)
        values["system_trial"] = None if system_return is None else float(system_return < threshold)
    return SeedValues(seed, int(r.size), values)


def wilson_interval(successes: float, n: float, z: float = Z95) -> tuple[float, float]:
    """The Wilson score interval of a binomial proportion ``successes / n`` (Wilson 1927)."""
    if n <= 0:
        return (0.0, 1.0)
    p = successes / n
    den = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(max(p * (1 - p), 0.0) / n + z * z / (4 * n * n)) / den
    return (max(0.0, centre - half), min(1.0, centre + half))


#: χ²₁'s 95 % quantile: the likelihood-ratio interval's cut
CHI2_95 = 3.841458820694124
#: the search range of logit(ρ), the intra-seed correlation (ρ from 8e-7 to 1 − 8e-7)
_LOGIT_RHO = (-14.0, 14.0)


def _beta_binomial_loglik(mu: float, rho, x: np.ndarray, m: np.ndarray):
    """log L(μ, ρ) of seeds with x_i of m_i rollouts successful, up to a constant: the beta-binomial,
    success probabilities varying over seeds as Beta with mean μ and intra-seed correlation ρ
    (a = μ(1 − ρ)/ρ, b = (1 − μ)(1 − ρ)/ρ). A float for a scalar ρ, an array for an array of ρ."""
    from scipy.special import betaln

    r = np.asarray(rho, dtype=float)
    s = ((1.0 - r) / r)[..., None]
    a, b = mu * s, (1.0 - mu) * s
    out = np.sum(betaln(x + a, m - x + b) - betaln(a, b), axis=-1)
    return float(out) if r.ndim == 0 else out


def _profile(mu: float, x: np.ndarray, m: np.ndarray) -> tuple[float, float]:
    """(max over ρ of log L(μ, ρ), the ρ that attains it): a coarse grid over logit ρ, then Brent's
    method around its best point."""
    from scipy.optimize import minimize_scalar
    from scipy.special import expit

    grid = np.linspace(*_LOGIT_RHO, 29)
    values = _beta_binomial_loglik(mu, expit(grid), x, m)
    best = int(np.argmax(values))
    t0 = grid[best]
    lo, hi = max(_LOGIT_RHO[0], t0 - 1.0), min(_LOGIT_RHO[1], t0 + 1.0)
    res = minimize_scalar(lambda t: -_beta_binomial_loglik(mu, expit(t), x, m), bounds=(lo, hi),
                          method="bounded", options={"xatol": 1e-5})
    if -float(res.fun) >= values[best]:
        return -float(res.fun), float(expit(res.x))
    return float(values[best]), float(expit(t0))


def _bernoulli_kl(p: float, q: float) -> float:
    """KL(Bernoulli(p) ‖ Bernoulli(q)) for 0 < q < 1 (0 · log 0 = 0)."""
    out = 0.0
    if p > 0.0:
        out += p * math.log(p / q)
    if p < 1.0:
        out += (1.0 - p) * math.log((1.0 - p) / (1.0 - q))
    return out


def effective_rollouts(rho: float, rollouts: np.ndarray) -> float:
    """Kish's effective sample size of the mean of per-seed fractions: the number of independent
    rollouts whose binomial proportion has the variance of ``mean(x_i / m_i)``, n² / Σ (ρ + (1 − ρ)/m_i).
    It holds for any distribution of the seeds' success probabilities with intra-seed correlation ρ
    (Var p_i = ρ μ(1 − μ)): ρ = 0 gives Σ m_i for equal m_i (every rollout independent), ρ = 1 gives
    n (each seed one all-or-nothing trial)."""
    m = np.asarray(rollouts, dtype=float)
    return float(m.size ** 2 / np.sum(rho + (1.0 - rho) / m))


def clustered_interval(successes: Sequence[int], rollouts: Sequence[int]) -> tuple[float, float]:
    """95 % interval of a per-trial rate from per-seed counts (``successes[i]`` of ``rollouts[i]``):
    the interval for the rate the tables print, the mean over seeds of the per-seed fractions p̄.

    The rollouts of one seed share a policy, so they are not independent. The interval is
    {μ : 2 n_eff(μ) · KL(p̄ ‖ μ) ≤ χ²₁(0.95)}, the likelihood-ratio interval of a binomial proportion
    p̄ observed on n_eff(μ) independent rollouts (:func:`effective_rollouts`), the connected part
    around p̄. n_eff(μ) follows from the intra-seed correlation ρ̂(μ), profiled at each μ from a
    beta-binomial model (each seed's success probability drawn from a Beta with mean μ and intra-seed
    correlation ρ), so seeds that disagree widen it. Where every seed is at 0 (or 1) the profile
    puts ρ̂ at 1 and n_eff at n: all of n seeds at 0 gives μ ≤ 1 − exp(−χ²/(2n)), as if each seed were
    one trial. Its coverage on simulated clustered data is measured in tests/test_readings.py and
    docs/results.md.

    Why not the beta-binomial's own profile-likelihood interval for μ (this function's earlier
    form): that interval is for the beta-binomial's maximum-likelihood μ̂, which is not p̄; where the
    seeds do not look like draws from one Beta it can lie far from p̄ and exclude it (18 seeds at
    1/30 and 2 at 30/30: p̄ = 0.13, that interval [0.14, 0.41]). p̄ is the thesis' counting
    ("averaged") and is unbiased for the seeds' mean success probability whatever their
    distribution, and its variance needs only ρ; so the Beta serves here only to estimate ρ, and the
    interval always contains the printed rate."""
    from scipy.optimize import brentq

    x = np.asarray(successes, dtype=float)
    m = np.asarray(rollouts, dtype=float)
    if x.size == 0:
        return (0.0, 1.0)
    if x.shape != m.shape or np.any(m <= 0) or np.any(x < 0) or np.any(x > m):
        raise ValueError(f"clustered_interval: need 0 <= successes <= rollouts per seed, got {x.tolist()} of {m.tolist()}")
    p_bar = float(np.mean(x / m))
    eps = 1e-9

    def excess(mu):
        rho = _profile(mu, x, m)[1]
        return 2.0 * effective_rollouts(rho, m) * _bernoulli_kl(p_bar, mu) - CHI2_95

    def end(edge):
        """The first μ from p̄ towards ``edge`` where the statistic reaches the cut: a grid outwards,
        then Brent's method in the first step that crosses (n_eff varies with μ, so the statistic
        need not be monotone; the interval is the part connected to p̄)."""
        if abs(edge - p_bar) <= eps:
            return round(edge)
        prev = p_bar
        for mu in np.linspace(p_bar, edge, 41)[1:]:
            if excess(mu) > 0:
                return brentq(excess, prev, mu, xtol=1e-7)
            prev = mu
        return round(edge)

    return (float(end(eps)), float(end(1.0 - eps)))


@dataclasses.dataclass(frozen=True)
class Rate:
    """A cell's rate under one reading: the mean of the per-seed values, its seed-level 95 % interval,
    the number of seeds and the per-seed values themselves (seed order)."""

    reading: Reading
    rate: float
    interval: tuple[float, float]
    seeds: tuple[int, ...]
    values: tuple[float, ...]
    rollouts: tuple[int, ...]

    @property
    def n(self) -> int:
        return len(self.values)

    @property
    def successes(self) -> int | None:
        """The count of successful seeds (per-seed readings only)."""
        return None if self.reading.per_trial else int(round(sum(self.values)))

    def covers(self, value: float | None) -> bool | None:
        if value is None or not self.n:
            return None
        lo, hi = self.interval
        return lo - 1e-12 <= value <= hi + 1e-12

    def text(self, digits: int = 2) -> str:
        if not self.n:
            return "—"
        lo, hi = self.interval
        count = "" if self.reading.per_trial else f"{self.successes}/{self.n} = "
        return f"{count}{self.rate:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def rate(name: str, per_seed: Sequence[SeedValues]) -> Rate | None:
    """The cell's :class:`Rate` under reading ``name`` over the seeds that have a value for it
    (None when no seed has one: the reading does not apply to the task)."""
    rd = reading(name)
    rows = [s for s in per_seed if s.get(name) is not None]
    if not rows:
        return None
    vals = np.array([s.get(name) for s in rows], dtype=float)
    m = [s.rollouts for s in rows]
    if rd.per_trial:
        interval = clustered_interval(np.rint(vals * np.asarray(m)).astype(int), m)
    else:
        interval = wilson_interval(float(np.sum(vals)), len(vals))
    return Rate(rd, float(np.mean(vals)), interval, tuple(s.seed for s in rows), tuple(vals.tolist()), tuple(m))


def rates(per_seed: Sequence[SeedValues]) -> dict[str, Rate]:
    """Every reading that applies, by name, in :data:`READINGS` order."""
    out = {}
    for rd in READINGS:
        r = rate(rd.name, per_seed)
        if r is not None:
            out[rd.name] = r
    return out


def newcombe_interval(p1: float, ci1: tuple[float, float], p2: float, ci2: tuple[float, float]) -> tuple[float, float]:
    """95 % interval of ``p1 − p2`` from the two rates' own intervals (Newcombe 1998, method 10: the
    square-and-add combination of the single-rate intervals, here the seed-level ones)."""
    (l1, u1), (l2, u2) = ci1, ci2
    d = p1 - p2
    return (d - math.sqrt((p1 - l1) ** 2 + (u2 - p2) ** 2), d + math.sqrt((u1 - p1) ** 2 + (p2 - l2) ** 2))


def permutation_p(a: Sequence[float], b: Sequence[float], *, exact_limit: int = 20_000, draws: int = 50_000,
                  seed: int = 0) -> float:
    """Two-sided p-value of the permutation test that two cells' per-seed values come from one
    distribution, on the difference of their means: exact over every split of the pooled seeds when
    there are at most ``exact_limit`` splits, else ``draws`` random splits (fixed ``seed``; the
    p-value counts the observed split, so it is never 0)."""
    x = np.asarray(a, dtype=float)
    y = np.asarray(b, dtype=float)
    if x.size == 0 or y.size == 0:
        return math.nan
    pooled = np.concatenate([x, y])
    n, total = x.size, float(np.sum(pooled))
    observed = abs(x.mean() - y.mean())
    tol = 1e-12 * max(1.0, abs(total))

    def diffs(sums):
        return np.abs(sums / n - (total - sums) / y.size)

    if math.comb(pooled.size, n) <= exact_limit:
        sums = np.array([pooled[list(c)].sum() for c in itertools.combinations(range(pooled.size), n)])
        return float(np.mean(diffs(sums) >= observed - tol))
    rng = np.random.default_rng(seed)
    idx = np.argsort(rng.random((draws, pooled.size)), axis=1)[:, :n]
    sums = pooled[idx].sum(axis=1)
    return float((np.sum(diffs(sums) >= observed - tol) + 1) / (draws + 1))


@dataclasses.dataclass(frozen=True)
class Difference:
    """``a − b`` under one reading: the difference of rates, its 95 % interval, the permutation p."""

    reading: Reading
    difference: float
    interval: tuple[float, float]
    p: float

    def text(self) -> str:
        lo, hi = self.interval
        return f"{self.difference:+.2f} [{lo:+.2f}, {hi:+.2f}], {p_text(self.p)}"


def p_text(p: float) -> str:
    """A p-value as the tables print it: two significant digits, ``p < 1e-4`` below the resolution of
    :func:`permutation_p`'s random splits."""
    return "p < 1e-4" if p < 1e-4 else f"p = {p:.2g}"


def compare(a: Rate, b: Rate) -> Difference:
    """The difference of two cells' rates under one reading, at the seed level."""
    if a.reading != b.reading:
        raise ValueError(f"cannot compare readings {a.reading.name} and {b.reading.name}")
    return Difference(a.reading, a.rate - b.rate, newcombe_interval(a.rate, a.interval, b.rate, b.interval),
                      permutation_p(a.values, b.values))
