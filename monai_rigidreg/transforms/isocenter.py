"""Random treatment isocentre: crop the fixed (CT) image to the network grid around a random point of the body.

Clinical CBCTs are centred on the treatment isocentre, often 0-100 mm from the planning CT's centre, and the
network grid follows the CBCT. In training, the fixed image is first resampled onto a larger *context* grid
(cached), this transform crops the network grid out of it at a random whole-voxel offset (so no interpolation and
no half-voxel error), and :class:`~monai_rigidreg.transforms.RandRigid6DoFd` with ``center_key`` = the fixed key
then moves the still uncropped moving image about the new centre, before
:class:`~monai_rigidreg.transforms.ResampleToNetworkGridd` (``ref_key`` = the fixed key) cuts it to the same grid.
"""

from __future__ import annotations

from collections.abc import Hashable, Mapping, Sequence
from typing import Any

import numpy as np
import torch
from monai.config import KeysCollection
from monai.transforms import MapTransform, RandomizableTransform, SpatialCrop
from monai.utils import ensure_tuple_rep

__all__ = ["RandIsocenterCropd"]


class RandIsocenterCropd(RandomizableTransform, MapTransform):
    """Crop ``keys`` (channel-first ``[C, x, y, z]``, usually only the fixed image) to ``size`` voxels centred on a
    random voxel near the image centre that lies inside the body.

    The offset of the crop centre from the image centre is drawn uniformly per axis in whole voxels within
    ``+-max_offset`` mm (and within the image); a draw whose centre voxel (3^3 mean, of the first key) is below
    ``body_threshold`` (HU: air) is rejected, up to ``tries`` times, after which the centred crop is used. The
    ``MetaTensor`` affine of the crop is updated by MONAI's :class:`~monai.transforms.SpatialCrop`, so its
    physical centre is the new isocentre; the offset (mm along the array axes) is kept in ``last_offset_mm``.

    Args:
        keys: keys to crop (all with the same spatial shape).
        size: crop size in voxels (the network grid size).
        max_offset: largest offset per axis in mm.
        spacing: voxel spacing in mm of the (context-grid) inputs, to turn ``max_offset`` into voxels.
        body_threshold: value below which the centre is outside the body (input units, HU).
        tries: draws before falling back to the centred crop.
        prob: probability of an offset crop (otherwise the centred crop).
        allow_missing_keys: don't raise if a key is missing.
    """

    def __init__(self, keys: KeysCollection, size: Sequence[int] | int, max_offset: float,
                 spacing: Sequence[float] | float, body_threshold: float = -500.0, tries: int = 10,
                 prob: float = 1.0, allow_missing_keys: bool = False) -> None:
        MapTransform.__init__(self, keys, allow_missing_keys)
        RandomizableTransform.__init__(self, prob)
        self.size = np.asarray(ensure_tuple_rep(size, 3), dtype=int)
        if max_offset < 0:
            raise ValueError(f"max_offset must be >= 0 mm, got {max_offset}")
        self.spacing = np.asarray(ensure_tuple_rep(spacing, 3), dtype=float)
        self.max_offset_vox = np.floor(float(max_offset) / self.spacing).astype(int)
        self.body_threshold = float(body_threshold)
        self.tries = int(tries)
        self.last_offset_mm = np.zeros(3)

    def _offset(self, img: torch.Tensor) -> np.ndarray:
        shape = np.asarray(img.shape[1:], dtype=int)
        if np.any(shape < self.size):
            raise ValueError(f"cannot crop {tuple(self.size)} out of {tuple(shape)}")
        base = (shape - self.size) // 2
        limit = np.minimum(self.max_offset_vox, np.minimum(base, shape - self.size - base))
        if not self._do_transform or not np.any(limit > 0):
            return np.zeros(3, dtype=int)
        vol = img[0]
        for _ in range(self.tries):
            off = np.array([self.R.randint(-m, m + 1) for m in limit], dtype=int)
            c = base + off + self.size // 2
            patch = vol[c[0] - 1:c[0] + 2, c[1] - 1:c[1] + 2, c[2] - 1:c[2] + 2]
            if float(patch.float().mean()) >= self.body_threshold:
                return off
        return np.zeros(3, dtype=int)

    def __call__(self, data: Mapping[Hashable, Any]) -> dict[Hashable, Any]:
        d = dict(data)
        self.randomize(None)
        first = next(iter(self.key_iterator(d)), None)
        if first is None:
            return d
        off = self._offset(d[first])
        start = (np.asarray(d[first].shape[1:], dtype=int) - self.size) // 2 + off
        crop = SpatialCrop(roi_start=start.tolist(), roi_end=(start + self.size).tolist())
        for key in self.key_iterator(d):
            d[key] = crop(d[key])
        self.last_offset_mm = off * self.spacing
        return d
