#!/usr/bin/env bash
# PILCO with release V0.9's policy-input noise term (pilco_policy_noise=true, docs/pilco.md) on
# Table 4.1 at k = 9 and 16, thesis preset otherwise: does the term move PILCO's learning toward
# the thesis' rates? One sweep per core, sharing the folder through the files' locks; resumable.
#   experiments/pilco_policy_noise_learning.sh [OUT] [SEEDS]     # default results/pilco-noise, 10 seeds
# First measured on the stored models: experiments/pilco_policy_noise.py (docs/results.md).
set -euo pipefail
out=${1:-results/pilco-noise}
seeds=${2:-10}
for core in 0 1; do
  taskset -c "$core" pipps sweep --table 4.1 --k 9,16 --methods pilco --seeds "$seeds" \
      --set pilco_policy_noise=true --jobs 1 --out "$out" &
done
wait
# both settings side by side, paired by seed
pipps table "$out" results/thesis --table 4.1 --by pilco_policy_noise --per-seed
