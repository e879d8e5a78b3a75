"""The training CTs are named once in Python (``io.shared_data.TRAINING_CTS``); the training shell script repeats
them and must say the same, and no training CT may be held out."""

from __future__ import annotations

import re
from pathlib import Path

from monai_rigidreg.io.shared_data import HELD_OUT_CTS, TRAINING_CTS, training_ct_paths

REPO = Path(__file__).resolve().parents[1]


def test_the_training_script_trains_on_the_package_s_training_cts():
    text = (REPO / "scripts" / "train_context_model.sh").read_text()
    block = re.search(r"TRAIN_CTS=\(([^)]*)\)", text)
    assert block is not None
    assert tuple(block.group(1).split()) == TRAINING_CTS
    assert not set(TRAINING_CTS) & set(HELD_OUT_CTS)


def test_training_ct_paths_keeps_the_order_and_skips_what_is_missing(tmp_path):
    for name in (TRAINING_CTS[2], TRAINING_CTS[0], HELD_OUT_CTS[0]):
        (tmp_path / f"{name}.nii.gz").write_bytes(b"")
    assert training_ct_paths(tmp_path) == [tmp_path / f"{TRAINING_CTS[0]}.nii.gz",
                                           tmp_path / f"{TRAINING_CTS[2]}.nii.gz"]


def test_benchmarks_label_every_training_ct_as_one():
    # the accuracy benchmarks head each CT's table "held out of training" or "TRAINING CT" from the package's list
    # (a stale copy once labelled the TCIA CTs held out); data-folder suffixes keep the label
    from benchmarks.bench_common import is_training_ct, training_mark

    for name in TRAINING_CTS:
        assert is_training_ct(name) and is_training_ct(f"{name}_rtk_ideal") and "TRAINING CT" in training_mark(name)
    for name in (*HELD_OUT_CTS, "my_own_ct", "head_tigre_ct_multi30"):
        assert not is_training_ct(name) and training_mark(name) == " (held out of training)"
