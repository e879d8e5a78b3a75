#!/usr/bin/env bash
# The learned network alone of one leave-one-CT-out fold (scripts/train_loco.sh) on its held-out CT: the fold's
# newest checkpoint exported as a bundle (the 8 mm level's 4 passes, as shipped), then the paper protocol (12 cases,
# bench_real_ct) and clinical geometry (4 small + 4 large pairs, bench_clinical_geometry) with
# --methods network-regression, the fold's five CTs labelled as its training CTs (BENCH_TRAINED_ON). With
# SHIPPED=1 the shipped network alone on the same cases too, for the row beside it (it trained on the four TCIA and
# TotalSegmentator CTs, so on those it is not held out).
#   usage: [SHARED=../shared/data] [SHIPPED=0|1] scripts/eval_loco.sh HOLD_OUT [RUN_DIR] [RESULTS_DIR]
# RUN_DIR defaults to training/loco/HOLD_OUT, RESULTS_DIR to benchmarks/results/loco; the exported bundle goes to
# scratch/<RUN_DIR's parent folder name>_<HOLD_OUT>_e<epoch>, the simulated pairs to bench_out/. Exit status 2 for an
# unknown HOLD_OUT or a fold without a checkpoint. Ends with the table of every fold evaluated so far
# (benchmarks/accuracy/loco_table.py).
# About 5 minutes on 2 cores (the pairs simulated once).
set -euo pipefail
cd "$(dirname "$0")/.."
HOLD=${1:-}
[ -n "$HOLD" ] || { echo "usage: scripts/eval_loco.sh HOLD_OUT [RUN_DIR] [RESULTS_DIR]" >&2; exit 2; }
RUN=${2:-training/loco/$HOLD}
OUT=${3:-benchmarks/results/loco}
SHARED=${SHARED:-../shared/data}
source scripts/loco_split.sh
source scripts/checkpoints.sh
loco_split eval_loco "$HOLD"
ckpt=$(newest_checkpoint "$RUN")
if [ -z "$ckpt" ]; then
    echo "eval_loco: no checkpoint in $RUN/models (train the fold first: scripts/train_loco.sh $HOLD)" >&2; exit 2
fi
epoch=$(newest_epoch "$RUN")
bundle="scratch/$(basename "$(dirname "$RUN")")_${HOLD}_e${epoch}"  # scratch/loco_<HOLD>_e<epoch> for training/loco
day=$(date -u +%F)
mkdir -p "$OUT"
python scripts/export_context_bundle.py "$ckpt" "$bundle" --passes 4 1
export BENCH_TRAINED_ON="${others[*]}"
python -m benchmarks.accuracy.bench_real_ct --ct "$SHARED/$HOLD.nii.gz" --methods network-regression --num-cases 12 \
    --threads 1 --output-dir bench_out/real_ct --bundle "$bundle" \
    --results "$OUT/bench_real_ct_loco_${HOLD}_e${epoch}_${day}.txt"
python -m benchmarks.accuracy.bench_clinical_geometry --groups small large --cases-per-group 4 --cts "$HOLD" \
    --output-dir bench_out/clinical --threads 1 --methods network-regression --bundle "$bundle" \
    --results "$OUT/bench_clinical_geometry_loco_${HOLD}_e${epoch}_${day}.txt"
if [ "${SHIPPED:-0}" = 1 ]; then
    unset BENCH_TRAINED_ON
    python -m benchmarks.accuracy.bench_real_ct --ct "$SHARED/$HOLD.nii.gz" --methods network-regression \
        --num-cases 12 --threads 1 --output-dir bench_out/real_ct \
        --results "$OUT/bench_real_ct_loco_${HOLD}_shipped_${day}.txt"
    python -m benchmarks.accuracy.bench_clinical_geometry --groups small large --cases-per-group 4 --cts "$HOLD" \
        --output-dir bench_out/clinical --threads 1 --methods network-regression \
        --results "$OUT/bench_clinical_geometry_loco_${HOLD}_shipped_${day}.txt"
fi
python -m benchmarks.accuracy.loco_table --results-dir "$OUT" --runs-dir "$(dirname "$RUN")"
echo "eval_loco: results in $OUT (fold $HOLD, epoch $epoch)"
