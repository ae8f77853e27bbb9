#!/usr/bin/env bash
# The `make demo` pipeline; the Makefile passes its DEMO_* settings in the environment (see the Makefile).
#
#   synthetic scenes -> shards -> { step-0 test [+ random-init test] -> fit -> trained test
#                                   -> shards at twice the size -> test rendered at twice the size } (the method)
#                                 { step-0 test -> fit -> trained test }   (diagnostic, DEMO_DIAGNOSE=1)
#   -> bench -> report
#
# The diagnostic chain (the same model trained with the data set's cameras) runs beside the method's, in the
# background, its output in $DEMO_DIR/posed/log.txt: each fit uses one core (the thread policy gives each one
# thread: 2 cores - 1 data-loader worker), and the demo's wall time is about that of one chain instead of two. Every stage's seconds go to $DEMO_DIR/timings.csv, then the wall time of
# the whole pipeline. A failing stage stops the demo with its exit status, the diagnostic included.
set -euo pipefail

: "${PY:?}" "${AESPLAT:?}" "${DEMO_CONFIG:?}" "${DEMO_DIR:?}" "${DEMO_SIZE:?}"
DEMO_DIAGNOSE=${DEMO_DIAGNOSE:-1}
DEMO_VAL_SCENES=${DEMO_VAL_SCENES:-12}
read -r -a scene_args <<<"${DEMO_SCENE_ARGS:-}"
read -r -a fit_args <<<"${DEMO_FIT_ARGS:-}"
run=$DEMO_DIR/run
posed=$DEMO_DIR/posed
times=$DEMO_DIR/timings.csv
ckpt=$run/checkpoints/last.ckpt
args=(-c "$DEMO_CONFIG" --data.root "$DEMO_DIR/shards" --data.image_size "$DEMO_SIZE")
# Lightning's CSV logger writes metrics.csv (the loss curve: every step) and config.yaml into the run directory.
log=(--trainer.logger+=CSVLogger --trainer.logger.save_dir "$run" --trainer.logger.name ""
    --trainer.logger.version "" --trainer.log_every_n_steps 1)

stage() { # stage NAME COMMAND...: run it, then append "NAME,seconds" to the timings table
    local name=$1 t0=$SECONDS
    shift
    "$@"
    echo "$name,$((SECONDS - t0))" >>"$times"
}

diagnostic() {
    stage "diagnostic: test with the data set's cameras (step 0)" "$AESPLAT" test "${args[@]}" \
        --model.cameras dataset --trainer.default_root_dir "$posed/initial" --trainer.logger false
    stage "diagnostic: fit with the data set's cameras" "$AESPLAT" fit "${args[@]}" --model.cameras dataset \
        --trainer.default_root_dir "$posed/run" --trainer.logger false --trainer.enable_progress_bar false \
        "${fit_args[@]}"
    stage "diagnostic: test with the data set's cameras (trained)" "$AESPLAT" test "${args[@]}" \
        --trainer.default_root_dir "$posed/run" --trainer.logger false --ckpt_path "$posed/run/checkpoints/last.ckpt"
}

load_start=$(cut -d' ' -f1-3 /proc/loadavg 2>/dev/null || true)  # the machine's load, for demo.json
rm -rf "$run" "$DEMO_DIR/initial" "$DEMO_DIR/random" "$DEMO_DIR/bench" "$DEMO_DIR/transfer" "$DEMO_DIR/shards_2x" "$posed"
mkdir -p "$DEMO_DIR"
echo "stage,seconds" >"$times"

# 12 validation scenes (a seed stream of their own: the train and test scenes are the same with or without
# them): `aesplat fit` validates on them, never on the test scenes (docs/validation.md).
stage "synthetic scenes" "$PY" data_prep/synthetic.py --out "$DEMO_DIR/src" --val-scenes "$DEMO_VAL_SCENES" \
    "${scene_args[@]}"
stage "shards" "$PY" data_prep/to_shards.py --src "$DEMO_DIR/src" --out "$DEMO_DIR/shards" --size "$DEMO_SIZE"

diag_pid=
if [[ $DEMO_DIAGNOSE == 1 ]]; then
    mkdir -p "$posed"
    echo "demo: the diagnostic (training with the data set's cameras) runs beside the method; log: $posed/log.txt"
    diagnostic >"$posed/log.txt" 2>&1 &
    diag_pid=$!
    # Stopping the demo (an error above the wait, Ctrl-C) stops the diagnostic's commands too.
    trap '[[ -n $diag_pid ]] && { pkill -P "$diag_pid" 2>/dev/null; kill "$diag_pid" 2>/dev/null; } || true' EXIT
fi

stage "aesplat test (step 0)" "$AESPLAT" test "${args[@]}" --trainer.default_root_dir "$DEMO_DIR/initial" \
    --trainer.logger false
# A config that starts from weights (conf/demo.yaml: the warm start of `make warmstart`) is also tested from a
# random initialisation, the report's reference for the rotation error.
weights=$("$PY" -c "import sys; from omegaconf import OmegaConf; print(OmegaConf.load(sys.argv[1]).model.net.get('weights') or '')" "$DEMO_CONFIG")
if [[ -n $weights ]]; then
    stage "aesplat test (random initialisation)" "$AESPLAT" test "${args[@]}" --model.net.weights null \
        --trainer.default_root_dir "$DEMO_DIR/random" --trainer.logger false
fi
stage "aesplat fit" "$AESPLAT" fit "${args[@]}" --trainer.default_root_dir "$run" "${log[@]}" "${fit_args[@]}"
stage "aesplat test (trained)" "$AESPLAT" test "${args[@]}" --trainer.default_root_dir "$run" \
    --trainer.logger false --ckpt_path "$ckpt"
# The resolution transfer: the test scenes converted again at twice the size, the trained model rendering its
# targets at that size against them (and its own render upsampled), docs/evaluation.md.
stage "shards at twice the size" "$PY" data_prep/to_shards.py --src "$DEMO_DIR/src" --out "$DEMO_DIR/shards_2x" \
    --size $((2 * DEMO_SIZE))
stage "aesplat test (rendered at twice the size)" "$AESPLAT" test "${args[@]}" --data.root "$DEMO_DIR/shards_2x" \
    --data.eval_transfer_scale 2 --trainer.default_root_dir "$run" --trainer.logger false \
    --model.eval.output_dir "$DEMO_DIR/transfer" --ckpt_path "$ckpt"

# Each `aesplat test` writes into a folder of its own, RUN_DIR/test-<UTC time>; test-latest links the newest.
report=(--run-dir "$run" --initial "$DEMO_DIR/initial/test-latest" --bench "$DEMO_DIR/bench" --timings "$times"
    --transfer "$DEMO_DIR/transfer/test-latest" --out "$DEMO_DIR")
[[ -n $weights ]] && report+=(--random-init "$DEMO_DIR/random/test-latest")
[[ -n $load_start ]] && report+=(--load-start "$load_start")
# DEMO_RESULTS=docs/results/demo: the report also writes the files the documentation quotes its figures from.
[[ -n ${DEMO_RESULTS:-} ]] && report+=(--results "$DEMO_RESULTS")
if [[ -n $diag_pid ]]; then
    echo "demo: waiting for the diagnostic (log: $posed/log.txt)"
    if ! wait "$diag_pid"; then
        diag_pid=
        echo "demo: the diagnostic failed; the end of $posed/log.txt:" >&2
        tail -n 30 "$posed/log.txt" >&2
        exit 1
    fi
    diag_pid=
    report+=(--posed-initial "$posed/initial/test-latest" --posed-trained "$posed/run/test-latest")
fi
# After the diagnostic: the bench times renders, which a fit beside it would slow down.
stage "aesplat bench" "$AESPLAT" bench --ckpt "$ckpt" --out "$DEMO_DIR/bench"
echo "wall clock (whole pipeline),$SECONDS" >>"$times"
"$PY" scripts/demo_report.py "${report[@]}"
