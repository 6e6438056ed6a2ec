"""Per learned trial of result files: the true return against the model's objective at the last
policy step, the median gradient norm, TP's k_LR averaged over time steps and policy steps (NaN for a
method without it), non-finite and skipped steps (for PILCO and the fixed-seed methods, whose
quasi-Newton search has no gradient steps: its objective at the end, the number of line searches and
how many failed), the fraction of the trial's evaluation
rollouts meeting the task's success criterion, and, on the cart-pole, where the recorded rollout left the
pole and the cart (docs/results.md, the flat-cost plateaus of k = 16 TP seed 2 and k = 9 TP seed 17;
docs/estimator-variance.md, the library's and the thesis' k_LR rules while learning).

    python experiments/trial_traces.py results/thesis/cartpole_swingup_angle_k16_tp_thesis_s2.h5
    python experiments/trial_traces.py --summary results/thesis/cartpole_swingup_angle_k1_{rp,lr,gr,tp}_thesis_s*.h5

``--summary`` prints one line per file instead: the final return and the largest per-trial median
gradient norm with the trial it occurred in (RP's exploding gradients in chaos, docs/results.md).
``--particles`` prints, per learned trial, where the model's stored particles put the pole at a few
time steps (quantiles of the unwrapped angle θ, upright at ±π, ±3π, …) and the fraction of them
within 0.3 rad of upright at the last step: a prediction that splits between the two swing-up
directions (the Tip Cost's multi-modality, docs/results.md claim 3) shows as quantiles on both sides.

    python experiments/trial_traces.py --particles results/thesis/cartpole_swingup_tip_k1_tp_thesis_s2.h5

``--shaped`` prints, per learned trial, the stored particles' objective Σ_t mean_i c(x_t,i) beside
the Gaussian-shaped one Σ_t E_N(μ_t,Σ_t)[c] that GTP and GLR follow (μ_t, Σ_t fitted to the stored
particles, 1/P as the estimator fits them), by the moment-matched formula the estimator uses and by
Monte Carlo under the same Gaussian (4000 draws per step, seed 0 for each file), and the true return: a minimum that
exploits the Gaussian's tail (thesis §4.6.1, on GTP's and PILCO's Tip Cost outliers) shows as a
shaped objective below the particles'.

    python experiments/trial_traces.py --shaped results/thesis/cartpole_swingup_tip_k1_gtp_thesis_s{0,1,2,3,4}.h5

Unfinished files are read too (no checksum verification). Cart-pole state order [x, v, ω, θ].
"""

import argparse
from pathlib import Path

import numpy as np

from pipps.experiments.results import read_result
from pipps.reporting.verdicts import final_flags
from pipps.tasks.registry import get_task

CARTPOLE = (get_task("cartpole_swingup"), get_task("cartpole_balance"))


def _mean(values) -> float:
    values = np.asarray(values, dtype=float)
    return float(np.nanmean(values)) if np.isfinite(values).any() else float("nan")


def summary(paths) -> None:
    print("| file | method | seed | final return | largest median gradient norm (trial) |")
    print("|---|---|---|---|---|")
    for path in paths:
        result = read_result(path, verify=False)
        learned = [t for t in result.trials if t.kind == "learned" and hasattr(t.opt_trace, "grad_norm")]
        if not learned:
            continue
        norms = [float(np.median(t.opt_trace.grad_norm)) for t in learned]
        i = int(np.argmax(norms))
        cfg = result.config
        print(f"| {path} | {cfg.method} | {cfg.seed} | {result.final_return:.2f} | {norms[i]:.2g} ({learned[i].index}) |")


def particles(paths, steps=(10, 15, 20, 30)) -> None:
    for path in paths:
        print(path)
        for t in read_result(path, verify=False).trials:
            if t.kind != "learned" or getattr(t.predicted, "particles", None) is None:
                continue
            theta = np.asarray(t.predicted.particles)[..., 3]  # (T+1, P)
            upright = np.abs(np.remainder(theta[-1], 2 * np.pi) - np.pi) < 0.3
            parts = [f"step {s}: {' '.join(f'{q:+.1f}' for q in np.quantile(theta[s], [0, 0.25, 0.5, 0.75, 1]))}"
                     for s in steps if s < theta.shape[0]]
            print(f"  trial {t.index:03d}: θ quantiles (min q25 median q75 max)  " + "  ".join(parts)
                  + f"  upright at the end {np.mean(upright):.2f} of {theta.shape[1]}")


def shaped(paths, draws: int = 4000) -> None:
    import jax
    import jax.numpy as jnp

    from pipps.precision import enable_float64
    from pipps.propagation.cost_terms import particle_fit
    from pipps.tasks.presets import make_cost

    enable_float64()
    for path in paths:
        rng = np.random.default_rng(0)  # per file: its numbers do not depend on the files listed with it
        result = read_result(path, verify=False)
        cfg = result.config
        cost = make_cost(cfg.task, cfg.cost, cfg.preset)
        per_particle = jax.jit(jax.vmap(cost))
        fitted = jax.jit(lambda x: particle_fit(x)[:2])
        expected = jax.jit(lambda m, S: cost.expected(m, S)[0])
        print(f"{path} ({cfg.method}, seed {cfg.seed})")
        for t in result.trials:
            if t.kind != "learned" or getattr(t.predicted, "particles", None) is None:
                continue
            X = jnp.asarray(t.predicted.particles)  # (T+1, P, D); the start state's cost is not summed
            particles_j = mm_j = mc_j = 0.0
            for x in X[1:]:
                mu, cov = fitted(x)
                particles_j += float(jnp.mean(per_particle(x)))
                mm_j += float(expected(mu, cov))
                z = rng.multivariate_normal(np.asarray(mu), np.asarray(cov), size=draws, method="eigh")
                mc_j += float(jnp.mean(per_particle(jnp.asarray(z))))
            print(f"  trial {t.index:03d}: particles {particles_j:6.2f}  shaped, moment-matched {mm_j:6.2f}  "
                  f"shaped, Monte Carlo {mc_j:6.2f}  true return {t.eval_return:6.2f}  ({X.shape[1]} stored particles)")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", nargs="+", type=Path, help="result files (.h5), finished or not")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--summary", action="store_true", help="one line per file: final return, largest median gradient norm")
    mode.add_argument("--particles", action="store_true", help="per trial, where the stored particles put the pole")
    mode.add_argument("--shaped", action="store_true",
                      help="per trial, the stored particles' objective beside the Gaussian-shaped one and the true return")
    args = parser.parse_args(argv)
    missing = [str(p) for p in args.files if not p.is_file()]
    if missing:
        parser.error("no such file: " + ", ".join(missing))
    if args.summary:
        summary(args.files)
        return
    if args.particles:
        particles(args.files)
        return
    if args.shaped:
        shaped(args.files)
        return
    for path in args.files:
        print(path)
        result = read_result(path, verify=False)
        cartpole = result.config.task_spec in CARTPOLE  # the pole and cart columns read a cart-pole's state
        for t in result.trials:
            if t.kind != "learned":
                continue
            trace, states = t.opt_trace, np.asarray(t.states)
            flags = final_flags(result.config, t)
            where = (f"  max |θ| {np.abs(states[:, 3]).max():.2f}  cart end {states[-1, 0]:.1f} m" if cartpole else "")
            met = "" if flags is None else f"  criterion met {np.mean(flags):.2f}"
            if hasattr(trace, "grad_norm"):  # a stochastic-gradient search (the particle methods)
                search = (f"model {float(trace.particle_objective[-1]):.2f}  "
                          f"median |grad| {np.median(trace.grad_norm):.2g}  mean k_LR {_mean(t.diagnostics.k_lr):.3f}  "
                          f"non-finite {int(np.sum(t.diagnostics.nonfinite_steps))}  skipped {int(np.sum(trace.skipped))}")
            else:  # a quasi-Newton search (PILCO, the fixed-seed methods): its own objective at the end
                search = (f"model {float(trace.value[-1]):.2f}  line searches {len(trace.value)}  "
                          f"failed {int(np.sum(trace.failed))}")
            print(f"  trial {t.index:03d}: return {t.eval_return:.2f}  {search}{met}{where}")


if __name__ == "__main__":
    main()
