#!/usr/bin/env bash
# Every GPU throughput figure of the training step in one command, on a machine with CUDA and gsplat:
#
#   bash benchmarks/gpu_throughput.sh [OUT] [PART ...]        # OUT defaults to outputs/gpu-throughput
#
# Parts (all by default, in this order); each writes OUT/<part>.md (and a loss curve OUT/<part>.csv):
#   tests        the gpu-marked tests: gsplat-vs-torch parity, a CUDA fit in bf16-mixed, predict, bench
#   render       benchmarks/bench_gsplat_overhead.py --batch 10: render(backend="gsplat") against gsplat itself
#   eager        the paper config (conf/re10k.yaml) eager with foreach AdamW, 200 timed steps: the baseline
#   eager-again  the same run again: how far two identical runs drift apart (the yardstick for the others)
#   tuned        the config as shipped (regional compile, fused AdamW), compared with eager's losses
#   bf16-heads   tuned + model.net.options.head_precision=bf16, compared with eager's losses
#   fit          `aesplat fit -c CONFIG` itself on synthetic shards, FIT_STEPS steps (default 300): median seconds
#                per step after the first FIT_WINDOW-step window (compilation), samples/s, peak memory and skipped
#                steps, read from the run's own logs (benchmarks/fit_throughput.py; also OUT/fit.json; the shards
#                in OUT/shards, the run in OUT/fit/run)
#   fit-N        the same fit at N context views (N >= 2) with the pooled appearance head
#                (--data.num_context_views N --model.net.view_aggregation pool): OUT/fit-N.md and .json
#   peer         benchmarks/peer_step.py: this project's network and NAS3R's (its code in PEER_SOURCE, default
#                .peer/nas3r), forward + backward without the render, batch 10, 2 + 1 views, 224², bf16,
#                one after the other in one process (PEER_RUNS, default "nas3r aesplat aesplat-compiled"; each
#                PEER_STEPS steps, default 20, after WARMUP): OUT/peer.md and OUT/peer.json
# Parts not named run in this order: tests render eager eager-again tuned bf16-heads fit fit-3 fit-4 fit-6 peer.
# A part whose .md exists is skipped, so an interrupted run resumes where it stopped; delete a file to redo
# that part. STEPS (default 200), WARMUP (5), SEED (0) and CONFIG (conf/re10k.yaml) change the runs; PYTHON
# picks the interpreter (default .venv/bin/python, else python3). DEVICE=cpu runs the training parts on the
# CPU (a rehearsal of the script with a small CONFIG; the tests and render parts need CUDA).
set -euo pipefail
cd "$(dirname "$0")/.."

OUT=${1:-outputs/gpu-throughput}
shift || true
PARTS=${*:-}
STEPS=${STEPS:-200}
WARMUP=${WARMUP:-5}
SEED=${SEED:-0}
CONFIG=${CONFIG:-conf/re10k.yaml}
FIT_STEPS=${FIT_STEPS:-300}
FIT_WINDOW=${FIT_WINDOW:-50}
DEVICE=${DEVICE:-cuda}
if [[ -z ${PYTHON:-} ]]; then
    if [[ -x .venv/bin/python ]]; then PYTHON=.venv/bin/python; else PYTHON=python3; fi
fi
export PYTHONUNBUFFERED=1
ALL_PARTS="tests render eager eager-again tuned bf16-heads fit fit-3 fit-4 fit-6 peer"
PEER_SOURCE=${PEER_SOURCE:-.peer/nas3r}
PEER_STEPS=${PEER_STEPS:-20}
PEER_RUNS=${PEER_RUNS:-nas3r aesplat aesplat-compiled}
if [[ $DEVICE == cpu ]]; then
    PARTS=${PARTS:-eager eager-again tuned bf16-heads fit fit-3}
    [[ " $PARTS " != *" tests "* && " $PARTS " != *" render "* ]] || {
        echo "gpu_throughput.sh: the tests and render parts need CUDA (DEVICE=cpu)" >&2
        exit 2
    }
fi
PARTS=${PARTS:-$ALL_PARTS}
for part in $PARTS; do
    [[ " $ALL_PARTS " == *" $part "* || ($part =~ ^fit-[0-9]+$ && ${part#fit-} -ge 2) ]] || {
        echo "gpu_throughput.sh: unknown part '$part'; the parts are: $ALL_PARTS (fit-N for any N >= 2)" >&2
        exit 2
    }
done

[[ $DEVICE == cpu ]] || "$PYTHON" -c 'import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)' || {
    echo "gpu_throughput.sh: CUDA is not available to $PYTHON; these measurements need a GPU" >&2
    exit 2
}
mkdir -p "$OUT"
"$PYTHON" - >"$OUT/versions.txt" <<'EOF'
import os, subprocess, sys
sys.path.insert(0, "benchmarks")
from common import versions
commit = os.environ.get("AESPLAT_COMMIT") or subprocess.run(  # a copy of the tree names its commit
    ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
v = versions()
print(f"commit {commit or 'unknown'}; {v['device']}; torch {v['torch']}; gsplat {v['gsplat']}; "
      f"lightning {v['lightning']}")
EOF
cat "$OUT/versions.txt"

bench() {  # bench PART [bench_train_step.py options]
    local part=$1
    shift
    "$PYTHON" benchmarks/bench_train_step.py -c "$CONFIG" --device "$DEVICE" --steps "$STEPS" --warmup "$WARMUP" \
        --seed "$SEED" --losses "$OUT/$part.csv" "$@"
}

# eager and eager-again must be the same run: their difference is the yardstick for the others.
EAGER=(--set model.net.compile=none --set model.optim.impl=foreach)

run_part() {
    case $1 in
        tests) "$PYTHON" -m pytest -q -rs -m gpu -p no:cacheprovider ;;
        render) "$PYTHON" benchmarks/bench_gsplat_overhead.py --batch 10 ;;
        eager) bench eager "${EAGER[@]}" ;;
        eager-again) bench eager-again "${EAGER[@]}" --compare "$OUT/eager.csv" ;;
        tuned) bench tuned --compare "$OUT/eager.csv" ;;
        bf16-heads) bench bf16-heads --set model.net.options.head_precision=bf16 --compare "$OUT/eager.csv" ;;
        fit | fit-*)
            rm -rf "${OUT:?}/$1/run"  # a failed or interrupted fit starts again
            local extra=()
            [[ $1 == fit ]] || extra=(--data.num_context_views "${1#fit-}" --model.net.view_aggregation pool)
            [[ $DEVICE != cpu ]] || extra+=(--trainer.accelerator cpu --trainer.precision 32-true)
            "$PYTHON" benchmarks/fit_throughput.py -c "$CONFIG" --out "$OUT/$1" --shards "$OUT" \
                --steps "$FIT_STEPS" --window "$FIT_WINDOW" --json "$OUT/$1.json" -- "${extra[@]}"
            ;;
        peer)
            local extra=()
            [[ $DEVICE != cpu ]] || extra=(--batch 1 --size 56 --precision fp32)
            "$PYTHON" benchmarks/peer_step.py --source "$PEER_SOURCE" --config "$CONFIG" --device "$DEVICE" \
                --steps "$PEER_STEPS" --warmup "$WARMUP" --runs $PEER_RUNS --out "$OUT/peer.json" "${extra[@]}"
            ;;
    esac
}

for part in $PARTS; do
    if [[ -s $OUT/$part.md ]]; then
        echo "== $part: done before ($OUT/$part.md), skipped"
        continue
    fi
    if [[ $part == eager-again || $part == tuned || $part == bf16-heads ]] && [[ ! -s $OUT/eager.csv ]]; then
        echo "gpu_throughput.sh: $part compares with $OUT/eager.csv; run the eager part first" >&2
        exit 2
    fi
    echo "== $part"
    start=$(date +%s)
    # The .md appears only when the part succeeded: a failed or interrupted part runs again next time.
    run_part "$part" 2>&1 | tee "$OUT/$part.log"
    echo "($part: $(($(date +%s) - start)) s)" | tee -a "$OUT/$part.log"
    mv "$OUT/$part.log" "$OUT/$part.md"
done
echo "== all parts done: $OUT"
