#!/usr/bin/env bash
# Issue 20's learning runs: the library's TP (since 222cbac: "previous" baseline, leave-one-out k_LR)
# on Table 4.1 (cart-pole swing-up, Angle Cost) at k = 1 and k = 9, 10 seeds each, thesis preset
# otherwise. The thesis' rule (eq. 4.3 baseline, same-batch k_LR) is the thesis-preset TP cells of
# results/thesis. One sweep per k, each pinned to its own core; resumable.
#   experiments/library_tp_learning.sh [OUT]      # default results/library-tp
set -euo pipefail
out=${1:-results/library-tp}
taskset -c 0 pipps sweep --table 4.1 --k 1 --methods tp --seeds 10 --jobs 1 --set estimator_choices=library --out "$out" &
taskset -c 1 pipps sweep --table 4.1 --k 9 --methods tp --seeds 10 --jobs 1 --set estimator_choices=library --out "$out" &
wait
pipps table "$out" --table 4.1 --custom
