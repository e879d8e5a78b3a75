"""The region of interest (monai_rigidreg.registration.match_region): masks that are not a 3D mask are refused,
naming the problem.

Split from the former tests/test_reliability.py (same assertions).
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from conftest import last_line, run_cli


def test_roi_masks_that_are_not_a_3d_mask_are_refused_naming_the_problem(pair, tmp_path, with_small_network, capsys):
    masks = {"flat.nii.gz": (sitk.Image([8, 8], sitk.sitkUInt8) + 1, "the ROI mask: expected a 3D volume, got a 2D"),
             "four_d.nii.gz": (sitk.GetImageFromArray(np.ones((2, 6, 6, 6), np.uint8), isVector=False),
                               "the ROI mask: expected a 3D volume, got a 4D"),
             "blank.nii.gz": (sitk.Image([8, 8, 8], sitk.sitkUInt8), "the ROI mask is empty (no non-zero voxel)"),
             "zero_bytes.nii.gz": (None, "the ROI mask: unreadable or corrupt image file (Unable to determine")}
    out = tmp_path / "out"
    base = ["register", "--fixed", pair["fixed"], "--moving", pair["moving"], "--output-dir", out]
    for name, (image, expected) in masks.items():
        path = tmp_path / name
        if image is None:
            path.write_bytes(b"")
        else:
            sitk.WriteImage(image, str(path))
        code, err = run_cli(capsys, [*base, "--roi", path])
        assert code == 2 and expected in last_line(err) and name in last_line(err), err
        assert "Traceback" not in err and not out.exists()
    code, err = run_cli(capsys, [*base, "--roi", tmp_path / "missing.nii.gz"])
    assert code == 2 and "got '" in last_line(err) and "no such file, and not six numbers" in last_line(err)
