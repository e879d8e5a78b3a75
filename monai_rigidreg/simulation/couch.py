"""A treatment couch painted into a volume in the scanner frame: test pairs whose couch stays while the patient moves.

The couch of a CT and the treatment couch seen in a CBCT are rigid objects of the room, not of the patient: when the
patient moves between the planning CT and the CBCT, the couch does not. :func:`add_couch` paints such a couch into
an image *after* the patient motion, at a fixed physical place (LPS mm), so that a pair with a static couch is::

    couch = place_couch(ct)                   # just posterior to the CT's patient
    ct_c = add_couch(ct, couch)
    cbct_c = add_couch(moved_patient, couch)  # same physical place: the couch did not move, the patient did

Model (:class:`Couch`), in LPS millimetres, invariant along the physical z axis (the couch's long axis, the
patient's superior direction): a couch top of width ``width_mm`` centred on ``x = center_x_mm``, its top surface
(the one the patient lies on) a circular arc of radius ``curvature_radius_mm`` (``None``: flat) whose most posterior
point is at ``y = top_y_mm`` on the centre line and whose lateral edges rise anteriorly (toward smaller ``y``), as
on a curved CT couch. Below that surface (posterior, larger ``y``), in depth order: a carbon-fibre shell
(``shell_mm`` at ``shell_hu``), a foam core (``core_mm`` at ``core_hu``) and a bottom carbon-fibre shell. Two rails
(``rail_width_mm`` x ``rail_height_mm`` at ``rail_hu``) hang under the lateral edges of the couch top. Depths are
measured along y from the curved top surface (exact for a flat couch, a close approximation for radii of a metre or
more).

Partial volume: every voxel gets the fraction of its box (the voxel's extent projected on the physical x and y axes)
that each part covers, from 1-D box overlaps, so thin shells do not alias into holes on a coarse or oblique grid.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import SimpleITK as sitk

__all__ = ["COUCH_LABELS", "Couch", "place_couch", "couch_labels", "couch_fractions", "add_couch"]

COUCH_LABELS: dict[str, int] = {"shell": 1, "core": 2, "rail": 3}
"""Label values of :func:`couch_labels` (0: no couch)."""


@dataclass(frozen=True)
class Couch:
    """Geometry and HU of a couch top with rails, in the physical LPS frame (mm), invariant along z.

    Attributes:
        top_y_mm: LPS y of the top surface on the centre line (its most posterior point when curved).
        center_x_mm: LPS x of the couch's centre line.
        width_mm: full width of the couch top.
        curvature_radius_mm: radius of the curved top surface; ``None`` for a flat couch top.
        shell_mm: thickness of each carbon-fibre shell (top and bottom).
        shell_hu: HU of the shells.
        core_mm: thickness of the foam core between the shells.
        core_hu: HU of the foam core.
        rail_width_mm: lateral width of each rail (0: no rails).
        rail_height_mm: height (along y) of each rail, below the couch top.
        rail_hu: HU of the rails.
    """

    top_y_mm: float
    center_x_mm: float = 0.0
    width_mm: float = 530.0
    curvature_radius_mm: float | None = 1500.0
    shell_mm: float = 3.0
    shell_hu: float = 500.0
    core_mm: float = 30.0
    core_hu: float = -800.0
    rail_width_mm: float = 20.0
    rail_height_mm: float = 40.0
    rail_hu: float = 1500.0

    @property
    def thickness_mm(self) -> float:
        """Total thickness of the couch top (two shells and the core), mm."""
        return 2 * self.shell_mm + self.core_mm

    def rise(self, x_mm: np.ndarray) -> np.ndarray:
        """How far (mm, toward anterior, i.e. smaller y) the top surface at LPS ``x_mm`` lies above its centre line."""
        if self.curvature_radius_mm is None:
            return np.zeros_like(np.asarray(x_mm, dtype=np.float64))
        r = float(self.curvature_radius_mm)
        dx = np.minimum(np.abs(np.asarray(x_mm, dtype=np.float64) - self.center_x_mm), r)
        return r - np.sqrt(r * r - dx * dx)


def _physical_xy(image: sitk.Image) -> tuple[np.ndarray, np.ndarray]:
    """Physical LPS x and y (mm) of every voxel centre, as arrays broadcastable to ``[z, y, x]`` (SimpleITK order).

    Built from 1-D index ramps, so an axial grid (whose z index axis does not change x or y) gives ``[1, y, x]``
    arrays and a 512x512x150 CT costs two slices, not two volumes.
    """
    direction = np.array(image.GetDirection()).reshape(3, 3)
    spacing = np.array(image.GetSpacing())
    origin = np.array(image.GetOrigin())
    ramps = [np.arange(n, dtype=np.float64).reshape([-1 if a == 2 - i else 1 for a in range(3)])
             for i, n in enumerate(image.GetSize())]  # index axis i (x, y, z) is array axis 2 - i
    out = []
    for axis in (0, 1):
        value: np.ndarray = np.full((1, 1, 1), origin[axis])
        for i in range(3):
            if direction[axis, i] != 0.0:
                value = value + direction[axis, i] * spacing[i] * ramps[i]
        out.append(value)
    return out[0], out[1]


def _voxel_extent(image: sitk.Image) -> np.ndarray:
    """Extent (mm) of a voxel's box projected on the physical x, y, z axes: ``sum_i |D[a, i]| * spacing_i``."""
    direction = np.abs(np.array(image.GetDirection()).reshape(3, 3))
    return direction @ np.array(image.GetSpacing())


def _overlap(u: np.ndarray, h: float, lo: np.ndarray | float, hi: np.ndarray | float) -> np.ndarray:
    """Fraction of the 1-D box ``[u - h/2, u + h/2]`` inside ``[lo, hi]``."""
    return np.clip((np.minimum(u + h / 2, hi) - np.maximum(u - h / 2, lo)) / h, 0.0, 1.0)


def place_couch(
    image: sitk.Image, gap_mm: float = 2.0, threshold_hu: float = -400.0, **couch_kwargs: float | None
) -> Couch:
    """A :class:`Couch` just posterior to the patient of ``image``.

    The top surface is placed ``gap_mm`` posterior (LPS +y) of every voxel centre above ``threshold_hu`` at the same
    x (the curvature is taken into account, so a curved couch touches a flat back at its lowest point only), and the
    centre line at the mean x of those voxels. ``gap_mm = 0`` makes the couch touch the patient: the voxel at the
    contact is then half covered by the shell. Any structure already in the image above the threshold (an existing
    couch) counts as patient: pass ``top_y_mm`` explicitly for such images.

    Args:
        image: a CT-like volume in HU.
        gap_mm: air gap between the patient's most posterior voxel centre and the couch's top surface (mm, >= 0).
        threshold_hu: voxels above it are the patient.
        couch_kwargs: other :class:`Couch` fields (``top_y_mm`` and ``center_x_mm`` override the placement).

    Raises:
        ValueError: no voxel above ``threshold_hu``, or a negative gap.
    """
    if gap_mm < 0:
        raise ValueError(f"gap_mm must be >= 0, got {gap_mm}")
    arr = sitk.GetArrayViewFromImage(image)
    inside = arr > threshold_hu
    if not inside.any():
        raise ValueError(f"no voxel above {threshold_hu} HU: nothing to place the couch under")
    x, y = (np.broadcast_to(v, arr.shape)[inside] for v in _physical_xy(image))
    kwargs = dict(couch_kwargs)
    top_y = kwargs.pop("top_y_mm", None)
    center_x = kwargs.pop("center_x_mm", None)
    couch = Couch(top_y_mm=0.0, center_x_mm=float(x.mean()) if center_x is None else center_x, **kwargs)
    if top_y is None:  # the surface at x is y_s(x) = top_y - rise(x); every patient point needs y <= y_s(x) - gap
        top_y = float(np.max(y + couch.rise(x))) + gap_mm
    return replace(couch, top_y_mm=float(top_y))


def couch_fractions(reference: sitk.Image, couch: Couch) -> dict[str, np.ndarray]:
    """Fraction (0..1) of every voxel of ``reference``'s grid covered by each part of ``couch``.

    Returns:
        ``{"shell", "core", "rail"}`` -> float32 arrays broadcastable to ``[z, y, x]`` (SimpleITK array order;
        ``[1, y, x]`` on an axial grid, the couch being invariant along z); the parts do not overlap, so their sum is
        at most 1.
    """
    x, y = _physical_xy(reference)
    hx, hy, _ = _voxel_extent(reference)
    depth = y - (couch.top_y_mm - couch.rise(x))  # mm below (posterior to) the top surface
    half = couch.width_mm / 2
    in_width = _overlap(x, hx, couch.center_x_mm - half, couch.center_x_mm + half)
    t_shell, t_core = couch.shell_mm, couch.core_mm
    shell = (_overlap(depth, hy, 0.0, t_shell) + _overlap(depth, hy, t_shell + t_core, couch.thickness_mm)) * in_width
    core = _overlap(depth, hy, t_shell, t_shell + t_core) * in_width
    rail = np.zeros_like(shell)
    if couch.rail_width_mm > 0 and couch.rail_height_mm > 0:
        in_rail_depth = _overlap(depth, hy, couch.thickness_mm, couch.thickness_mm + couch.rail_height_mm)
        for side in (-1.0, 1.0):
            edge = couch.center_x_mm + side * half
            inner = edge - side * couch.rail_width_mm
            rail += _overlap(x, hx, min(edge, inner), max(edge, inner)) * in_rail_depth
    return {"shell": shell.astype(np.float32), "core": core.astype(np.float32), "rail": rail.astype(np.float32)}


def couch_labels(reference: sitk.Image, couch: Couch) -> sitk.Image:
    """uint8 label map of ``couch`` on ``reference``'s grid: where the couch covers more than half a voxel, the
    :data:`COUCH_LABELS` value of the part covering most of it (0 elsewhere). The truth for tests."""
    fractions = couch_fractions(reference, couch)
    names = list(COUCH_LABELS)
    stack = np.stack(np.broadcast_arrays(*[fractions[k] for k in names]))
    values = np.array([COUCH_LABELS[k] for k in names], dtype=np.uint8)
    out = np.where(stack.sum(axis=0) > 0.5, values[stack.argmax(axis=0)], 0).astype(np.uint8)
    shape = sitk.GetArrayViewFromImage(reference).shape
    img = sitk.GetImageFromArray(np.ascontiguousarray(np.broadcast_to(out, shape)))
    img.CopyInformation(reference)
    return img


def add_couch(
    image: sitk.Image, couch: Couch | None = None, gap_mm: float = 2.0, fov: sitk.Image | None = None
) -> sitk.Image:
    """Copy of ``image`` (HU) with ``couch`` painted in, partial-volume blended: ``(1 - f) * image + sum f_k HU_k``.

    The couch is placed in the physical frame, so two images sharing a :class:`Couch` show it at the same LPS
    place whatever their grids. It replaces whatever it covers (keep the patient anterior to it: a patient moved
    into the couch is overwritten there).

    Args:
        image: a CT or CBCT in HU (any pixel type; the result is float32).
        couch: the couch; default :func:`place_couch` ``(image, gap_mm)``.
        gap_mm: air gap of the default placement (mm).
        fov: optional mask on ``image``'s grid (a CBCT's field of view): the couch is painted only where it is
            non-zero, as a scanner reconstructs nothing outside its field of view.

    Returns:
        float32 image on ``image``'s grid.
    """
    if couch is None:
        couch = place_couch(image, gap_mm=gap_mm)
    fractions = couch_fractions(image, couch)
    hu = {"shell": couch.shell_hu, "core": couch.core_hu, "rail": couch.rail_hu}
    total = sum(fractions.values())
    painted = sum(fractions[k] * np.float32(hu[k]) for k in fractions)
    if fov is not None:
        keep = sitk.GetArrayViewFromImage(fov) != 0
        total = np.where(keep, total, 0.0)
        painted = np.where(keep, painted, 0.0)
    arr = sitk.GetArrayFromImage(sitk.Cast(image, sitk.sitkFloat32))
    out = sitk.GetImageFromArray((arr * (1.0 - total) + painted).astype(np.float32))
    out.CopyInformation(image)
    return out
