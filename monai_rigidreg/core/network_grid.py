"""The network grid: the one axis-aligned grid (size, spacing) on which the network sees both volumes.

A checkpoint is tied to the grid it was trained on (the regression learns mm at that spacing, the Gauss-Newton
stage works in physical units), so the grid's size and spacing are read from one place, the bundle's configs
(``network_size``, ``network_spacing``), through :meth:`NetworkGridSpec.from_bundle`.

The spec is placed in two ways, which must not be confused:

* :meth:`NetworkGridSpec.on_fixed`: centred on the **fixed (CT) image centre**: the training and validation
  preprocessing (:func:`~monai_rigidreg.engine.registration_transforms`), where estimates are about the CT centre;
* :meth:`NetworkGridSpec.on_moving`: centred on the **moving (CBCT) image centre**: inference
  (:class:`~monai_rigidreg.registration.RigidRegistrar`), so the CBCT's field of view stays on the grid when the
  CT is much larger or the CBCT is off the CT centre; estimates are about that centre and are re-expressed about
  the CT centre before they are reported.

In simulated pairs both centres are the isocentre, so the two placements coincide there.
:meth:`NetworkGridSpec.canonical` (centred on the origin) is the grid the training criterion uses for a batch: every
item's grid has the same size and spacing and its parameters are about its own centre, so the voxel-space action of
the parameters is the same for all of them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import SimpleITK as sitk

from monai_rigidreg.core.errors import InputError
from monai_rigidreg.core.geometry import Grid

__all__ = ["NetworkGridSpec"]


@dataclass(frozen=True)
class NetworkGridSpec:
    """Size (voxels) and spacing (mm) of the network grid; axis-aligned (identity LPS direction).

    Args:
        size: ``(nx, ny, nz)`` voxels (one int: isotropic).
        spacing: ``(sx, sy, sz)`` mm (one number: isotropic).
    """

    size: tuple[int, int, int]
    spacing: tuple[float, float, float]

    def __init__(self, size: Sequence[int] | int, spacing: Sequence[float] | float) -> None:
        size_t = tuple(int(v) for v in (size if isinstance(size, Sequence) else (size,) * 3))
        spacing_t = tuple(float(v) for v in (spacing if isinstance(spacing, Sequence) else (spacing,) * 3))
        if len(size_t) != 3 or min(size_t) < 2:
            raise InputError(f"network grid size must be three integers >= 2, got {size}")
        if len(spacing_t) != 3 or min(spacing_t) <= 0:
            raise InputError(f"network grid spacing must be three positive mm values, got {spacing}")
        object.__setattr__(self, "size", size_t)
        object.__setattr__(self, "spacing", spacing_t)

    @classmethod
    def from_bundle(cls, bundle: str | Path | None = None) -> NetworkGridSpec:
        """The spec declared by a bundle's ``inference.json`` (default: the shipped ``cbct_ct_rigid``)."""
        # imported here: core/ reads no files and imports no other subpackage; the bundle's reader is asked when
        # the sizes come from a bundle
        from monai_rigidreg.bundle.loader import bundle_settings

        settings = bundle_settings(bundle)
        return cls(settings["network_size"], settings["network_spacing"])

    def centered(self, center: Sequence[float]) -> Grid:
        """The grid centred on ``center`` (LPS mm)."""
        return Grid.centered(self.size, self.spacing, tuple(float(c) for c in center))

    def on_fixed(self, fixed: Any) -> Grid:
        """Training/validation placement: centred on the fixed (CT) image centre (``Grid``, ``SimpleITK.Image``
        or channel-first ``MetaTensor``)."""
        return self.centered(_grid_of(fixed).center())

    def on_moving(self, moving: Any) -> Grid:
        """Inference placement: centred on the moving (CBCT) image centre."""
        return self.centered(_grid_of(moving).center())

    def canonical(self) -> Grid:
        """Centred on the origin (the criterion's grid for a whole batch)."""
        return self.centered((0.0, 0.0, 0.0))

    def pooled(self, factor: int) -> NetworkGridSpec:
        """The spec average-pooled by ``factor`` (``size // factor`` voxels of ``spacing * factor`` mm)."""
        return NetworkGridSpec([s // factor for s in self.size], [sp * factor for sp in self.spacing])


def _grid_of(reference: Any) -> Grid:
    if isinstance(reference, Grid):
        return reference
    if isinstance(reference, sitk.Image):
        return Grid.from_sitk(reference)
    return Grid.from_metatensor(reference)
