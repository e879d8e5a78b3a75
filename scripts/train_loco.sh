#!/usr/bin/env bash
# One fold of the leave-one-CT-out table (issue 32): the context network trained from scratch, with the bundle's
# config and sampler (scripts/train_context_model.sh), on five of the six real CTs of SHARED (all but HOLD_OUT) and on
# the simulated phantom and synthetic-anatomy pairs of DATA except those simulated from HOLD_OUT, by the main run's
# recipe: the coarse level pretrained alone (scripts/pretrain_context_coarse.py, 6 400 samples, RUN_DIR/init.pt),
# then EPOCHS epochs of 400 samples of the full loss from those weights (default 50: 20 000 samples), checkpointed
# every epoch and resumable like the main run (--resume: the full-loss run from its newest checkpoint).
#   usage: [DATA=data] [SHARED=../shared/data] [LOCO_DATA=data_loco] [DEVICE=cpu|cuda] [BATCH=4] [EPOCH_LENGTH=100] \
#          [CASES=12] [SIM_DEVICE=cpu|cuda] [SAMPLER_DEVICE=cpu|cuda] [WORKERS=1] [PREPARE_ONLY=1] \
#          scripts/train_loco.sh HOLD_OUT [RUN_DIR] [EPOCHS] [--resume]
# HOLD_OUT: one of the six real CTs' file stems (python -c "from monai_rigidreg.io.shared_data import TRAINING_CTS,
# HELD_OUT_CTS; print(*TRAINING_CTS, *HELD_OUT_CTS)"). RUN_DIR defaults to training/loco/HOLD_OUT. The fold's data
# folder LOCO_DATA/HOLD_OUT gets the filtered train.json, a link to DATA/val_paper and its own clinical pairs of the
# five CTs (simulated on the first call, about 2-3 minutes per CT on 2 cores); PREPARE_ONLY=1 writes the filtered
# train.json and the link and prints the training command instead of running it. On a GPU (about 10 minutes a call):
#   DEVICE=cuda BATCH=16 EPOCH_LENGTH=25 SAMPLER_DEVICE=cuda SIM_DEVICE=cuda WORKERS=0 scripts/train_loco.sh HOLD_OUT
# Then the fold's network alone on its held-out CT (BENCH_TRAINED_ON labels the CTs the fold trained on):
#   python scripts/export_context_bundle.py "$(source scripts/checkpoints.sh; newest_checkpoint RUN_DIR)" OUT \
#       --passes 4 1
#   BENCH_TRAINED_ON="<the five>" python -m benchmarks.accuracy.bench_real_ct --ct SHARED/HOLD_OUT.nii.gz \
#       --methods network-regression --num-cases 12 --threads 1 --bundle OUT --results ...
# Exit status 2 (nothing written) for an unknown HOLD_OUT or a missing CT; the training script's own checks apply
# (a RUN_DIR holding a run needs --resume; --resume needs a matching checkpoint).
set -euo pipefail
cd "$(dirname "$0")/.."
HOLD=${1:-}
[ -n "$HOLD" ] || { echo "usage: scripts/train_loco.sh HOLD_OUT [RUN_DIR] [EPOCHS] [--resume]" >&2; exit 2; }
RUN=${2:-training/loco/$HOLD}
EPOCHS=${3:-50}
RESUME=${4:-}
DATA=${DATA:-data}
SHARED=${SHARED:-../shared/data}
LOCO_DATA=${LOCO_DATA:-data_loco}
source scripts/loco_split.sh
loco_split train_loco "$HOLD"
for name in "${REAL[@]}"; do
    [ -f "$SHARED/$name.nii.gz" ] || { echo "train_loco: missing real CT $SHARED/$name.nii.gz" >&2; exit 2; }
done
if [ ! -f "$DATA/train.json" ]; then
    scripts/make_training_data.sh "$DATA" "$SHARED"
fi
FOLD="$LOCO_DATA/$HOLD"
mkdir -p "$FOLD"
[ -e "$FOLD/val_paper" ] || ln -s "$(realpath "$DATA/val_paper")" "$FOLD/val_paper"
# the simulated pairs, less those simulated from the held-out CT (their folder's simulation.json names it)
python - "$DATA" "$FOLD/train.json" "$HOLD" <<'PY'
import json, sys
from pathlib import Path
data, out, hold = Path(sys.argv[1]).resolve(), Path(sys.argv[2]), sys.argv[3]
# a folder simulated from the held-out CT names it as its phantom (simulation.json); each item names its object too
dropped = {p.parent.name for p in data.glob("*/simulation.json")
           if Path(str(json.loads(p.read_text())["config"].get("phantom") or "")).name.startswith(hold + ".")}
base = json.loads((data / "train.json").read_text())
items = []
for it in base["training"]:
    if Path(it["fixed"]).parts[0] in dropped or str(it.get("object", "")).startswith(hold + "."):
        continue
    # the fold's datalist lives elsewhere: its paths absolute
    items.append({**it, **{k: str(data / it[k]) for k in ("fixed", "moving", "moving_fov") if it.get(k)}})
out.write_text(json.dumps({**base, "training": items}, indent=1))
print(f"train_loco: {len(items)} of {len(base['training'])} simulated pairs kept (held out: {hold}; "
      f"dropped folders: {sorted(dropped) or 'none'})")
PY
INIT_WEIGHTS="$RUN/init.pt"
if [ "${PREPARE_ONLY:-0}" = 1 ]; then  # the fold's data only, and the commands it would run
    echo "train_loco: python scripts/pretrain_context_coarse.py --data $FOLD --shared $SHARED --cts ${others[*]}" \
        "--schedule 10:10:500 25:15:500 40:30:400 60:45:200 --output $INIT_WEIGHTS (a new fold only)"
    init_env=""; [ -n "$RESUME" ] || init_env="INIT=$INIT_WEIGHTS "
    echo "train_loco: TRAIN_CT_NAMES=\"${others[*]}\" DATA=$FOLD SHARED=$SHARED" \
        "${init_env}scripts/train_context_model.sh $RUN $EPOCHS $RESUME"
    exit 0
fi
if [ -z "$RESUME" ]; then
    # the training script's checks (a folder holding a run is refused) and the fold's clinical pairs first, then the
    # main run's recipe: the coarse level pretrained alone (its match is not learned under the full loss from
    # scratch: bundles/cbct_ct_rigid/docs/context_network.md), then the full loss from those weights
    TRAIN_CT_NAMES="${others[*]}" DATA="$FOLD" SHARED="$SHARED" PREPARE_DATA_ONLY=1 \
        scripts/train_context_model.sh "$RUN" "$EPOCHS"
    if [ ! -f "$INIT_WEIGHTS" ]; then
        # the main run's schedule (training/context_run_v3/pretrain_log.json), 1 600 steps of batch 4
        python scripts/pretrain_context_coarse.py --data "$FOLD" --shared "$SHARED" --cts "${others[@]}" \
            --schedule 10:10:500 25:15:500 40:30:400 60:45:200 --threads "${THREADS:-2}" \
            --output "$INIT_WEIGHTS" --log "$RUN/pretrain_log.json"
    fi
    TRAIN_CT_NAMES="${others[*]}" DATA="$FOLD" SHARED="$SHARED" INIT="$INIT_WEIGHTS" \
        exec scripts/train_context_model.sh "$RUN" "$EPOCHS"
fi
TRAIN_CT_NAMES="${others[*]}" DATA="$FOLD" SHARED="$SHARED" \
    exec scripts/train_context_model.sh "$RUN" "$EPOCHS" "$RESUME"
