"""The contact studies, one function per figure of Suh et al. (docs/contact.md), each with a quick and
a full setting (:data:`SETTINGS`), returning a :class:`~pipps.studies.contact.StudyResult` whose
``verdicts`` table says, for each of the source's claims, *supported*, *contradicted* or *cannot
tell*, with the numbers and the test that decide it.

=============  ====================================================================================
``heaviside``  002 Example III.2, Fig. 2: FoBG ≡ 0 with zero empirical variance; ZoBG unbiased; TP's
               inverse-variance weight, and AoBG's, at every θ
``relaxed``    002 Example III.5, Fig. 3: the empirical bias (c_σν, c_σ, 0), FoBG variance ∝ 1/ν, its
               empirical variance → 0, the estimates against the number of samples and ν
``fig1``       002 Fig. 1: the drop, the throw and the pivot — their objectives, smoothed objectives,
               the estimators along θ, and a descent with each estimator
``ball``       002 Example III.6, Fig. 4 (MJX): the ball against the rectangular wall and the dome, and
               the dome's contact stiffness swept
``pushing``    002 Example III.7, Fig. 5: FoBG and ZoBG variance against the penalty stiffness k until
               the integrator goes unstable; the implicit and barrier models (IV.1, IV.2), and Fig. 6
``scaling``    000 "Scaling results": a trajectory optimisation through contact as the stiffness
               grows, and a policy optimisation through contact (FoBG, ZoBG, AoBG, TP)
=============  ====================================================================================

Every study also fills the ``tension`` table: at its base setting, each estimator's bias, variance
and MSE, TP's weight on the LR part ``k_LR`` beside AoBG's ``1 − α``.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from pipps.stats import z_bound
from pipps.studies.contact import (
    StudyResult,
    batch_objective,
    descend,
    estimators,
    reference_gradient,
    replicate_estimates,
    summarise,
)
from pipps.systems.contact import base, fig1, heaviside, pushing

from pipps.studies.contact_catalog import ALPHA, SETTINGS, STUDIES, estimated_minutes, settings_of  # noqa: F401


def _verdict(claim: str, holds: bool | None, numbers: str, test: str) -> dict:
    word = "cannot tell" if holds is None else ("supported" if holds else "contradicted")
    return dict(claim=claim, verdict=word, numbers=numbers, test=test)


def _tension_rows(system: str, summaries: dict, gamma: float) -> list[dict]:
    rows = []
    for name in sorted(summaries, key=("FoBG", "ZoBG", "TP", "AoBG").index):
        s = summaries[name]
        rows.append(dict(system=system, estimator=name, bias_norm=s.get("bias_norm"), max_z=s.get("max_z"),
                         variance=s["expected_variance"], empirical_variance=s["empirical_variance"], mse=s.get("mse"),
                         weight_on_lr=s["k_lr"] if name in ("TP", "AoBG") else None, gamma=gamma if name == "AoBG" else None))
    return rows


def _variance_between(system: str, summ: dict) -> dict:
    """000's "the variance of AoBG is between FoBG and ZoBG", read on one system's summaries."""
    v = {n: summ[n]["expected_variance"] for n in ("FoBG", "ZoBG", "AoBG")}
    lo, hi = sorted((v["FoBG"], v["ZoBG"]))
    return _verdict(f"{system}: AoBG's variance lies between FoBG's and ZoBG's (000, robust-interpolation results)",
                    lo <= v["AoBG"] <= hi, ", ".join(f"{n} {x:.3g}" for n, x in v.items()),
                    "expected per-sample variance (trace) of each estimator over the batches")


def _lemma_coverage(reps: dict, exact: np.ndarray, gamma: float, z: float, N: int) -> dict:
    """Lemma 4.3's event on the batches where its premise can hold: ε = z·sqrt(tr Σ̂_LR/N) ≤ γ (the
    ZoBG's own confidence radius within the bound; elsewhere AoBG is ZoBG and promises nothing). Returns
    the number of such batches and the fraction of them with ‖ĝ_AoBG − ∇F‖ ≤ γ."""
    eps = z * np.sqrt(np.sum(reps["ZoBG"].empirical, axis=1) / N)
    feasible = eps <= gamma
    err = np.linalg.norm(reps["AoBG"].grad - exact[None, :], axis=1)
    n = int(np.sum(feasible))
    return dict(feasible=n, coverage=float(np.mean(err[feasible] <= gamma)) if n else float("nan"))


# -- 002 Example III.2, Fig. 2 ---------------------------------------------------------------------------


def heaviside_study(key, *, thetas, samples, replicates, sigma=1.0, gamma=0.2, z=2.0) -> StudyResult:
    grid = np.linspace(-3.0, 3.0, thetas)
    ests = estimators(gamma, z)
    ex = heaviside.heaviside(0.0, sigma)
    rows, tension, zs, coverage = [], [], [], []
    for i, th in enumerate(grid):
        F, dF = heaviside.heaviside_exact(float(th), sigma)
        reps = replicate_estimates(ex, ests, samples, replicates, jax.random.fold_in(key, i), policy=base.as_policy(th))
        summ = {n: summarise(s, np.array([dF]), samples) for n, s in reps.items()}
        rows.append(dict(theta=float(th), F=F, dF=dF, **{n: summ[n] for n in summ}))
        zs.append(summ["ZoBG"]["max_z"])
        coverage.append(_lemma_coverage(reps, np.array([dF]), gamma, z, samples))
        if abs(th - 0.5) == np.min(np.abs(grid - 0.5)):
            tension = _tension_rows("heaviside", summ, gamma)
    fobg_zero = all(r["FoBG"]["zero_fraction"] == 1.0 and r["FoBG"]["empirical_variance"] == 0.0 for r in rows)
    bound = z_bound(len(grid), ALPHA)
    tp_is_fobg = all(r["TP"]["zero_fraction"] == 1.0 for r in rows)
    delta = 1.0 - 1.0 / z**2  # Chebyshev's bound on the LR mean's confidence radius ε = z·sqrt(tr Σ̂/N)
    near = min(rows, key=lambda r: abs(r["theta"] - 0.5))
    covered = [c for c in coverage if c["feasible"] > 0]
    worst = min(covered, key=lambda c: c["coverage"]) if covered else None
    verdicts = [
        _verdict("FoBG ≡ 0 with zero empirical variance, while ∇F ≠ 0 (002 Ex. III.2)", fobg_zero,
                 f"every FoBG estimate 0 at all {len(grid)} θ ({replicates} batches of {samples}); min ∇F = "
                 f"{min(r['dF'] for r in rows):.3g}", "exact: FoBG == 0 and its within-batch variance == 0"),
        _verdict("ZoBG is unbiased (002 §III.A)", max(zs) < bound, f"max |z| {max(zs):.2f} over the θ grid (bound {bound:.2f})",
                 f"|mean − ∇F| / SE below the Bonferroni bound at family-wise α = {ALPHA:g}"),
        _verdict("the inverse-variance weight trusts FoBG wrongly (002 §IV.C against PIPPS)", tp_is_fobg,
                 ("every TP estimate is exactly 0 = FoBG: k_LR = σ²_RP/(σ²_RP + σ²_LR) = 0 wherever ZoBG varies"
                  if tp_is_fobg else "TP is not 0 everywhere")
                 + f"; at θ = {near['theta']:.3g} TP's bias is {near['TP']['bias_norm']:.3g}, ∇F = {near['dF']:.3g}",
                 "TP's estimates == 0 at every θ"),
        _verdict(f"AoBG's error is within γ with probability δ when the bound is feasible (000 Lemma 4.3; γ = {gamma:g}, "
                 f"z = {z:g}, δ ≥ 1 − 1/z² = {delta:.2f})",
                 None if worst is None else worst["coverage"] >= delta - 3 * math.sqrt(delta * (1 - delta) / worst["feasible"]),
                 "no batch had ε ≤ γ" if worst is None else
                 f"coverage {worst['coverage']:.3f} at its lowest (θ index {coverage.index(worst)}, {worst['feasible']} "
                 f"feasible batches), {max(c['coverage'] for c in covered):.3f} at its highest",
                 "among batches with ε ≤ γ, the fraction with ‖ĝ_AoBG − ∇F‖ ≤ γ, against δ less 3 binomial SEs"),
        _variance_between(f"heaviside at θ = {near['theta']:.3g}", near),
    ]
    return StudyResult("heaviside", dict(thetas=thetas, samples=samples, replicates=replicates, sigma=sigma, gamma=gamma),
                       dict(grid=rows, tension=tension, verdicts=verdicts, aobg_coverage=coverage))


# -- 002 Example III.5, Fig. 3 ---------------------------------------------------------------------------


def relaxed_study(key, *, nus, samples, replicates, sigma=1.0, gamma=0.1) -> StudyResult:
    ests = estimators(gamma)
    rows, tension, emp_bias = [], [], []
    first = heaviside.relaxed(1.0, sigma=sigma)
    for i, nu in enumerate(nus):
        ex = dataclasses.replace(heaviside.relaxed(float(nu), sigma=sigma), problem=first.problem)
        F, dF = heaviside.relaxed_exact(0.5 * nu, sigma, nu)
        p = heaviside.slope_probability(0.5 * nu, sigma, nu)
        emp_bias.append(dict(nu=float(nu), **heaviside.empirical_bias(sigma, float(nu)),
                             fobg_variance=heaviside.fobg_variance(0.5 * nu, sigma, nu)))
        for j, N in enumerate(samples):
            reps = replicate_estimates(ex, ests, N, replicates, jax.random.fold_in(key, 1000 * i + j))
            summ = {n: summarise(s, np.array([dF]), N) for n, s in reps.items()}
            rows.append(dict(nu=float(nu), samples=int(N), dF=dF, p=p, zero_theory=(1 - p) ** N,
                             empirical_variance_median=float(np.median(np.sum(reps["FoBG"].empirical, axis=1))),
                             **summ))
            if N == max(samples) and nu == min(nus):
                tension = _tension_rows(f"relaxed, ν = {nu:g}", summ, gamma)
    # variance ∝ 1/ν: slope of log(theory and measured expected variance) against log ν
    big = [r for r in rows if r["samples"] == max(samples)]
    slope = float(np.polyfit(np.log([r["nu"] for r in big]), np.log([r["FoBG"]["expected_variance"] for r in big]), 1)[0])
    small = [r for r in rows if r["samples"] == min(s for s in samples if s >= 10)]
    emp_trend = [r["empirical_variance_median"] for r in sorted(small, key=lambda r: -r["nu"])]
    from scipy import stats

    zero_p = [stats.binomtest(int(round(r["FoBG"]["zero_fraction"] * replicates)), replicates,
                              min(max(r["zero_theory"], 0.0), 1.0)).pvalue for r in rows]
    zero_ok = min(zero_p) > ALPHA / len(rows)
    c_ratio = [e["delta"] / e["source"][1] for e in emp_bias]
    verdicts = [
        _verdict("FoBG has (c_σν, c_σ, 0) empirical bias at θ = ν/2 (002 Ex. III.5)",
                 all(e["beta"] <= e["source"][0] and e["delta"] >= e["source"][1] for e in emp_bias),
                 "P(the sample is on the slope) = " + ", ".join(f"{e['beta']:.3g} (c_σν = {e['source'][0]:.3g})" for e in emp_bias)
                 + "; ‖E[z | off the slope] − E[z]‖ = ∇F_ν = " + ", ".join(f"{r:.3f}·c_σ" for r in c_ratio),
                 "exact, Definition III.3 with its inequalities: P(off) ≥ 1 − c_σν and Δ ≥ c_σ at every ν. Δ tends to "
                 "2c_σ, not c_σ: H̄_ν jumps by 2, so the source's c_σ is a lower bound here"),
        _verdict("the FoBG's variance grows as 1/ν (002 Ex. III.5)", -1.2 < slope < -0.8,
                 f"slope of log expected variance against log ν: {slope:.3f} (N = {max(samples)})",
                 "least-squares slope in (−1.2, −0.8)"),
        _verdict("FoBG is exactly 0 in the low-sample regime, with probability (1 − p)^N (002 Fig. 3)", zero_ok,
                 "zero fractions " + ", ".join(f"ν={r['nu']:g},N={r['samples']}: {r['FoBG']['zero_fraction']:.2f} "
                                                f"(theory {r['zero_theory']:.2f})" for r in rows[: min(6, len(rows))]) + " …",
                 f"exact binomial test of each count against (1 − p)^N, smallest p-value {min(zero_p):.2g} against "
                 f"α/{len(rows)} (α = {ALPHA:g})"),
        _verdict("the inverse-variance weight trusts FoBG wrongly on the stiff relaxation too (002 §IV.C against PIPPS)",
                 tension[2]["max_z"] > z_bound(1, ALPHA) if tension else None,
                 (f"at ν = {min(nus):g}, N = {max(samples)}: TP's bias {tension[2]['bias_norm']:.3g} (|z| {tension[2]['max_z']:.1f}) "
                  f"against ∇F_ν = {rows[-1]['dF']:.3g}; its weight on LR {tension[2]['weight_on_lr']:.3g}") if tension else "",
                 "|bias|/SE of TP's mean against the Bonferroni bound; the weight comes from the batch it weighs"),
        _verdict("as ν → 0 the FoBG's empirical variance goes to 0 while its expected variance grows (002 Fig. 3)",
                 bool(emp_trend[-1] < emp_trend[0]) and slope < 0,
                 "median empirical variance (N = " + f"{small[0]['samples']}) from ν = {max(nus):g} to {min(nus):g}: "
                 + " → ".join(f"{v:.3g}" for v in emp_trend), "median falls from the largest ν to the smallest"),
    ]
    return StudyResult("relaxed", dict(nus=list(nus), samples=list(samples), replicates=replicates, sigma=sigma, gamma=gamma),
                       dict(grid=rows, empirical_bias=emp_bias, tension=tension, verdicts=verdicts))


# -- 002 Fig. 1 ------------------------------------------------------------------------------------------

FIG1 = {"drop": (fig1.drop, (0.5, 5.0), 0.5, 0.05), "throw": (fig1.throw, (0.25, 1.2), 0.02, 0.5),
        "pivot": (fig1.pivot, (0.3, 1.3), 0.01, 0.05)}  # factory, θ range, descent step, γ


def fig1_study(key, *, thetas, samples, replicates, iterations, descents) -> StudyResult:
    tables, verdicts, tension = {}, [], []
    for pi, (name, (make, (lo, hi), step, gamma)) in enumerate(FIG1.items()):
        ex0 = make()
        ests = estimators(gamma)
        grid = []
        for i, th in enumerate(np.linspace(lo, hi, thetas)):
            pol = base.as_policy(float(th))
            F, dF, err = ex0.exact(pol)
            f_value = float(np.asarray(ex0.simulator.step(None, jnp.asarray([th])))[0])
            reps = replicate_estimates(ex0, ests, samples, replicates, jax.random.fold_in(key, 100 * pi + i), policy=pol)
            grid.append(dict(theta=float(th), f=f_value, F=F, dF=float(dF[0]), quad_error=err,
                             **{n: summarise(s, dF, samples) for n, s in reps.items()}))
        F0, dF0, _ = ex0.exact(ex0.policy)
        dF0 = float(dF0[0])
        reps = replicate_estimates(ex0, ests, samples, max(replicates, 100), jax.random.fold_in(key, 100 * pi + 99))
        summ = {n: summarise(s, np.array([dF0]), samples) for n, s in reps.items()}
        tension += _tension_rows(name, summ, gamma)
        verdicts.append(_variance_between(f"{name} at θ = {base.scalar_of(ex0.policy):.3g}", summ))
        runs = {n: [descend(ex0, est, iterations=iterations, num_samples=samples, step=step,
                            key=jax.random.fold_in(key, 7000 + 100 * pi + d)).tolist() for d in range(descents)]
                for n, est in ests.items()}
        finals = {n: float(np.mean([r[-1][1] for r in v])) for n, v in runs.items()}
        tables[name] = dict(grid=grid, descent=runs, final=finals, start=dict(theta=float(base.scalar_of(ex0.policy)),
                                                                               F=F0, dF=dF0))
        verdicts.append(_verdict(f"{name}: FoBG is biased at the discontinuity while ZoBG is not (002 §III.A)",
                                 summ["FoBG"]["max_z"] > z_bound(3, ALPHA) and summ["ZoBG"]["max_z"] < z_bound(3, ALPHA),
                                 f"at θ = {base.scalar_of(ex0.policy):.3g}: FoBG |z| {summ['FoBG']['max_z']:.1f}, ZoBG |z| "
                                 f"{summ['ZoBG']['max_z']:.2f} (∇F = {dF0:.3g})", "|bias|/SE against the Bonferroni bound"))
        a, b = (np.array([r[-1][1] for r in runs[n]]) for n in ("FoBG", "ZoBG"))
        se = math.sqrt(np.var(a, ddof=1) / len(a) + np.var(b, ddof=1) / len(b)) if len(a) > 1 else float("nan")
        d = float(a.mean() - b.mean())
        verdicts.append(_verdict(f"{name}: a descent with FoBG ends worse than with ZoBG",
                                 None if not math.isfinite(se) else (True if d > 2 * se else False if d < -2 * se else None),
                                 "final F: " + ", ".join(f"{n} {v:.4g}" for n, v in finals.items()) + f"; FoBG − ZoBG {d:+.3g} ± {se:.2g}",
                                 f"exact F after {iterations} iterations over {descents} runs (lower is better); a difference counts at 2 SE"))
    return StudyResult("fig1", dict(thetas=thetas, samples=samples, replicates=replicates, iterations=iterations,
                                    descents=descents), dict(**tables, tension=tension, verdicts=verdicts))


# -- 002 Example III.6, Fig. 4 (MJX) ---------------------------------------------------------------------


def ball_study(key, *, thetas, samples, replicates, timeconsts, reference, gamma=0.5) -> StudyResult:
    from pipps.systems.contact import mjx_scenes

    ests = estimators(gamma)
    tables, tension, verdicts = {}, [], []
    for si, dome in enumerate((False, True)):
        for ti, tc in enumerate(timeconsts if dome else timeconsts[-1:]):
            rows = []
            ex = mjx_scenes.ball(dome, tc)
            for i, th in enumerate(np.radians(np.linspace(20.0, 40.0, thetas))):
                pol = base.as_policy(float(th))
                k = jax.random.fold_in(key, 10000 * si + 100 * ti + i)
                ref, ref_se = reference_gradient(ex, samples, reference, jax.random.fold_in(k, 1), policy=pol)
                reps = replicate_estimates(ex, ests, samples, replicates, k, policy=pol)
                rows.append(dict(theta=float(th), reference=ref.tolist(), reference_se=ref_se.tolist(),
                                 **{n: summarise(s, ref, samples) for n, s in reps.items()}))
            name = f"{'dome' if dome else 'wall'}_timeconst{tc:g}"
            tables[name] = rows
            mid = rows[len(rows) // 2]
            tension += _tension_rows(f"ball, {'dome' if dome else 'wall'}, timeconst {tc:g}",
                                     {n: mid[n] for n in ests}, gamma)
    def zs(rows, name):  # |mean − reference| over the combined standard error of both, per θ
        return [abs(r[name]["mean"][0] - r["reference"][0]) / math.hypot(r[name]["se"][0], r["reference_se"][0])
                for r in rows]

    bound = z_bound(thetas, ALPHA)
    wall = tables[f"wall_timeconst{timeconsts[-1]:g}"]
    domes = [tables[f"dome_timeconst{tc:g}"] for tc in timeconsts]
    wall_z, zobg_z = max(zs(wall, "FoBG")), max(max(zs(rows, "ZoBG")) for rows in [wall, *domes])
    dome_z = [max(zs(rows, "FoBG")) for rows in domes]
    dome_bias = [max(abs(r["FoBG"]["mean"][0] - r["reference"][0]) for r in rows) for rows in domes]
    verdicts.append(_verdict("the rectangular wall's corner makes FoBG biased (002 Ex. III.6)", wall_z > bound,
                             f"FoBG's largest |z| against the reference over {thetas} angles: {wall_z:.1f} (bound {bound:.2f}); "
                             f"ZoBG's largest, as a check of the reference: {zobg_z:.2f}",
                             "|FoBG mean − ZoBG reference| / sqrt(SE² + reference SE²) against the Bonferroni bound"))
    verdicts.append(_verdict("the dome's stiff relaxation still leaves FoBG empirically biased at finite N, more as it "
                             "stiffens (002 Ex. III.6)", (dome_z[-1] > bound and dome_bias[-1] > dome_bias[0]) if len(domes) > 1 else None,
                             "FoBG's largest |z| and |bias| by time constant " + ", ".join(
                                 f"{tc:g} s: {z:.1f}, {b:.3g}" for tc, z, b in zip(timeconsts, dome_z, dome_bias))
                             + f" (N = {samples})", "at the stiffest contact |z| above the Bonferroni bound, and the bias "
                             "larger than at the softest"))
    return StudyResult("ball", dict(thetas=thetas, samples=samples, replicates=replicates, timeconsts=list(timeconsts),
                                    reference=reference, gamma=gamma), dict(**tables, tension=tension, verdicts=verdicts))


# -- 002 Example III.7, IV.1, IV.2; Figs. 5 and 6 ---------------------------------------------------------


def pushing_study(key, *, stiffness, kappas, samples, replicates, gamma=1.0) -> StudyResult:
    ests = {n: e for n, e in estimators(gamma).items()}
    rows, tension = [], []
    configs = [("penalty", dict(stiffness=k)) for k in stiffness] + [("implicit", {})]
    configs += [("barrier", dict(kappa=k)) for k in kappas]
    for i, (model, kw) in enumerate(configs):
        ex = pushing.pushing(model, **kw)
        reps = replicate_estimates(ex, ests, samples, replicates, jax.random.fold_in(key, i))
        summ = {n: summarise(s, None, samples) for n, s in reps.items()}
        finite = {n: bool(np.all(np.isfinite(reps[n].grad))) and bool(np.all(np.isfinite(reps[n].value))) for n in ests}
        rows.append(dict(model=model, **{k: float(v) for k, v in kw.items()}, finite=finite,
                         cost=float(np.mean(reps["FoBG"].value)), **summ))
    # Fig. 6: x⁺ against the impulse u at (x, v) = 0
    u = np.linspace(-2.0, 2.0, 81)
    curves = {"implicit": np.asarray(pushing.wall_step("implicit", u)).tolist(),
              "penalty": np.asarray(pushing.wall_step("penalty", u)).tolist()}
    curves.update({f"barrier_kappa{k:g}": np.asarray(pushing.wall_step("barrier", u, kappa=k)).tolist() for k in kappas})
    pen = [r for r in rows if r["model"] == "penalty"]
    bound = pushing.Pushing().stable_stiffness
    stable = [r for r in pen if r["stiffness"] < bound and all(r["finite"].values())]
    unstable_k = [r["stiffness"] for r in pen if r not in stable]
    ratio = [r["FoBG"]["expected_variance"] / r["ZoBG"]["expected_variance"] for r in stable]
    beyond = [r["FoBG"]["expected_variance"] / r["ZoBG"]["expected_variance"] for r in pen if r not in stable]
    crossed = any(x > 1 for x in ratio) and ratio[-1] > ratio[0]
    verdicts = [
        _verdict("ZoBG has less variance than FoBG as the stiffness grows, until semi-implicit integration goes unstable "
                 "(002 Ex. III.7, Fig. 5)", crossed if stable else None,
                 "Var FoBG / Var ZoBG at k = " + ", ".join(f"{r['stiffness']:g}: {x:.3g}" for r, x in zip(stable, ratio))
                 + (f"; past the step's stability bound ({bound:.4g}): " + ", ".join(
                     f"k = {k:g}: {x:.3g}" for k, x in zip(unstable_k, beyond)) if unstable_k else ""),
                 "below the semi-implicit step's stability bound, the ratio of expected per-sample variances "
                 "(traces) rises with k and passes 1"),
        _verdict("implicit time-stepping keeps the FoBG's norm, and its variance, bounded (002 §IV.A)",
                 None if not pen else bool(rows[len(pen)]["FoBG"]["expected_variance"] < max(r["FoBG"]["expected_variance"] for r in stable)),
                 f"FoBG variance: implicit {rows[len(pen)]['FoBG']['expected_variance']:.3g}, penalty up to "
                 f"{max(r['FoBG']['expected_variance'] for r in stable):.3g}", "implicit below the stiffest stable penalty"),
    ]
    base_k = min((r["stiffness"] for r in stable), key=lambda k: abs(math.log(k / 1e3))) if stable else stiffness[0]
    ex = pushing.pushing("penalty", stiffness=base_k)
    ref, ref_se = reference_gradient(ex, samples, 16 * replicates, jax.random.fold_in(key, 999))
    reps = replicate_estimates(ex, ests, samples, replicates, jax.random.fold_in(key, 998))
    base_summ = {n: summarise(s, ref, samples) for n, s in reps.items()}
    verdicts.append(_variance_between(f"pushing, penalty k = {base_k:g}", base_summ))
    tension = _tension_rows(f"pushing, penalty k = {base_k:g} (bias against a ZoBG reference of {16 * replicates * samples} "
                            f"samples, SE norm {np.linalg.norm(ref_se):.2g})", base_summ, gamma)
    return StudyResult("pushing", dict(stiffness=list(stiffness), kappas=list(kappas), samples=samples,
                                       replicates=replicates, gamma=gamma),
                       dict(grid=rows, fig6=dict(u=u.tolist(), **curves), tension=tension, verdicts=verdicts))


# -- 000 "Scaling results" --------------------------------------------------------------------------------


def scaling_study(key, *, stiffness, iterations, samples, seeds, policy_iterations, gamma=0.02, step=50.0,
                  policy_step=5.0) -> StudyResult:
    ests = estimators(gamma)
    traj = []
    for i, k in enumerate(stiffness):
        ex = pushing.pushing("penalty", stiffness=k, horizon=40)
        evaluate = batch_objective(ex, 256, jax.random.PRNGKey(123), replicates=4)
        for n, est in ests.items():
            runs = [descend(ex, est, iterations=iterations, num_samples=samples, step=step, clip=0.2,
                            key=jax.random.fold_in(key, 1000 * i + 10 * s + list(ests).index(n)), evaluate=evaluate)
                    for s in range(seeds)]
            traj.append(dict(stiffness=float(k), estimator=n, curves=[r.tolist() for r in runs],
                             final=float(np.mean([r[-1, 1] for r in runs]))))
    pol = []
    ex = _policy_problem()
    evaluate = batch_objective(ex, 512, jax.random.PRNGKey(321), replicates=4)
    for n, est in ests.items():
        runs = [descend(ex, est, iterations=policy_iterations, num_samples=samples, step=policy_step, clip=1.0,
                        key=jax.random.fold_in(key, 50000 + 10 * s + list(ests).index(n)), evaluate=evaluate)
                for s in range(seeds)]
        pol.append(dict(estimator=n, curves=[r.tolist() for r in runs], final=float(np.mean([r[-1, 1] for r in runs]))))
    runs_of = {(r["stiffness"], r["estimator"]): np.array([c[-1][1] for c in r["curves"]]) for r in traj}
    final = {k: float(v.mean()) for k, v in runs_of.items()}
    pruns = {r["estimator"]: np.array([c[-1][1] for c in r["curves"]]) for r in pol}
    pmean = {r["estimator"]: np.array([np.mean(np.asarray(c)[:, 1]) for c in r["curves"]]) for r in pol}
    soft, stiff = min(stiffness), max(stiffness)

    def worse(a, b):  # mean(a) − mean(b) and its standard error over the independent runs
        se = math.sqrt(np.var(a, ddof=1) / len(a) + np.var(b, ddof=1) / len(b)) if len(a) > 1 else float("nan")
        return float(np.mean(a) - np.mean(b)), se

    def word(d, se):  # "a is worse than b" at two standard errors, either way; one run decides nothing
        if not math.isfinite(se):
            return None
        return True if d > 2 * se else (False if d < -2 * se else None)

    d_soft, se_soft = worse(runs_of[(soft, "FoBG")], runs_of[(soft, "ZoBG")])
    d_stiff, se_stiff = worse(runs_of[(stiff, "FoBG")], runs_of[(stiff, "ZoBG")])
    trend, trend_se = d_stiff - d_soft, math.hypot(se_soft, se_stiff)
    pf, pf_se = worse(pruns["FoBG"], pruns["ZoBG"])
    pa, pa_se = worse(pmean["AoBG"], pmean["ZoBG"])
    runs = f"final cost over {seeds} runs of {iterations} iterations (mean ± SE); a difference counts at 2 SE"
    verdicts = [
        _verdict("trajectory optimisation: FoBG falls behind ZoBG as the contact stiffens (000)", word(trend, trend_se),
                 f"FoBG − ZoBG: {d_soft:+.3g} ± {se_soft:.2g} at k = {soft:g}, {d_stiff:+.3g} ± {se_stiff:.2g} at k = {stiff:g}", runs),
        _verdict("trajectory optimisation: ZoBG does worse than FoBG on the softest system (000)", word(-d_soft, se_soft),
                 f"ZoBG − FoBG at k = {soft:g}: {-d_soft:+.3g} ± {se_soft:.2g}", runs),
        _verdict("trajectory optimisation: AoBG selects between the two, never far from the better (000)",
                 all(final[(k, "AoBG")] <= min(final[(k, "FoBG")], final[(k, "ZoBG")])
                     + 2 * math.sqrt(np.var(runs_of[(k, "AoBG")], ddof=1) / seeds) for k in stiffness) if seeds > 1 else None,
                 ", ".join(f"k = {k:g}: AoBG {final[(k, 'AoBG')]:.4g}, FoBG {final[(k, 'FoBG')]:.4g}, ZoBG {final[(k, 'ZoBG')]:.4g}"
                           for k in stiffness), "AoBG's mean final cost within 2 SE of the better of FoBG and ZoBG at every k"),
        _verdict("policy optimisation: FoBG ends worse than ZoBG (000)", word(pf, pf_se),
                 "final cost: " + ", ".join(f"{n} {float(np.mean(v)):.4g}" for n, v in pruns.items()) + f"; FoBG − ZoBG {pf:+.3g} ± {pf_se:.2g}",
                 f"final cost over {seeds} runs of {policy_iterations} iterations; a difference counts at 2 SE"),
        _verdict("policy optimisation: AoBG descends faster than ZoBG (000)", word(-pa, pa_se),
                 f"mean cost along the run: AoBG − ZoBG {pa:+.3g} ± {pa_se:.2g} (AoBG {float(np.mean(pmean['AoBG'])):.4g}, "
                 f"ZoBG {float(np.mean(pmean['ZoBG'])):.4g}, FoBG {float(np.mean(pmean['FoBG'])):.4g})",
                 "the mean of each run's evaluated learning curve (lower: faster); a difference counts at 2 SE"),
    ]
    return StudyResult("scaling", dict(stiffness=list(stiffness), iterations=iterations, samples=samples, seeds=seeds,
                                       policy_iterations=policy_iterations, gamma=gamma, step=step,
                                       policy_step=policy_step, clip=(0.2, 1.0)),
                       dict(trajectory=traj, policy=pol, verdicts=verdicts, tension=[]))


def _area(rows, name) -> float:
    r = next(r for r in rows if r["estimator"] == name)
    return float(np.mean([np.asarray(c)[:, 1] for c in r["curves"]]))


def _policy_problem():
    """000's policy optimisation through contact, read here as the pushing task from random starts:
    the box's starting gap ~ N(0.1, 0.04²), the pusher driven by a linear feedback policy on
    ``(x1, v1, x2, v2)`` (unsaturated, starting from the constant force 2 N)."""
    import dataclasses as dc

    from pipps.policies import LinearPolicy

    ex = pushing.pushing("penalty", stiffness=1e3, gap=0.1, horizon=40)
    cov = np.zeros((5, 5))
    cov[3, 3] = 0.04**2
    problem = dc.replace(ex.problem, name="pushing_policy", model_init_cov=cov, policy_input_idx=(1, 2, 3, 4))
    policy = LinearPolicy(jnp.zeros((1, 4)), jnp.full((1,), 2.0), u_max=(1.0,), saturated=False)
    return dc.replace(ex, name="pushing_policy", title="000 policy optimisation through contact (pushing from random starts)",
                      problem=problem, policy=policy)


RUNNERS = {"heaviside": heaviside_study, "relaxed": relaxed_study, "fig1": fig1_study, "ball": ball_study,
           "pushing": pushing_study, "scaling": scaling_study}


def run_study(study: str, key=None, *, full: bool = False, **overrides) -> StudyResult:
    """Run one study (quick unless ``full``) from ``key`` (default PRNGKey(0))."""
    from pipps.experiments.results import code_version

    kw = settings_of(study, full, **overrides)
    result = RUNNERS[study](jax.random.PRNGKey(0) if key is None else key, **kw)
    result.settings["preset"] = "full" if full else "quick"
    result.versions = dict(code=code_version(), jax=jax.__version__)
    return result
