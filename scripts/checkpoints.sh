# Sourced by scripts/loco_folds.sh, scripts/eval_loco.sh, scripts/train_context_model.sh and
# scripts/train_context_gpu.sh (not run on its own): a run folder's checkpoints are RUN/models/checkpoint_*epoch=N.pt
# (monai_rigidreg.engine.handlers), the newest the one with the largest N (not the latest file time: a copied or
# restored file keeps no order).
# `newest_epoch RUN` prints that N (0: no checkpoint); `newest_checkpoint RUN` prints its path (nothing: none).
newest_checkpoint() {
    local f n best=0 path=""
    for f in "$1"/models/checkpoint_*epoch=*.pt; do
        [ -e "$f" ] || continue
        n=${f##*=}; n=${n%.pt}
        if [ "$n" -gt "$best" ]; then best=$n; path=$f; fi
    done
    echo "$path"
}
newest_epoch() {
    local path
    path=$(newest_checkpoint "$1")
    if [ -z "$path" ]; then echo 0; else path=${path##*=}; echo "${path%.pt}"; fi
}
