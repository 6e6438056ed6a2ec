#!/usr/bin/env bash
# Learning runs of the library's TP (since 222cbac: "previous" baseline, leave-one-out k_LR)
# on Table 4.1 (cart-pole swing-up, Angle Cost) at k = 1 and k = 9, thesis preset otherwise. The
# thesis' rule (eq. 4.3 baseline, same-batch k_LR) is the thesis-preset TP cells of results/thesis.
# One sweep per k, each pinned to its own core; resumable (complete files are skipped, a file with
# finished trials continues after them, results/in-progress/ holds unfinished ones to copy in).
#   experiments/library_tp_learning.sh [OUT] [SEEDS]     # default results/library-tp, 10 seeds
# What is committed: k = 1 seeds 0-9 and k = 9 seeds 0-5 from these sweeps (CPU), k = 9 seeds 10-19
# as one batch on a lent H100 (experiments/gpu_batched_cell.sh, docs/performance.md), so that k = 9
# pairs with the thesis rule's 20 seeds.
set -euo pipefail
out=${1:-results/library-tp}
seeds=${2:-10}
taskset -c 0 pipps sweep --table 4.1 --k 1 --methods tp --seeds "$seeds" --jobs 1 --set estimator_choices=library --out "$out" &
taskset -c 1 pipps sweep --table 4.1 --k 9 --methods tp --seeds "$seeds" --jobs 1 --set estimator_choices=library --out "$out" &
wait
# both rules side by side, paired by seed (rates with Wilson intervals, Newcombe differences, McNemar, Wilcoxon)
pipps table "$out" results/thesis --table 4.1 --by estimator_choices --per-seed
