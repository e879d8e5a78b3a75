#!/usr/bin/env bash
# Train the shipped bundle weights (bundles/cbct_ct_rigid/models/model.pt) on the data of make_training_data.sh.
#   usage: [LR=1e-3] [LR_STEP=30] [INIT_WEIGHTS=PATH] [TRAIN_FINE_PASSES=1] \
#          scripts/train_shipped_model.sh [DATA_DIR] [RUN_DIR] [EPOCHS] [--resume]
# Resumable: run the same command with --resume (4th argument) to continue from the newest checkpoint in
# RUN_DIR/ckpt, e.g. after the session that started it ended. CPU by default; the same command uses CUDA where
# torch sees a GPU (the bundle's "device"). INIT_WEIGHTS starts the network from earlier weights (fine-tuning; the
# optimizer and the learning-rate schedule start afresh, a --resume'd run continues from its checkpoint instead);
# TRAIN_FINE_PASSES sets the learned network's fine passes during training (each intermediate estimate is
# supervised with w_levels).
set -euo pipefail
DATA=${1:-data}
RUN=${2:-runs/shipped}
EPOCHS=${3:-80}
RESUME=${4:-}
LR=${LR:-1e-3}
LR_STEP=${LR_STEP:-30}
TRAIN_FINE_PASSES=${TRAIN_FINE_PASSES:-1}
INIT=()
if [ -n "${INIT_WEIGHTS:-}" ]; then INIT=(--init-weights "$INIT_WEIGHTS"); fi
export OMP_WAIT_POLICY=PASSIVE
monai-rigidreg -v train --datalist "$DATA/train.json" --val-datalist "$DATA/val_paper/dataset.json" \
    --output-dir "$RUN" --ckpt-dir "$RUN/ckpt" --epochs "$EPOCHS" --epoch-length 50 --learning-rate "$LR" \
    --num-workers 1 --seed 0 $RESUME "${INIT[@]}" \
    --set batch_size=4 lr_step_epochs="$LR_STEP" network_def#regression#fine_passes="$TRAIN_FINE_PASSES" \
    loss#loss#w_ssim=0.0 loss#loss#w_ncc=0.0 loss#loss#w_mi=0.0
# What differs from the bundle's train.json: batch 4, learning rate LR (1e-3) halved every LR_STEP (30) epochs, 50 iterations per
# epoch, and the image-similarity terms (SSIM, NCC, MI) off: the supervised point distance of the final estimate and
# of the coarse level (w_levels) is the learning signal. benchmarks/ablation/bench_ablation.py measures what the composite
# loss buys on held-out real CTs at an equal training budget. Everything else is train.json: CorrelationRigidNet
# trained alone (fine_stage false, so validation measures the learned network alone), on-the-fly motion up to
# +-30 mm / +-30 deg per axis (each axis with probability 0.8, composed with the base pair's own motion), the
# isocentre up to 50 mm per axis from the CT centre (context_size / isocenter_offset), and the CBCT degradation
# including field-of-view truncation after the motion.
# The shipped model is the final epoch's network (model_final.pt).
python - "$RUN/ckpt" <<'PY'
import re
import sys
from pathlib import Path
import torch
ckpt = Path(sys.argv[1])
last = max(ckpt.glob("checkpoint_checkpoint_epoch=*.pt"), key=lambda p: int(re.findall(r"=(\d+)", p.name)[0]))
state = torch.load(last, map_location="cpu", weights_only=True)
torch.save(state["network"], ckpt / "model_final.pt")
print(f"final model ({last.name}): {ckpt / 'model_final.pt'} (copy to bundles/cbct_ct_rigid/models/model.pt)")
PY
