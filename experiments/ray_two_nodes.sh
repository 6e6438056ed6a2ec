#!/usr/bin/env bash
# A pipps sweep on a two-node Ray cluster, run for real on one Linux machine.
#
# Two network namespaces joined by a veth pair stand in for two machines: "head" (10.231.0.1) and
# "worker" (10.231.0.2). Each namespace has only its loopback and its end of the pair, and no route
# anywhere else, so the cluster's traffic goes between these two addresses and nowhere else. Each
# node's Ray processes also get a hostname of their own (a UTS namespace), so a result file's
# /versions/host says which node ran it, as it would on two real machines.
#
# The recipe for real machines is the part marked RECIPE below; the rest only builds the two
# "machines". docs/experiments.md ("Sweeps on a Ray cluster") walks through it, and
# tests/test_ray_cluster.py runs this script (up, on, kill-raylet, down).
#
# Usage (as root; needs `ip` and `unshare`):
#   experiments/ray_two_nodes.sh demo                # up, a small sweep through both addresses, down
#   experiments/ray_two_nodes.sh up                  # make the machines, start both nodes
#   experiments/ray_two_nodes.sh on head|worker CMD… # run CMD on that machine (with the cluster's token)
#   experiments/ray_two_nodes.sh kill-raylet worker  # that node dies (its raylet gets SIGKILL)
#   experiments/ray_two_nodes.sh down                # stop both nodes, remove the machines
# Environment: PIPPS_CLUSTER_DIR (token, Ray's temp folders and logs, the demo's results; default
# /tmp/pipps-ray: Ray's socket paths must stay under 108 characters), PIPPS_CLUSTER_NAME (the
# namespaces' prefix; default pipps-ray), PYTHON (the interpreter with pipps and ray[client]).
set -euo pipefail

DIR=${PIPPS_CLUSTER_DIR:-/tmp/pipps-ray}
NAME=${PIPPS_CLUSTER_NAME:-pipps-ray}
PYTHON=${PYTHON:-python3}
REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
HEAD_IP=10.231.0.1
WORKER_IP=10.231.0.2
HEAD_PORT=6379           # the cluster address: HEAD_IP:6379
CLIENT_PORT=10001        # the Ray Client address: ray://HEAD_IP:10001

ns() { echo "$NAME-$1"; }                      # the namespace of machine head|worker
ip_of() { [ "$1" = head ] && echo "$HEAD_IP" || echo "$WORKER_IP"; }

# Every node and every launching process sees the same settings: token authentication, with the
# token in a file (on real machines: the same file copied to each, or RAY_AUTH_TOKEN); pipps and
# Ray from this checkout's interpreter.
export RAY_AUTH_MODE=token
export RAY_AUTH_TOKEN_PATH="$DIR/auth_token"
unset RAY_AUTH_TOKEN RAY_ADDRESS               # a token or an address from the caller's environment would win
export RAY_USAGE_STATS_ENABLED=0
export PYTHONPATH="$REPO${PYTHONPATH:+:$PYTHONPATH}"

make_machines() {
    # two namespaces, a veth pair with one end in each (created there, never in this namespace)
    ip netns add "$(ns head)"
    ip netns add "$(ns worker)"
    ip link add eth-head netns "$(ns head)" type veth peer name eth-worker netns "$(ns worker)"
    for m in head worker; do
        ip -n "$(ns $m)" addr add "$(ip_of $m)/24" dev "eth-$m"
        ip -n "$(ns $m)" link set lo up
        ip -n "$(ns $m)" link set "eth-$m" up
    done
}

on() {  # on MACHINE CMD…: run CMD in that machine's network namespace
    local machine=$1
    shift
    ip netns exec "$(ns "$machine")" "$@"
}

start_node() {  # start_node MACHINE RAY-START-OPTIONS…: `ray start` there, its processes named after the machine
    local machine=$1
    shift
    on "$machine" unshare --uts sh -c 'hostname "$0" && exec "$@"' "$NAME-$machine" \
        "$PYTHON" -m ray.scripts.scripts start "$@"
}

up() {
    mkdir -p "$DIR"
    make_machines
    # RECIPE 1. One token for the whole cluster (any secret string; `ray get-auth-token --generate`
    # makes one in ~/.ray/auth_token). Every node and every machine that launches a sweep needs it,
    # with RAY_AUTH_MODE=token; a node or a driver without it is refused.
    if [ ! -s "$RAY_AUTH_TOKEN_PATH" ]; then
        (umask 077 && "$PYTHON" -c 'import secrets; print(secrets.token_hex(32), end="")' > "$RAY_AUTH_TOKEN_PATH")
    fi
    # RECIPE 2. The head node (on a real machine: without --node-ip-address and --temp-dir). One CPU
    # per node here: each sweep task reserves one CPU, so a node runs as many experiments at once as
    # it has CPUs.
    start_node head --head --node-ip-address "$HEAD_IP" --port "$HEAD_PORT" \
        --ray-client-server-port "$CLIENT_PORT" --num-cpus 1 --object-store-memory 100000000 \
        --include-dashboard false --disable-usage-stats --temp-dir "$DIR/h"
    # RECIPE 3. Each worker node joins through the head's address.
    start_node worker --address "$HEAD_IP:$HEAD_PORT" --node-ip-address "$WORKER_IP" --num-cpus 1 \
        --object-store-memory 100000000 --disable-usage-stats --temp-dir "$DIR/w"
}

kill_raylet() {  # the node dies: SIGKILL its raylet (its workers notice and exit)
    local pid
    for pid in $(ip netns pids "$(ns "$1")"); do
        if [ "$(cat "/proc/$pid/comm" 2>/dev/null)" = raylet ]; then
            kill -KILL "$pid"
            echo "killed the raylet of $1 (pid $pid)"
        fi
    done
}

down() {
    # RECIPE 5. On real machines: `ray stop` on every node. Here every process of each machine's
    # namespace is killed by its pid (`ray stop` would stop every Ray process of this computer, by
    # name), then the namespaces go, and the veth pair with them.
    local m n pids
    for m in head worker; do
        [ -e "/run/netns/$(ns $m)" ] || continue
        for n in $(seq 100); do
            pids=$(ip netns pids "$(ns $m)")
            [ -z "$pids" ] && break
            kill -KILL $pids 2>/dev/null || true
            sleep 0.1
        done
        if [ -n "$(ip netns pids "$(ns $m)")" ]; then
            echo "$(ns $m): processes still running: $(ip netns pids "$(ns $m)")" >&2
            return 1
        fi
        ip netns del "$(ns $m)"
    done
}

demo() {
    trap down EXIT
    up
    local sweep=(-m pipps.cli sweep --table 4.1 --k 1 --methods tp --seeds 2 --preset quick
                 --set num_particles=8 --set num_learned=1 --set policy_evals=4 --set eval_rollouts=2 --jobs 2 --backend ray)
    # RECIPE 4. Launch the sweep from a node, through the cluster address ...
    on head "$PYTHON" "${sweep[@]}" --address "$HEAD_IP:$HEAD_PORT" --out "$DIR/runs/gcs"
    # ... or from any machine that can reach the head, through the Ray Client. --out is a folder
    # every node and the launching machine see at the same path (here: one filesystem).
    on worker "$PYTHON" "${sweep[@]}" --address "ray://$HEAD_IP:$CLIENT_PORT" --out "$DIR/runs/client"
    "$PYTHON" - "$DIR/runs" <<'EOF'
import sys
from pathlib import Path

import h5py

for path in sorted(Path(sys.argv[1]).glob("*/*.h5")):
    with h5py.File(path) as f:
        print(f"{path}: {f.attrs['status']}, ran on {f['versions'].attrs['host']}")
EOF
}

case "${1:-demo}" in
    demo) demo ;;
    up) up ;;
    down) down ;;
    on) shift; on "$@" ;;
    kill-raylet) kill_raylet "${2:?kill-raylet head|worker}" ;;
    *) echo "usage: $0 demo | up | down | on head|worker CMD… | kill-raylet head|worker" >&2; exit 2 ;;
esac
