"""Stage 1 of a registration: the inputs, checked once, before any work.

:func:`check_register_inputs` checks paths, cascade steps and the output folder before anything is read (the
``register`` command and the bundle's ``inference.json``); :func:`read_inputs` reads both images, refuses a
constant image or two images that do not overlap, and warns about intensities that are not HU
(:func:`check_intensities`, :func:`not_hu`) and about a fixed image that looks like the CBCT.

>>> not_hu(0.0, 255.0), not_hu(-1024.0, 3071.0)
(True, False)
>>> check_cascade_steps(2)
2
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk

from monai_rigidreg.core.errors import InputError
from monai_rigidreg.core.geometry import Grid
from monai_rigidreg.export.outputs import OUTPUT_FILES
from monai_rigidreg.io.staging import check_replaceable
from monai_rigidreg.io.volumes import as_image, check_output_dir, grid_within, grids_overlap

__all__ = ["HU_AIR_LIMIT", "EIGHT_BIT_RANGE", "Inputs", "check_intensities", "not_hu", "check_hu",
           "check_cascade_steps", "check_register_inputs", "read_inputs"]

logger = logging.getLogger(__name__)

HU_AIR_LIMIT = -500.0
"""A CT or CBCT in HU holds air (about -1000 HU) somewhere: an image whose minimum lies above this is probably not in
HU (or is cropped to the body)."""
EIGHT_BIT_RANGE = 256.0
"""An image whose intensities span at most this many units is an 8-bit export (or a normalized image), never a CT
in HU: tissue alone spans fat (-100 HU) to bone (several hundred HU)."""


def check_intensities(image: sitk.Image, name: str, hu_range: tuple[float, float] = (-1000.0, 2000.0)) -> list[str]:
    """Check that ``image`` can be registered as a CT/CBCT in Hounsfield units.

    Returns:
        warnings (also logged): an intensity range that is not HU, or may not be (no air: e.g. a uint8 or int8
        export, a normalized or raw-detector image, or a CT cropped to the body), which the network, trained on
        HU, reads as something else. See :func:`not_hu` for the ranges that are certainly not HU.

    Raises:
        InputError: the image is constant (every voxel the same value, e.g. all zero): nothing to register.
    """
    return check_hu(image, name, hu_range)[0]


def not_hu(lo: float, hi: float) -> bool:
    """Whether an intensity range ``[lo, hi]`` is certainly not a CT or CBCT in HU: no negative value (an unsigned
    export, raw detector units, or HU stored without the rescale intercept) or a span of at most
    :data:`EIGHT_BIT_RANGE`. A range from about -100 HU up, without air, may be a CT cropped to the body: not this."""
    return lo >= 0.0 or hi - lo <= EIGHT_BIT_RANGE


def check_hu(image: sitk.Image, name: str, hu_range: tuple[float, float]) -> tuple[list[str], bool]:
    """:func:`check_intensities`' warnings and whether the range is certainly not HU (:func:`not_hu`)."""
    stats = sitk.MinimumMaximumImageFilter()
    stats.Execute(image)
    lo, hi = stats.GetMinimum(), stats.GetMaximum()
    if not hi > lo:
        raise InputError(f"the {name} image is constant (every voxel is {lo:g}): there is nothing to register")
    if lo <= HU_AIR_LIMIT:
        return [], False
    if not_hu(lo, hi):
        msg = (f"the {name} image's intensities range from {lo:g} to {hi:g}, which is not HU (CT air is about -1000; "
               f"the network maps {hu_range[0]:g}..{hu_range[1]:g} HU to its input range): convert it to HU first "
               "(e.g. rescale slope/intercept); the result is flagged")
    else:
        msg = (f"the {name} image holds no air: its intensities range from {lo:g} to {hi:g} (air is about -1000 HU): "
               "if it is not in HU, convert it first; a CT cropped to the body can look like this")
    logger.warning("%s", msg)
    return [msg], not_hu(lo, hi)


def check_cascade_steps(steps: Any) -> int:
    """``steps`` (network applications of a cascade) as an int >= 1, else
    :class:`~monai_rigidreg.core.errors.InputError` naming the value."""
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or int(steps) < 1:
        raise InputError(f"cascade_steps must be a whole number >= 1, got {steps!r}")
    return int(steps)


def check_register_inputs(
    fixed: str | Path | None,
    moving: str | Path | None,
    output_dir: str | Path,
    overwrite: bool = False,
    cascade_steps: Any = None,
) -> Path:
    """The checks of a registration run, done once before anything is loaded: both inputs given and present, the
    cascade steps (if given) a whole number >= 1, and an output folder that may be written
    (:func:`~monai_rigidreg.io.volumes.check_output_dir`). The ``register`` command and the bundle's
    ``inference.json`` both go through it.

    Returns:
        ``output_dir`` as a ``Path``.

    Raises:
        InputError: a missing input (naming it), a bad ``cascade_steps``, an output folder that cannot be made.
        OutputExistsError: the output folder is a file, or not empty and ``overwrite`` is False.
    """
    for name, path in (("fixed", fixed), ("moving", moving)):
        if path is None or not str(path).strip():
            raise InputError(f"no {name} image given: both 'fixed' (the CT) and 'moving' (the CBCT) are needed "
                             "(e.g. --fixed CT.nii.gz --moving CBCT.nii.gz)")
        if not Path(path).exists():
            raise InputError(f"no such file or directory (the {name} image)", path)
    if cascade_steps is not None:
        check_cascade_steps(cascade_steps)
    out = check_output_dir(output_dir, overwrite)
    if overwrite:
        check_replaceable(out, OUTPUT_FILES)  # never delete what this package did not write, e.g. the inputs
    return out


@dataclass
class Inputs:
    """Both images of a registration as :func:`read_inputs` returns them: float32 ``SimpleITK.Image`` s, their
    grids, the warnings about them, and the names of those whose intensities are certainly not HU."""

    fixed: sitk.Image
    moving: sitk.Image
    fixed_grid: Grid
    moving_grid: Grid
    warnings: list[str]
    not_hu: list[str]


def read_inputs(fixed: sitk.Image | str | Path, moving: sitk.Image | str | Path,
                hu_range: tuple[float, float]) -> Inputs:
    """Read (or take) the CT (``fixed``) and the CBCT (``moving``) and check them as a pair.

    Raises:
        InputError: an unreadable or constant image, or two images that do not overlap in physical space.
    """
    fixed_img = as_image(fixed, "fixed")
    moving_img = as_image(moving, "moving")
    checked = {name: check_hu(img, name, hu_range)
               for img, name in ((fixed_img, "fixed (CT)"), (moving_img, "moving (CBCT)"))}
    warnings = [w for found, _ in checked.values() for w in found]
    fixed_grid, moving_grid = Grid.from_sitk(fixed_img), Grid.from_sitk(moving_img)
    if not grids_overlap(fixed_grid, moving_grid):
        raise InputError(
            "the CT (fixed) and CBCT (moving) do not overlap in physical space: check that both are in the "
            "same patient coordinate system (origins and directions)"
        )
    if grid_within(fixed_grid, moving_grid):
        msg = ("the fixed image lies inside the moving one and covers less than half of it, as a CBCT would the "
               "planning CT: check that fixed (--fixed) is the CT and moving (--moving) the CBCT (swapped, the "
               "transform and the couch shifts come out inverted)")
        logger.warning("%s", msg)
        warnings.append(msg)
    return Inputs(fixed_img, moving_img, fixed_grid, moving_grid, warnings,
                  [name for name, (_, certain) in checked.items() if certain])
