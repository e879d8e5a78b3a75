# Sourced by scripts/train_loco.sh, scripts/eval_loco.sh and scripts/loco_folds.sh (not run on its own):
# `loco_real` sets REAL (the six real CTs: monai_rigidreg.io.shared_data's training CTs and held-out pair);
# `loco_others NAME HOLD_OUT` sets `others` (REAL, already set, all but HOLD_OUT) or stops the calling script with exit
# status 2 where HOLD_OUT is none of them; `loco_split NAME HOLD_OUT` is the two.
loco_real() {
    read -r -a REAL <<< "$(python -c "from monai_rigidreg.io.shared_data import TRAINING_CTS, HELD_OUT_CTS
print(*TRAINING_CTS, *HELD_OUT_CTS)")"
}
loco_others() {
    local caller=$1 hold=$2 name found=0
    others=()
    for name in "${REAL[@]}"; do
        if [ "$name" = "$hold" ]; then found=1; else others+=("$name"); fi
    done
    if [ "$found" != 1 ]; then
        echo "$caller: HOLD_OUT must be one of: ${REAL[*]} (got '$hold')" >&2; exit 2
    fi
}
loco_split() {
    loco_real
    loco_others "$1" "$2"
}
