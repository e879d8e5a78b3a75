#!/usr/bin/env bash
# The main training run measured while it goes on: its newest checkpoint's learned network alone on the held-out CTs
# (thorax_4dct_phase00_itkelastix, head_tigre_ct), with the commands of the bundle docs' "Where the run stands"
# (bundles/cbct_ct_rigid/docs/context_network.md):
#   1. the checkpoint copied to scratch/ (the run keeps only its newest), exported as a bundle (4 passes, as shipped);
#   2. bench_generalisation_gap: 200 draws of the training sampler from the trained-on and from the held-out CTs
#      (paired against BASELINE, an earlier checkpoint's .json, where given);
#   3. bench_real_ct: the paper protocol, 21 cases per held-out CT;
#   4. bench_clinical_geometry: 4 small, 4 large and 4 deformed pairs per held-out CT (seed 1500).
#   usage: [SHARED=../shared/data] [BASELINE=earlier.json] scripts/eval_main_run.sh [RUN_DIR] [RESULTS_DIR]
# RUN_DIR defaults to training/context_run_v3, RESULTS_DIR to benchmarks/results/0.6.3.dev; files
# <bench>_main_e<epoch>_<date>.txt (and the gap's .json). Exit status 2, nothing written, for a run folder without a
# checkpoint or a BASELINE that is not a file. About 15 minutes on 2 cores beside the run (the pairs simulated once,
# into bench_out/).
set -euo pipefail
cd "$(dirname "$0")/.."
RUN=${1:-training/context_run_v3}
OUT=${2:-benchmarks/results/0.6.3.dev}
SHARED=${SHARED:-../shared/data}
BASELINE=${BASELINE:-}
source scripts/checkpoints.sh
ckpt=$(newest_checkpoint "$RUN")
if [ -z "$ckpt" ]; then
    echo "eval_main_run: no checkpoint in $RUN/models" >&2; exit 2
fi
if [ -n "$BASELINE" ] && [ ! -f "$BASELINE" ]; then
    echo "eval_main_run: BASELINE $BASELINE is not a file" >&2; exit 2
fi
epoch=$(newest_epoch "$RUN")
day=$(date -u +%F)
name="$(basename "$RUN")_e${epoch}"
mkdir -p scratch "$OUT"
cp "$ckpt" "scratch/${name}.pt"
python scripts/export_context_bundle.py "scratch/${name}.pt" "scratch/${name}" --passes 4 1
gap_args=()
[ -n "$BASELINE" ] && gap_args=(--baseline "$BASELINE")
python -m benchmarks.accuracy.bench_generalisation_gap "scratch/${name}.pt" --samples 200 --shared "$SHARED" \
    "${gap_args[@]}" --results "$OUT/bench_generalisation_gap_main_e${epoch}_${day}.txt"
python -m benchmarks.accuracy.bench_real_ct --methods network-regression --num-cases 21 --threads 1 \
    --ct "$SHARED/thorax_4dct_phase00_itkelastix.nii.gz" "$SHARED/head_tigre_ct.nii.gz" \
    --output-dir bench_out/real_ct_42 --bundle "scratch/${name}" \
    --results "$OUT/bench_real_ct_heldout_main_e${epoch}_network_alone_${day}.txt"
python -m benchmarks.accuracy.bench_clinical_geometry --groups small large deformed --cases-per-group 4 \
    --cts thorax_4dct_phase00_itkelastix head_tigre_ct --output-dir bench_out/clinical --threads 1 \
    --methods network-regression --bundle "scratch/${name}" \
    --results "$OUT/bench_clinical_geometry_heldout_main_e${epoch}_network_alone_${day}.txt"
echo "eval_main_run: epoch $epoch measured, results in $OUT"
