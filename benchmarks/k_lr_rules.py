"""Total propagation's k_LR rules side by side: variance, bias, MSE and time
(docs/estimator-variance.md, "Choosing k_LR").

One table, one row per (cell, rule). Cells: the kicked rotor of :mod:`pipps.systems.chaotic`
("chaotic" K = 2 and "smooth" K = 0.1, T = 30; docs/estimator-variance.md) at each P, and the
linear-Gaussian reference system (noise 0.3, saturating cost, T = 10) whose exact gradient is known.
Rules: RP and BIW-LR (the parts), TP with k_LR "previous", "batch" (thesis),
"leave_one_out" (the library default), "split", "cross_fit", "guarded", the robust combiner (γ = 1, z = 2, batch), and
"previous" and "leave_one_out" with ``messages="pathwise"`` (k mixes the contributions only; the
pathwise message is passed back).

Per cell, R replicates of every rule on common random numbers
(:func:`~pipps.stats.paired_replicate_gradients`). Columns:

* ``var``: trace of the covariance over replicates;
* ``var / min(parts)``: against the smaller of RP's and BIW-LR's in that cell, with a 95 % interval
  from the delta method on paired replicates (:func:`~pipps.stats.log_variance_ratio`);
* ``bias``: ‖mean − reference‖/‖reference‖ and the largest per-coordinate |z|. The reference is the
  exact gradient (linear-Gaussian), or BIW-LR on the same particles (kicked rotor: a paired
  difference against an exactly unbiased estimator, so z is the bias of the rule relative to it);
* ``MSE`` of one estimate = var + ‖bias‖² (the bias vector as estimated; for an unbiased rule that
  term is only sampling noise, about var/R);
* ``mean k``: k_LR averaged over steps and replicates;
* ``s / eval``: median seconds of one jitted value-and-gradient (`estimate`), 15 calls with fresh
  keys after compilation; ``Gflop-eq``: seconds × the float64 GEMM rate measured in this run, a
  machine-independent cost; ``MSE × s``: the MSE at equal time (averaging n estimates divides the
  variance, not the bias², by n — for a biased rule this product understates its MSE at long times).

``--lg-bias R`` adds a second table at higher power: on the linear-Gaussian system, each TP rule's
bias against the exact gradient and, paired on the same particles, against TP "previous" (exactly
unbiased), whose common sampling error the paired difference cancels.

The cores may be shared with other work: times are medians, and the GEMM rate is measured in the
same run so that the Gflop-equivalents stay comparable.

    JAX_PLATFORMS=cpu python benchmarks/k_lr_rules.py            # the documented table
    JAX_PLATFORMS=cpu python benchmarks/k_lr_rules.py --quick    # a smoke run
    JAX_PLATFORMS=cpu python benchmarks/k_lr_rules.py --cells --lg-bias 40000 --lg-particles 10 30   # the bias table only

The action-node rules (``tpx``) and the cells added with them — the two-action
linear-Gaussian system (``pipps.systems.linear_gaussian.two_action_reference_system``) and the
cart-pole snapshot of the landscape study (``CARTPOLE_FILE`` trial 6, θ + Δ·d along PILCO's
direction, Δ = 0 and 1.5; bias against BIW-LR on the same particles) — run on their own with
``--rules``; the rows of the other rules do not change when rules are left out (every rule sees the
same particles in a replicate):

    JAX_PLATFORMS=cpu python benchmarks/k_lr_rules.py --rules "TP previous" "TP batch (thesis)" \
        "TP leave-one-out (default)" "TPX previous" "TPX batch" "TPX leave-one-out" \
        --cells chaotic smooth "linear-Gaussian 2u" "cart-pole Δ=0" "cart-pole Δ=1.5"
"""

from __future__ import annotations

import argparse
import functools
import time

import jax
import numpy as np
from jax.flatten_util import ravel_pytree

import pipps
from machine import gemm_gflops  # benchmarks/machine.py
from pipps.particles.forward import RolloutConfig
from pipps.propagation.combine import inverse_variance
from pipps.propagation.estimators import compose, estimator
from pipps.propagation.cost_terms import plain_costs
from pipps.propagation.parts import biw_lr, pathwise
from pipps.propagation.estimate import estimate, init_estimator_state
from pipps.stats import paired_replicate_gradients, trace_variance, variance_ratio_text
from pipps.systems import exact_objective, reference_system
from pipps.systems.linear_gaussian import two_action_reference_system
from pipps.systems.chaotic import kicked_rotor_system

pipps.enable_float64()

RULES = {
    "RP": estimator("rp"),
    "BIW-LR": estimator("lr"),
    "TP previous": estimator("tp", k_lr="previous"),
    "TP batch (thesis)": estimator("tp", k_lr="batch"),
    "TP leave-one-out (default)": estimator("tp", k_lr="leave_one_out"),
    "TP split": estimator("tp", k_lr="split"),
    "TP cross-fit (LOO pilot)": estimator("tp", k_lr="cross_fit"),
    "TP guarded": estimator("tp", k_lr="guarded"),
    "TP robust γ=1 (batch)": estimator("tp", combiner="robust", robust_gamma=1.0, k_lr="batch"),
    "TP previous, RP messages": compose(plain_costs(), pathwise(), biw_lr(), combiner=inverse_variance("previous", "pathwise")),
    "TP leave-one-out, RP messages": compose(plain_costs(), pathwise(), biw_lr(), combiner=inverse_variance("leave_one_out", "pathwise")),
    "TPX previous": estimator("tpx", k_lr="previous"),
    "TPX batch": estimator("tpx", k_lr="batch"),
    "TPX leave-one-out": estimator("tpx", k_lr="leave_one_out"),
}
PARTS = ("RP", "BIW-LR")  # every run has them: the variance ratios and the kicked-rotor and cart-pole bias read them

# the cart-pole cells: the landscape study's snapshot (docs/gradients.md), at Δ along PILCO's direction
CARTPOLE_FILE = "results/thesis/cartpole_swingup_angle_k1_tp_thesis_s0.h5"
CARTPOLE_TRIAL = 6
CARTPOLE_DELTAS = {"cart-pole Δ=0": 0.0, "cart-pole Δ=1.5": 1.5}
CELLS = ("chaotic", "smooth", "linear-Gaussian", "linear-Gaussian 2u", *CARTPOLE_DELTAS)
EXACT = ("linear-Gaussian", "linear-Gaussian 2u")  # cells whose exact gradient is known


@functools.lru_cache(maxsize=None)
def _cartpole_snapshot():
    from pipps.studies.snapshot import load_snapshot, pilco_direction

    snap = load_snapshot(CARTPOLE_FILE, CARTPOLE_TRIAL)
    return snap, np.asarray(pilco_direction(snap))


@functools.lru_cache(maxsize=None)
def system(name: str):
    if name == "linear-Gaussian":
        return reference_system(0.3, "saturating")
    if name == "linear-Gaussian 2u":
        return two_action_reference_system(0.3)
    if name in CARTPOLE_DELTAS:
        snap, d = _cartpole_snapshot()
        return snap.task, snap.model, snap.unravel(jax.numpy.asarray(snap.theta + CARTPOLE_DELTAS[name] * d))
    return kicked_rotor_system(name)


def rollout_config(name: str, P: int) -> RolloutConfig:
    if name in EXACT:
        return RolloutConfig(num_particles=P)
    if name in CARTPOLE_DELTAS:  # the thesis' TP rollout: the GP's variance, the experiment's horizon
        return RolloutConfig(num_particles=P, horizon=_cartpole_snapshot()[0].config.horizon)
    return RolloutConfig(num_particles=P, model_variance=False)


def seconds_per_eval(name: str, P: int, est, calls: int = 15) -> float:
    task, model, policy = system(name)
    cfg = rollout_config(name, P)
    st = init_estimator_state(jax.random.PRNGKey(1), policy, model, problem=task, config=cfg, estimator=est)
    if est.cold_start:  # time the warm state an optimizer runs in, not the first call's fallback
        st, _ = estimate(jax.random.PRNGKey(2), st, policy, model, problem=task, config=cfg, estimator=est)
    f = jax.jit(lambda k: estimate(k, st, policy, model, problem=task, config=cfg, estimator=est)[1].grad)
    jax.block_until_ready(f(jax.random.PRNGKey(3)))
    times = []
    for i in range(calls):
        t = time.perf_counter()
        jax.block_until_ready(f(jax.random.PRNGKey(10 + i)))
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def replicates(name: str, P: int, R: int, seed: int, rules: dict):
    task, model, policy = system(name)
    run = jax.jit(
        functools.partial(
            paired_replicate_gradients, problem=task, model=model, policy=policy, config=rollout_config(name, P),
            estimators=rules, num_replicates=R, batch_size=25 if P <= 100 else 5,
        )
    )
    out = run(jax.random.PRNGKey(seed))
    return {n: np.asarray(g) for n, g in out.grad.items()}, {n: np.asarray(k) for n, k in out.k_lr.items()}



def bias(g, reference) -> tuple[np.ndarray, float, float]:
    """(bias vector, relative norm, max |z|) against an exact vector or paired reference replicates."""
    if reference.ndim == 1:
        d, ref_mean = g, reference
        b = g.mean(0) - reference
    else:
        d, ref_mean = g - reference, reference.mean(0)
        b = d.mean(0)
    se = d.std(0, ddof=1) / np.sqrt(d.shape[0])
    z = np.where(se > 0, np.abs(b) / np.where(se > 0, se, 1.0), 0.0)
    return b, float(np.linalg.norm(b) / np.linalg.norm(ref_mean)), float(np.max(z))


def cell_rows(name: str, P: int, R: int, seed: int, gflops: float, timing: bool, rules: dict) -> list[str]:
    g, k = replicates(name, P, R, seed, rules)
    if name in EXACT:
        task, model, policy = system(name)
        reference = np.asarray(ravel_pytree(jax.grad(exact_objective, argnums=2)(task, model, policy))[0])
    else:
        reference = g["BIW-LR"]
    parts = min(("RP", "BIW-LR"), key=lambda n: trace_variance(g[n]))
    rows = []
    for rule, est in rules.items():
        v = trace_variance(g[rule])
        if reference.ndim == 2 and rule == "BIW-LR":
            b_cell, mse = "(reference)", v
        else:
            b, rel, zmax = bias(g[rule], reference)
            b_cell, mse = f"{rel:.3f} ({zmax:.1f})", v + float(b @ b)
        ratio = "1" if rule == parts else variance_ratio_text(g[rule], g[parts])
        s = seconds_per_eval(name, P, est) if timing else float("nan")
        cells = [name, str(P), str(R), rule, f"{v:.3g}", ratio, b_cell, f"{mse:.3g}", f"{np.mean(k[rule]):.2f}",
                 f"{s:.4f}", f"{s * gflops:.3g}", f"{mse * s:.3g}"]
        rows.append("| " + " | ".join(cells) + " |")
    return rows


BIAS_RULES = ("previous", "batch", "leave_one_out", "split", "cross_fit", "guarded")


def lg_bias_rows(P: int, R: int, seed: int) -> list[str]:
    """Bias of each TP rule at P on the linear-Gaussian system: against the exact gradient, and
    paired against TP "previous" on the same particles."""
    task, model, policy = system("linear-Gaussian")
    exact = np.asarray(ravel_pytree(jax.grad(exact_objective, argnums=2)(task, model, policy))[0])
    ests = {n: estimator("tp", k_lr=n) for n in BIAS_RULES}
    run = jax.jit(
        functools.partial(
            paired_replicate_gradients, problem=task, model=model, policy=policy, config=rollout_config("linear-Gaussian", P),
            estimators=ests, num_replicates=R, batch_size=200,
        )
    )
    g = {n: np.asarray(v) for n, v in run(jax.random.PRNGKey(seed)).grad.items()}
    rows = []
    for n in BIAS_RULES:
        _, rel, zmax = bias(g[n], exact)
        z = (g[n].mean(0) - exact) / (g[n].std(0, ddof=1) / np.sqrt(R))
        if n == "previous":
            paired = "(reference)"
        else:
            b, _, pz = bias(g[n], g["previous"])
            paired = f"{np.linalg.norm(b) / np.linalg.norm(exact):.4f} ({pz:.1f})"
        rows.append(f"| {P} | {R} | {n} | {rel:.4f} | {np.array2string(z, precision=1, separator=', ')} | {paired} |")
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--particles", type=int, nargs="+", default=[30, 100])
    ap.add_argument("--replicates", type=int, default=1000, help="R per kicked-rotor cell at P < 100")
    ap.add_argument("--replicates-large-p", type=int, default=400, help="R per kicked-rotor cell at P >= 100")
    ap.add_argument("--lg-particles", type=int, nargs="+", default=[30])
    ap.add_argument("--lg-replicates", type=int, default=20000, help="R per linear-Gaussian cell")
    ap.add_argument("--cells", nargs="*", default=["chaotic", "smooth", "linear-Gaussian"], choices=CELLS,
                    help="also 'linear-Gaussian 2u' (two actions) and the cart-pole snapshot cells")
    ap.add_argument("--cartpole-particles", type=int, nargs="+", default=[100, 300])
    ap.add_argument("--cartpole-replicates", type=int, default=300)
    ap.add_argument("--rules", nargs="+", default=None, choices=list(RULES), metavar="RULE",
                    help=f"only these rules (with {' and '.join(PARTS)}); default: all of {list(RULES)}")
    ap.add_argument("--lg-bias", type=int, default=0, metavar="R", help="also the linear-Gaussian bias table with R replicates")
    ap.add_argument("--no-timing", action="store_true")
    ap.add_argument("--seed", type=int, default=20)
    ap.add_argument("--quick", action="store_true", help="smoke run: P = 30, R = 60, linear-Gaussian R = 200")
    args = ap.parse_args(argv)
    if args.quick:
        args.particles, args.replicates, args.lg_particles, args.lg_replicates = [30], 60, [30], 200

    start = time.perf_counter()
    gflops = gemm_gflops()
    print(f"jax {jax.__version__}, backend {jax.default_backend()}, seed {args.seed}, "
          f"float64 GEMM (512³) {gflops:.2f} Gflop/s measured at the start\n")
    head = ["system", "P", "R", "rule", "var", "var / min(RP, BIW-LR) [95 %]", "bias: rel. (max |z|)", "MSE",
            "mean k", "s / eval", "Gflop-eq", "MSE × s"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    rules = RULES if args.rules is None else {n: RULES[n] for n in (*PARTS, *args.rules)}
    for name in args.cells:
        for P in (args.lg_particles if name in EXACT else args.cartpole_particles if name in CARTPOLE_DELTAS else args.particles):
            if name in EXACT:
                R = args.lg_replicates
            elif name in CARTPOLE_DELTAS:
                R = args.cartpole_replicates
            else:
                R = args.replicates if P < 100 else args.replicates_large_p
            lines += cell_rows(name, P, R, args.seed + P, gflops, not args.no_timing, rules)
            print(f"[{name} P={P} done at {time.perf_counter() - start:.0f} s]", flush=True)
    if args.cells:
        print("\n" + "\n".join(lines) + "\n")
    if args.lg_bias:
        head = ["P", "R", "k_lr", "bias vs exact: ‖b‖/‖∇J‖", "z per coordinate", "paired vs previous: ‖b‖/‖∇J‖ (max |z|)"]
        rows = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for P in args.lg_particles:
            rows += lg_bias_rows(P, args.lg_bias, args.seed + 1000 + P)
        print(f"### Linear-Gaussian bias at higher power (R = {args.lg_bias})\n")
        print("\n".join(rows) + "\n")
    print(f"float64 GEMM rate at the end: {gemm_gflops():.2f} Gflop/s")
    print(f"wall time: {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
