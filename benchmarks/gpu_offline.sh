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
# when LIMITS names one ("tests=150 peer=120", seconds); after each, OUT/reports.tgz is rewritten whole with
# every report, figure file, run log and the versions made so far, and OUT/progress.log holds the output. So
# a run stopped at any point leaves in OUT all it finished. A part that fails or runs out of time is
# reported and the next one runs. The exit status is that of the last part that failed (0 if none did).
# DEVICE=cpu rehearses it on a CPU with CONFIG=conf/smoke.yaml (see gpu_throughput.sh).
set -uo pipefail
cd "$(dirname "$0")/.."

[[ $# -ge 2 ]] || { echo "usage: bash benchmarks/gpu_offline.sh WHEELS OUT [PART ...]" >&2; exit 2; }
WHEELS=$1 OUT=$2
shift 2
PARTS=${*:-tests fit fit-3 fit-4 fit-6 peer}
SITE=${SITE:-/tmp/aesplat-site}
WORK=${WORK:-/tmp/gpu-throughput}
PYTHON=${PYTHON:-python3}
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

status=0
for part in $PARTS; do
    limit=0
    for entry in ${LIMITS:-}; do [[ ${entry%%=*} != "$part" ]] || limit=${entry#*=}; done
    part_start=$(date +%s)
    timeout --signal=TERM --kill-after=15 "$limit" bash benchmarks/gpu_throughput.sh "$WORK" "$part"
    code=$?
    if [[ $code -eq 124 || $code -eq 137 ]]; then
        echo "gpu_offline.sh: $part stopped at its limit of $limit s"
    elif [[ $code -ne 0 ]]; then
        echo "gpu_offline.sh: $part failed (exit $code)"
    fi
    [[ $code -eq 0 ]] || status=$code
    echo "== $part: $(($(date +%s) - part_start)) s; $(($(date +%s) - start)) s since the start"
    pack
done
exit $status
