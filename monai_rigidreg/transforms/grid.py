"""Network-grid preprocessing, shared by training, the bundle and the CLI.

The network sees both images on ONE axis-aligned grid (identity LPS direction) of ``size`` voxels and ``spacing``
mm, centred on the physical centre of the fixed image (or a given centre). Resampling is purely physical (identity
transform, no motion): a structure at LPS point ``p`` in the input is at ``p`` on the network grid, so a transform
estimated on the network grid is the transform between the original images.

Intensity normalization: :class:`NormalizeHUd` is MONAI's ``ScaleIntensityRanged`` with CT defaults
(``[-1000, 2000]`` HU -> ``[0, 1]``, clipped).
"""

from __future__ import annotations

from collections.abc import Hashable, Mapping, Sequence
from typing import Any

import numpy as np
import SimpleITK as sitk
import torch
from monai.config import KeysCollection
from monai.data import MetaTensor
from monai.data.meta_obj import get_track_meta
from monai.transforms import InvertibleTransform, MapTransform, ScaleIntensityRange, ScaleIntensityRanged
from monai.utils import TraceKeys, convert_to_dst_type, convert_to_tensor, ensure_tuple, ensure_tuple_rep

from monai_rigidreg.core.geometry import Grid
from monai_rigidreg.core.grid_sampling import (  # re-exported: the resampling itself lives there, without MONAI
    PaddingValue,
    antialias_for_grid,
    antialias_sigmas,
    crop_to_grid,
    resample_physical,
    resample_to_grid,
    sitk_on_grid,
    sitk_tensor,
)
from monai_rigidreg.transforms.utils import as_matrix, grid_of

__all__ = [
    "network_grid",
    "antialias_sigmas",
    "antialias_for_grid",
    "crop_to_grid",
    "resample_to_grid",
    "sitk_tensor",
    "sitk_on_grid",
    "ResampleToNetworkGrid",
    "ResampleToNetworkGridd",
    "NormalizeHU",
    "NormalizeHUd",
]


def network_grid(
    reference: Any,
    size: Sequence[int] | int,
    spacing: Sequence[float] | float,
    center: Sequence[float] | None = None,
) -> Grid:
    """The axis-aligned network grid (identity LPS direction) centred on a reference image.

    Args:
        reference: a :class:`~monai_rigidreg.core.geometry.Grid`, a channel-first ``MetaTensor`` ``[C, x, y, z]`` or a
            3D ``SimpleITK.Image`` (the fixed image); ignored for the centre when ``center`` is given.
        size: grid size in voxels ``(nx, ny, nz)`` (one int: isotropic).
        spacing: grid spacing in mm (one number: isotropic).
        center: physical centre in LPS mm (default: the physical centre of ``reference``).

    Returns:
        ``Grid.centered(size, spacing, center)``.
    """
    size_t = ensure_tuple_rep(size, 3)
    spacing_t = ensure_tuple_rep(spacing, 3)
    if center is None:
        if isinstance(reference, Grid):
            ref_grid = reference
        elif isinstance(reference, sitk.Image):
            ref_grid = Grid.from_sitk(reference)
        else:
            ref_grid = grid_of(reference)
        center = ref_grid.center()
    return Grid.centered(size_t, spacing_t, center)


def _grid_affine(img: torch.Tensor, grid: Grid) -> torch.Tensor:
    """The affine of ``grid`` in the space of ``img``'s affine (RAS unless ``meta["space"]`` is LPS)."""
    space = "RAS"
    if isinstance(img, MetaTensor) and "space" in img.meta:
        space = str(img.meta["space"]).upper()
    return torch.as_tensor(grid.affine(space), dtype=torch.float64)


class ResampleToNetworkGrid(InvertibleTransform):
    """Resample a channel-first image ``[C, x, y, z]`` (any grid, any direction) onto the network grid.

    Physical resampling with the identity transform (:func:`monai_rigidreg.core.warp.warp_volume`), linear (or
    nearest) interpolation, constant padding. The output ``MetaTensor`` carries the network grid's affine (RAS, or
    LPS if the input's ``meta["space"]`` is LPS), so ``Grid.from_metatensor(out)`` is the network grid.
    ``inverse()`` resamples back onto the original grid.

    Args:
        size: grid size in voxels (one int: isotropic).
        spacing: grid spacing in mm (one number: isotropic).
        center: physical centre (LPS mm); default the image's own centre (pass ``grid=`` to ``__call__`` to share
            the fixed image's grid between images).
        mode: ``"bilinear"`` (trilinear) or ``"nearest"``.
        padding_value: value outside the input: a number (default ``-1000.0`` HU), ``"min"`` or ``None``
            (``padding_mode`` applies).
        padding_mode: ``grid_sample`` padding mode used when ``padding_value`` is ``None``.
        antialias: with ``"bilinear"``, Gaussian-smooth the input first along every axis whose spacing is finer
            than the grid's (sigma = (ratio - 1) / 2 input voxels), so that a 1 mm clinical CBCT and a coarse
            simulated one look alike on the network grid (plain trilinear sampling would alias their noise).
    """

    def __init__(
        self,
        size: Sequence[int] | int,
        spacing: Sequence[float] | float,
        center: Sequence[float] | None = None,
        mode: str = "bilinear",
        padding_value: PaddingValue = -1000.0,
        padding_mode: str = "zeros",
        antialias: bool = True,
    ) -> None:
        self.size = ensure_tuple_rep(size, 3)
        self.spacing = ensure_tuple_rep(spacing, 3)
        self.center = center
        self.mode = mode
        self.padding_value = padding_value
        self.padding_mode = padding_mode
        self.antialias = bool(antialias)

    def __call__(
        self,
        img: Any,
        grid: Grid | None = None,
        mode: str | None = None,
        padding_value: PaddingValue | str = "default",
    ) -> torch.Tensor:
        """
        Args:
            img: channel-first image ``[C, x, y, z]`` (``MetaTensor``, tensor or array).
            grid: target grid (default: :func:`network_grid` of ``img`` with this transform's settings).
            mode: override the constructor's.
            padding_value: override the constructor's (``"default"``: keep it).

        Returns:
            ``[C, *size]`` image on the network grid, same dtype and device.
        """
        img = convert_to_tensor(img, track_meta=get_track_meta())
        if grid is None:
            grid = network_grid(img, self.size, self.spacing, self.center)
        mode = mode or self.mode
        pval = self.padding_value if isinstance(padding_value, str) and padding_value == "default" else padding_value
        return _resample_and_push(self, img, grid, mode, self.padding_mode, pval)

    def inverse(self, data: torch.Tensor) -> torch.Tensor:
        """Resample back onto the original grid (detail finer than the network grid is lost)."""
        transform = self.pop_transform(data)
        return _undo(self, data, transform, self.padding_value, self.padding_mode)


def _resample_and_push(
    xform: InvertibleTransform,
    img: torch.Tensor,
    grid: Grid,
    mode: str,
    padding_mode: str,
    padding_value: PaddingValue,
) -> torch.Tensor:
    in_grid = grid_of(img)
    raw = img.as_tensor() if isinstance(img, MetaTensor) else img
    out = resample_to_grid(raw, in_grid, grid, mode, padding_mode, padding_value, getattr(xform, "antialias", False))
    out = convert_to_dst_type(out, img)[0]
    if not isinstance(img, MetaTensor):
        return out
    new_affine = _grid_affine(img, grid)
    old_affine = torch.as_tensor(img.affine, dtype=torch.float64)
    rel = torch.linalg.solve(old_affine, new_affine)  # new = old @ rel (MONAI's convention for pushed affines)
    extra = {"orig_affine": old_affine.clone(), "mode": mode}
    out = xform.push_transform(out, sp_size=grid.size, affine=rel, extra_info=extra, orig_size=in_grid.size)
    out.affine = new_affine  # exact (avoid the round-off of old @ rel)
    return out


def _undo(
    xform: InvertibleTransform,
    data: torch.Tensor,
    transform: Mapping,
    padding_value: PaddingValue,
    padding_mode: str,
) -> torch.Tensor:
    info = transform[TraceKeys.EXTRA_INFO]
    orig_size = tuple(int(s) for s in transform[TraceKeys.ORIG_SIZE])
    space = str(data.meta.get("space", "RAS")).upper() if isinstance(data, MetaTensor) else "RAS"
    orig_grid = Grid.from_affine(as_matrix(info["orig_affine"]), orig_size, space=space)
    raw = data.as_tensor() if isinstance(data, MetaTensor) else data
    out = resample_physical(raw, np.eye(4), orig_grid, grid_of(data), info["mode"], padding_mode, padding_value)
    out = convert_to_dst_type(out, data)[0]
    if isinstance(out, MetaTensor):
        out.affine = torch.as_tensor(as_matrix(info["orig_affine"]), dtype=torch.float64)
    return out


class ResampleToNetworkGridd(MapTransform, InvertibleTransform):
    """Dictionary version of :class:`ResampleToNetworkGrid`: every key goes onto ONE network grid.

    The grid is ``network_grid(data[ref_key], size, spacing, center)``: axis-aligned, centred on the physical
    centre of the ``ref_key`` image (the fixed image) or on ``center``. It is computed before any key is
    resampled. Ground-truth keys (e.g. ``"rigid_params"``) need no change: they are physical (LPS mm) and the
    recorded centre is the fixed image centre, which is also the network grid centre.

    Args:
        keys: image keys to resample (default ``("moving", "fixed")``).
        size: grid size in voxels. spacing: grid spacing in mm.
        ref_key: key of the image whose centre centres the grid (if missing: the first key present).
        center: physical centre (LPS mm), overrides ``ref_key``.
        mode: ``"bilinear"`` or ``"nearest"``, one or one per key.
        padding_value: value outside each input, one or one per key (default ``-1000.0`` HU).
        padding_mode: ``grid_sample`` padding when a ``padding_value`` is ``None``.
        antialias: Gaussian pre-filter of inputs finer than the grid (see :class:`ResampleToNetworkGrid`).
        grid_key: if given, the network grid's RAS affine (``Tensor[4, 4]``, float64) is also written there.
        allow_missing_keys: don't raise if a key is missing.
    """

    def __init__(
        self,
        keys: KeysCollection = ("moving", "fixed"),
        size: Sequence[int] | int | None = None,
        spacing: Sequence[float] | float | None = None,
        ref_key: Hashable | None = "fixed",
        center: Sequence[float] | None = None,
        mode: str | Sequence[str] = "bilinear",
        padding_value: PaddingValue | Sequence[PaddingValue] = -1000.0,
        padding_mode: str = "zeros",
        antialias: bool = True,
        grid_key: Hashable | None = None,
        allow_missing_keys: bool = False,
    ) -> None:
        MapTransform.__init__(self, keys, allow_missing_keys)
        if size is None or spacing is None:
            raise ValueError("size and spacing of the network grid are required (the bundle's network_size and "
                             "network_spacing, see monai_rigidreg.core.network_grid.NetworkGridSpec)")
        self.resampler = ResampleToNetworkGrid(size, spacing, center, padding_mode=padding_mode, antialias=antialias)
        self.ref_key = ref_key
        self.center = center
        n = len(self.keys)
        self.mode = ensure_tuple_rep(mode, n)
        if padding_value is None or isinstance(padding_value, (str, int, float)):
            self.padding_value: tuple = (padding_value,) * n
        else:
            self.padding_value = ensure_tuple(padding_value)
            if len(self.padding_value) != n:
                raise ValueError(f"padding_value needs one value or {n}, got {padding_value!r}")
        self.grid_key = grid_key

    def grid_for(self, data: Mapping[Hashable, Any]) -> Grid:
        """The network grid for a data dictionary."""
        r = self.resampler
        if self.center is not None:
            return Grid.centered(r.size, r.spacing, self.center)
        ref = data.get(self.ref_key) if self.ref_key is not None else None
        if ref is None:
            ref = next((data[k] for k in self.keys if k in data), None)
        if ref is None:
            raise KeyError(f"none of {self.ref_key!r} / {self.keys} in the data")
        return network_grid(ref, r.size, r.spacing)

    def __call__(self, data: Mapping[Hashable, Any]) -> dict[Hashable, Any]:
        """
        Args:
            data: dictionary of channel-first images ``[C, x, y, z]``.

        Returns:
            a new dictionary with every key on the network grid (``[C, *size]``).
        """
        d = dict(data)
        grid = self.grid_for(d)
        for key, mode, pval in self.key_iterator(d, self.mode, self.padding_value):
            img = convert_to_tensor(d[key], track_meta=get_track_meta())
            d[key] = _resample_and_push(self, img, grid, mode, self.resampler.padding_mode, pval)
        if self.grid_key is not None:
            d[self.grid_key] = torch.as_tensor(grid.affine("RAS"), dtype=torch.float64)
        return d

    def inverse(self, data: Mapping[Hashable, Any]) -> dict[Hashable, Any]:
        """Resample every key back onto its original grid."""
        d = dict(data)
        for key, pval in self.key_iterator(d, self.padding_value):
            transform = self.pop_transform(d[key])
            d[key] = _undo(self, d[key], transform, pval, self.resampler.padding_mode)
        return d


class NormalizeHU(ScaleIntensityRange):
    """MONAI's ``ScaleIntensityRange`` with CT defaults: ``[a_min, a_max]`` HU -> ``[b_min, b_max]``, clipped."""

    def __init__(
        self, a_min: float = -1000.0, a_max: float = 2000.0, b_min: float = 0.0, b_max: float = 1.0, clip: bool = True
    ) -> None:
        super().__init__(a_min=a_min, a_max=a_max, b_min=b_min, b_max=b_max, clip=clip)


class NormalizeHUd(ScaleIntensityRanged):
    """MONAI's ``ScaleIntensityRanged`` with CT defaults: ``[a_min, a_max]`` HU -> ``[b_min, b_max]``, clipped."""

    def __init__(
        self,
        keys: KeysCollection = ("moving", "fixed"),
        a_min: float = -1000.0,
        a_max: float = 2000.0,
        b_min: float = 0.0,
        b_max: float = 1.0,
        clip: bool = True,
        allow_missing_keys: bool = False,
    ) -> None:
        super().__init__(
            keys, a_min=a_min, a_max=a_max, b_min=b_min, b_max=b_max, clip=clip, allow_missing_keys=allow_missing_keys
        )
