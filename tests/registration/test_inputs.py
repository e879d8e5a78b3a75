"""The inputs of a registration (monai_rigidreg.registration.inputs): constant images refused, intensities that are
not HU warned about, a CT inside a larger CBCT warned about.

Split from the former tests/test_reliability.py (same assertions).
"""

from __future__ import annotations

import json

import pytest
import SimpleITK as sitk
from conftest import constant_like, run_cli

from monai_rigidreg.core.errors import InputError
from monai_rigidreg.io import load_volume


def test_constant_inputs_are_refused_naming_which(pair, small_registrar):
    fixed, moving = load_volume(pair["fixed"]), load_volume(pair["moving"])
    with pytest.raises(InputError, match=r"the moving \(CBCT\) image is constant \(every voxel is 0\)"):
        small_registrar(fixed, constant_like(moving))
    with pytest.raises(InputError, match=r"the fixed \(CT\) image is constant \(every voxel is -1000\)"):
        small_registrar(constant_like(fixed, -1000.0), moving)


@pytest.mark.parametrize(("pixel", "lo", "hi"), [(sitk.sitkUInt8, 0, 255), (sitk.sitkInt8, -128, 127)])
def test_integer_cbct_registers_with_a_warning_naming_its_range(pair, tmp_path, with_small_network, capsys, caplog,
                                                               pixel, lo, hi):
    small = tmp_path / "cbct_preview.nii.gz"
    sitk.WriteImage(sitk.Cast(sitk.RescaleIntensity(load_volume(pair["moving"]), lo, hi), pixel), str(small))
    out = tmp_path / "out"
    with caplog.at_level("WARNING", logger="monai_rigidreg.registration"):
        code, err = run_cli(capsys, ["register", "--fixed", pair["fixed"], "--moving", small, "--output-dir", out])
    assert code == 0, err
    expected = f"the moving (CBCT) image's intensities range from {lo} to {hi}, which is not HU"
    assert expected in caplog.text
    result = json.loads((out / "result.json").read_text())
    assert [w for w in result["details"]["warnings"] if expected in w]
    assert not any("fixed" in w for w in result["details"]["warnings"])  # the CT is in HU
    # flagged whatever the signals say (they are calibrated on HU), naming the image
    assert result["flagged"] is True and result["confidence"] == 0.0
    assert result["details"]["signals"]["not_hu"] == ["moving (CBCT)"]


def test_a_fixed_image_inside_a_larger_moving_one_gets_a_swapped_inputs_warning(pair, small_registrar):
    """A CBCT given as --fixed and the CT as --moving registers (the inverse transform, couch shifts of the wrong
    sign) with a warning in the result; the usual order gets none. On the clinical-geometry and paper-protocol
    benchmark pairs the rule never fires in the usual order (``python -m benchmarks.accuracy.bench_damaged_inputs``,
    last line: 102 pairs, bench_damaged_inputs_0.4.9_2026-12-03.txt)."""
    ct = load_volume(pair["fixed"])
    nx, ny, nz = ct.GetSize()
    inner = ct[nx // 4: 3 * nx // 4, ny // 4: 3 * ny // 4, nz // 4: 3 * nz // 4]  # keeps its physical place
    swapped = small_registrar(inner, ct, assess=False, resample_moving=False)
    assert [w for w in swapped.details.get("warnings", []) if "the fixed image lies inside the moving one" in w]
    usual = small_registrar(ct, inner, assess=False, resample_moving=False)
    assert not [w for w in usual.details.get("warnings", []) if "lies inside" in w]


def test_a_ct_without_air_is_warned_about_but_not_flagged_by_rule(pair, small_registrar):
    """A CT cropped to the body has no air, yet is in HU: a warning, but no forced flag (only ranges that are
    certainly not HU are flagged: no negative value, or an 8-bit span)."""
    from monai_rigidreg.registration import not_hu

    assert not_hu(0, 4095) and not_hu(0, 255) and not_hu(-128, 127) and not_hu(0.0, 1.0)
    assert not not_hu(-110, 1100) and not not_hu(-1000, 2000)
    ct = load_volume(pair["fixed"])
    cropped = sitk.Clamp(ct, lowerBound=-110.0, upperBound=3000.0)  # as if the air were cut away
    result = small_registrar(cropped, load_volume(pair["moving"]), resample_moving=False)
    assert [w for w in result.details.get("warnings", []) if "the fixed (CT) image holds no air" in w]
    assert "not_hu" not in result.details["signals"]
