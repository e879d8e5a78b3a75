#!/usr/bin/env bash
# A training run branched: the newest checkpoint of RUN_DIR and the run's records copied into a new folder, which
# then goes on with --resume (with CHANGE_ANATOMY=1 / CHANGE_ORIENTATION=1 where the branch trains on other data)
# while RUN_DIR stays as it was: two continuations of one checkpoint compared on the same footing (the augmentation
# trials on a finished leave-one-CT-out fold), or a long run's state kept before a change of its data.
#   usage: scripts/branch_run.sh RUN_DIR NEW_DIR
#   e.g.   scripts/branch_run.sh training/loco/HOLD training/loco_turn_e50/HOLD
#          CHANGE_ORIENTATION=1 ORIENTATION_PROB=0.5 ORIENTATION_MAX=30 \
#              scripts/train_loco.sh HOLD training/loco_turn_e50/HOLD 60 --resume
# Copied where present: models/<newest checkpoint> (older ones and model.pt are not: the branch writes its own),
# history.json, train_log.txt, curves.png, init.pt, pretrain_log.json, anatomy_prob, anatomy_prob_history,
# orientation, orientation_history. NEW_DIR/branched_from gets "RUN_DIR epoch N" (RUN_DIR as given).
# The copy is made in a temporary folder beside NEW_DIR and renamed into place: NEW_DIR is whole or absent.
# Exit status 2, nothing written: a RUN_DIR without a checkpoint, an existing NEW_DIR, a wrong number of arguments.
set -euo pipefail
source "$(dirname "$0")/checkpoints.sh"
[ $# -eq 2 ] || { echo "usage: scripts/branch_run.sh RUN_DIR NEW_DIR" >&2; exit 2; }
SRC=$1
DST=${2%/}
ckpt=$(newest_checkpoint "$SRC")
[ -n "$ckpt" ] || { echo "branch_run: no checkpoint in $SRC/models to branch from" >&2; exit 2; }
[ ! -e "$DST" ] || { echo "branch_run: $DST exists: nothing was changed (choose a new folder)" >&2; exit 2; }
mkdir -p "$(dirname "$DST")"
tmp="$DST.tmp-$$"  # made by mkdir: the umask's permissions, as the folder the training would make
trap 'rm -rf "$tmp"' EXIT
mkdir -p "$tmp/models"
cp -p "$ckpt" "$tmp/models/"
for f in history.json train_log.txt curves.png init.pt pretrain_log.json anatomy_prob anatomy_prob_history \
         orientation orientation_history; do
    [ -f "$SRC/$f" ] && cp -p "$SRC/$f" "$tmp/"
done
echo "$SRC epoch $(newest_epoch "$SRC")" > "$tmp/branched_from"
mv -T "$tmp" "$DST"
trap - EXIT
echo "branch_run: $DST from $ckpt"
