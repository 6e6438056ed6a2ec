#!/usr/bin/env bash
# Table 4.4 (unicycle balancing): TP, thesis preset (5 random + 30 learned trials), seeds 0-3
# (docs/results.md: seeds 0-3 ran one per pinned core, about 2 h each).
set -euo pipefail
out=${1:-results/thesis}
pipps sweep --table 4.4 --methods tp --seeds 4 --jobs 2 --out "$out"
pipps table "$out" --table 4.4
