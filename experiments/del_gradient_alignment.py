"""How well each reading of DEL points down the true gradient at a snapshot of a learning run.

    JAX_PLATFORMS=cpu taskset -c 1 python experiments/del_gradient_alignment.py \
        results/thesis/cartpole_balance_angle_k1_del_thesis_s0.h5 --trial 1 [--trial 3 ...]

At the optimisation start of each ``--trial`` (the policy and GP model the run had there,
:func:`pipps.studies.snapshot.load_snapshot`), each estimator makes ``--repeats`` independent
estimates at ``--particles`` (the run's own P by default), each from a fresh estimator state as at
an optimisation's first iteration. A reference gradient ``g_ref`` averages ``--reference-repeats``
estimates of the library's TP (nearly unbiased: its leave-one-out k_LR has an O(1/P) bias,
docs/estimator-variance.md) at ``--reference-particles``. Per estimator the script
prints:

* ``cos(E ĝ, g_ref)`` and ``E ĝ·g_ref / ‖g_ref‖²`` (± its 95 % Monte Carlo half-width over the
  repeats): the direction and size of its mean, i.e. its bias as seen by the learner (1 and 1 for
  an unbiased estimator, up to the Monte Carlo error; with a small SNR the mean's direction is
  itself uncertain, and the projection's interval says by how much);
* ``E cos(ĝ, g_ref)``: how well one raw estimate points;
* ``SNR = ‖E ĝ‖² / tr Cov ĝ``: signal against noise of one estimate, from the sample mean, so noise
  alone gives about 1/repeats: a value at or below that says no signal is detectable;
* ``max/median ‖ĝ‖``: how heavy the tail of the estimates' sizes is (a chain that explodes now and
  then makes a few estimates orders of magnitude larger than the rest).

The reference's own quality is printed beside it: the cosine between the means of its two halves
(a weak check where estimates are heavy-tailed: rare large ones that the reference's draws miss
would not show).
Estimators: the thesis preset's DEL (returns-to-go, the fit's derivative down the whole chain), the
library's DEL (one step to θ), DEL_c (own cost, whole chain), TP both ways, and the library's
BIW-LR: the same returns-to-go and the same one step to θ as the library's DEL, with the score of
the particles' exact one-step mixture density in place of a fitted Gaussian's, so that the two
differ only in the density.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from pipps.precision import enable_float64
from pipps.propagation.estimators import spec_label
from pipps.studies.gradients import estimator_program
from pipps.studies.snapshot import load_snapshot

#: (estimator, estimator_choices, label)
READINGS = (
    ("del", "thesis", "DEL, thesis preset (returns-to-go, whole chain)"),
    ("del", "library", "DEL, library (returns-to-go, one step)"),
    ("del_cost", "thesis", "DEL_c (own cost, whole chain)"),
    ("tp", "thesis", "TP, thesis preset"),
    ("tp", "library", "TP, library"),
    ("lr", "library", "BIW-LR, library (returns-to-go, one step, the mixture density)"),
)


def estimates(snap, name: str, choices: str, P: int, repeats: int, seed: int) -> np.ndarray:
    """(repeats, n_θ) independent gradient estimates at the snapshot's θ; rows with a non-finite entry dropped."""
    program = estimator_program(snap, name, P, choices)
    theta = jnp.asarray(snap.theta)
    key = jax.random.PRNGKey(seed)
    g = np.stack([np.asarray(program(jax.random.fold_in(key, r), theta)[0]) for r in range(repeats)])
    return g[np.all(np.isfinite(g), axis=1)]


def cosine(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (a @ b) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("result")
    ap.add_argument("--trial", type=int, action="append", required=True, help="learned trial (repeatable)")
    ap.add_argument("--particles", type=int, default=None, help="default: the run's num_particles")
    ap.add_argument("--repeats", type=int, default=100)
    ap.add_argument("--reference-particles", type=int, default=1000)
    ap.add_argument("--reference-repeats", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--readings", default=None,
                    help="comma-separated NAME:CHOICES of the estimators to run (default all: "
                         + ",".join(f"{n}:{c}" for n, c, _ in READINGS) + ")")
    args = ap.parse_args(argv)
    readings = list(enumerate(READINGS))
    if args.readings:
        wanted = [r.strip() for r in args.readings.split(",")]
        known = {f"{n}:{c}" for n, c, _ in READINGS}
        if unknown := [r for r in wanted if r not in known]:
            ap.error(f"--readings: unknown {', '.join(unknown)}; choose from {', '.join(sorted(known))}")
        readings = [(i, r) for i, r in readings if f"{r[0]}:{r[1]}" in wanted]
    if args.repeats < 2 or args.reference_repeats < 4:
        ap.error("--repeats must be >= 2 and --reference-repeats >= 4")
    enable_float64()
    for trial in args.trial:
        start = time.perf_counter()
        snap = load_snapshot(args.result, trial)
        P = args.particles or snap.config.num_particles
        ref = estimates(snap, "tp", "library", args.reference_particles, args.reference_repeats, args.seed + 1)
        g_ref = ref.mean(axis=0)
        half = len(ref) // 2
        halves = float(cosine(ref[:half].mean(axis=0), ref[half:].mean(axis=0)))
        print(f"\n{args.result}, trial {trial}: P = {P}, {args.repeats} estimates each; reference: library TP at "
              f"P = {args.reference_particles}, {len(ref)} estimates (cosine between its halves' means {halves:.3f}), "
              f"‖g_ref‖ = {np.linalg.norm(g_ref):.3g}\n")
        print("| estimator | finite | cos(E ĝ, g_ref) | E ĝ·g_ref / ‖g_ref‖² | E cos(ĝ, g_ref) | SNR ‖E ĝ‖² / tr Cov ĝ "
              "| max/median ‖ĝ‖ |")
        print("|---|---|---|---|---|---|---|")
        for i, (name, choices, label) in readings:  # i keeps each reading's keys whichever run
            g = estimates(snap, name, choices, P, args.repeats, args.seed + 10 + i)
            mean = g.mean(axis=0)
            per = cosine(g, g_ref)
            along = g @ g_ref / (g_ref @ g_ref)
            snr = float(mean @ mean / np.sum(np.var(g, axis=0, ddof=1)))
            sizes = np.linalg.norm(g, axis=1)
            print(f"| {label} | {len(g)}/{args.repeats} | {float(cosine(mean, g_ref)):+.3f} | "
                  f"{along.mean():+.3g} ± {1.96 * along.std(ddof=1) / np.sqrt(len(along)):.2g} | {per.mean():+.3f} ± {1.96 * per.std(ddof=1) / np.sqrt(len(per)):.3f} | "
                  f"{snr:.3g} | {sizes.max() / np.median(sizes):.3g} |")
        print(f"\n({spec_label('tp')} reference and {len(readings)} estimators in {time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
