#!/usr/bin/env bash
# The thesis' table cells, breadth first: one worker per core walks experiments/cells.queue (the
# order, and what each entry runs) with `pipps sweep ... --jobs 1`, pinned with taskset.
#
#   experiments/thesis_cells.sh [OUT] [WORKERS]    # default runs/cells, 2 workers (cores 0..WORKERS-1)
#   CORE=1 experiments/thesis_cells.sh OUT          # one worker pinned to core 1 (join a running queue)
#   experiments/thesis_cells.sh --status [OUT]      # what is done: per entry, complete files of all it names
#
# Two workers share OUT through the result files' locks: a worker skips the experiment the other
# runs and takes the next. After every entry that ran something a worker starts again from the top
# of the queue file, so entries added above the one it was on are taken next; it stops after a pass
# in which nothing ran. Resumable: complete files are skipped and an unfinished one continues after
# its last finished trial (copy results/in-progress/* of this queue into OUT first).
#
# To stop it: end the worker shells first, then the sweeps (a sweep stopped by SIGTERM writes its
# file as interrupted, resumable):   pkill -f thesis_cells.sh; pkill -TERM -f "pipps sweep"
set -uo pipefail
here=$(cd "$(dirname "$0")" && pwd)
queue_file=${QUEUE_FILE:-$here/cells.queue}
entries() { sed -e 's/#.*//' -e 's/[[:space:]]*$//' -e '/^[[:space:]]*$/d' "$queue_file"; }

if [ "${1:-}" = "--status" ]; then
  out=${2:-runs/cells}
  while IFS= read -r q; do
    # shellcheck disable=SC2086
    line=$(pipps sweep $q --out "$out" --dry-run 2>&1 | head -1)
    printf '%-60s %s\n' "$q" "${line%% with *}"
  done < <(entries)
  exit 0
fi

out=${1:-runs/cells}
workers=${2:-2}
worker() {
  local core=$1 q start ran
  while :; do
    ran=0
    while IFS= read -r q; do
      start=$SECONDS
      # shellcheck disable=SC2086
      taskset -c "$core" pipps sweep $q --out "$out" --jobs 1 </dev/null
      # an entry that took more than two minutes ran something: read the queue again from the top
      if ((SECONDS - start > 120)); then ran=1; break; fi
    done < <(entries)
    ((ran)) || break
  done
}
if [ -n "${CORE:-}" ]; then worker "$CORE"; exit; fi
for ((w = 0; w < workers; w++)); do worker "$w" & done
wait
pipps table "$out"
