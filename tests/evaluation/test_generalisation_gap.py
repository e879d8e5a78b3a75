"""The generalisation-gap benchmark's grouping: which CTs go to which side, and how a draw is binned."""

import pytest

from benchmarks.accuracy.bench_generalisation_gap import (
    FOV_ORDER,
    REAL_CTS,
    fov_group,
    paired_changes,
    rotated_axes,
    split_cts,
)


def test_split_puts_each_found_ct_on_exactly_one_side(tmp_path):
    for name in REAL_CTS[:5]:  # the sixth is missing
        (tmp_path / f"{name}.nii.gz").write_bytes(b"")
    (tmp_path / "some_other_ct.nii.gz").write_bytes(b"")  # not one of the six: on neither side
    seen = [REAL_CTS[3], REAL_CTS[0], REAL_CTS[5]]  # the missing one named too
    sides = split_cts(tmp_path, seen)
    assert sides["trained on"] == [REAL_CTS[3], REAL_CTS[0]]
    assert sides["held out"] == [REAL_CTS[1], REAL_CTS[2], REAL_CTS[4]]


def test_split_follows_a_leave_one_ct_out_fold(tmp_path):
    for name in REAL_CTS:
        (tmp_path / f"{name}.nii.gz").write_bytes(b"")
    fold = [n for n in REAL_CTS if n != "head_tigre_ct"]
    assert split_cts(tmp_path, fold) == {"trained on": fold, "held out": ["head_tigre_ct"]}


@pytest.mark.parametrize(("share", "group"), [(0.0, "< 0.2"), (0.199, "< 0.2"), (0.2, "0.2-0.4"), (0.41, "0.4-0.6"),
                                              (0.6, "0.6-0.8"), (0.799, "0.6-0.8"), (0.8, ">= 0.8"), (1.0, ">= 0.8")])
def test_fov_groups_have_closed_lower_edges(share, group):
    assert fov_group(share) == group
    assert group in FOV_ORDER


def test_rotated_axes_counts_angles_not_translations_and_ignores_sign():
    assert rotated_axes([60.0, -60.0, 60.0, 0.0, 0.0, 0.0]) == 0  # translations of 60 mm are not angles
    assert rotated_axes([0.0, 0.0, 0.0, -30.0, 30.0, 24.9]) == 2
    assert rotated_axes([0.0, 0.0, 0.0, 25.0, -25.0, 25.0]) == 0  # the limit itself is not above it
    assert rotated_axes([0.0, 0.0, 0.0, 45.0, -26.0, 31.0]) == 3
    assert rotated_axes([0.0, 0.0, 0.0, 45.0, 10.0, 10.0], limit=40.0) == 1


def _draw(params, mm, ct="a"):
    return {"ct": ct, "params": [params, 0.0], "distance_mm": mm}


def test_paired_changes_count_each_direction_at_the_limit():
    now = [_draw(1.0, 0.5), _draw(2.0, 9.0), _draw(3.0, 5.0), _draw(4.0, 4.99), _draw(5.0, 1.0)]
    before = [_draw(1.0, 7.0), _draw(2.0, 8.0), _draw(3.0, 4.0), _draw(4.0, 5.0), _draw(5.0, 2.0)]
    # draw 1 fixed, draw 3 broken (5.0 is not under 5), draw 4 fixed (4.99 against 5.0); 2 and 5 unchanged
    assert paired_changes(now, before) == (2, 1)
    assert paired_changes(before, now) == (1, 2)
    assert paired_changes(now, before, limit=2.0) == (2, 0)  # draws 1 and 5 (1.0 against 2.0)


@pytest.mark.parametrize("other", [
    [_draw(1.0, 0.5)],  # fewer draws
    [_draw(1.0, 0.5), _draw(2.5, 0.5)],  # another motion
    [_draw(1.0, 0.5), _draw(2.0, 0.5, ct="b")],  # another CT
])
def test_paired_changes_refuse_other_draws(other):
    with pytest.raises(ValueError, match="other draws"):
        paired_changes([_draw(1.0, 0.5), _draw(2.0, 0.5)], other)
