#!/usr/bin/env bash
# Every leave-one-CT-out fold of issue 32 in turn, each taken up where it stopped, so that after a restart the same
# command goes on: a fold whose newest checkpoint is epoch EPOCHS and whose evaluation at that epoch is in RESULTS is
# done (skipped); one at EPOCHS without it is evaluated (scripts/eval_loco.sh); one with an earlier checkpoint is
# resumed (scripts/train_loco.sh HOLD_OUT RUN EPOCHS --resume), then evaluated; one without a checkpoint is started
# (its data, the coarse pretraining where RUN/init.pt is missing, the full loss), then evaluated. The shipped network's
# rows for a CT are measured with its fold's evaluation where RESULTS has none (SHIPPED=1 of eval_loco.sh).
#   usage: [SHARED=../shared/data] [DATA=data] [LOCO_DATA=data_loco] [RUNS=training/loco] \
#          [RESULTS=benchmarks/results/loco] [DRY_RUN=1] scripts/loco_folds.sh [EPOCHS] [HOLD_OUT ...]
# EPOCHS defaults to 50 (20 000 samples of the full loss); the folds run in the order given, by default the six real
# CTs (monai_rigidreg.io.shared_data: the training CTs, then the held-out pair). DRY_RUN=1 prints each fold's state
# and next step and runs nothing. Exit status 2 for an unknown HOLD_OUT (before anything runs) or a fold that another
# process is training already; a fold's training or evaluation failing stops the script with its exit status.
set -euo pipefail
cd "$(dirname "$0")/.."
EPOCHS=${1:-50}
shift || true
[[ "$EPOCHS" =~ ^[1-9][0-9]*$ ]] || { echo "loco_folds: EPOCHS must be a positive integer, got '$EPOCHS'" >&2; exit 2; }
RUNS=${RUNS:-training/loco}
RESULTS=${RESULTS:-benchmarks/results/loco}
source scripts/loco_split.sh
source scripts/checkpoints.sh
loco_real
folds=("$@")
[ ${#folds[@]} -gt 0 ] || folds=("${REAL[@]}")
for hold in "${folds[@]}"; do  # every name checked before any fold runs
    (loco_others loco_folds "$hold") || exit 2
done

for hold in "${folds[@]}"; do
    run="$RUNS/$hold"
    epoch=$(newest_epoch "$run")
    evaluated=0
    ls "$RESULTS"/bench_real_ct_loco_"${hold}"_e"${EPOCHS}"_*.txt >/dev/null 2>&1 \
        && ls "$RESULTS"/bench_clinical_geometry_loco_"${hold}"_e"${EPOCHS}"_*.txt >/dev/null 2>&1 && evaluated=1
    shipped=1
    ls "$RESULTS"/bench_real_ct_loco_"${hold}"_shipped_*.txt >/dev/null 2>&1 && shipped=0
    if [ "$epoch" -ge "$EPOCHS" ] && [ "$evaluated" = 1 ]; then
        step="done"
    elif [ "$epoch" -ge "$EPOCHS" ]; then
        step="evaluate"
    elif [ "$epoch" -gt 0 ]; then
        step="resume from epoch $epoch, then evaluate"
    else
        step="start, then evaluate"
    fi
    echo "loco_folds: $hold: newest checkpoint epoch $epoch of $EPOCHS; next: $step" \
         "(the shipped network's rows: $([ "$shipped" = 1 ] && echo "to measure" || echo "measured"))"
    [ "${DRY_RUN:-0}" = 1 ] && continue
    if [ "$step" != done ] && pgrep -f "train_loco.sh $hold" >/dev/null 2>&1; then
        echo "loco_folds: $hold is training in another process already (pgrep -af 'train_loco.sh $hold'); stopping" >&2
        exit 2
    fi
    case "$step" in
        done) continue ;;
        resume*) scripts/train_loco.sh "$hold" "$run" "$EPOCHS" --resume ;;
        start*) scripts/train_loco.sh "$hold" "$run" "$EPOCHS" ;;
    esac
    SHIPPED=$shipped scripts/eval_loco.sh "$hold" "$run" "$RESULTS"
done
