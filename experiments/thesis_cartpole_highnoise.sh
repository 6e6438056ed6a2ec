#!/usr/bin/env bash
# Table 4.1 (cart-pole swing-up, Angle Cost) at high observation noise, k = 9 and k = 16: TP and PILCO,
# thesis preset, seeds 0-19 (the thesis' central claim). One sweep per k, each pinned to its
# own core; resumable (complete files are skipped, unfinished ones resume from their last finished trial).
#   experiments/thesis_cartpole_highnoise.sh [OUT]      # default results/thesis
set -euo pipefail
out=${1:-results/thesis}
taskset -c 0 pipps sweep --table 4.1 --k 9 --methods tp,pilco --seeds 20 --jobs 1 --out "$out" &
taskset -c 1 pipps sweep --table 4.1 --k 16 --methods tp,pilco --seeds 20 --jobs 1 --out "$out" &
wait
pipps table "$out" --table 4.1
