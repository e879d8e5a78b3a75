#!/usr/bin/env bash
# The long, resumable training run of the context correlation network (bundle 0.5 weights; see
# bundles/cbct_ct_rigid/docs/README.md, "Training the next weights").
#   usage: [DATA=data] [SHARED=../shared/data] [DEVICE=cpu|cuda] [BATCH=4] [EPOCH_LENGTH=100] [WORKERS=1] \
#          [SAMPLER_DEVICE=cpu|cuda] [CASES=12] [SIM_DEVICE=cpu|cuda] [INIT=weights.pt [INIT_PARTIAL=1]] \
#          [[CHANGE_ANATOMY=1] ANATOMY_PROB=0..1] [[CHANGE_ORIENTATION=1] ORIENTATION_PROB=0..1 [ORIENTATION_MAX=deg]] \
#          scripts/train_context_model.sh [RUN_DIR] [EPOCHS] [--resume]
# First call: simulates the training data when it is missing (scripts/make_training_data.sh, about 8 minutes on
# 2 cores; scripts/make_clinical_training_data.py, about 10 minutes), then trains from scratch. Resumed (3rd argument
# --resume): continues from the newest checkpoint in RUN_DIR/models (epoch, optimizer, learning-rate schedule,
# samples seen and wall time included); without a checkpoint there it stops with exit status 2 and writes nothing.
# A new run into a folder that holds an earlier run also stops with exit status 2 (use --resume or another folder).
# PREPARE_DATA_ONLY=1: the same checks and the missing data, then exit 0 without training (nothing written in RUN_DIR).
# INIT (a new run only): start the network from these weights (a model.pt or a training checkpoint) instead of from
# scratch; INIT_PARTIAL=1 takes only the tensors whose names and shapes match (a changed design keeping trained parts).
# ANATOMY_PROB: the share of samples whose anatomy is the CT stretched per axis (RigidPairSampler's anatomy_prob,
# default 0); a run's value is kept in RUN_DIR/anatomy_prob and reused on --resume (another value: exit status 2).
# CHANGE_ANATOMY=1 with --resume and ANATOMY_PROB: the run goes on from its checkpoint with this value instead
# (optimizer, schedule, samples seen kept); RUN_DIR/anatomy_prob_history gets a line "epoch N: OLD -> NEW" (N: the
# first epoch trained with NEW), so the run's docs can say which samples saw which data.
# ORIENTATION_PROB, ORIENTATION_MAX: the share of samples whose anatomy is turned about the isocentre in both images
# and the largest angle per axis (RigidPairSampler's orientation_prob, orientation_max; default 0 and 15 degrees); a
# run's values are kept in RUN_DIR/orientation ("PROB MAX") and reused on --resume (other values: exit status 2; one
# of the two left out: the run's own; ORIENTATION_MAX alone for a new run: exit status 2).
# CHANGE_ORIENTATION=1 with --resume and ORIENTATION_PROB and/or ORIENTATION_MAX: the run goes on with these values
# instead (a run without the option counts as '0 15'); RUN_DIR/orientation_history gets "epoch N: OLD -> NEW".
# One epoch = 100 iterations of batch 4 = 400 samples; 750 epochs = 300 000 samples.
# Held out of training (never read here): thorax_4dct_phase00_itkelastix, head_tigre_ct (and the stock Shepp-Logan
# phantom, the validation set), unless TRAIN_CT_NAMES names them (a leave-one-CT-out fold: scripts/train_loco.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/checkpoints.sh
DATA=${DATA:-data}
SHARED=${SHARED:-../shared/data}
RUN=${1:-training/context_run}
EPOCHS=${2:-750}
RESUME=${3:-}
DEVICE=${DEVICE:-cpu}
BATCH=${BATCH:-4}
EPOCH_LENGTH=${EPOCH_LENGTH:-100}
WORKERS=${WORKERS:-1}
SAMPLER_DEVICE=${SAMPLER_DEVICE:-cpu}  # cuda: samples drawn on the GPU (then WORKERS=0)
CASES=${CASES:-12}                     # clinical training pairs per CT
SIM_DEVICE=${SIM_DEVICE:-cpu}
INIT=${INIT:-}
INIT_PARTIAL=${INIT_PARTIAL:-0}
TRAIN_CTS=(abdomen_pelvis_totalsegmentator_example_ct head_tcia_cptac_lscc_ct thorax_tcia_cptac_pda_ct
           abdomen_pelvis_tcia_tcga_ov_ct)
# TRAIN_CT_NAMES (space-separated file stems in SHARED) replaces the list: a leave-one-CT-out fold
# (scripts/train_loco.sh), which may train on the held-out pair and holds out another CT
if [ -n "${TRAIN_CT_NAMES:-}" ]; then read -r -a TRAIN_CTS <<< "$TRAIN_CT_NAMES"; fi
cts=()
for name in "${TRAIN_CTS[@]}"; do
    f="$SHARED/$name.nii.gz"
    [ -f "$f" ] || { echo "train_context_model: missing training CT $f" >&2; exit 2; }
    cts+=("$(realpath "$f")")
done
if [ -n "$RESUME" ] && [ "$RESUME" != "--resume" ]; then
    echo "train_context_model: the third argument must be --resume, got '$RESUME'" >&2; exit 2
fi
if [ -n "$INIT" ] && [ ! -f "$INIT" ]; then
    echo "train_context_model: INIT=$INIT: no such file" >&2; exit 2
fi
if [ -n "$INIT" ] && [ -n "$RESUME" ]; then
    echo "train_context_model: INIT starts a new run; a resumed run continues from its checkpoint" >&2; exit 2
fi
same_number() { awk -v a="$1" -v b="$2" 'BEGIN { exit !(a + 0 == b + 0) }'; }
# the orientation first: its checks need no python
orientation_change=""  # "OLD -> NEW" (CHANGE_ORIENTATION=1)
kept_orientation=""  # "PROB MAX" of the run in RUN (none: a run without the option, 0 15)
[ -f "$RUN/orientation" ] && kept_orientation=$(cat "$RUN/orientation")
orientation=$kept_orientation
if [ -n "${ORIENTATION_PROB:-}" ] || [ -n "${ORIENTATION_MAX:-}" ]; then
    if [ -z "${ORIENTATION_PROB:-}" ] && [ -z "$kept_orientation" ] && [ -z "$RESUME" ]; then
        echo "train_context_model: ORIENTATION_MAX without ORIENTATION_PROB turns nothing: give both" >&2; exit 2
    fi
    read -r k_prob k_max <<< "${kept_orientation:-0 15}"
    o_prob=${ORIENTATION_PROB:-$k_prob}; o_max=${ORIENTATION_MAX:-$k_max}  # one left out: the run's own
    [[ "$o_prob" =~ ^[0-9]*\.?[0-9]+$ ]] && [[ "$o_max" =~ ^[0-9]*\.?[0-9]+$ ]] \
        && awk -v p="$o_prob" -v m="$o_max" 'BEGIN { exit !(p + 0 <= 1 && m + 0 <= 180) }' || {
        echo "train_context_model: ORIENTATION_PROB must be in [0, 1] and ORIENTATION_MAX in [0, 180] degrees," \
             "got '$o_prob' and '$o_max'" >&2; exit 2; }
    if { [ -n "$kept_orientation" ] || [ -n "$RESUME" ]; } \
            && ! { same_number "$k_prob" "$o_prob" && same_number "$k_max" "$o_max"; }; then
        if [ "${CHANGE_ORIENTATION:-0}" != 1 ] || [ -z "$RESUME" ]; then
            echo "train_context_model: $RUN was trained with ORIENTATION_PROB ORIENTATION_MAX '$k_prob $k_max', not" \
                 "'$o_prob $o_max': nothing was changed (CHANGE_ORIENTATION=1 with --resume continues it with them)" >&2
            exit 2
        fi
        orientation_change="$k_prob $k_max -> $o_prob $o_max"
    fi
    orientation="$o_prob $o_max"
fi
if [ "${CHANGE_ORIENTATION:-0}" = 1 ] && { [ -z "$RESUME" ] || [ -z "${orientation_change:-}" ]; }; then
    echo "train_context_model: CHANGE_ORIENTATION=1 changes a resumed run's orientation: give --resume and" \
         "ORIENTATION_PROB and/or ORIENTATION_MAX other than the run's" >&2; exit 2
fi
[ -n "$orientation" ] && read -r o_prob o_max <<< "$orientation"
if [ -n "$RESUME" ]; then
    if ! ls "$RUN"/models/checkpoint_*epoch=*.pt >/dev/null 2>&1; then
        echo "train_context_model: --resume: no checkpoint in $RUN/models to resume from" >&2; exit 2
    fi
    # the checkpoint must hold this config's network (same parameter names and shapes)
    python - "$RUN/models" <<'PY' || exit 2
import re, sys
from pathlib import Path
import torch
from monai.bundle import ConfigParser
ckpts = sorted(Path(sys.argv[1]).glob("checkpoint_*epoch=*.pt"), key=lambda p: int(re.search(r"epoch=(\d+)", p.name)[1]))
try:
    state = torch.load(ckpts[-1], map_location="cpu", weights_only=True)["network"]
except Exception as exc:  # unreadable, or not a training checkpoint
    sys.exit(f"train_context_model: --resume: {ckpts[-1]} is not a readable training checkpoint ({exc})")
parser = ConfigParser()
parser.read_config(["bundles/cbct_ct_rigid/configs/train.json", "bundles/cbct_ct_rigid/configs/train_context.json"])
want = {k: tuple(v.shape) for k, v in parser.get_parsed_content("network_def").state_dict().items()}
have = {k: tuple(v.shape) for k, v in state.items()}
if want != have:
    diff = sorted(set(want) ^ set(have)) or sorted(k for k in want if want[k] != have[k])
    sys.exit(f"train_context_model: --resume: {ckpts[-1]} holds another network than the config's "
             f"(first differences: {', '.join(diff[:3])}): nothing was changed")
PY
elif [ -e "$RUN/history.json" ] || ls "$RUN"/models/checkpoint_*epoch=*.pt >/dev/null 2>&1; then
    echo "train_context_model: $RUN holds an earlier run: continue it with --resume, or choose another folder" >&2
    exit 2
fi
CHANGE_ANATOMY=${CHANGE_ANATOMY:-0}
if [ "$CHANGE_ANATOMY" = 1 ] && { [ -z "$RESUME" ] || [ -z "${ANATOMY_PROB:-}" ]; }; then
    echo "train_context_model: CHANGE_ANATOMY=1 changes a resumed run's ANATOMY_PROB: give both --resume and" \
         "ANATOMY_PROB" >&2; exit 2
fi
kept=0
[ -f "$RUN/anatomy_prob" ] && kept=$(cat "$RUN/anatomy_prob")
change_from=""  # the first epoch trained with the changed value (CHANGE_ANATOMY=1)
if [ -n "$RESUME" ] && [ -n "${ANATOMY_PROB:-}" ] && ! same_number "$ANATOMY_PROB" "$kept"; then
    if [ "$CHANGE_ANATOMY" != 1 ]; then
        echo "train_context_model: $RUN was trained with ANATOMY_PROB=$kept, not $ANATOMY_PROB: nothing was changed" \
             "(CHANGE_ANATOMY=1 continues it with the new value)" >&2
        exit 2
    fi
    change_from=$(($(newest_epoch "$RUN") + 1))
elif [ -f "$RUN/anatomy_prob" ]; then
    if [ -n "${ANATOMY_PROB:-}" ] && ! same_number "$ANATOMY_PROB" "$kept"; then
        echo "train_context_model: $RUN was trained with ANATOMY_PROB=$kept, not $ANATOMY_PROB: nothing was changed" >&2
        exit 2
    fi
    ANATOMY_PROB=$kept
fi
export OMP_WAIT_POLICY=PASSIVE
if [ ! -f "$DATA/train.json" ]; then
    scripts/make_training_data.sh "$DATA" "$SHARED"
fi
if [ ! -f "$DATA/clinical/dataset.json" ]; then
    OMP_NUM_THREADS=1 python scripts/make_clinical_training_data.py --output-dir "$DATA/clinical" \
        --cases "$CASES" --threads 1 --device "$SIM_DEVICE" "${cts[@]}"
fi
if [ "${PREPARE_DATA_ONLY:-0}" = 1 ]; then  # the checks and the data, no training (scripts/train_loco.sh)
    exit 0
fi
list() { local out="[" sep=""; for v in "$@"; do out+="$sep'$v'"; sep=","; done; echo "$out]"; }
mkdir -p "$RUN"
if [ -n "$change_from" ]; then
    echo "epoch $change_from: $kept -> $ANATOMY_PROB" >> "$RUN/anatomy_prob_history"
    echo "$ANATOMY_PROB" > "$RUN/anatomy_prob"
elif [ -n "${ANATOMY_PROB:-}" ] && [ ! -f "$RUN/anatomy_prob" ]; then
    echo "$ANATOMY_PROB" > "$RUN/anatomy_prob"
fi
if [ -n "${orientation_change:-}" ]; then
    echo "epoch $(($(newest_epoch "$RUN") + 1)): $orientation_change" >> "$RUN/orientation_history"
    echo "$orientation" > "$RUN/orientation"
elif [ -n "${orientation:-}" ] && [ ! -f "$RUN/orientation" ]; then
    echo "$orientation" > "$RUN/orientation"
fi
python -m monai.bundle run \
    --config_file "['bundles/cbct_ct_rigid/configs/train.json','bundles/cbct_ct_rigid/configs/train_context.json']" \
    --bundle_root bundles/cbct_ct_rigid --output_dir "$RUN" --ckpt_dir "$RUN/models" \
    --train_datalists "$(list "$(realpath "$DATA/train.json")" "$(realpath "$DATA/clinical/dataset.json")")" \
    --train_cts "$(list "${cts[@]}")" --val_datalist "$DATA/val_paper/dataset.json" \
    --epochs "$EPOCHS" --seed 0 --device "\$torch.device('$DEVICE')" --batch_size "$BATCH" \
    --epoch_length "$EPOCH_LENGTH" --num_workers "$WORKERS" --train#dataset#device "$SAMPLER_DEVICE" \
    --resume "$([ -n "$RESUME" ] && echo True || echo False)" \
    ${ANATOMY_PROB:+--train#dataset#anatomy_prob "$ANATOMY_PROB"} \
    ${orientation:+--train#dataset#orientation_prob "$o_prob" --train#dataset#orientation_max "$o_max"} \
    ${INIT:+--init_weights "$(realpath "$INIT")" --init_partial "$([ "$INIT_PARTIAL" = 1 ] && echo True || echo False)"} \
    2>&1 | tee -a "$RUN/train_log.txt"
