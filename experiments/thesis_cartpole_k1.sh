#!/usr/bin/env bash
# Table 4.1 (cart-pole swing-up, Angle Cost), k = 1: TP and PILCO, thesis preset, seeds 0-4.
# Resumable: complete result files in the output folder are skipped.
set -euo pipefail
out=${1:-results/thesis}
pipps sweep --table 4.1 --k 1 --methods tp,pilco --seeds 5 --jobs 2 --out "$out"
pipps table "$out" --table 4.1
