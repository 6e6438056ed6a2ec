#!/usr/bin/env bash
# One lent-GPU session's fixed protocol (docs/performance.md, "Many seeds at once"): the device's
# float64 GEMM rates, a smoke run of the vmapped batch, then one table cell's seeds as one batch
# under a time limit; result files and timings come back through $OUT.
#
#   PIPPS_CODE_VERSION=$(git rev-parse HEAD) CELL_SECONDS=400 \
#     bash experiments/gpu_batched_cell.sh --table 4.1 --k 9 --methods tp --seeds 10 --seed-start 10 \
#     --set estimator_choices=library
#
# The lent machine gets the working tree, at most 64 MiB: results/ (~115 MB) is over that, so move it
# out of the checkout for the call and back afterwards (git sees it deleted meanwhile; commit nothing then).
# Runs from a copied source tree (no install: PYTHONPATH), the device's own jax. Files are written
# after every finished trial, so a cell cut off by CELL_SECONDS resumes from them elsewhere.
set -u
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
OUT=${OUT:-/tmp/gpu_out}; mkdir -p "$OUT"
CELL=/tmp/gpu_cell; mkdir -p "$CELL"
t0=$(date +%s)
nvidia-smi --query-gpu=name,memory.total,clocks.sm,clocks.max.sm --format=csv,noheader
python3 benchmarks/machine.py 8192 400x300 40x300  # the device's float64 GEMM rates
if [ "${SMOKE:-1}" = 1 ]; then
echo "== smoke: quick preset, 2 seeds, 1 learned trial, vmapped ($(( $(date +%s) - t0 )) s)"
timeout 150 python3 -m pipps.cli sweep --table 4.1 --k 1 --methods tp --seeds 2 --preset quick \
    --set num_learned=1 --batched --batching vmap --out /tmp/gpu_smoke > "$OUT/smoke.log" 2>&1
rc=$?; tail -n 15 "$OUT/smoke.log"; echo "smoke rc=$rc"
[ $rc -eq 0 ] || exit $rc
python3 experiments/trial_timings.py /tmp/gpu_smoke/*.h5
fi
left=$(( ${CELL_SECONDS:-400} ))
echo "== cell: $* (limit $left s, started at $(( $(date +%s) - t0 )) s)"
timeout "$left" python3 -m pipps.cli sweep "$@" --batched --batching vmap --out "$CELL" > "$OUT/cell.log" 2>&1
echo "cell rc=$?"; tail -n 20 "$OUT/cell.log"
python3 experiments/trial_timings.py "$CELL"/*.h5 2>&1 | head -n 60
(cd "$CELL" && tar czf /tmp/cell.tgz --exclude='.*.lock' .) && split -b 15m -d /tmp/cell.tgz "$OUT/cell.tgz.part"
ls -la "$OUT"; echo "total $(( $(date +%s) - t0 )) s"
