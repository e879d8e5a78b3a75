"""The MONAI transform chains of training, validation and inference, shared by the bundle configs and the API."""

from __future__ import annotations

import logging
import warnings
from collections.abc import Sequence
from typing import Any

from monai.transforms import Compose, CopyItemsd, EnsureTyped, LoadImaged, SelectItemsd

from monai_rigidreg.transforms import (
    CBCT_KEY,
    RIGID_KEY,
    NormalizeHUd,
    RandCBCTDegradationd,
    RandIsocenterCropd,
    RandRigid6DoFd,
    ResampleToNetworkGridd,
)

__all__ = ["registration_transforms", "IMAGE_KEYS", "MASK_KEY", "CONTEXT_KEY"]

# With pydicom installed (a dependency, for the DICOM Spatial Registration), MONAI's LoadImage builds its pydicom
# reader and announces, once per construction, that the optional nvImageCodec GPU decoder is absent: a logger warning
# and a UserWarning about a reader these NIfTI datalists never use. Silenced here, narrowly, so training logs stay
# readable; any other warning of MONAI's still shows.
logging.getLogger("monai.data.nvimgcodec_pydicom_plugin").setLevel(logging.ERROR)
warnings.filterwarnings("ignore", message="NvImgCodecPydicomReader: nvImageCodec decoder plugin did not register")

IMAGE_KEYS = ("moving", "fixed")
MASK_KEY = "moving_fov"
CONTEXT_KEY = "context"


def registration_transforms(
    mode: str,
    network_size: Sequence[int],
    network_spacing: Sequence[float],
    translate_range: Any = 15.0,
    rotate_range: Any = 15.0,
    axis_prob: Any = 0.7,
    degrade: bool = True,
    hu_range: tuple[float, float] = (-1000.0, 2000.0),
    degradation_kwargs: dict | None = None,
    context_size: Sequence[int] | None = None,
    isocenter_offset: float = 0.0,
    context_factor: int | None = None,
) -> Compose:
    """Transform chain for a datalist of ``fixed`` / ``moving`` (paths) items with ground truth ``params`` /
    ``matrix`` / ``center`` (as ``monai-rigidreg simulate`` writes) and an optional ``moving_fov`` mask.

    Steps: load (channel first, RAS ``MetaTensor``) -> resample ``moving``, ``fixed`` and ``moving_fov`` onto one
    network grid centred on the fixed image (the training placement,
    :meth:`~monai_rigidreg.core.network_grid.NetworkGridSpec.on_fixed`; deterministic: ``CacheDataset`` caches up to
    here) -> ``train`` only: random rigid motion of the moving CBCT (and its mask) composed with the recorded
    ground truth, and random CBCT degradation -> HU window to [0, 1]. In every mode the ground truth ends up under
    ``"rigid_params"`` (``{"params" [6], "matrix" [4, 4], "center" [3]}``).

    Args:
        mode: ``"train"`` (random motion + degradation) or ``"val"`` (the recorded motion only).
        network_size, network_spacing: network grid (voxels, mm): the bundle's ``network_size`` /
            ``network_spacing``.
        translate_range, rotate_range, axis_prob: :class:`~monai_rigidreg.transforms.RandRigid6DoFd` ranges (mm,
            degrees) and per-axis probability of the extra random motion.
        degrade: apply :class:`~monai_rigidreg.transforms.RandCBCTDegradationd` in training.
        hu_range: HU window mapped to [0, 1].
        degradation_kwargs: overrides of the degradation defaults.
        context_size: ``train`` only: cache the pair on a larger grid (voxels, at ``network_spacing``) centred on
            the fixed image, and cut the network grid out of it per sample after the motion (so rotated corners
            carry anatomy, not padding) around a random isocentre
            (:class:`~monai_rigidreg.transforms.RandIsocenterCropd`). ``None``: the network grid directly.
        isocenter_offset: largest offset per axis (mm) of that isocentre from the fixed image centre.
        context_factor: ``val`` only: also put the fixed image on the CT context grid of
            :class:`~monai_rigidreg.networks.ContextCorrelationNet` under ``"context"`` (same centre, as many voxels
            as the network grid, ``context_factor`` times its spacing). ``None``: no context.
    """
    if mode not in ("train", "val"):
        raise ValueError(f"mode must be 'train' or 'val', got {mode!r}")
    keys = [*IMAGE_KEYS, MASK_KEY]
    train = mode == "train"
    context = train and context_size is not None
    ct_context = not train and context_factor is not None
    xforms: list = [
        LoadImaged(keys=keys, ensure_channel_first=True, image_only=True, allow_missing_keys=True),
        EnsureTyped(keys=keys, dtype="float32", allow_missing_keys=True),
    ]
    if ct_context:
        xforms += [
            CopyItemsd(keys="fixed", names=CONTEXT_KEY),
            ResampleToNetworkGridd(keys=CONTEXT_KEY, size=network_size,
                                   spacing=[float(s) * int(context_factor) for s in network_spacing],
                                   ref_key="fixed", padding_value=hu_range[0]),
        ]
    xforms += [
        ResampleToNetworkGridd(
            keys=keys,
            size=context_size if context else network_size,
            spacing=network_spacing,
            ref_key="fixed",
            mode=("bilinear", "bilinear", "nearest"),
            padding_value=(hu_range[0], hu_range[0], 0.0),
            allow_missing_keys=True,
        ),
    ]
    if context:
        xforms.append(RandIsocenterCropd(keys="fixed", size=network_size, max_offset=isocenter_offset,
                                         spacing=network_spacing, body_threshold=-500.0))
    xforms.append(
        RandRigid6DoFd(
            keys="moving",
            mask_keys=MASK_KEY,
            prob=1.0 if train else 0.0,
            translate_range=translate_range,
            rotate_range=rotate_range,
            axis_prob=axis_prob,
            center_key="fixed",
            padding_value=hu_range[0],
            allow_missing_keys=True,
        )
    )
    if context:
        xforms.append(ResampleToNetworkGridd(keys=["moving", MASK_KEY], size=network_size, spacing=network_spacing,
                                             ref_key="fixed", mode=("bilinear", "nearest"),
                                             padding_value=(hu_range[0], 0.0), allow_missing_keys=True))
    if train and degrade:
        xforms.append(RandCBCTDegradationd(keys="moving", **(degradation_kwargs or {})))
    norm_keys = [*IMAGE_KEYS, CONTEXT_KEY] if ct_context else list(IMAGE_KEYS)
    xforms.append(NormalizeHUd(keys=norm_keys, a_min=hu_range[0], a_max=hu_range[1]))
    # only what the engine uses goes on to collation (datalists may carry free-form fields, even nulls)
    xforms.append(SelectItemsd(keys=[*keys, CONTEXT_KEY, RIGID_KEY, CBCT_KEY, "case_id"], allow_missing_keys=True))
    return Compose(xforms)
