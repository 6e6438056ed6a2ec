"""What the ``pipps`` command prints besides results: cost estimates before a run, a sweep's
progress after every trial, what an interrupted sweep kept, and the caveats of a study whose
settings are not the thesis'. Printing only; the numbers come from the library
(:mod:`pipps.experiments.budget`, :mod:`pipps.experiments.storage`)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

from pipps.experiments import budget
from pipps.experiments.config import ExperimentConfig


def _err(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


# -- estimates ---------------------------------------------------------------------------------------


def machine_line(gflops: float) -> str:
    return (f"this machine's float64 GEMM rate {gflops:.0f} Gflop/s per core (the model's reference: "
            f"{budget.REFERENCE_GFLOPS:.0f} Gflop/s; docs/performance.md, \"Estimating a run's cost\")")


def run_cost(cfg: ExperimentConfig, gflops: float) -> budget.Estimate:
    """The cost model's estimate of ``cfg`` on this machine, with the compilation cache as it is now:
    what ``pipps run`` prints as its estimated cost and counts its ETA down from (:class:`RunProgress`)."""
    return budget.estimate(cfg, gflops, cold=budget.cache_is_cold())


def run_estimate(cfg: ExperimentConfig, est: budget.Estimate, done: int, cpus: int) -> str:
    """One experiment's estimate (:func:`run_cost`): core-minutes of what is left (trials ``done`` on), by phase."""
    left = est.remaining(done)
    share = left / est.total if est.total else 0.0
    where = (f"; with {cpus} CPUs a lone experiment's step ran 1.4-1.5× faster than on one (measured on 2)"
             if cpus > 1 else "")
    return (f"estimated cost: {left / 60:.1f} core-minutes"
            + (f" for trials {done}-{cfg.num_trials - 1}" if done else "")
            + f" (policy search {share * est.search / 60:.1f}, GP training {share * est.gp / 60:.1f}){where}; "
            + machine_line(est.gflops))


def sweep_estimate(rows, gflops: float, workers: int) -> list[str]:
    """A sweep's estimate: per experiment (``rows`` of (config, path, trials done)) and in total."""
    lines, total, cold = [], 0.0, budget.cache_is_cold()
    for cfg, path, done in rows:
        left = budget.estimate(cfg, gflops, cold=cold).remaining(done)
        total += left
        lines.append((left, cfg, path, done))
    out = []
    if lines:
        per = [left for left, *_ in lines]
        out.append(f"estimated cost: {len(lines)} experiment(s), {min(per) / 60:.1f}-{max(per) / 60:.1f} "
                   f"core-minutes each, {total / 60:.0f} core-minutes in all ({budget.minutes(total)} of one core); "
                   f"on {workers} worker(s) about {budget.minutes(total / max(workers, 1))} of wall time")
        out.append(machine_line(gflops))
    return out


# -- progress -------------------------------------------------------------------------------------------


class RunProgress:
    """The one-line progress display of ``pipps run`` (on stderr by default): trial, elapsed time,
    ETA, and the trial's phase (GP training, policy step and objective, evaluated return).

    The ETA is the cost model's per-trial estimate (``est``, the one the "estimated cost" line
    prints) of the trials not finished yet, with the running trial's time so far taken off its
    share, until a learned trial has finished; from then on that estimate is rescaled by how long
    the learned trials took against their estimates. A random trial (no model, no policy search)
    says nothing about them and does not rescale it. What is left is read off the trial index, so
    a resumed run counts the trials it resumed after as finished, and the last trial leaves 0."""

    def __init__(self, est: budget.Estimate, num_random: int, stream=None, clock=time.perf_counter):
        self.trials = est.trials
        self.num_random = num_random
        self.actual = self.predicted = 0.0
        self.clock = clock
        self.start = self.trial_start = clock()
        self.trial, self.total = 0, len(est.trials)
        self.running = False  # a trial has started and not finished
        self.stream = stream

    def factor(self) -> float:
        """Measured over estimated seconds of the learned trials finished here (1 before the first)."""
        return self.actual / self.predicted if self.predicted > 0 else 1.0

    def left(self) -> float:
        """Seconds the experiment still needs: the trials after the running one, and its rest."""
        f = self.factor()
        if not self.running:
            return f * sum(self.trials[self.trial + 1:])
        rest = max(f * self.trials[self.trial] - (self.clock() - self.trial_start), 0.0)
        return rest + f * sum(self.trials[self.trial + 1:])

    def finished(self, trial: int, seconds: float) -> None:
        self.trial, self.running = trial, False
        if self.num_random <= trial < len(self.trials):
            self.actual += seconds
            self.predicted += self.trials[trial]

    def __call__(self, event: dict) -> None:
        out = sys.stderr if self.stream is None else self.stream  # looked up per call: stderr may be replaced
        phase = event["phase"]
        if phase == "trial":
            self.trial, self.total, self.running = event["trial"], event["trials"], True
            self.trial_start = self.clock()
        elif phase == "evaluated":
            self.finished(event["trial"], event["seconds"])
        elapsed = self.clock() - self.start
        head = f"\rtrial {self.trial} of 0-{self.total - 1} [{elapsed / 60:5.1f} min ETA {self.left() / 60:.1f} min]"
        if phase == "gp":
            out.write(f"{head} training GP on {event['points']} points".ljust(100))
        elif phase == "optimize":
            out.write(f"{head} policy step {event['step']}/{event['steps']} objective {event['objective']:.3f}".ljust(100))
        elif phase == "evaluated":
            name = event.get("criterion", "upright")
            passed = event.get("passed", event.get(name, event["upright"]))  # the rollouts meeting the task's criterion
            out.write(f"{head} evaluated return {event['eval_return']:.3f} ({name} {passed:.0%})".ljust(100) + "\n")
        out.flush()


class SweepProgress:
    """Prints a line after every trial of every worker: the trial's time and return, the time its
    experiment still needs, and the sweep's ETA. The estimates of :mod:`pipps.experiments.budget`
    are rescaled by how long the finished learned trials really took (so a machine busy with other
    work, or a model that is off, corrects itself as the sweep goes); random trials, with no model
    and no policy search, do not rescale them."""

    def __init__(self, rows, gflops: float, workers: int, stream=None):
        cold = budget.cache_is_cold()
        self.estimates = {str(path): budget.estimate(cfg, gflops, cold=cold) for cfg, path, _ in rows}
        self.done = {str(path): done for _, path, done in rows}
        self.trials = {str(path): cfg.num_trials for cfg, path, _ in rows}
        self.random = {str(path): cfg.num_random for cfg, path, _ in rows}
        self.workers = max(workers, 1)
        self.actual = self.predicted = 0.0
        self.start = time.perf_counter()
        self.stream = stream

    def factor(self) -> float:
        return self.actual / self.predicted if self.predicted > 0 else 1.0

    def left(self) -> float:
        """Wall seconds the sweep still needs, at the current factor, on its workers."""
        core = sum(e.remaining(self.done[p]) for p, e in self.estimates.items())
        return self.factor() * core / self.workers

    def finished(self, path: str) -> None:
        """An experiment ended (complete, failed or skipped): nothing of it is left."""
        if path in self.done:
            self.done[path] = self.trials[path]

    def __call__(self, event: dict) -> None:
        path = str(event.get("path"))
        if event.get("phase") != "evaluated" or path not in self.estimates:
            return
        i, n = int(event["trial"]), int(event["trials"])
        seconds = float(event.get("seconds", 0.0))
        est = self.estimates[path]
        if self.random[path] <= i < len(est.trials):
            self.actual += seconds
            self.predicted += est.trials[i]
        self.done[path] = i + 1
        mine = self.factor() * est.remaining(i + 1)
        experiments = sum(1 for p in self.done if self.done[p] < self.trials[p])
        who = f"cpu {','.join(map(str, event['cpus']))}" if event.get("cpus") else f"pid {event.get('pid')}"
        ret = f", return {event['eval_return']:.2f}" if "eval_return" in event else ""
        line = (f"[{who}] {Path(path).name}: trial {i} of 0-{n - 1} done in {budget.minutes(seconds)}{ret}; "
                + (f"~{budget.minutes(mine)} more for it; " if i + 1 < n else "")
                + f"sweep: {experiments} experiment(s) unfinished, ETA {budget.minutes(self.left())} "
                  f"({(time.perf_counter() - self.start) / 60:.1f} min so far)")
        print(line, file=self.stream or sys.stderr, flush=True)


# -- what an interrupted sweep kept ----------------------------------------------------------------------


def kept_report(rows, command: str) -> list[str]:
    """After Ctrl-C: each planned file that holds something, with its finished trials, and the
    command that resumes the rest. ``rows``: (config, path) of the planned experiments."""
    from pipps.experiments.storage import existing_result

    lines, unfinished = [], 0
    for cfg, path in rows:
        found = existing_result(path, cfg)
        if found.kind == "complete":
            lines.append(f"  complete: {path}")
        elif found.kind == "unfinished" and found.trials:
            unfinished += 1
            lines.append(f"  {found.describe(cfg.num_trials)}: {path}")
        elif found.kind == "unfinished":  # stopped in its first trial: nothing to keep, the rerun starts it afresh
            lines.append(f"  no trial finished (the same command starts it again): {path}")
        elif found.kind != "missing":
            lines.append(f"  {found.kind}: {path} ({found.detail})")
    head = (f"kept: {sum(1 for line in lines if 'complete:' in line)} complete file(s), {unfinished} with finished "
            "trials to resume from" if lines else "kept: no experiment had finished a trial")
    return [head, *lines, f"resume with the same command: {command}"]


# -- caveats of a study ------------------------------------------------------------------------------------

#: the task the thesis' gradient studies measured on (a reference experiment's setting, like a table's task)
THESIS_STUDY_TASK = "cartpole_swingup"
#: the settings of the thesis' figures that pipps study quotes numbers of
THESIS_STUDY = {
    "landscape": dict(particles=1000, repeats=10, direction="pilco", deltas=(0.0, 1.5),
                      quote="RP's variance ratio (thesis: ~4·10⁵× at Δ = 1.5 against 0; Fig. 4.2)"),
    "variance": dict(particles=250, repeats=30, direction="pilco", deltas=(1.5,),
                     quote="TP against BIW-LR (thesis: TP 10-50 % below BIW-LR at P ≤ 250, chaotic case; Fig. 4.13)"),
}


def study_caveat(kind: str, cfg: ExperimentConfig, *, particles, repeats: int, direction: str, deltas,
                 choices: str) -> str | None:
    """A line saying how a study departs from the setting of the thesis number it prints, or None.

    The thesis measured on a thesis-protocol cart-pole swing-up policy (swing-up task, thesis
    preset), the moment-matching descent direction, the estimators' thesis variants (variance),
    with at least the particles and repeats of :data:`THESIS_STUDY` and Δ spanning its values."""
    ref = THESIS_STUDY[kind]
    off = []
    if cfg.task != THESIS_STUDY_TASK:  # a comparison with the thesis' setting for the caveat, not a task's behaviour
        off.append(f"a {cfg.task} policy (the thesis: cart-pole swing-up)")
    if cfg.protocol != "thesis":
        off.append(f"a {cfg.protocol}-preset file (the thesis protocol is --preset thesis)")
    ps = [int(p) for p in (particles if isinstance(particles, (list, tuple)) else [particles])]
    if kind == "landscape" and max(ps) < ref["particles"]:
        off.append(f"P = {max(ps)} (the thesis: {ref['particles']})")
    if kind == "variance" and min(ps) > ref["particles"]:
        off.append(f"no P ≤ {ref['particles']}")
    if repeats < ref["repeats"]:
        off.append(f"{repeats} repeats (these defaults: {ref['repeats']})")
    if direction != ref["direction"]:
        off.append(f"a {direction} direction (the thesis: the moment-matching descent direction)")
    ds = [float(d) for d in deltas]
    missing = [d for d in ref["deltas"] if not any(abs(d - x) < 1e-9 for x in ds)]
    if missing:
        off.append(f"no Δ = {', '.join(f'{d:g}' for d in missing)}")
    if kind == "variance" and choices != "thesis":
        off.append("the library's estimator variants (the thesis': --choices thesis)")
    if not off:
        return None
    return (f"caveat: not the thesis' setting, so {ref['quote']} is for orientation only: this study has "
            + "; ".join(off) + ".")
