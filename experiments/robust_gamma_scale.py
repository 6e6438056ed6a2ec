"""How large the robust combiner's bound γ is on cart-pole: at stored snapshots of the thesis TP runs,
the fraction of steps whose weight the bound changes, against γ.

The robust combiner (Suh et al.'s AoBG inside total propagation) weighs each step like TP's
inverse-variance rule unless ε + α_∞ B > γ, where B = ‖ḡ_RP − ḡ_LR‖ and ε the LR mean's confidence
radius; then it moves weight to the LR part. γ is absolute (gradient units), so the cart-pole cell
needs a γ read off the task. For each snapshot and γ this estimates with the thesis' TP (inverse
variance, this batch's weights) and with the robust combiner on the same particles, and reports
the fraction of the T steps whose k_LR the bound raised, and the mean k_LR of both.

    python experiments/robust_gamma_scale.py results/thesis/cartpole_swingup_angle_k1_tp_thesis_s{0,1,2}.h5 \\
        --trials 2,6,10 --gammas 1e-4,1e-3,1e-2,1e-1,1
"""

import argparse

import jax
import numpy as np

import pipps


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="+")
    ap.add_argument("--trials", default="2,6,10")
    ap.add_argument("--gammas", default="1e-4,1e-3,1e-2,1e-1,1")
    ap.add_argument("--particles", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    pipps.enable_float64()
    from pipps.particles import RolloutConfig
    from pipps.propagation import estimate, init_estimator_state, thesis_estimator
    from pipps.studies import load_snapshot

    gammas = [float(g) for g in args.gammas.split(",")]
    cfg = RolloutConfig(num_particles=args.particles)
    print("| snapshot | γ | steps whose weight the bound raised | mean k_LR, TP | mean k_LR, robust |")
    print("|---|---|---|---|---|")
    for path in args.files:
        for trial in (int(t) for t in args.trials.split(",")):
            snap = load_snapshot(path, trial)
            ests = {"tp": thesis_estimator("tp")} | {g: thesis_estimator("tp", combiner="robust", robust_gamma=g) for g in gammas}
            fns = {n: jax.jit(lambda k, s, e=e: estimate(k, s, snap.policy, snap.model, problem=snap.task, config=cfg,
                                                         estimator=e)[1].diagnostics.k_lr) for n, e in ests.items()}
            k = {n: [] for n in ests}
            for r in range(args.repeats):
                key = jax.random.PRNGKey(r)
                for n, e in ests.items():
                    st = init_estimator_state(jax.random.PRNGKey(100 + r), snap.policy, snap.model, problem=snap.task,
                                              config=cfg, estimator=e)
                    k[n].append(np.asarray(fns[n](key, st)))
            base = np.array(k["tp"])
            for g in gammas:
                rob = np.array(k[g])
                raised = float(np.mean(rob > base + 1e-12))
                print(f"| {path.split('/')[-1]} trial {trial} | {g:g} | {raised:.2f} | {base.mean():.3f} | {rob.mean():.3f} |",
                      flush=True)


if __name__ == "__main__":
    main()
