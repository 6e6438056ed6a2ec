"""The ``pipps`` command line. Thin: parsing and printing only; the work is in library functions.

Commands: ``run`` (one learning experiment), ``sweep`` (a table's grid over seeds, parallel and
resumable), ``table`` (success rates against the thesis), ``plot`` (rerun recordings), ``study``
(gradient studies on a stored policy: ``landscape``, ``variance``), ``bench`` (run time against
gradient error) and ``rollout`` (true-system rollouts with a random policy).
``pipps COMMAND --help`` lists the options.

Errors are one line naming the problem (exit status 2 for bad input); ``--debug`` or
``PIPPS_DEBUG=1`` shows the traceback of an unexpected one. Ctrl-C (SIGINT) and ``kill PID``
(SIGTERM, :class:`Terminated`) both stop a command keeping every finished trial (exit status 130
and 143); a process started in the background by a script ignores SIGINT, so ``kill`` stops it.

Every command computes in float64: :func:`main` switches on JAX's 64-bit mode before anything
else runs (:func:`pipps.enable_float64`; importing the library does not).

Compiled programs are kept in JAX's persistent compilation cache (:func:`enable_compilation_cache`),
so the second experiment of a sweep, and every later command, reuses the first one's programs.

``--task`` names a built-in task, a task registered by an installed package (entry point group
``pipps.tasks``), or a task of your own as ``MODULE:ATTRIBUTE`` (``pipps run --task
mytasks:pendulum``; docs/tutorial.md). The module is imported with the current directory on the
path (appended, so it shadows nothing), as ``python -m`` would find it; ``table`` and ``plot``
take ``--task`` to find the task of results whose stored source has moved.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import signal
import sys
import threading

from pipps import cli_options as opt


def _int_at_least(lowest: int):
    """An argparse type: an integer >= ``lowest``."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer >= {lowest}, got {text!r}") from None
        if value < lowest:
            raise argparse.ArgumentTypeError(f"must be an integer >= {lowest}, got {text}")
        return value

    return parse


_positive_int = _int_at_least(1)


def _seed(text: str) -> int:
    """``--seed``, ``--seed-start``: an integer in [0, MAX_SEED], the seeds every draw can start from
    (:data:`pipps.experiments.config.MAX_SEED`)."""
    from pipps.experiments.config import MAX_SEED

    return opt.int_at_least(0, MAX_SEED)(text)


#: the most seeds per cell ``pipps sweep --seeds`` takes: ten times the thesis' 100 (a dry run of
#: Table 4.1 plans about 40 experiments a second)
MAX_SEEDS = 1000


def _jobs(text: str) -> int | None:
    """``--jobs``: a positive integer, or ``auto`` (None: :func:`pipps.experiments.sweep.cpu_layout`)."""
    return None if text == "auto" else _positive_int(text)


def _layout(args, experiments: int) -> str:
    """How ``pipps sweep`` will run ``experiments``: workers × CPUs each, for its start-up line."""
    if args.backend == "ray":
        return f"{args.jobs or 'all'} task(s) in flight"
    from pipps.experiments.sweep import available_cpus, cpu_layout

    workers, width = cpu_layout(args.jobs, max(experiments, 1), available_cpus())
    where = "this process" if workers == 1 else f"{workers} pinned worker(s)"
    layout = f"{where} × {width if workers > 1 else available_cpus()} CPU(s)"
    if getattr(args, "batched", False):  # each cell's seeds as one batch here; the rest as above
        return f"each cell's seeds as one batch in this process (--batched; what cannot batch: {layout})"
    return layout


def _method_pair(text: str) -> tuple[str, str]:
    """``A,B``: two method names of the registry (pipps table --compare)."""
    from pipps.experiments.methods import METHODS

    parts = [p.strip() for p in text.split(",")]
    if len(parts) != 2 or any(p not in METHODS for p in parts):
        raise argparse.ArgumentTypeError(f"expected two methods as A,B from {', '.join(METHODS)}, got {text!r}")
    return parts[0], parts[1]


def _nonnegative_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text!r}") from None
    if not value >= 0.0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value


def _setting(text: str) -> tuple[str, str]:
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    key, value = text.split("=", 1)
    return key.strip(), value


#: ``--set`` keys that have an option of their own (one way to give each setting; docs/experiments.md)
RUN_OWN_OPTIONS = {"task": "--task", "method": "--method", "cost": "--cost", "k": "--k", "seed": "--seed",
                   "num_particles": "--particles", "preset": "--preset", "protocol": "--preset"}
SWEEP_OWN_OPTIONS = {"task": "--table or --task", "method": "--methods", "k": "--k", "seed": "--seeds/--seed-start",
                     "preset": "--preset", "protocol": "--preset"}


#: what ``pipps plot --figure`` draws: of experiment results, then of a study file
FIGURES = ("overview", "cells", "curves", "diagnostics", "landscape", "variance", "bench")
_STUDY_FIGURES = ("landscape", "variance", "bench")


class UsageError(ValueError):
    """Bad command-line input; the message is printed as one line."""


def _check_settings(settings: list[tuple[str, str]], own: dict[str, str], fixed_by_cells: set[str] = frozenset()):
    """``--set`` pairs as a dict, refusing a key given twice, one that has its own option, or one the
    sweep's table cells fix (cost, cost_scale)."""
    out: dict[str, str] = {}
    for key, value in settings:
        name = key.replace("-", "_")
        if name in own:
            raise UsageError(f"--set {key}=…: {name} has its own option; use {own[name]} instead")
        if name in fixed_by_cells:
            raise UsageError(f"--set {key}=…: the table's cells fix {name}; pick cells with --table/--k/--methods")
        if name in out:
            raise UsageError(f"--set {key} is given twice ({out[name]!r} and {value!r})")
        out[name] = value
    return out


#: ``--task``'s help: what it accepts
TASK_HELP = ("a built-in task (cartpole_swingup, cartpole_balance, unicycle), one an installed package registers, or "
             "MODULE:ATTRIBUTE of a task of your own (docs/tutorial.md)")


def _add_experiment_options(p: argparse.ArgumentParser, *, single: bool) -> None:
    from pipps.experiments.config import PRESET_NAMES
    from pipps.experiments.methods import METHODS

    # run: None means "not given" (the defaults are filled in by _run_config; --resume keeps the file's)
    p.add_argument("--preset", default=None if single else "thesis", choices=PRESET_NAMES,
                   help="thesis (the thesis protocol; default), pilco (PILCO's task defaults) or quick (a few "
                        "minutes on a CPU)")
    if single:
        p.add_argument("--task", default=None, metavar="TASK", help=f"{TASK_HELP}; default cartpole_swingup")
        p.add_argument("--method", default=None, choices=list(METHODS), help="default tp")
        p.add_argument("--cost", default=None, help="angle | tip (cart-pole), unicycle; default: the task preset's")
        p.add_argument("--k", type=_nonnegative_float, default=None,
                       help="observation-noise variance multiplier (default 1)")
        p.add_argument("--seed", type=_seed, default=None, help="default 0")
        p.add_argument("--particles", type=_positive_int, default=None, help="P (default: the preset's)")
    p.add_argument("--set", dest="settings", type=_setting, action="append", default=[], metavar="KEY=VALUE",
                   help="override any experiment setting (repeatable), e.g. --set policy_evals=300")


def build_parser() -> argparse.ArgumentParser:
    from pipps.experiments.config import PRESET_NAMES

    parser = argparse.ArgumentParser(prog="pipps", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--debug", action="store_true", help="show the traceback of an unexpected error")
    sub = parser.add_subparsers(dest="command", required=True)

    ro = sub.add_parser("rollout", help="simulate a few episodes with a random policy and print the returns")
    ro.add_argument("--task", default="cartpole_swingup", metavar="TASK", help=f"{TASK_HELP}; default cartpole_swingup")
    ro.add_argument("--preset", default=None, help="the task preset (built-in tasks: thesis or pilco; default: the "
                                                   "task's first)")
    ro.add_argument("--k", type=_nonnegative_float, default=1.0, help="observation-noise variance multiplier")
    ro.add_argument("--policy", default="random-actions", choices=["random-actions", "random-policy"])
    ro.add_argument("--episodes", type=opt.int_at_least(1, 100_000), default=3)
    ro.add_argument("--seed", type=_seed, default=0)

    run = sub.add_parser("run", help="run one episodic learning experiment and write its HDF5 result")
    _add_experiment_options(run, single=True)
    run.add_argument("--out", default=None, help="result file (default: runs/<experiment name>.h5)")
    run.add_argument("--quiet", action="store_true", help="no progress display")
    run.add_argument("--resume", action="store_true",
                     help="continue the unfinished result at --out from its last finished trial, with the "
                          "configuration the file stores (options given must agree with it)")
    run.add_argument("--dry-run", action="store_true",
                     help="print what would run and its estimated cost, and run nothing")
    run.add_argument("--overwrite", action="store_true",
                     help="replace the file at --out even if it holds a complete result or another experiment "
                          "(without it, an existing result is never replaced)")

    sw = sub.add_parser("sweep", help="run a table's cells, or a task's methods and k values, over seeds in parallel "
                                      "workers (resumable)")
    what = sw.add_mutually_exclusive_group(required=True)
    what.add_argument("--table", type=opt.one_of("table", opt.tables),
                      help="4.1, 4.2, 4.3, 4.4, q001 (Q × 0.01 cell) or del")
    what.add_argument("--task", metavar="TASK",
                      help=f"{TASK_HELP}: its --methods (default tp) × --k (default 1) × seeds, its own table")
    sw.add_argument("--seeds", type=opt.int_at_least(1, MAX_SEEDS), default=20,
                    help=f"seeds per cell, from --seed-start on (default 20, at most {MAX_SEEDS})")
    sw.add_argument("--seed-start", type=_seed, default=0, help="the first seed (default 0)")
    sw.add_argument("--methods", default=None, type=opt.names("methods", opt.methods),
                    help="comma-separated subset of the table's methods (with --task: the methods to run, default tp)")
    sw.add_argument("--k", dest="ks", default=None, type=opt.float_list(0.0),
                    help="comma-separated subset of the table's k values (with --task: the k values, default 1)")
    sw.add_argument("--jobs", type=_jobs, default=None,
                    help="parallel worker processes (local; default auto: one per CPU, each pinned, and the CPUs "
                         "shared out when fewer experiments remain) or Ray tasks in flight (ray; default: all)")
    sw.add_argument("--backend", default="local", choices=["local", "ray"],
                    help="local worker processes, or tasks on a Ray cluster (needs pipps[ray])")
    sw.add_argument("--address", default=None,
                    help="Ray cluster address (ray://HOST:10001 or auto; default: a local Ray instance); "
                         "--out must be a folder every node sees")
    sw.add_argument("--batched", action="store_true",
                    help="run each cell's unfinished seeds as one vectorized batch in this process (for a GPU; "
                         "PILCO and the fixed-seed methods still run one by one)")
    sw.add_argument("--batching", default="auto", choices=["auto", "vmap", "map"],
                    help="how --batched computes the seed axis: vmap (one batched program; on CPU the GP training "
                         "still maps, batched CPU LAPACK deadlocks), map (seeds in sequence inside it), auto "
                         "(map on CPU, vmap on GPU)")
    sw.add_argument("--out", default="runs", help="result folder (one file per experiment)")
    sw.add_argument("--dry-run", action="store_true",
                    help="list what would run, what is already complete or interrupted, and the estimated cost")
    _add_experiment_options(sw, single=False)

    tb = sub.add_parser("table", help="success rates under every reading (per trial, per seed, final system trial; "
                                      "by the return threshold and by the physical criterion) with 95%% intervals "
                                      "over seeds, next to the thesis' tables")
    tb.add_argument("results", nargs="*", default=["runs"], help="result files or folders (default: runs)")
    tb.add_argument("--table", default=None, type=opt.one_of("table", opt.tables),
                    help="one table (default: every table with results)")
    tb.add_argument("--preset", default=None, choices=PRESET_NAMES,
                    help="count the results of this experiment preset; results of another preset, or whose "
                         "settings depart from it, are listed as not counted. Default: thesis, or, when no "
                         "result is of the thesis preset and all are of one other preset, that one, labelled "
                         "as not the thesis protocol")
    tb.add_argument("--custom", action="store_true",
                    help="also count results whose settings depart from the preset (each table names them)")
    tb.add_argument("--curves", action="store_true", help="also print every result's evaluated return per trial (with "
                    "--table, that table's results), and per cell its median and quartiles over the seeds")
    tb.add_argument("--per-seed", action="store_true",
                    help="also print, per cell, every seed's final return and fraction of rollouts balanced (upright)")
    tb.add_argument("--compare", default="tp,pilco", type=_method_pair, metavar="A,B",
                    help="the two methods whose difference each table gives under every reading (default tp,pilco)")
    tb.add_argument("--task", dest="tasks", action="append", default=[], metavar="MODULE:ATTRIBUTE",
                    help="where to find a task of your own whose results are read, when its stored source has moved "
                         "(repeatable)")
    tb.add_argument("--by", default=None, metavar="SETTING",
                    help="compare the results by one setting's value (e.g. estimator_choices): each cell's headline "
                         "rate per value side by side, every reading per value with its interval over seeds and, with "
                         "two values, their difference under every reading (Newcombe's interval, permutation p over "
                         "seeds) and paired by seed; results that depart from the preset only in SETTING count "
                         "without --custom")

    rs = sub.add_parser("resimulate", help="re-run each complete result's final policy on the true system: its own "
                                           "evaluation keys must reproduce the stored returns and verdict, and fresh "
                                           "rollouts test whether the verdict holds")
    rs.add_argument("results", nargs="*", default=["runs"], help="result files or folders (default: runs); incomplete "
                                                                 "files are listed and skipped")
    rs.add_argument("--fresh", type=_positive_int, default=300,
                    help="independent rollouts per final policy, with keys the experiment never used (default 300)")
    rs.add_argument("--seed", type=int, default=0, help="seed of the fresh rollouts' keys (default 0; the same seed "
                                                       "gives every file the same keys, so files compare paired)")

    pl = sub.add_parser("plot", help="write a rerun recording (.rrd) of results or a study; --png renders it",
                        description="Writes a rerun recording of experiment results (files or folders) or of one study "
                                    "file (pipps study / pipps bench output). --figure picks what it shows; the "
                                    "figures other than overview are drawn for a paper (labelled axes, no viewer "
                                    "panels) and docs/experiments.md says which thesis figure each corresponds to.")
    pl.add_argument("results", nargs="+", help="result files or folders, or one study file")
    pl.add_argument("--figure", default=None, choices=FIGURES,
                    help="overview (default for results: the interactive four-panel recording), cells (per method "
                         "against k: the headline success rate with its 95%% interval over seeds, the per-trial "
                         "physical rate as a bar, the per-seed readings as small dots, thesis' rates marked), curves "
                         "(evaluated return per trial of each table cell: median, quartiles, seeds), diagnostics (final-trial predictions, "
                         "k_LR and gradient variances per step); landscape, variance, bench (a study file's figure, "
                         "its default)")
    pl.add_argument("--table", default=None, type=opt.one_of("table", opt.tables),
                    help="cells/curves: the table whose cells to draw (curves needs it when the results fill cells "
                         "of more than one table)")
    pl.add_argument("--preset", default=None, choices=PRESET_NAMES,
                    help="cells/curves: count the results of this experiment preset, as pipps table does (default: "
                         "as pipps table)")
    pl.add_argument("--custom", action="store_true",
                    help="cells/curves: also count results whose settings depart from the preset")
    pl.add_argument("--by", default=None, metavar="SETTING",
                    help="cells/curves: draw the results apart by one setting's value (e.g. estimator_choices), as "
                         "pipps table --by compares them: curves, a panel per cell and value; cells, a panel per "
                         "value; results that depart from the preset only in SETTING count without --custom")
    pl.add_argument("--task", dest="tasks", action="append", default=[], metavar="MODULE:ATTRIBUTE",
                    help="where to find a task of your own whose results are drawn, when its stored source has moved "
                         "(repeatable)")
    pl.add_argument("--out", default="pipps.rrd", type=opt.file_name(".rrd"), help="recording to write")
    pl.add_argument("--png", default=None, type=opt.file_name(".png"),
                    help="also render the recording to this PNG (needs xvfb-run, Mesa and the rerun viewer)")
    pl.add_argument("--svg", default=None, type=opt.file_name(".svg"),
                    help="also write the figure as SVG: vector, plain text labels, no viewer or display needed "
                         "(every figure but the interactive overview)")
    pl.add_argument("--size", default=None, type=opt.window_size,
                    help="PNG window size WxH (default: the figure's own layout; 1600x1000 for the overview)")
    pl.add_argument("--overwrite", action="store_true",
                    help="replace existing --out/--png/--svg files (never an experiment result)")

    from pipps.propagation.estimators import estimator_help

    st = sub.add_parser("study", help="gradient studies on a policy snapshot from a result file (docs/gradients.md)")
    studies = st.add_subparsers(dest="study", required=True)
    from pipps.studies.contact_catalog import STUDIES as CONTACT_STUDIES, estimated_minutes

    ct = studies.add_parser("contact", help="first-, zeroth- and α-order gradients on contact (Suh et al.; docs/contact.md)",
                            description="Runs one of Suh et al.'s examples with its sweep and writes a JSON result "
                                        "(tables, verdicts) and its figure. Quick by default (minutes); --full gives "
                                        "the numbers in docs/contact.md.")
    ct.add_argument("example", choices=CONTACT_STUDIES,
                    help="; ".join(f"{n}: about {q:g} min quick, {f:g} min full" for n, (q, f) in estimated_minutes().items()))
    ct.add_argument("--full", action="store_true", help="the full sweep of docs/contact.md (longer: see the choices)")
    ct.add_argument("--seed", type=_seed, default=0)
    ct.add_argument("--out", default=None, type=opt.file_name(".json"),
                    help="JSON output (default: contact_EXAMPLE.json); an existing file is kept unless --overwrite")
    ct.add_argument("--svg", default=None, type=opt.file_name(".svg"), help="the figure as SVG (default: --out with .svg)")
    ct.add_argument("--rrd", default=None, type=opt.file_name(".rrd"), help="the figure as a rerun recording (default: none)")
    ct.add_argument("--overwrite", action="store_true", help="replace existing output files (never an experiment result)")
    for name, text in (("landscape", "objective and each estimator's gradient along θ + Δ·d (thesis Fig. 4.2)"),
                       ("variance", "gradient variance against the number of particles (thesis Fig. 4.13)")):
        p = studies.add_parser(name, help=text)
        p.add_argument("result", help="a result file of a pipps run/sweep experiment, on any task with moment "
                                      "matching (cart-pole, unicycle, …)")
        p.add_argument("--trial", type=_positive_int, default=None,
                       help="learned trial whose optimisation start is the snapshot (default: the last one the file can rebuild)")
        p.add_argument("--estimators", default=None, help=f"comma-separated, each NAME or NAME:SETTING=VALUE "
                       f"(e.g. tp:k_lr=previous; docs/estimators.md): {estimator_help()}")
        p.add_argument("--repeats", type=_int_at_least(2), default=None, help="independent estimates per point")
        p.add_argument("--direction", default="pilco", choices=["pilco", "random"],
                       help="pilco: the moment-matching descent direction (the thesis'); random: a random unit vector")
        p.add_argument("--choices", default="library", choices=["library", "thesis"],
                       help="library (unbiased) or the thesis' own baseline and k_LR")
        p.add_argument("--seed", type=_seed, default=0)
        p.add_argument("--out", default=None, type=opt.file_name(".h5"), help=f"HDF5 output (default: study_{name}.h5)")
        p.add_argument("--rrd", default=None, type=opt.file_name(".rrd"),
                       help="rerun recording (default: the --out name with .rrd)")
        p.add_argument("--overwrite", action="store_true",
                       help="replace existing --out/--rrd files (never an experiment result)")
        p.add_argument("--quick", action="store_true", help="a small version that runs in well under a minute")
        if name == "landscape":
            p.add_argument("--particles", type=_int_at_least(2), default=None, help="P (default 1000)")
            p.add_argument("--deltas", default=None, type=opt.grid, help="START:STOP:NUM grid of Δ (default 0:1.5:16)")
        else:
            p.add_argument("--particles", default=None, type=opt.int_list(2),
                           help="comma-separated P values (default 10,30,100,300,1000)")
            p.add_argument("--deltas", default=None, type=opt.float_list(),
                           help="comma-separated Δ values (default 0,1.5: smooth, chaotic)")

    bn = sub.add_parser("bench", help="run time against gradient error per estimator and P, and the Pareto table")
    bn.add_argument("result", help="a result file of a pipps run/sweep experiment, on any task with moment matching "
                                   "(cart-pole, unicycle, …; the snapshot, as for pipps study)")
    bn.add_argument("--trial", type=_positive_int, default=None, help="learned trial (default: the last one the file can rebuild)")
    bn.add_argument("--estimators", default=None,
                    help=f"comma-separated, as for pipps study (default rp,lr,tp,gtp): {estimator_help()}")
    bn.add_argument("--particles", default=None, type=opt.int_list(2),
                    help="comma-separated P values (default 30,100,300,1000)")
    bn.add_argument("--deltas", default=None, type=opt.float_list(),
                    help="comma-separated Δ values (default 0,1.5: smooth, chaotic)")
    bn.add_argument("--repeats", type=_int_at_least(2), default=None, help="estimates per entry for its MSE (default 20)")
    bn.add_argument("--reference-repeats", type=_int_at_least(2), default=None,
                    help="estimates averaged into the reference gradient (default 50)")
    bn.add_argument("--reference", default="tp", help="the unbiased estimator of the reference (at the largest P)")
    bn.add_argument("--variance-tols", default=[0.0], type=opt.float_list(0.0), help="comma-separated GP variance tolerances: 0 is the exact "
                    "variance, T > 0 the certified low-rank form at T·σ² (docs/gp.md); each adds a series, with each "
                    "estimate's change from the exact-variance one (default 0)")
    bn.add_argument("--direction", default="pilco", choices=["pilco", "random"])
    bn.add_argument("--seed", type=_seed, default=0)
    bn.add_argument("--out", default="bench.h5", type=opt.file_name(".h5"), help="HDF5 output")
    bn.add_argument("--rrd", default=None, type=opt.file_name(".rrd"),
                    help="rerun recording (default: the --out name with .rrd)")
    bn.add_argument("--overwrite", action="store_true",
                    help="replace existing --out/--rrd files (never an experiment result)")
    bn.add_argument("--quick", action="store_true", help="a small version that runs in well under a minute")
    return parser


#: what `pipps run` runs when an option is not given (and `--resume --out FILE` does not read it from FILE)
RUN_DEFAULTS = {"preset": "thesis", "task": "cartpole_swingup", "method": "tp", "k": 1.0, "seed": 0}


def _task_name(ref: str) -> str:
    """The name of the task ``ref`` names (a name or MODULE:ATTRIBUTE, loaded and registered here),
    or :class:`UsageError` saying why it is not available."""
    from pipps.tasks.registry import TaskUnavailable, get_task

    try:
        return get_task(ref).name
    except TaskUnavailable as err:
        raise UsageError(f"--task {ref}: {err}") from None


def _given(args) -> dict:
    """The experiment settings given on the command line (options left out are not in it)."""
    given = {name: getattr(args, name) for name in ("task", "method", "cost", "k", "seed")
             if getattr(args, name) is not None}
    if args.particles is not None:
        given["num_particles"] = args.particles
    given.update(_check_settings(args.settings, RUN_OWN_OPTIONS))
    return given


def _run_config(args):
    """The configuration the options ask for, with :data:`RUN_DEFAULTS` where they are left out."""
    from pipps.experiments.config import resolve_config

    given = _given(args)
    task = given.pop("task", RUN_DEFAULTS["task"])
    overrides = {name: RUN_DEFAULTS[name] for name in ("method", "k", "seed")} | {"cost": None} | given
    return resolve_config(args.preset or RUN_DEFAULTS["preset"], task, **overrides)


def _resume_config(args, out):
    """``--resume --out FILE``: the configuration FILE stores; every option given must agree with it."""
    from pipps.experiments.config import config_difference, refuse_unused, same_experiment
    from pipps.experiments.results import ResultError, verify_result

    try:
        _, stored, _ = verify_result(out)
    except ResultError as err:  # its message starts with the path, named here already
        raise UsageError(f"--resume: nothing to continue at {out}: {str(err).removeprefix(f'{out}: ')}") from None
    given = _given(args)
    if ":" in given.get("task", ""):  # where the task is now: the resumed run records it
        stored = stored.replace(task=given.pop("task")) if _task_name(args.task) == stored.task else stored
    refuse_unused(given.get("method", stored.method), given)
    differ = []
    if args.preset is not None and args.preset != stored.protocol:
        differ.append(f"preset: {stored.protocol!r} stored, {args.preset!r} asked")
    if given and not same_experiment(stored, stored.replace(**given)):
        differ.append(config_difference(stored, stored.replace(**given)))
    if differ:
        raise UsageError(f"--resume: {out} stores another configuration than the options ask ({'; '.join(differ)}); "
                         f"pipps run --resume --out {out} alone continues it as stored")
    return stored


def _plan_line(cfg, out) -> str:
    return (f"{cfg.task} / {cfg.table_name} / k={cfg.k:g} / seed {cfg.seed} ({cfg.protocol} preset): "
            f"{cfg.num_random} random + {cfg.num_learned} learned trials (trials 0-{cfg.num_trials - 1})"
            + ("" if cfg.is_pilco else f", P={cfg.num_particles}, {cfg.policy_evals} policy evaluations per trial")
            + f" -> {out}")


def _cmd_run(args) -> int:
    from pipps.cli_report import RunProgress, run_cost, run_estimate
    from pipps.experiments.budget import gemm_gflops
    from pipps.experiments.config import experiment_name
    from pipps.experiments.loop import run_experiment
    from pipps.experiments.preflight import check_experiment
    from pipps.experiments.results import read_result, study_file, write_result
    from pipps.experiments.storage import ResultLock, check_output_file, existing_result
    from pipps.experiments.sweep import available_cpus

    if args.resume and args.overwrite:
        raise UsageError("--resume and --overwrite contradict each other; give one")
    if args.resume and args.out:
        cfg = _resume_config(args, check_output_file(args.out, create=False))
        out = args.out
    else:
        cfg = _run_config(args)
        out = args.out or f"runs/{experiment_name(cfg)}.h5"
    check_experiment(cfg)  # the noise it can represent, the memory it needs: before anything runs
    out = check_output_file(out, create=not args.dry_run)
    if args.dry_run:
        found = existing_result(out, cfg)
        done = found.trials if found.kind == "unfinished" else 0
        fate = "--overwrite replaces it" if args.overwrite else "refused without --overwrite"
        study = _study_kind(out) if found.kind == "damaged" else None
        there = {"missing": "no file yet", "complete": f"a complete result of it ({fate})",
                 "other": f"another experiment ({found.detail}; {fate})",
                 "damaged": f"{study_file(study)} ({fate})" if study else f"a damaged file ({found.detail}; {fate})",
                 "unreadable": f"a file it cannot read now ({found.detail})"}.get(found.kind)
        if there is None:
            there = found.describe(cfg.num_trials) + (f"; {fate}" if args.overwrite and found.trials else
                                                      f"; --resume continues at trial {done}" if done else "")
        print(f"would run 1 experiment: {_plan_line(cfg, out)}")
        print(f"  at {out}: {there}")
        print(f"  {run_estimate(cfg, run_cost(cfg, gemm_gflops()), done if args.resume else 0, available_cpus())}")
        return 0
    with ResultLock(out):  # held for the whole run: no other process writes this file meanwhile
        found = existing_result(out, cfg)
        if found.kind == "unfinished" and not found.trials:  # stopped in trial 0: nothing to keep or resume
            found = dataclasses.replace(found, kind="missing")
        resume = None
        if args.resume:
            if found.kind != "unfinished" or not found.trials:
                why = {"missing": "there is no file, or it holds no finished trial", "complete": "it is already complete",
                       "other": f"it holds another experiment ({found.detail})",
                       "damaged": found.detail, "unreadable": found.detail}.get(found.kind, "it holds no finished trial")
                raise UsageError(f"--resume: nothing to continue at {out}: {why}")
            resume = read_result(out, verify=False)
        elif found.kind != "missing" and not args.overwrite:
            study = _study_kind(out) if found.kind == "damaged" else None
            why = {"complete": "a complete result of this experiment",
                   "unfinished": f"an unfinished run of this experiment ({found.trials} of {cfg.num_trials} "
                                 "trials); --resume continues it",
                   "other": f"another experiment ({found.detail})",
                   "damaged": study_file(study) if study else f"a file that is not an intact pipps result ({found.detail})",
                   "unreadable": f"a file it cannot read now ({found.detail})"}[found.kind]
            raise UsageError(f"{out} already holds {why}; --overwrite replaces it, or pick another --out")
        progress = None
        if not args.quiet:
            est = run_cost(cfg, gemm_gflops())  # the estimate printed is the one the ETA counts down from
            print(_plan_line(cfg, out), file=sys.stderr)
            print(run_estimate(cfg, est, len(resume.trials) if resume else 0, available_cpus()), file=sys.stderr)
            if resume is not None:
                print(f"resuming at trial {len(resume.trials)} (trials 0-{cfg.num_trials - 1})", file=sys.stderr)
            progress = RunProgress(est, cfg.num_random)
        try:
            result = run_experiment(cfg, progress=progress, on_trial=lambda r: write_result(out, r), resume=resume)
        except KeyboardInterrupt as err:
            kept = existing_result(out, cfg)
            print(f"\npipps run: interrupted; {out}: {kept.describe(cfg.num_trials)}"
                  + (f"; pipps run --resume --out {out} continues it" if kept.trials else ""), file=sys.stderr)
            return _interrupted_status(err)
    returns = " ".join(f"{t.eval_return:.2f}" for t in result.trials)
    print(f"evaluated return per trial (trial 0 first): {returns}")
    verdict = "success" if result.success else "failure"
    print(f"final evaluated return {result.final_return:.3f}: {verdict} "
          f"({result.wall_seconds / 60:.1f} min); results in {out}")
    return 0


def _cmd_sweep(args) -> int:
    from pipps.experiments.config import MAX_SEED
    from pipps.experiments.sweep import import_ray, run_sweep, survey
    from pipps.reporting.tables import table_configs

    if args.address is not None and args.backend != "ray":
        print("pipps sweep: error: --address needs --backend ray", file=sys.stderr)
        return 2
    if args.batched and args.backend != "local":
        print("pipps sweep: error: --batched runs on the local backend", file=sys.stderr)
        return 2
    if args.batching != "auto" and not args.batched:
        print("pipps sweep: error: --batching needs --batched", file=sys.stderr)
        return 2
    if args.backend == "ray":
        try:
            import_ray()
        except ImportError as err:
            print(f"pipps sweep: error: --backend ray: {err}", file=sys.stderr)
            return 2
    from pipps.experiments.storage import check_output_folder, claim_sweep_folder
    from pipps.reporting.tables import get_table, task_table

    if args.task is not None:  # the task's own table: its methods × k values
        table = task_table(_task_name(args.task), args.ks or [1.0], args.methods or ["tp"])
    else:
        try:
            table = get_table(args.table)
        except ValueError as err:
            raise UsageError(str(err)) from None
    fixed = {name for cell in table.cells for name, _ in cell.values}
    overrides = _check_settings(args.settings, SWEEP_OWN_OPTIONS, fixed)
    methods, ks = args.methods, args.ks  # lists, read and checked by argparse
    seeds = range(args.seed_start, args.seed_start + args.seeds)
    if seeds[-1] > MAX_SEED:
        raise UsageError(f"--seed-start {args.seed_start} with --seeds {args.seeds} reaches seed {seeds[-1]}; "
                         f"seeds must lie in [0, {MAX_SEED}]")
    try:
        configs = table_configs(table, seeds, args.preset, methods=methods, ks=ks, overrides=overrides)
    except ValueError as err:  # unknown methods; ConfigError (a ValueError) names a bad --set value
        raise UsageError(str(err)) from None
    if not configs:
        raise UsageError("no cell of the table matches --methods/--k")
    check_output_folder(args.out, create=not args.dry_run)
    claim_sweep_folder(args.out, configs, write=False)  # the real sweep writes it (run_sweep)
    rows = survey(configs, args.out)
    todo = [(cfg, path, found) for cfg, path, found in rows if found.kind != "complete"]
    resumed = sum(1 for *_, found in todo if found.kind == "unfinished" and found.trials)
    workers = _sweep_workers(args, len(todo))
    _preflight_sweep(args, todo, workers)
    print(f"{len(configs)} experiments: {len(rows) - len(todo)} already complete, {len(todo)} to run "
          f"({resumed} resumed from their last finished trial) with {_layout(args, len(todo))} "
          f"({args.backend}) -> {args.out}/", file=sys.stderr)
    from pipps.cli_report import SweepProgress, kept_report, sweep_estimate
    from pipps.experiments.budget import gemm_gflops

    starts = [(cfg, path, found.trials if found.kind == "unfinished" else 0) for cfg, path, found in todo]
    gflops = gemm_gflops() if todo else 0.0
    if args.dry_run:
        for cfg, path, found in todo:
            if found.kind == "unfinished" and found.trials:
                print(f"  resume at trial {found.trials}  {path}  ({found.describe(cfg.num_trials)})")
            elif found.kind == "damaged":
                print(f"  run  {path}  (a damaged file there is set aside first: {found.detail})")
            else:
                print(f"  run  {path}")
        for line in sweep_estimate(starts, gflops, workers):
            print(line)
        return 0
    for line in sweep_estimate(starts, gflops, workers):
        print(line, file=sys.stderr)
    progress = SweepProgress(starts, gflops, workers) if todo else None

    def on_done(path, err, finished, total):
        status = "FAILED " + err.splitlines()[0] if err else "done"
        if progress is not None:
            progress.finished(path)
        print(f"[{finished}/{total}] {status}: {path}", file=sys.stderr, flush=True)

    try:
        report = run_sweep(configs, args.out, jobs=args.jobs, on_done=on_done, backend=args.backend,
                           address=args.address, batched=args.batched, batching=args.batching, on_trial=progress)
    except KeyboardInterrupt as err:
        print("\npipps sweep: interrupted; the workers are stopped", file=sys.stderr)
        for line in kept_report([(cfg, path) for cfg, path, _ in todo], _command_line()):
            print(line, file=sys.stderr)
        return _interrupted_status(err)
    for path, note in report.notes.items():
        print(f"  note: {path}: {note}", file=sys.stderr)
    print(f"ran {len(report.ran)}, skipped {len(report.skipped)} (complete, or running in another process), "
          f"failed {len(report.failed)} "
          f"in {report.seconds / 60:.1f} min")
    return 1 if report.failed else 0


def _sweep_workers(args, experiments: int) -> int:
    """How many experiments a sweep runs at once (for its memory check and its ETA)."""
    if args.batched:
        return 1
    if args.backend == "ray":
        return args.jobs or max(experiments, 1)
    from pipps.experiments.sweep import available_cpus, cpu_layout

    return cpu_layout(args.jobs, max(experiments, 1), available_cpus())[0]


def _preflight_sweep(args, todo, workers: int) -> None:
    """The noise and memory checks of :mod:`pipps.experiments.preflight`, once per cell."""
    from pipps.experiments.preflight import check_experiment

    cells: dict = {}
    for cfg, *_ in todo:
        cells[dataclasses.replace(cfg, seed=0)] = cells.get(dataclasses.replace(cfg, seed=0), 0) + 1
    for cfg, seeds in cells.items():
        check_experiment(cfg, seeds=seeds if args.batched else 1, processes=workers,
                         particles="--set num_particles", k="--k")


#: the command line as typed (set by :func:`main`), for the "resume with" line of an interrupted sweep
_ARGV: list[str] = []


def _command_line() -> str:
    import shlex

    return "pipps " + shlex.join(_ARGV)


def _result_paths(items):
    from pathlib import Path

    paths = []
    for item in items:
        p = Path(item)
        if p.is_dir():
            paths += sorted(p.glob("*.h5"))
        elif p.exists():
            paths.append(p)
        else:
            raise FileNotFoundError(f"no such result file or folder: {item}")
    return paths


def _cmd_table(args) -> int:
    from pipps.experiments.results import ResultError, read_summary
    from pipps.reporting.tables import (TABLES, cell_summaries, comparable_settings, counts, get_table, judge_counted,
                                        render_curves, result_tables)

    paths = _result_paths(args.results)
    try:
        tables = [get_table(args.table)] if args.table else list(TABLES.values())
    except ValueError as err:
        raise UsageError(str(err)) from None
    if args.by is not None and args.by not in comparable_settings():
        raise UsageError(f"--by {args.by}: not a setting of an experiment; choose one of {', '.join(comparable_settings())}")
    for task in args.tasks:
        _task_name(task)
    summaries, skipped = [], []
    for p in paths:
        try:
            summaries.append(read_summary(p))
        except ResultError as err:
            skipped.append(str(err))
    if not args.table:  # a task no thesis table has gets its own
        tables += result_tables(summaries)
    args.preset, note = _resolve_preset(args.preset, summaries, args.results)
    tables = [_labelled(t, args.preset) for t in tables]
    # with --by, a result that departs from the preset only in that setting counts: the groups keep it apart
    counted_here = [s for s in summaries if not counts(s["config"], args.preset, args.custom, vary=args.by)]
    counted, unjudged = judge_counted(counted_here, args.preset, custom=True)
    skipped += unjudged.values()  # legacy files whose evaluation does not re-simulate
    summaries = [s for s in summaries if s["path"] not in unjudged]
    resimulated = [s for s in counted if s.get("resimulated")]
    printed = (_print_tables if args.by is None else _print_comparison)(args, tables, counted)
    if args.curves and summaries:
        shown = counted
        if args.table:  # the results of the table asked for, not every result found
            inside = {r["path"] for t in tables for c in t.cells
                      for r in cell_summaries(t, c, counted, args.preset, True)}
            shown = [s for s in counted if s["path"] in inside]
        if shown:
            print("Evaluated return per trial (trial 0 is the random trial):\n")
            print(render_curves(shown))
            print()
    if note:
        print(note, file=sys.stderr)
    print(f"{len(counted)} complete results of the {args.preset} preset"
          + ("" if args.preset == "thesis" else " (not the thesis protocol)") + " counted; "
          f"{len(summaries) - len(counted)} complete results of other settings and {len(skipped)} incomplete or "
          "corrupt files not counted")
    for s in summaries:
        why = counts(s["config"], args.preset, args.custom, vary=args.by)
        if why:
            print(f"  not counted: {s['path']}: {why}")
    for s in skipped:
        print(f"  not counted: {s}")
    if resimulated:
        worst = max(s["resim_error"] for s in resimulated)
        print(f"{len(resimulated)} {_tasks_of(resimulated)} files predate the stored physical criterion: their final trial's "
              f"evaluation rollouts were re-simulated (stored policy and keys; largest return difference {worst:.1e})")
    if not printed:
        where = ", ".join(map(str, args.results))
        print(f"pipps table: no complete result of the {args.preset} preset in {where}"
              + (f" for table {args.table}" if args.table else "") + _other_presets(summaries, args.preset),
              file=sys.stderr)
        return 1
    return 0


def _tasks_of(summaries) -> str:
    """The tasks of result summaries in words (their records' labels), for a line about them."""
    return " and ".join(dict.fromkeys(s["config"].task_spec.label for s in sorted(summaries, key=lambda s: s["config"].task)))


def _resolve_preset(asked: str | None, summaries, where) -> tuple[str, str]:
    """The experiment preset pipps table / plot count: ``--preset`` if given; else thesis, unless no
    complete result is of the thesis preset and all are of one other, which is then counted (tables
    labelled by :func:`_labelled`). Returns it and a note for stderr when it was chosen so."""
    if asked is not None:
        return asked, ""
    found = sorted({s["config"].protocol for s in summaries})
    if "thesis" in found or len(found) != 1:
        return "thesis", ""
    preset = found[0]
    n = len(summaries)
    return preset, (f"note: no complete result of the thesis preset in {', '.join(map(str, where))}: counting its {n} "
                    f"result(s) of the {preset} preset instead, which is not the thesis protocol; the thesis' values "
                    f"are shown for orientation only (--preset thesis counts the thesis preset alone)")


def _other_presets(summaries, preset: str) -> str:
    others = sorted({s["config"].protocol for s in summaries} - {preset})
    return f"; the complete results there are of the {' and '.join(others)} preset(s): --preset {others[0]} counts " \
           "them" if others else ""


def _labelled(table, preset: str):
    """``table`` titled as counting ``preset``'s results when that is not the thesis protocol."""
    if preset == "thesis":
        return table
    head, sep, rest = table.title.partition(" — ")
    if not table.thesis:  # a task's own table: only the preset to say
        return dataclasses.replace(table, title=f"{head} ({preset} preset){sep}{rest}")
    return dataclasses.replace(table, title=f"{head} ({preset} preset, not the thesis protocol; thesis values for "
                                            f"orientation only){sep}{rest}")


def _print_tables(args, tables, counted) -> int:
    """pipps table: each table with results (render_table), with its per-seed rows and cell curves
    where asked. Returns the number of tables printed."""
    from pipps.reporting.tables import collect, render_cell_curves, render_seeds, render_table

    printed = 0
    for t in tables:
        cells = collect(t, counted, preset=args.preset, custom=args.custom)
        if any(c.n for c in cells) or args.table:
            print(render_table(t, cells, compare=args.compare))
            print()
            printed += 1
            if args.per_seed and any(c.n for c in cells):
                print(render_seeds(t, counted, preset=args.preset, custom=args.custom))
                print()
            if args.curves and any(c.n for c in cells):
                print(render_cell_curves(t, counted, preset=args.preset, custom=args.custom))
                print()
    return printed


def _print_comparison(args, tables, counted) -> int:
    """pipps table --by: each table's cells per value of the setting (render_comparison), every
    reading per value (render_group_readings) and, with two values, their difference under every
    reading (render_group_differences) and paired by seed (render_paired); then the per-seed rows
    and curves of each value's results. Returns the number of tables printed."""
    from pipps.reporting.tables import (collect, render_cell_curves, render_comparison, render_group_differences,
                                        render_group_readings, render_paired, render_seeds, split_by)

    groups = split_by(counted, args.by)
    printed = 0
    for t in tables:
        cells = [(value, collect(t, rows, preset=args.preset, custom=True)) for value, rows in groups]
        if not (any(c.n for _, cs in cells for c in cs) or args.table):
            continue
        print(render_comparison(t, args.by, cells))
        print()
        for render in (render_group_readings, render_group_differences, render_paired):
            text = render(t, args.by, cells)
            if text:
                print(text)
                print()
        printed += 1
        for value, rows in groups:
            for wanted, render in ((args.per_seed, render_seeds), (args.curves, render_cell_curves)):
                text = render(t, rows, preset=args.preset, custom=True) if wanted else ""
                if text:
                    print(f"{args.by} = {value}:\n\n{text}\n")
    return printed


def _study_kind(path) -> str | None:
    """The study a file holds (landscape, variance, bench), or None for anything else."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            kind = f.attrs.get("study")
    except OSError:
        return None
    return str(kind) if kind is not None else None


def _cmd_resimulate(args) -> int:
    from pipps.experiments.resimulate import Resimulator
    from pipps.experiments.results import ResultError, read_result
    from pipps.reporting.resimulation import check_final, render

    if args.fresh < 2:
        raise UsageError(f"--fresh {args.fresh}: a fresh verdict needs at least 2 rollouts")
    simulator, checks, skipped = Resimulator(), [], []
    for path in _result_paths(args.results):
        try:
            result = read_result(path)
        except ResultError as err:
            skipped.append(str(err))
            continue
        if result.trials[-1].kind != "learned":
            skipped.append(f"{path}: its last trial is a random one; nothing learned to re-simulate")
            continue
        checks.append(check_final(result, simulator, fresh=args.fresh, seed=args.seed, path=str(path)))
    for text in skipped:
        print(f"skipped: {text}", file=sys.stderr)
    if not checks:
        raise UsageError("no complete result to re-simulate in " + ", ".join(args.results))
    try:
        text = render(checks, args.fresh)
    except ValueError as err:  # one experiment given twice
        raise UsageError(str(err)) from None
    print(text)
    # a file whose own keys do not give its stored returns or flags stores a verdict its policy does not earn
    return 0 if all(c.reproduced for c in checks) else 1


def _cmd_plot(args) -> int:
    from pipps.reporting.plot import check_viewer, render_png
    from pipps.experiments.storage import check_new_file, publish

    if args.png:
        check_viewer()  # before anything is read or drawn: what is missing is named with its install line
    if args.size and not args.png:
        raise UsageError("--size sizes the --png rendering; give --png too")
    try:
        paths = _result_paths(args.results)
    except FileNotFoundError as err:
        print(f"pipps plot: error: {err}", file=sys.stderr)
        return 2
    check_new_file(args.out, overwrite=args.overwrite, option="--out", inputs=tuple(paths), command="pipps plot")
    if args.png:
        if args.png == args.out:
            raise UsageError("--png and --out name one file")
        check_new_file(args.png, overwrite=args.overwrite, option="--png", inputs=tuple(paths), command="pipps plot")
    if args.svg:
        check_new_file(args.svg, overwrite=args.overwrite, option="--svg", inputs=tuple(paths), command="pipps plot")
    for task in args.tasks:
        _task_name(task)
    studies = [k for k in map(_study_kind, paths) if k is not None]
    if studies:
        if len(paths) != 1:
            raise UsageError(f"a study file is drawn alone; got {len(paths)} files")
        figure = args.figure or studies[0]
        if figure != studies[0]:
            raise UsageError(f"{paths[0]} holds a {studies[0]} study; its figure is --figure {studies[0]}")
    else:
        figure = args.figure or "overview"
        if figure in _STUDY_FIGURES:
            raise UsageError(f"--figure {figure} draws a study file (pipps study {figure} / pipps bench output)")
    if args.table is not None and figure not in ("cells", "curves"):
        raise UsageError("--table selects the cells of --figure cells or curves")
    if args.by is not None:
        from pipps.reporting.tables import comparable_settings

        if figure not in ("cells", "curves"):
            raise UsageError("--by draws the cells of --figure cells or curves apart by a setting")
        if args.by not in comparable_settings():
            raise UsageError(f"--by {args.by}: not a setting of an experiment; choose one of "
                             f"{', '.join(comparable_settings())}")
    if args.svg and figure == "overview":
        raise UsageError("--svg writes a figure for a paper (--figure cells, curves, diagnostics or a study's figure); "
                         "the overview is an interactive recording (--png renders it)")
    draw = _study_figure if studies else (_result_figure if figure in ("overview", "diagnostics") else _table_figure)
    with contextlib.ExitStack() as stack:
        tmp = stack.enter_context(publish(args.out, overwrite=args.overwrite, command="pipps plot"))
        svg = stack.enter_context(publish(args.svg, overwrite=args.overwrite, command="pipps plot")) if args.svg else None
        size, what = draw(figure, paths, args, [tmp] + ([svg] if svg else []))
        if args.png:
            with publish(args.png, overwrite=args.overwrite, command="pipps plot") as png:
                render_png(tmp, png, args.size or size)
    print(f"wrote {args.out} ({what})")
    for extra in (args.png, args.svg):
        if extra:
            print(f"wrote {extra}")
    return 0


def _study_figure(figure, paths, args, outs):
    from pipps import charts as ch
    from pipps.studies import figures as f

    if figure == "bench":
        from pipps.studies.bench import read_bench

        result = read_bench(paths[0])
        fig, _ = f.bench_figure(result)
        for out in outs:
            f.record_bench(result, out)
    else:
        from pipps.studies.gradients import read_study

        result = read_study(paths[0])
        fig, _ = (f.landscape_figure if figure == "landscape" else f.variance_figure)(result)
        for out in outs:
            (f.record_landscape if figure == "landscape" else f.record_variance)(result, out)
    return ch.size(fig), f"the {figure} figure of {paths[0]}"


def _read_each(paths, reader) -> list:
    """``reader(p)`` for every path, naming on stderr the files it cannot read (``ResultError``)."""
    from pipps.experiments.results import ResultError

    read = []
    for p in paths:
        try:
            read.append(reader(p))
        except ResultError as err:
            print(f"  skipped: {err}", file=sys.stderr)
    return read


def _result_figure(figure, paths, args, outs):
    from pipps import charts as ch
    from pipps.reporting.figures import diagnostics_figure, record_diagnostics
    from pipps.reporting.plot import group_name, record
    from pipps.experiments.results import read_result

    results = _read_each(paths, read_result)
    if not results:
        raise UsageError("no complete results to plot")
    if figure == "overview":
        record(results, outs[0])
        return "1600x1000", f"{len(results)} experiments"
    groups = {}
    for r in sorted(results, key=lambda r: (group_name(r), r.config.seed)):
        groups.setdefault(group_name(r), r)  # the lowest seed of each group
    for out in outs:
        record_diagnostics(list(groups.items()), out)
    return ch.size(diagnostics_figure(list(groups.items()))), f"the final trials of {len(groups)} experiment groups"


def _table_figure(figure, paths, args, outs):
    from pipps import charts as ch
    from pipps.experiments.results import read_summary
    from pipps.reporting import figures as f
    from pipps.reporting.tables import (TABLES, cell_summaries, collect, counts, get_table, group_table, grouped,
                                        judge_counted, result_tables, split_by)

    summaries = _read_each(paths, read_summary)
    try:
        tables = [get_table(args.table)] if args.table else list(TABLES.values()) + result_tables(summaries)
    except ValueError as err:
        raise UsageError(str(err)) from None
    args.preset, note = _resolve_preset(args.preset, summaries, args.results)
    if note:
        print(note, file=sys.stderr)
    tables = [_labelled(t, args.preset) for t in tables]
    custom = args.custom
    if args.by is not None:  # as pipps table --by: what departs from the preset only in that setting counts
        summaries = [s for s in summaries if not counts(s["config"], args.preset, args.custom, vary=args.by)]
        custom = True
    if figure == "curves":
        if args.by is None:
            filled = [(t, [(c, cell_summaries(t, c, summaries, args.preset, custom)) for c in t.cells]) for t in tables]
        else:
            groups = split_by(summaries, args.by)
            filled = []
            for t in tables:  # each value's cells, filled from that value's results alone
                filled.append((grouped(t, args.by, [value for value, _ in groups]),
                               [(c, cell_summaries(t, c, rs, args.preset, custom))
                                for value, rs in groups for c in grouped(t, args.by, [value]).cells]))
        filled = [(t, cells) for t, cells in filled if any(rs for _, rs in cells)]
        if len(filled) > 1:
            raise UsageError(f"the results fill cells of tables {', '.join(t.name for t, _ in filled)}: pick one with --table")
        if not filled:
            raise UsageError(f"no result of the {args.preset} preset counts in "
                             + (f"table {args.table}" if args.table else "any table") + _other_presets(summaries, args.preset))
        table, cells = filled[0]
        for out in outs:
            f.record_curves(table, cells, out)
        n = sum(len(rs) for _, rs in cells)
        return ch.size(f.curves_figure(table, cells)), f"learning curves of {n} experiments in table {table.name}"
    judged, errors = judge_counted(summaries, args.preset, custom)
    for err in errors.values():
        print(f"  not counted: {err}", file=sys.stderr)
    if args.by is None:
        filled = [(t, collect(t, judged, args.preset, custom)) for t in tables]
    else:
        filled = [(group_table(t, args.by, value), collect(t, rs, args.preset, custom))
                  for t in tables for value, rs in split_by(judged, args.by)]
    filled = [(t, cells) for t, cells in filled if any(c.n for c in cells)]
    if not filled:
        raise UsageError(f"no result of the {args.preset} preset counts in "
                         + (f"table {args.table}" if args.table else "any table") + _other_presets(summaries, args.preset))
    for out in outs:
        f.record_cells(filled, out)
    n = sum(c.n for _, cells in filled for c in cells)
    return ch.size(f.cells_figure(filled)), f"success rates in table(s) {', '.join(t.name for t, _ in filled)} " \
        f"({n} results counted over their cells)"


def _default_trial(path) -> int:
    from pipps.experiments.results import read_result
    from pipps.experiments.state import rebuildable_trials

    ok = rebuildable_trials(read_result(path))
    if not ok:
        raise ValueError(f"{path} has no learned trial whose model can be rebuilt")
    return ok[-1]


def _study_outputs(args, default: str, command: str):
    """The study's --out and --rrd, checked before any work (storage.check_new_file)."""
    from pathlib import Path

    from pipps.experiments.storage import check_new_file

    out = args.out or default
    rrd = args.rrd or str(Path(out).with_suffix(".rrd"))
    check_new_file(out, overwrite=args.overwrite, option="--out", suffix=".h5", inputs=(args.result,), command=command)
    check_new_file(rrd, overwrite=args.overwrite, option="--rrd", suffix=".rrd", inputs=(args.result,),
                   command=command)
    return out, rrd


def _snapshot(args, particles: int, estimators):
    """The study's snapshot, after the memory check of its largest estimate (preflight.check_study)."""
    from pipps.experiments.preflight import check_study
    from pipps.studies.snapshot import load_snapshot

    trial = args.trial if args.trial is not None else _default_trial(args.result)
    snap = load_snapshot(args.result, trial)
    size = snap.config.num_inducing if snap.sparse else snap.num_points
    check_study(snap.config, size, particles, estimators)
    return snap


def _cmd_contact(args) -> int:
    from pathlib import Path

    from pipps.experiments.storage import check_new_file, publish
    from pipps.studies import contact, contact_figures, contact_studies
    from pipps.studies.contact_catalog import estimated_minutes

    out = args.out or f"contact_{args.example}.json"
    svg = args.svg or str(Path(out).with_suffix(".svg"))
    outputs = [(out, "--out", ".json"), (svg, "--svg", ".svg")] + ([(args.rrd, "--rrd", ".rrd")] if args.rrd else [])
    for path, option, suffix in outputs:
        check_new_file(path, overwrite=args.overwrite, option=option, suffix=suffix, command="pipps study contact")
    quick, full = estimated_minutes()[args.example]
    print(f"pipps study contact {args.example}: {'full' if args.full else 'quick'} sweep, about "
          f"{full if args.full else quick:g} min on one core of the machine docs/contact.md was measured on", file=sys.stderr)
    import jax

    result = contact_studies.run_study(args.example, jax.random.PRNGKey(args.seed), full=args.full)
    result.settings["seed"] = args.seed
    with publish(out, overwrite=args.overwrite, command="pipps study contact") as tmp:
        contact.write_study(tmp, result)
    for path, _, _ in outputs[1:]:
        with publish(path, overwrite=args.overwrite, command="pipps study contact") as tmp:
            contact_figures.record(result, tmp)
    print(contact_figures.verdict_table(result))
    print(f"\nwrote {', '.join(p for p, _, _ in outputs)}")
    return 0


def _cmd_study(args) -> int:
    import numpy as np

    if args.study == "contact":
        return _cmd_contact(args)

    from pipps.cli_report import study_caveat
    from pipps.experiments.results import ResultError
    from pipps.experiments.storage import publish
    from pipps.studies import gradients as g

    landscape = args.study == "landscape"
    quick = {"estimators": ["rp", "tp"], "repeats": 3, "direction": "random"}
    quick.update({"particles": 30, "deltas": (0.0, 1.5, 3)} if landscape else {"particles": [10, 30], "deltas": [0.0, 1.5]})
    full = {"estimators": list(g.DEFAULT_ESTIMATORS) if landscape else ["rp", "lr_plain", "lr", "tp"],
            "repeats": 10 if landscape else 30}
    full.update({"particles": 1000, "deltas": (0.0, 1.5, 16)} if landscape
                else {"particles": [10, 30, 100, 300, 1000], "deltas": [0.0, 1.5]})
    value = lambda k: getattr(args, k) if getattr(args, k) is not None else (quick if args.quick else full)[k]  # noqa: E731
    direction = "random" if args.quick and args.direction == "pilco" else args.direction
    out, rrd = _study_outputs(args, f"study_{args.study}.h5", f"pipps study {args.study}")
    estimators = value("estimators") if isinstance(value("estimators"), list) else value("estimators").split(",")
    deltas = np.linspace(*value("deltas")) if landscape else np.array(value("deltas"), dtype=float)
    particles = value("particles")
    try:
        snap = _snapshot(args, max(particles) if not landscape else particles, estimators)
        common = dict(estimators=estimators, repeats=value("repeats"), direction=direction,
                      seed=args.seed, choices=args.choices, progress=lambda msg: print(f"  {msg}", file=sys.stderr))
        if landscape:
            result = g.landscape(snap, deltas=deltas, particles=particles, **common)
        else:
            result = g.variance_study(snap, deltas=deltas, particles=particles, **common)
    except (ValueError, FileNotFoundError, ResultError) as err:
        print(f"pipps study {args.study}: error: {err}", file=sys.stderr)
        return 2
    from pipps.studies import figures

    with publish(out, overwrite=args.overwrite, command="pipps study") as tmp_out, \
            publish(rrd, overwrite=args.overwrite, command="pipps study") as tmp_rrd:
        g.write_study(tmp_out, result)
        (figures.record_landscape if landscape else figures.record_variance)(result, tmp_rrd)
    print(g.landscape_table(result) if landscape else g.variance_table(result))
    caveat = study_caveat(args.study, snap.config, particles=particles, repeats=value("repeats"), direction=direction,
                          deltas=deltas, choices=args.choices)
    if caveat:
        print(f"\n{caveat}")
    print(f"\nwrote {out} and {rrd} ({result.seconds:.0f} s)")
    return 0


def _cmd_bench(args) -> int:
    from pipps.experiments.results import ResultError
    from pipps.experiments.storage import publish
    from pipps.studies import bench as b

    quick = {"estimators": "rp,tp", "particles": [20], "deltas": [0.0, 1.5], "repeats": 3, "reference_repeats": 4}
    full = {"estimators": "rp,lr,tp,gtp", "particles": [30, 100, 300, 1000], "deltas": [0.0, 1.5], "repeats": 20,
            "reference_repeats": 50}
    value = lambda k: getattr(args, k) if getattr(args, k) is not None else (quick if args.quick else full)[k]  # noqa: E731
    out, rrd = _study_outputs(args, args.out, "pipps bench")
    estimators = value("estimators").split(",")
    try:
        snap = _snapshot(args, max(value("particles")), estimators + [args.reference])
        result = b.bench(
            snap, deltas=list(value("deltas")), particles=list(value("particles")), estimators=estimators,
            repeats=value("repeats"), reference=args.reference, reference_repeats=value("reference_repeats"),
            time_repeats=2 if args.quick else 5, direction="random" if args.quick else args.direction, seed=args.seed,
            variance_tols=list(args.variance_tols), progress=lambda msg: print(f"  {msg}", file=sys.stderr))
    except (ValueError, FileNotFoundError, ResultError) as err:
        print(f"pipps bench: error: {err}", file=sys.stderr)
        return 2
    from pipps.studies.figures import record_bench

    with publish(out, overwrite=args.overwrite, command="pipps bench") as tmp_out, \
            publish(rrd, overwrite=args.overwrite, command="pipps bench") as tmp_rrd:
        b.write_bench(tmp_out, result)
        record_bench(result, tmp_rrd)
    print(b.bench_table(result))
    print(f"\nwrote {out} and {rrd} ({result.seconds:.0f} s)")
    return 0


def enable_compilation_cache() -> str | None:
    """Switch on JAX's persistent compilation cache for this process and the workers it spawns.

    The folder is ``$JAX_COMPILATION_CACHE_DIR`` if set, else ``$PIPPS_COMPILATION_CACHE``, else
    ``$XDG_CACHE_HOME/pipps/jax`` (``~/.cache/pipps/jax``); ``PIPPS_COMPILATION_CACHE=off`` leaves it
    off. A cached program is the compiled executable itself, so results are bit for bit those of a
    fresh compilation; the cache key covers the program, the jaxlib version and the device, and a
    program compiled for another CPU is recompiled. Only programs that took a second or more to
    compile are stored. Returns the folder, or None when off.
    """
    import os

    chosen = os.environ.get("PIPPS_COMPILATION_CACHE", "")
    if chosen.lower() in ("off", "0", "no", "none"):
        return None
    default = os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "pipps", "jax")
    folder = os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", chosen or default)  # spawned workers inherit it
    import jax

    jax.config.update("jax_compilation_cache_dir", folder)
    return folder


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill PID``) taken as Ctrl-C: a run writes its file as interrupted, a sweep stops its
    workers the same way, and the process exits 143 (128 + SIGTERM) instead of 130. A
    ``KeyboardInterrupt`` so that every path that keeps finished trials on Ctrl-C keeps them here too.
    It matters for runs started in the background by a script (``nohup pipps sweep … &``): such a
    process inherits SIGINT ignored, as every program started so does, and ``kill`` is how it is stopped."""


def _on_sigterm(signum, frame):
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # a second SIGTERM ends the process at once
    raise Terminated(f"stopped by signal {signum} (SIGTERM)")


@contextlib.contextmanager
def _sigterm_as_interrupt():
    """Take SIGTERM as :class:`Terminated` while the command runs, where SIGTERM has its default
    action (a handler the embedding program set, or an inherited ``ignore``, is left alone) and this is
    the main thread (the only one Python may set a handler in)."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGTERM) != signal.SIG_DFL:
        yield
        return
    signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _interrupted_status(err: BaseException) -> int:
    """The exit status of a command stopped by ``err``: 143 after SIGTERM, 130 after Ctrl-C."""
    return 128 + signal.SIGTERM if isinstance(err, Terminated) else 130


def main(argv: list[str] | None = None) -> int:
    import os

    from pipps.precision import enable_float64

    global _ARGV
    _ARGV = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    enable_float64()
    enable_compilation_cache()
    if os.getcwd() not in sys.path:  # a task of your own as MODULE:ATTRIBUTE, from here (module doc)
        sys.path.append(os.getcwd())
    name = f"pipps {args.command}" + (f" {args.study}" if args.command == "study" else "")
    try:
        with _sigterm_as_interrupt():
            return _dispatch(args)
    except KeyboardInterrupt as err:
        print(f"{name}: interrupted; result files keep every finished trial (resume with --resume or the same sweep)",
              file=sys.stderr)
        return _interrupted_status(err)
    except Exception as err:
        from pipps.experiments.config import ConfigError
        from pipps.experiments.results import ResultError
        from pipps.experiments.storage import OutputError

        if args.debug or os.environ.get("PIPPS_DEBUG"):
            raise
        expected = isinstance(err, (UsageError, ConfigError, OutputError, ResultError, FileNotFoundError))
        text = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        if expected:
            print(f"{name}: error: {text}", file=sys.stderr)
            return 2
        print(f"{name}: error: {type(err).__name__}: {text} (pipps --debug {args.command} … or PIPPS_DEBUG=1 "
              "shows the traceback)", file=sys.stderr)
        return 1


def _dispatch(args) -> int:
    if args.command == "rollout":
        from pipps.demo import random_policy_rollouts
        from pipps.experiments.preflight import check_noise
        from pipps.tasks.registry import get_task

        spec = get_task(_task_name(args.task))
        preset = args.preset or spec.presets[0]
        if preset not in spec.presets:
            raise UsageError(f"--preset {preset}: {spec.name}'s task presets are {', '.join(spec.presets)}")
        horizon = spec.make(preset).problem.horizon
        check_noise(spec.name, preset, args.k, horizon * args.episodes)  # the policy squares observations too

        rep = random_policy_rollouts(spec.name, preset, args.k, args.policy, args.episodes, args.seed)
        print(f"{rep.task} ({rep.preset} preset, k={rep.k:g}), {rep.policy}:")
        for i, (ret, n) in enumerate(zip(rep.returns, rep.lengths)):
            print(f"  episode {i}: return (total cost) {ret:.4f} over {n} steps")
        print(f"  mean return {rep.returns.mean():.4f}")
        return 0
    handlers = {"run": _cmd_run, "sweep": _cmd_sweep, "table": _cmd_table, "resimulate": _cmd_resimulate,
                "plot": _cmd_plot, "study": _cmd_study,
                "bench": _cmd_bench}
    return handlers[args.command](args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
