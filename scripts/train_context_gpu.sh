#!/usr/bin/env bash
# Continue the context network's training run on a GPU for at most MINUTES minutes (default 9), from the newest
# checkpoint of RUN_DIR (the CPU run's folder, carried to the GPU machine), and bring back its checkpoint, history and
# log. The same bundle config and sampler as scripts/train_context_model.sh, with the samples drawn on the GPU, a
# larger batch and the simulation of missing training data on the GPU too.
#   usage: [MINUTES=9] [BATCH=16] [DATA=data] [SHARED=../shared/data] [DEVICE=cuda] \
#          scripts/train_context_gpu.sh RUN_DIR [OUT_DIR]
# The training stops itself at the time limit (SIGTERM: the checkpoint of the last complete epoch stays); OUT_DIR
# (default RUN_DIR) receives the newest checkpoint, history.json, curves.png and train_log.txt.
# On the CPU at a tiny size: DEVICE=cpu MINUTES=2 BATCH=2 EPOCH_LENGTH=2 CASES=1 (MINUTES=1 ends before its first
# epoch). Its own steps (--resume only where RUN_DIR holds a checkpoint, the newest by epoch brought back, the exit
# status) are tested with a stand-in training script (tests/test_training_cts.py); the training itself is
# scripts/train_context_model.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/checkpoints.sh
RUN=${1:?usage: scripts/train_context_gpu.sh RUN_DIR [OUT_DIR]}
OUT=${2:-$RUN}
MINUTES=${MINUTES:-9}
export DEVICE=${DEVICE:-cuda}
export BATCH=${BATCH:-16}
export EPOCH_LENGTH=${EPOCH_LENGTH:-25}  # 400 samples an epoch at batch 16, as on the CPU (100 x 4)
export SAMPLER_DEVICE=${SAMPLER_DEVICE:-$DEVICE}
export SIM_DEVICE=${SIM_DEVICE:-$DEVICE}
export WORKERS=${WORKERS:-0}  # samples drawn in the main process, on the device
resume=()
[ "$(newest_epoch "$RUN")" -gt 0 ] && resume=(--resume)
rc=0
timeout --signal=TERM "$((MINUTES * 60))" scripts/train_context_model.sh "$RUN" 100000 "${resume[@]}" || rc=$?
if [ "$rc" -ne 0 ] && [ "$rc" -ne 124 ]; then
    echo "train_context_gpu: training stopped with exit status $rc" >&2
    exit "$rc"
fi
if [ "$OUT" != "$RUN" ]; then
    mkdir -p "$OUT/models"
    newest=$(newest_checkpoint "$RUN")
    [ -n "$newest" ] && cp "$newest" "$OUT/models/"
    for f in history.json curves.png train_log.txt; do [ -f "$RUN/$f" ] && cp "$RUN/$f" "$OUT/"; done
fi
echo "train_context_gpu: stopped after ${MINUTES} min (exit status $rc); newest checkpoint in $OUT/models"
