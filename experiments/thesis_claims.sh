#!/usr/bin/env bash
# The thesis' other claims (docs/results.md, "The thesis' claims"): Table 4.1's k = 1 row (RP
# against TP in chaos), the Tip Cost at k = 1 (Tables 4.2-4.3, Gaussian shaping), Table 4.3's
# Angle Cost GTP and GLR, Table 4.4 (unicycle) and DEL on the balancing task; thesis preset.
#
#   experiments/thesis_claims.sh [OUT] [WORKERS]     # default results/thesis, 2 workers
#   CORE=1 experiments/thesis_claims.sh OUT            # one worker pinned to core 1 (join a running queue)
#
# To stop it: end the worker shells first, then the sweeps (`kill PID` stops a sweep as Ctrl-C
# does, its file written as interrupted; a worker shell would otherwise start the next entry):
#   pkill -f thesis_claims.sh; pkill -TERM -f "pipps sweep"
#
# One ordered queue of sweeps, walked by WORKERS processes each pinned to its own core: two sweeps
# share a folder through the result files' locks, so a worker skips the experiment another runs
# and takes the next. Resumable: complete files are skipped, an unfinished file continues after
# its last finished trial (copy results/in-progress/* into OUT first).
#
# Order: the claims in the order of docs/results.md, breadth first (seeds 0-4 of a group's cells before seeds 5-9).
# The first entries, written when a GPU was expected for the batchable cells, ran the CPU-only ones
# (PILCO, the fixed-seed quasi-Newton methods) first; they are complete. On a lent GPU, run the
# batchable cells with experiments/gpu_concurrent_cells.sh (its runs are in results/README.md): this
# queue skips every file that is complete there.
set -uo pipefail
out=${1:-results/thesis}
workers=${2:-2}
queue=(
  # group 1: Table 4.1, Angle Cost, k = 1 (RP, LR, GR ran on a GPU; TP has 10 seeds)
  "--table 4.1 --k 1 --methods rp_fs,gr_fs --seeds 5"
  "--table 4.1 --k 1 --methods pilco --seeds 10"
  # group 2: Tip Cost, k = 1 (Tables 4.2 and 4.3 share these runs): PILCO, TP and GTP first, the
  # cells of the claim "Gaussian shaping lets particles match PILCO" (GTP's sweep also runs the
  # Angle Cost GTP of group 3); they run on the CPU because no GPU may be lent
  "--table 4.2 --k 1 --methods pilco --seeds 5"
  "--table 4.2 --k 1 --methods tp --seeds 5"
  # PILCO's Tip Cost policies balance without observation noise and lose the pole with it
  # (docs/results.md, claim 3): the same cell with PILCO V0.9's policy-input noise term, beside the
  # Table 4.1 cells in the sibling folder pilco-noise/
  "--table 4.2 --k 1 --methods pilco --seeds 5 --set pilco_policy_noise=true --out {parent}/pilco-noise"
  "--table 4.3 --k 1 --methods gtp --seeds 5"
  # The rest group by group, breadth first: seeds 0-4 of every cell of a group before
  # seeds 5-9 of any (few tasks are lent a GPU, so the batchable cells are not left to wait for one).
  # group 1: TP-sigma_f, the one cell of Table 4.1's k = 1 row without 5 seeds, then seeds 5-9
  "--table 4.1 --k 1 --methods tp-sf --seeds 5"
  "--table 4.1 --k 1 --methods rp_fs,gr_fs --seeds 10"
  "--table 4.1 --k 1 --methods tp-sf --seeds 10"
  # groups 2-3: Tip Cost GR, then GLR on both costs (Table 4.3's sweep runs Tip and Angle)
  "--table 4.2 --k 1 --methods gr --seeds 5"
  "--table 4.3 --k 1 --methods glr --seeds 5"
  # then seeds 0-4 of the cells no run has reached, so that at any stop every claim has a
  # comparable count (the issue's breadth-first order across groups, not only within one):
  # group 5, DEL on cart-pole balancing, TP beside it (their learning curves, thesis Fig. 4.17a):
  # the thesis preset's DEL (its fit's derivative down the whole pathwise chain), then the library's
  # (one step to θ, consistent; docs/estimator-bias.md) in the sibling folder del-library/
  "--table del --methods del,tp --seeds 5"
  "--table del --methods del --seeds 5 --set estimator_choices=library --out {parent}/del-library"
  # DEL_c (each step's own cost as the weight, down the whole chain; a third reading, code >= the
  # commit that added the method `del-cost`: older code refuses the entry and the worker goes on)
  "--table del --methods del-cost --seeds 5"
  # group 4: unicycle, 5 seeds per cell
  "--table 4.4 --methods pilco --seeds 5"
  "--table 4.4 --methods rp,lr,tp --seeds 5"
  # last, seeds 5-9 of groups 2-3
  "--table 4.2 --k 1 --methods pilco --seeds 10"
  "--table 4.2 --k 1 --methods tp,gr --seeds 10"
  "--table 4.3 --k 1 --methods gtp,glr --seeds 10"
  # beyond the issue's 5 seeds: group 4 to 10 (about 2 core-hours per unicycle run), PILCO and TP
  # first, the pair that decides claim 4
  "--table 4.4 --methods pilco,tp --seeds 10"
  "--table 4.4 --methods rp,lr --seeds 10"
)
worker() {
  local core=$1 q
  for q in "${queue[@]}"; do
    # an entry with its own --out names a folder beside OUT ({parent}); the others write into OUT
    if [[ $q == *"--out "* ]]; then q=${q//\{parent\}/$(dirname "$out")}; else q="$q --out $out"; fi
    # shellcheck disable=SC2086
    taskset -c "$core" pipps sweep $q --jobs 1
  done
}
if [ -n "${CORE:-}" ]; then worker "$CORE"; exit; fi
for ((w = 0; w < workers; w++)); do worker "$w" & done
wait
pipps table "$out"
