#!/usr/bin/env bash
# Several table cells on one lent GPU at once: one process per cell, each cell's seeds as one
# vmapped batch (`pipps sweep --batched --batching vmap`), all processes running concurrently so
# that one device call advances several cells (docs/performance.md, "Several cells at once").
#
#   PIPPS_CODE_VERSION=$(git rev-parse HEAD) CELL_SECONDS=540 bash experiments/gpu_concurrent_cells.sh \
#       "--table 4.1 --k 1 --methods rp --seeds 10" \
#       "--table 4.1 --k 1 --methods lr --seeds 10" \
#       "--table 4.1 --k 1 --methods gr --seeds 10"
#
# Each argument is one sweep's options (one cell). The batched path is bound by its sequence of
# small kernels, not by flops, so processes overlap on the GPU; the script samples the GPU's
# utilisation and memory every 5 s (gpu.csv) so the overlap can be read back. Memory is not
# preallocated (each process takes what it uses). Files are written after every finished trial:
# a cell cut off by CELL_SECONDS resumes from them anywhere (`pipps sweep` with the same options).
# The lent machine gets the working tree (at most 64 MiB): move results/ out for the call.
set -u
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
export XLA_PYTHON_CLIENT_PREALLOCATE=false
OUT=${OUT:-/tmp/gpu_out}; mkdir -p "$OUT"
CELLS=/tmp/gpu_cells; mkdir -p "$CELLS"
t0=$(date +%s)
nvidia-smi --query-gpu=name,memory.total,clocks.sm,clocks.max.sm --format=csv,noheader
nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv,noheader -l 5 > "$OUT/gpu.csv" 2>/dev/null &
smi=$!
python3 benchmarks/machine.py 8192 40x300  # the device's float64 GEMM rates
ncpu=$(nproc); n=$#; per=$(( ncpu / (n > 0 ? n : 1) )); [ "$per" -ge 1 ] || per=1
i=0; pids=()
for cell in "$@"; do
    lo=$(( i * per )); hi=$(( lo + per - 1 ))
    mkdir -p "$CELLS/$i"
    echo "== cell $i: $cell (cores $lo-$hi, limit ${CELL_SECONDS:-540} s, at $(( $(date +%s) - t0 )) s)"
    # shellcheck disable=SC2086
    taskset -c "$lo-$hi" timeout "${CELL_SECONDS:-540}" python3 -m pipps.cli sweep $cell --batched --batching vmap \
        --out "$CELLS/$i" > "$OUT/cell$i.log" 2>&1 &
    pids+=($!); i=$(( i + 1 ))
done
for j in "${!pids[@]}"; do wait "${pids[$j]}"; echo "cell $j rc=$? at $(( $(date +%s) - t0 )) s"; done
kill "$smi" 2>/dev/null
for j in $(seq 0 $(( n - 1 ))); do
    echo "== cell $j"; tail -n 5 "$OUT/cell$j.log"
    python3 experiments/trial_timings.py "$CELLS/$j"/*.h5 2>&1 | head -n 40
done
(cd "$CELLS" && tar czf /tmp/cells.tgz --exclude='.*.lock' .) && split -b 15m -d /tmp/cells.tgz "$OUT/cells.tgz.part"
ls -la "$OUT"; echo "total $(( $(date +%s) - t0 )) s"
