"""The MONAI-free resampling and HU normalization of the register path (monai_rigidreg.core.grid_sampling) against the
MONAI transforms that wrap them for training."""

from __future__ import annotations

import pytest
import torch

from monai_rigidreg.core.grid_sampling import normalize_hu


@pytest.mark.parametrize("clip", [True, False])
@pytest.mark.parametrize("window", [(-1000.0, 2000.0), (-200.0, 300.0)])
def test_normalize_hu_is_monai_scale_intensity_range(clip, window):
    from monai.transforms import ScaleIntensityRange

    from monai_rigidreg.transforms import NormalizeHU

    hu = torch.linspace(-1500.0, 3500.0, 1001).reshape(1, 7, 11, 13)
    a_min, a_max = window
    ref = ScaleIntensityRange(a_min=a_min, a_max=a_max, b_min=0.0, b_max=1.0, clip=clip)(hu)
    got = normalize_hu(hu, a_min, a_max, clip=clip)
    assert got.dtype == hu.dtype and got.shape == hu.shape
    torch.testing.assert_close(got, torch.as_tensor(ref), atol=0, rtol=0)
    if clip:
        torch.testing.assert_close(got, torch.as_tensor(NormalizeHU(a_min, a_max)(hu)), atol=0, rtol=0)
        assert float(got.min()) == 0.0 and float(got.max()) == 1.0
    # -1000 HU (air) is 0 and the window's top is 1; 500 HU sits at its fraction of the window
    assert float(normalize_hu(torch.tensor(-1000.0))) == 0.0
    assert float(normalize_hu(torch.tensor(500.0))) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="differ"):
        normalize_hu(hu, 10.0, 10.0)
