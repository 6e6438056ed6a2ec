"""Figures and tables of the contact studies (:mod:`pipps.studies.contact_studies`), drawn with
:mod:`pipps.charts` as SVG or rerun recordings.

Colours and labels are the estimator registry's: FoBG is ``rp``'s, ZoBG ``zobg``'s, TP ``tp``'s and
AoBG ``aobg``'s (:data:`pipps.propagation.estimators.ESTIMATORS`), so one colour means one estimator
in every figure of the project. The exact gradient is black, a reference estimated by sampling grey.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipps import charts as ch
from pipps.propagation.estimators import ESTIMATORS
from pipps.studies.contact import SUH_NAMES, StudyResult

PANEL = (480.0, 360.0)
NAMES = ("FoBG", "ZoBG", "TP", "AoBG")


def colour(name: str):
    return ESTIMATORS[SUH_NAMES[name]].colour


def label(name: str) -> str:
    return {"FoBG": "FoBG (RP)", "ZoBG": "ZoBG (plain LR, whole return)", "TP": "TP (inverse-variance k_LR)",
            "AoBG": "AoBG (robust, bound γ)"}[name]


def _keys(extra=()):
    return [*(ch.Key(label(n), colour(n)) for n in NAMES), *extra]


def _estimates(rec, c, x, rows, names=NAMES, dodge=0.0):
    """Each estimator's mean through the points at their true x; its ±2 SE bars dodged sideways by
    ``dodge`` per estimator so that bars at one x do not hide each other."""
    for i, n in enumerate(names):
        m = np.array([r[n]["mean"][0] for r in rows])
        se = np.array([r[n]["se"][0] for r in rows])
        ch.line(rec, c, f"{n}/mean", x, m, colour(n))
        ch.points(rec, c, f"{n}/points", x, m, colour(n), size=2.0)
        xs = np.asarray(x) + (i - 1.5) * dodge
        ch.intervals(rec, c, f"{n}/se", xs, m - 2 * se, m + 2 * se, colour(n), cap=1.5)


def _log_values(rows, key, names=NAMES):
    return [[r[n][key] for r in rows] for n in names]


def heaviside_figure(r: StudyResult) -> tuple:
    rows = r.tables["grid"]
    th = np.array([x["theta"] for x in rows])
    est = [[x[n]["mean"][0] for x in rows] for n in NAMES] + [[x["dF"] for x in rows]]
    charts = [
        ch.chart("contact/f", "(a) f = H(θ) and F(θ) = E H(θ + w)", ch.Axis("θ", th.min(), th.max()),
                 ch.Axis("value", -0.05, 1.05), PANEL),
        ch.chart("contact/grad", f"(b) the estimates, ±2 SE ({r.settings['replicates']} batches of "
                                 f"{r.settings['samples']})", ch.Axis("θ", th.min(), th.max()),
                 ch.Axis("∂F/∂θ", *ch.data_range(est)), PANEL),
        ch.chart("contact/var", "(c) empirical variance within a batch", ch.Axis("θ", th.min(), th.max()),
                 ch.Axis("variance (0 is not drawn)", *ch.data_range(_log_values(rows, "empirical_variance"), log=True), log=True),
                 PANEL),
    ]
    fig = ch.figure(charts, 3, _keys([ch.Key("exact", ch.BLACK)]))

    def draw(rec):
        a, b, c = fig.charts
        fine = np.linspace(th.min(), th.max(), 400)
        ch.line(rec, a, "H", fine, (fine >= 0).astype(float), ch.GREY)
        from scipy import stats

        ch.line(rec, a, "F", fine, stats.norm.cdf(fine / r.settings["sigma"]), ch.BLACK, width=1.6)
        ch.line(rec, b, "exact", th, [x["dF"] for x in rows], ch.BLACK, width=1.6)
        _estimates(rec, b, th, rows, dodge=0.004 * (th.max() - th.min()))
        ch.note(rec, b, "fobg_zero", "FoBG and TP coincide at 0", row=1)
        for n in NAMES:
            ch.line(rec, c, n, th, [x[n]["empirical_variance"] for x in rows], colour(n))
        ch.note(rec, c, "fobg_zero", "FoBG and TP: empirical variance exactly 0", row=1)

    return fig, draw


def relaxed_figure(r: StudyResult) -> tuple:
    rows = r.tables["grid"]
    nus = sorted({x["nu"] for x in rows}, reverse=True)
    Ns = sorted({x["samples"] for x in rows})
    by = {(x["nu"], x["samples"]): x for x in rows}
    nax = ch.Axis("number of samples N", min(Ns) / 1.5, max(Ns) * 1.5, log=True)
    ratio = [[by[(nu, N)]["FoBG"]["mean"][0] / by[(nu, N)]["dF"] for N in Ns] for nu in nus]
    big = [by[(nu, max(Ns))] for nu in nus]
    vax = ch.Axis("slip tolerance ν", min(nus) / 1.5, max(nus) * 1.5, log=True)
    charts = [
        ch.chart("contact/mean", "(a) FoBG's mean over batches / ∇F_ν", nax, ch.Axis("ratio", *ch.data_range(ratio, include=(0, 1))), PANEL),
        ch.chart("contact/zero", "(b) batches whose FoBG is exactly 0", nax, ch.Axis("fraction", -0.03, 1.03), PANEL),
        ch.chart("contact/var", f"(c) per-sample variance at N = {max(Ns)}", vax,
                 ch.Axis("variance", *ch.data_range([[b["FoBG"]["expected_variance"] for b in big],
                                                     [b["ZoBG"]["expected_variance"] for b in big],
                                                     [b["empirical_variance_median"] for b in big if b["empirical_variance_median"] > 0]],
                                                    log=True), log=True), PANEL),
    ]
    shades = {nu: ch.lighter(colour("FoBG"), 0.7 * i / max(len(nus) - 1, 1)) for i, nu in enumerate(nus)}
    keys = [ch.Key(f"FoBG, ν = {nu:g}", shades[nu]) for nu in nus]
    keys += [ch.Key("(1 − p)^N, the exact zero probability", ch.BLACK, "dash"),
             ch.Key("FoBG expected", colour("FoBG")), ch.Key("FoBG empirical (median)", colour("FoBG"), "dash"),
             ch.Key("ZoBG expected", colour("ZoBG")), ch.Key("(4/ν²) p (1 − p), exact", ch.BLACK, "dash")]
    fig = ch.figure(charts, 3, keys)

    def draw(rec):
        a, b, c = fig.charts
        for nu, rat in zip(nus, ratio):
            ch.line(rec, a, f"nu{nu:g}", Ns, rat, shades[nu])
            ch.line(rec, b, f"nu{nu:g}", Ns, [by[(nu, N)]["FoBG"]["zero_fraction"] for N in Ns], shades[nu])
            ch.line(rec, b, f"nu{nu:g}_theory", Ns, [by[(nu, N)]["zero_theory"] for N in Ns], ch.BLACK, dash=True, width=0.8)
        ch.line(rec, a, "one", [min(Ns), max(Ns)], [1.0, 1.0], ch.GREY, dash=True)
        ch.line(rec, c, "fobg", nus, [b["FoBG"]["expected_variance"] for b in big], colour("FoBG"))
        ch.line(rec, c, "fobg_emp", nus, [b["empirical_variance_median"] for b in big], colour("FoBG"), dash=True)
        ch.line(rec, c, "zobg", nus, [b["ZoBG"]["expected_variance"] for b in big], colour("ZoBG"))
        ch.line(rec, c, "theory", [e["nu"] for e in r.tables["empirical_bias"]],
                [e["fobg_variance"] for e in r.tables["empirical_bias"]], ch.BLACK, dash=True)

    return fig, draw


def fig1_figure(r: StudyResult) -> tuple:
    names = [n for n in ("drop", "throw", "pivot") if n in r.tables]
    charts = []
    for n in names:
        g = r.tables[n]["grid"]
        th = [x["theta"] for x in g]
        tx = ch.Axis("θ", min(th), max(th))
        charts.append(ch.chart(f"contact/{n}_f", f"{n}: f(θ) and F(θ)", tx, ch.Axis("cost", *ch.data_range([[x["f"] for x in g], [x["F"] for x in g]])), PANEL))
        charts.append(ch.chart(f"contact/{n}_g", f"{n}: estimates ±2 SE, exact ∇F", tx,
                               ch.Axis("∂F/∂θ", *ch.data_range([[x[e]["mean"][0] for x in g] for e in NAMES] + [[x["dF"] for x in g]])), PANEL))
        d = r.tables[n]["descent"]
        vals = [np.asarray(c)[:, 1] for runs in d.values() for c in runs]
        its = np.asarray(next(iter(d.values()))[0])[:, 0]
        charts.append(ch.chart(f"contact/{n}_d", f"{n}: exact F along a descent", ch.Axis("iteration", 0, max(its.max(), 1)),
                               ch.Axis("F", *ch.data_range(vals)), PANEL))
    fig = ch.figure(charts, 3, _keys([ch.Key("f (no smoothing)", ch.GREY), ch.Key("F, exact", ch.BLACK)]))

    def draw(rec):
        for k, n in enumerate(names):
            a, b, c = fig.charts[3 * k: 3 * k + 3]
            g = r.tables[n]["grid"]
            th = np.array([x["theta"] for x in g])
            ch.line(rec, a, "f", th, [x["f"] for x in g], ch.GREY)
            ch.line(rec, a, "F", th, [x["F"] for x in g], ch.BLACK, width=1.6)
            ch.line(rec, b, "exact", th, [x["dF"] for x in g], ch.BLACK, width=1.6)
            _estimates(rec, b, th, g, dodge=0.004 * (th.max() - th.min()))
            for e, runs in r.tables[n]["descent"].items():
                for i, run in enumerate(runs):
                    run = np.asarray(run)
                    ch.line(rec, c, f"{e}_{i}", run[:, 0], run[:, 1], colour(e), width=0.9)

    return fig, draw


def ball_figure(r: StudyResult) -> tuple:
    scenes = [k for k in r.tables if k.startswith(("wall", "dome"))]
    charts = []
    for s in scenes:
        g = r.tables[s]
        th = np.degrees([x["theta"] for x in g])
        vals = [[x[e]["mean"][0] for x in g] for e in NAMES] + [[x["reference"][0] for x in g]]
        charts.append(ch.chart(f"contact/{s}", s.replace("_", ", ").replace("timeconst", "time constant "),
                               ch.Axis("launch angle θ (degrees)", th.min() - 0.5, th.max() + 0.5),
                               ch.Axis("∂F/∂θ (F = −final x)", *ch.data_range(vals)), PANEL))
    fig = ch.figure(charts, min(3, len(charts)), _keys([ch.Key("ZoBG reference (many samples), ±2 SE", ch.GREY, "interval")]))

    def draw(rec):
        for c, s in zip(fig.charts, scenes):
            g = r.tables[s]
            th = np.degrees([x["theta"] for x in g])
            ref, se = np.array([x["reference"][0] for x in g]), np.array([x["reference_se"][0] for x in g])
            ch.line(rec, c, "reference", th, ref, ch.GREY, width=1.6)
            ch.intervals(rec, c, "reference_se", th, ref - 2 * se, ref + 2 * se, ch.GREY)
            _estimates(rec, c, th, g, dodge=0.05)

    return fig, draw


def pushing_figure(r: StudyResult) -> tuple:
    rows = r.tables["grid"]
    pen = [x for x in rows if x["model"] == "penalty"]
    bar = [x for x in rows if x["model"] == "barrier"]
    imp = [x for x in rows if x["model"] == "implicit"]
    ks = [x["stiffness"] for x in pen]
    f6 = r.tables["fig6"]
    charts = [
        ch.chart("contact/k", "(a) Fig. 5: per-sample variance against k (penalty)", ch.Axis("stiffness k", min(ks) / 1.5, max(ks) * 1.5, log=True),
                 ch.Axis("tr Var (per sample)", *ch.data_range([[x[n]["expected_variance"] for x in pen] for n in ("FoBG", "ZoBG")], log=True), log=True), PANEL),
        ch.chart("contact/kappa", "(b) log-barrier (IV.2) against κ; implicit (IV.1) dashed",
                 ch.Axis("barrier weight κ", min(x["kappa"] for x in bar) / 1.5, max(x["kappa"] for x in bar) * 1.5, log=True),
                 ch.Axis("tr Var (per sample)", *ch.data_range([[x[n]["expected_variance"] for x in bar + imp] for n in ("FoBG", "ZoBG")], log=True), log=True), PANEL),
        ch.chart("contact/fig6", "(c) Fig. 6: x⁺ against the impulse u at (x, v) = 0", ch.Axis("impulse u", min(f6["u"]), max(f6["u"])),
                 ch.Axis("x⁺", *ch.data_range([v for k, v in f6.items() if k.startswith(("implicit", "penalty", "barrier"))])), PANEL),
    ]
    kap = [k for k in f6 if k.startswith("barrier")]
    navy = (20, 40, 90)  # not an estimator's colour: these are contact models, not estimates
    shades = {k: ch.lighter(navy, 0.65 * i / max(len(kap) - 1, 1)) for i, k in enumerate(kap)}
    keys = [ch.Key(label("FoBG"), colour("FoBG")), ch.Key(label("ZoBG"), colour("ZoBG")),
            ch.Key("the step's stability bound (4 − 2hc/m_r) m_r/h²", ch.GREY, "dash"), ch.Key("implicit (QP) step", ch.BLACK, "dash"),
            ch.Key("penalty step (k = 100)", ch.GREY)] + [ch.Key(k.replace("barrier_kappa", "barrier κ = "), shades[k]) for k in kap]
    fig = ch.figure(charts, 3, keys)

    def draw(rec):
        a, b, c = fig.charts
        for n in ("FoBG", "ZoBG"):
            ch.line(rec, a, n, ks, [x[n]["expected_variance"] for x in pen], colour(n))
            ch.points(rec, a, f"{n}_pts", ks, [x[n]["expected_variance"] for x in pen], colour(n), size=2.5)
            ch.line(rec, b, n, [x["kappa"] for x in bar], [x[n]["expected_variance"] for x in bar], colour(n))
            if imp:
                v = imp[0][n]["expected_variance"]
                ch.line(rec, b, f"{n}_implicit", [b.x.lo, b.x.hi], [v, v], colour(n), dash=True)
        from pipps.systems.contact.pushing import Pushing

        bound = Pushing().stable_stiffness
        ch.line(rec, a, "bound", [bound, bound], [a.y.lo, a.y.hi], ch.GREY, dash=True)
        ch.line(rec, c, "penalty", f6["u"], f6["penalty"], ch.GREY)
        for k in kap:
            ch.line(rec, c, k, f6["u"], f6[k], shades[k])
        ch.line(rec, c, "implicit", f6["u"], f6["implicit"], ch.BLACK, width=1.0, dash=True, order=12.0)

    return fig, draw


def scaling_figure(r: StudyResult) -> tuple:
    traj = r.tables["trajectory"]
    ks = sorted({x["stiffness"] for x in traj})
    final = {(x["stiffness"], x["estimator"]): x["final"] for x in traj}
    pol = r.tables["policy"]
    curves = [np.asarray(c)[:, 1] for x in pol for c in x["curves"]]
    its = np.asarray(pol[0]["curves"][0])[:, 0]
    charts = [
        ch.chart("contact/traj", "(a) trajectory optimisation: final cost against stiffness", ch.Axis("stiffness k", min(ks) / 1.5, max(ks) * 1.5, log=True),
                 ch.Axis("final cost", *ch.data_range([list(final.values())])), PANEL),
        ch.chart("contact/policy", "(b) policy optimisation: cost along the descent", ch.Axis("iteration", 0, max(its.max(), 1)),
                 ch.Axis("cost", *ch.data_range(curves)), PANEL),
    ]
    fig = ch.figure(charts, 2, _keys())

    def draw(rec):
        a, b = fig.charts
        for n in NAMES:
            ch.line(rec, a, n, ks, [final[(k, n)] for k in ks], colour(n))
            ch.points(rec, a, f"{n}_pts", ks, [final[(k, n)] for k in ks], colour(n), size=2.5)
            for i, c in enumerate(next(x for x in pol if x["estimator"] == n)["curves"]):
                c = np.asarray(c)
                ch.line(rec, b, f"{n}_{i}", c[:, 0], c[:, 1], colour(n), width=0.9)

    return fig, draw


FIGURES = {"heaviside": heaviside_figure, "relaxed": relaxed_figure, "fig1": fig1_figure, "ball": ball_figure,
           "pushing": pushing_figure, "scaling": scaling_figure}


def record(r: StudyResult, out: str | Path) -> Path:
    """The study's figure, as SVG (``.svg``) or a rerun recording (``.rrd``)."""
    fig, draw = FIGURES[r.study](r)
    with ch.recording(out, f"pipps-contact-{r.study}", fig) as rec:
        ch.draw(rec, fig)
        draw(rec)
    return Path(out)


def verdict_table(r: StudyResult) -> str:
    """The study's verdicts and its TP-against-AoBG rows, as Markdown."""
    lines = ["| claim | verdict | numbers | test |", "|---|---|---|---|"]
    lines += [f"| {v['claim']} | **{v['verdict']}** | {v['numbers']} | {v['test']} |" for v in r.tables["verdicts"]]
    if r.tables.get("tension"):
        lines += ["", "| system | estimator | ‖bias‖ | max \\|z\\| | variance (per sample) | MSE | weight on LR |",
                  "|---|---|---|---|---|---|---|"]
        for t in r.tables["tension"]:
            def f(v):
                return "—" if v is None else f"{v:.3g}"
            lines.append(f"| {t['system']} | {t['estimator']} | {f(t['bias_norm'])} | {f(t['max_z'])} | {f(t['variance'])} | "
                         f"{f(t['mse'])} | {f(t['weight_on_lr'])} |")
    return "\n".join(lines)
