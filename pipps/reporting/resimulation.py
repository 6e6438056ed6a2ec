"""Re-simulating each result's final policy on the true system (``pipps resimulate``).

A success must survive an independent re-simulation of the stored policy. For one complete result
file, :func:`check_final` runs the final trial's policy twice, outside the learning loop
(:class:`pipps.experiments.resimulate.Resimulator`):

1. with the trial's own evaluation keys. The true system is deterministic given them, so the
   returns must equal the stored ones to rounding, and the task's per-rollout criterion must give
   the stored flags: the check that the file's verdict is what its policy does;
2. with ``fresh`` rollouts whose keys the experiment never used: the fraction of them that meet the
   task's criterion (the per-trial reading of that seed, from many more rollouts), the per-seed
   verdict again, and, where the task has a return threshold (the cart-pole's), the fraction of
   rollouts whose return is below it.

:func:`cell_rows` pools the checks per cell (task and task preset, cost, k, method, experiment preset
and the settings that depart from it): the per-trial rate (the mean over seeds of the final policy's fractions) from the stored and from the
fresh rollouts, and how many per-seed verdicts hold.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from pipps.reporting.readings import clustered_interval, wilson_interval
from pipps.reporting.verdicts import Verdict, criterion, final_flags, standard_error, verdict


@dataclass(frozen=True)
class FinalCheck:
    """One result file's final policy re-simulated (:func:`check_final`)."""

    path: str
    seed: int
    cell: tuple  # (task, task preset, cost, k, method label, experiment preset, departures from it)
    own_max_difference: float  # largest |return with the trial's own keys − stored return|
    returns_equal: bool  # that difference is within RESIM_TOLERANCE of the returns' size (rounding only)
    flags_stored: bool  # the file stores the criterion's flags (files from before they were stored do not)
    flags_equal: bool  # the criterion's flags with the own keys equal the stored ones (True where none are stored)
    stored: Verdict  # the verdict on the stored rollouts
    fresh: Verdict  # the verdict on the fresh rollouts
    fresh_returns: np.ndarray
    stored_below: float | None  # fraction of stored returns below the task's threshold (None: it has none)
    stored_rollouts: int  # the final trial's evaluation rollouts

    @property
    def reproduced(self) -> bool:
        """The trial's own keys give the stored returns and, where the file stores them, the stored flags:
        the stored verdict is what the policy does."""
        return self.returns_equal and self.flags_equal

    @property
    def holds(self) -> bool:
        """The fresh rollouts give the stored per-seed verdict."""
        return self.fresh.success == self.stored.success

    @property
    def fresh_interval(self) -> tuple[float, float]:
        """95 % Wilson interval of the fresh fraction (its rollouts share one policy and are independent)."""
        n = self.fresh_returns.size
        return wilson_interval(round(self.fresh.fraction * n), n)

    @property
    def return_holds(self) -> bool | None:
        """The fresh rollouts' mean return is on the stored mean's side of the threshold (None: no threshold)."""
        return None if self.stored.return_success is None else self.fresh.return_success == self.stored.return_success

    @property
    def fresh_return_se(self) -> float:
        return standard_error(self.fresh_returns)

    @property
    def fresh_below(self) -> float | None:
        t = self.fresh.threshold
        return None if t is None else float(np.mean(self.fresh_returns < t))


def check_final(result, simulator, *, fresh: int, seed: int = 0, path: str = "") -> FinalCheck:
    """Re-simulate the final trial of a complete ``result`` (:class:`ExperimentResult`) with its own
    keys and with ``fresh`` new rollouts from ``seed`` (:meth:`Resimulator.trial`)."""
    from pipps.experiments.methods import METHODS
    from pipps.reporting.tables import returns_reproduced

    if fresh < 2:
        raise ValueError(f"fresh must be at least 2 rollouts (a standard error needs two), got {fresh}")
    cfg, index = result.config, len(result.trials) - 1
    final = result.trials[index]
    if final.kind != "learned":
        raise ValueError(f"{path or 'result'}: its last trial is a random one; is the experiment complete?")
    stored_flags = final_flags(cfg, final)
    own_returns, _, own_flags = simulator.trial(result, index)
    stored_returns = np.asarray(final.eval_returns, dtype=float)
    difference = float(np.max(np.abs(own_returns - stored_returns)))
    returns_equal = returns_reproduced(own_returns, stored_returns)
    flags_equal = stored_flags is None or bool(np.array_equal(np.asarray(own_flags, bool),
                                                              np.asarray(stored_flags, bool)))
    stored = verdict(cfg, final.eval_returns, own_flags if stored_flags is None else stored_flags)
    returns, _, flags = simulator.trial(result, index, fresh=fresh, seed=seed)
    threshold = criterion(cfg).threshold
    below = None if threshold is None else float(np.mean(np.asarray(final.eval_returns) < threshold))
    cost = cfg.cost_name
    if cfg.cost_scale != 1.0:
        cost += f" ×{cfg.cost_scale:g}"
    cell = (cfg.task, cfg.preset, cost, cfg.k, METHODS[cfg.method].label, cfg.protocol, _departures(cfg))
    return FinalCheck(path, cfg.seed, cell, difference, returns_equal, stored_flags is not None, flags_equal, stored,
                      verdict(cfg, returns, flags), np.asarray(returns, dtype=float), below, len(final.eval_returns))


def _departures(cfg) -> str:
    """The settings in which ``cfg`` departs from its experiment preset, ``name=value`` (``–``: none), so
    that results of different settings never pool into one cell."""
    from pipps.experiments.config import ConfigError, config_hash, departures

    try:
        away = departures(cfg.replace(seed=0))
    except ConfigError:  # the preset cannot express this cell at all: its whole configuration tells it apart
        return f"custom (configuration {config_hash(cfg.replace(seed=0))[:8]})"
    return ", ".join(f"{name}={value!r}" for name, (value, _) in sorted(away.items())) or "–"


@dataclass(frozen=True)
class CellRow:
    """The checks of one cell pooled over its seeds."""

    cell: tuple
    seeds: int
    stored_rate: float  # mean over seeds of the stored fraction meeting the criterion (per-trial rate)
    stored_interval: tuple[float, float]  # its 95 % interval over seeds (readings.clustered_interval)
    fresh_rate: float  # the same from the fresh rollouts
    fresh_interval: tuple[float, float]
    stored_below: float | None  # mean over seeds of the fraction below the return threshold (None: none)
    fresh_below: float | None
    verdicts_hold: int  # seeds whose fresh per-seed verdict equals the stored one


def cell_rows(checks) -> list[CellRow]:
    """:class:`CellRow` per cell of ``checks``, sorted by cell. ValueError where one cell holds one seed
    twice (the same experiment given in two places would count twice)."""
    groups = defaultdict(list)
    for c in checks:
        groups[c.cell].append(c)
    rows = []
    for cell, cs in sorted(groups.items(), key=lambda kv: tuple(map(str, kv[0]))):
        seen = {}
        for c in cs:
            if c.seed in seen:
                raise ValueError(f"seed {c.seed} of one cell twice: {seen[c.seed]} and {c.path}; give each "
                                 "experiment once")
            seen[c.seed] = c.path
        thresholded = [c for c in cs if c.stored_below is not None]
        stored_n = [c.stored_rollouts for c in cs]
        fresh_n = [c.fresh_returns.size for c in cs]
        stored_k = [round(c.stored.fraction * n) for c, n in zip(cs, stored_n)]
        fresh_k = [round(c.fresh.fraction * n) for c, n in zip(cs, fresh_n)]
        rows.append(CellRow(
            cell, len(cs), float(np.mean([c.stored.fraction for c in cs])), clustered_interval(stored_k, stored_n),
            float(np.mean([c.fresh.fraction for c in cs])), clustered_interval(fresh_k, fresh_n),
            float(np.mean([c.stored_below for c in thresholded])) if thresholded else None,
            float(np.mean([c.fresh_below for c in thresholded])) if thresholded else None,
            sum(c.holds for c in cs)))
    return rows


def _ci(interval) -> str:
    return f"[{interval[0]:.2f}, {interval[1]:.2f}]"


def _pass(v: Verdict) -> str:
    return "pass" if v.success else "fail"


def _own_keys(c: FinalCheck) -> str:
    returns = f"{c.own_max_difference:.1e}" + ("" if c.returns_equal else " (NOT rounding)")
    flags = "not stored" if not c.flags_stored else ("yes" if c.flags_equal else "NO")
    return f"{returns}, {flags}"


def render(checks, fresh: int) -> str:
    """The per-file and per-cell Markdown tables of ``checks`` (what ``pipps resimulate`` prints)."""
    from pathlib import Path

    rows = cell_rows(checks)  # first: it refuses a seed given twice
    lines = ["| file | seed | own keys: max abs. return difference, flags equal | stored: fraction meeting the "
             "criterion, verdict | fresh: fraction [95 % Wilson], mean return ± SE, verdict | verdict holds | return "
             "threshold: fraction below it, stored and fresh; the mean-return verdict holds |",
             "|---|---|---|---|---|---|---|"]
    for c in checks:
        lines.append(
            f"| {Path(c.path).name} | {c.seed} | {_own_keys(c)} | "
            f"{c.stored.fraction:.2f}, {_pass(c.stored)} | {c.fresh.fraction:.2f} {_ci(c.fresh_interval)}, "
            f"{np.mean(c.fresh_returns):.2f} ± {c.fresh_return_se:.2f}, {_pass(c.fresh)} | "
            f"{'yes' if c.holds else 'NO'} | "
            + ("– |" if c.stored_below is None else
               f"{c.stored_below:.2f}, {c.fresh_below:.2f}; {'yes' if c.return_holds else 'NO'} |"))
    worst = max(c.own_max_difference for c in checks)
    off = [Path(c.path).name for c in checks if not c.returns_equal]
    differ = [Path(c.path).name for c in checks if not c.flags_equal]
    unstored = [Path(c.path).name for c in checks if not c.flags_stored]
    text = f"Own keys: the largest return difference from the stored returns is {worst:.1e}"
    text += ("; " if not off else f", beyond rounding in {', '.join(off)}; ")
    text += ("every stored set of criterion flags is reproduced." if not differ else
             f"the criterion's flags differ from the stored ones in {', '.join(differ)}.")
    if off or differ:
        text += " Those files' stored verdicts are not what their policies do."
    if unstored:
        text += (f" {len(unstored)} file(s) store no flags (written before they were stored): their stored "
                 "verdict is the re-simulated one, checked through the returns alone.")
    lines += ["", text]
    lines += ["", f"Per cell, the per-trial rate (mean over seeds of the final policy's fraction meeting the task's "
              f"criterion) with its 95 % interval over seeds, from the stored evaluation rollouts and from {fresh} fresh "
              "ones per seed (the same fresh keys for every seed); where the task has a return threshold, the mean "
              "fraction of rollouts below it. A cell is a task and task preset, cost, k, method and experiment preset, "
              "with the settings in which its results depart from that preset:",
              "| task | task preset | cost | k | method | experiment preset | departures | seeds | criterion: stored "
              "| fresh | below threshold: stored | fresh | per-seed verdicts that hold |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        task, preset, cost, k, label, protocol, away = r.cell
        below = ("–", "–") if r.stored_below is None else (f"{r.stored_below:.2f}", f"{r.fresh_below:.2f}")
        lines.append(f"| {task} | {preset} | {cost} | {k:g} | {label} | {protocol} | {away} | {r.seeds} | "
                     f"{r.stored_rate:.2f} {_ci(r.stored_interval)} | {r.fresh_rate:.2f} {_ci(r.fresh_interval)} | "
                     f"{below[0]} | {below[1]} | {r.verdicts_hold}/{r.seeds} |")
    return "\n".join(lines)
