#!/usr/bin/env bash
# benchmarks/gpu_throughput.sh on a GPU machine without network, the project's packages installed from wheels:
#
#   bash benchmarks/gpu_offline.sh WHEELS OUT [PART ...]
#
# WHEELS holds what the project needs beyond the machine's own torch, Lightning and test tools, made
# beforehand where the package index can be reached by scripts/gpu_wheels.sh (kornia, jsonargparse,
# omegaconf, webdataset, and gsplat compiled for the machine's Python, torch, CUDA and GPU). They are
# installed into a folder of their own (SITE, default /tmp/aesplat-site) without an index or dependency
# resolution, and the code runs from this tree's src/. The parts (default: tests fit fit-3 fit-4 fit-6 peer,
# the most wanted first) run one by one in WORK (default /tmp/gpu-throughput), each under its own time limit
# when LIMITS names one ("tests=150 peer=120", seconds), in a process group of its own that is stopped whole
# when the part ends or reaches its limit (TERM, then KILL after GRACE seconds, default 15), so that no
# process of one part holds the GPU in the next; after each, OUT/reports.tgz is rewritten whole with
# every report, figure file, run log and the versions made so far, and OUT/progress.log holds the output. So
# a run stopped at any point leaves in OUT all it finished. A part that fails or runs out of time is
# reported and the next one runs. The exit status is that of the last part that failed (0 if none did).
# AESPLAT_COMMIT names the commit of the tree (a copy sent to the machine may carry no git, or a stale one);
# the figure files record it. DEVICE=cpu rehearses it on a CPU with CONFIG=conf/smoke.yaml (gpu_throughput.sh).
set -uo pipefail
cd "$(dirname "$0")/.."

[[ $# -ge 2 ]] || { echo "usage: bash benchmarks/gpu_offline.sh WHEELS OUT [PART ...]" >&2; exit 2; }
WHEELS=$1 OUT=$2
shift 2
PARTS=${*:-tests fit fit-3 fit-4 fit-6 peer}
SITE=${SITE:-/tmp/aesplat-site}
WORK=${WORK:-/tmp/gpu-throughput}
PYTHON=${PYTHON:-python3}
GRACE=${GRACE:-15}
export PYTHON PYTHONUNBUFFERED=1
compgen -G "$WHEELS/*.whl" >/dev/null || { echo "gpu_offline.sh: no wheels in $WHEELS" >&2; exit 2; }
mkdir -p "$OUT" "$WORK"
exec > >(tee -a "$OUT/progress.log") 2>&1

start=$(date +%s)
"$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" \
    "$WHEELS"/*.whl || { echo "gpu_offline.sh: the wheels in $WHEELS did not install"; exit 2; }
export PYTHONPATH="$PWD/src:$SITE${PYTHONPATH:+:$PYTHONPATH}"
echo "installed $(ls "$WHEELS" | wc -l) wheels into $SITE in $(($(date +%s) - start)) s"

pack() {  # every report, figure file, run log and the versions made so far, replaced whole
    (cd "$WORK" && find . -maxdepth 3 -not -path './shards/*' -not -path './src/*' \( -name '*.md' -o \
        -name '*.log' -o -name '*.json' -o -name '*.txt' -o -name '*.csv' \) -print0 |
        tar -czf "$OUT/reports.tgz.part" --null -T -) && mv "$OUT/reports.tgz.part" "$OUT/reports.tgz"
}

run_part() {  # run_part LIMIT PART: in a process group of its own, so nothing it started outlives it
    local limit=$1 part=$2 waited=0
    # A background job of a script leads no process group, so setsid makes it the leader of a new process
    # group whose id is its pid.
    setsid bash benchmarks/gpu_throughput.sh "$WORK" "$part" &
    local pid=$!
    current=$pid
    while kill -0 "$pid" 2>/dev/null; do
        if [[ $limit -gt 0 && $waited -ge $limit ]]; then
            stop_group "$pid"
            wait "$pid" 2>/dev/null
            current=
            return 124
        fi
        sleep 1
        waited=$((waited + 1))
    done
    wait "$pid"
    local code=$?
    stop_group "$pid"  # whatever the part left running (a fit that outlived its benchmark holds the GPU)
    current=
    return $code
}

stop_group() {  # TERM to the whole group, KILL to what is left after GRACE seconds
    kill -TERM -- "-$1" 2>/dev/null || return 0
    for _ in $(seq "$GRACE"); do
        kill -0 -- "-$1" 2>/dev/null || return 0
        sleep 1
    done
    kill -KILL -- "-$1" 2>/dev/null || true
}

current=
# Stopped itself (a time limit, Ctrl-C): the running part goes whole, and what was finished is packed.
trap 'trap - TERM INT; echo "gpu_offline.sh: stopped"; [[ -z $current ]] || stop_group "$current"; pack; exit 143' \
    TERM INT

status=0
for part in $PARTS; do
    limit=0
    for entry in ${LIMITS:-}; do [[ ${entry%%=*} != "$part" ]] || limit=${entry#*=}; done
    part_start=$(date +%s)
    run_part "$limit" "$part"
    code=$?
    if [[ $code -eq 124 ]]; then
        echo "gpu_offline.sh: $part stopped at its limit of $limit s"
    elif [[ $code -ne 0 ]]; then
        echo "gpu_offline.sh: $part failed (exit $code)"
    fi
    [[ $code -eq 0 ]] || status=$code
    echo "== $part: $(($(date +%s) - part_start)) s; $(($(date +%s) - start)) s since the start"
    pack
done
exit $status
