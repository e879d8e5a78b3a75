"""The cases of the confidence calibration (``bench_confidence_calibration.py``): held-out real anatomy, the failures
of issue 35, damaged inputs and negative cases, each with its ground truth where one exists.

A :class:`CalCase` is one registration to run: the images, the ``register`` options, and a function that scores the
result (TRE in mm and success, the benchmarks' rule: TRE < 2 mm; on deformed clinical pairs the landmark error within
2 mm of the best rigid fit). The sets:

* ``paper``: the paper protocol's pairs (``bench_real_ct``'s simulation, seed 6000), default path;
* ``paper_regression``: the same, the learned network alone (``fine_stage=False``: unconverged failures);
* ``clinical``: the clinical-geometry pairs (``bench_clinical_geometry``), default path (deformed pairs with their ROI);
* ``clinical_no_search``: the same without the global search (wrong basins on the large setup errors: converged
  failures);
* ``partial``: the CT cut to a part of its extent (a short planning scan): paper pairs cut across z, y or x at the
  CBCT centre or 32 mm either side, clinical pairs across z near the isocentre; TRE over the cut CT's points;
* ``swapped``: CBCT as fixed, CT as moving (scored against the intended CT -> CBCT transform: a failure);
* ``negative``: a CBCT of another patient or another body region (re-centred on the CT: no right answer), the CBCT
  with the opposite head/feet orientation, rotated 90 degrees, and an empty field of view;
* ``damaged``: a CBCT without the rescale intercept (not HU), with a quarter of its slices blank, with heavy noise.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk

SUCCESS_MM = 2.0
NEGATIVE_PARTNERS = (  # (CT, a CBCT of another body region, a CBCT of another patient's same region)
    ("thorax_4dct_phase00_itkelastix", "head_tigre_ct", "thorax_tcia_cptac_pda_ct"),
    ("head_tigre_ct", "thorax_4dct_phase00_itkelastix", "head_tcia_cptac_lscc_ct"),
    ("head_tcia_cptac_lscc_ct", "abdomen_pelvis_tcia_tcga_ov_ct", "head_tigre_ct"),
    ("thorax_tcia_cptac_pda_ct", "abdomen_pelvis_tcia_tcga_ov_ct", "thorax_4dct_phase00_itkelastix"),
    ("abdomen_pelvis_tcia_tcga_ov_ct", "head_tcia_cptac_lscc_ct", ""),
)
"""The negative set's pairs; the CTs come from ``--paper-cts``' data (the shipped weights trained on none of them)."""


@dataclass
class CalCase:
    """One registration of the calibration: ``key`` names it uniquely (``set/ct/case/variant``)."""

    key: str
    set: str
    ct: str
    fixed: sitk.Image
    moving: sitk.Image
    fov: sitk.Image | None
    score: Callable[[np.ndarray, np.ndarray], tuple[float, bool]] | None  # (params, centre) -> (error mm, success)
    options: dict[str, Any] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)


def _matrix_tre(points: np.ndarray, truth: np.ndarray) -> Callable[[np.ndarray, np.ndarray], tuple[float, bool]]:
    """Scoring by the mean distance over ``points`` (CT frame) between the estimate and the true 4x4."""
    from monai_rigidreg.core.geometry import params_to_matrix, transform_points

    def score(params: np.ndarray, center: np.ndarray) -> tuple[float, bool]:
        est = params_to_matrix(params, center)
        err = float(np.linalg.norm(transform_points(est, points) - transform_points(truth, points), axis=1).mean())
        return err, err < SUCCESS_MM

    return score


def _cut(image: sitk.Image, axis: int, plane_mm: float, keep: str) -> sitk.Image:
    """``image`` cut by the plane ``x[axis] = plane_mm`` (axis-aligned grids), the part ``"lower"`` or ``"upper"``
    kept, on its own voxels (the physical place unchanged)."""
    from monai_rigidreg.core.geometry import Grid, transform_points

    grid = Grid.from_sitk(image)
    point = grid.center().copy()
    point[axis] = plane_mm
    k = float(transform_points(grid.physical_to_index(), point[None])[0][axis])
    n = image.GetSize()[axis]
    k = int(np.clip(round(k), 8, n - 8))
    sl = [slice(None)] * 3
    sl[axis] = slice(0, k) if keep == "lower" else slice(k, n)
    return image[tuple(sl)]


def _inside_image(image: sitk.Image, points: np.ndarray) -> np.ndarray:
    from monai_rigidreg.core.geometry import Grid, transform_points

    grid = Grid.from_sitk(image)
    idx = transform_points(grid.physical_to_index(), points)
    return np.all((idx >= -0.5) & (idx <= np.asarray(grid.size) - 0.5), axis=1)


def _recentred(moving: sitk.Image, on: sitk.Image) -> sitk.Image:
    """``moving`` with its header moved so that its centre lies on ``on``'s centre (another patient's CBCT placed
    where this CT is: the boxes overlap, the anatomy does not correspond)."""
    from monai_rigidreg.core.geometry import Grid

    out = sitk.Image(moving)
    shift = Grid.from_sitk(on).center() - Grid.from_sitk(moving).center()
    out.SetOrigin(tuple(float(v) for v in np.asarray(moving.GetOrigin()) + shift))
    return out


def _content_rotated(image: sitk.Image, axes: tuple[int, ...], flips: tuple[int, ...], transpose: tuple[int, int]
                     | None = None) -> sitk.Image:
    """``image``'s voxels flipped along ``flips`` (x=0, y=1, z=2) and transposed in-plane, on the same grid."""
    arr = sitk.GetArrayFromImage(image)  # [z, y, x]
    for a in flips:
        arr = np.flip(arr, axis=2 - a)
    if transpose is not None:
        arr = np.swapaxes(arr, 2 - transpose[0], 2 - transpose[1])
    out = sitk.GetImageFromArray(np.ascontiguousarray(arr))
    out.CopyInformation(image)
    return out


def _content_matrix(image: sitk.Image, flips: tuple[int, ...], transpose: tuple[int, int] | None) -> np.ndarray:
    """The 4x4 (LPS mm) that maps a point of the original content to where :func:`_content_rotated` puts it (a
    rotation about the grid centre for square in-plane grids)."""
    from monai_rigidreg.core.geometry import Grid

    grid = Grid.from_sitk(image)
    m = np.eye(4)
    for a in flips:
        f = np.eye(4)
        f[a, a] = -1.0
        m = f @ m
    if transpose is not None:
        p = np.eye(4)
        i, j = transpose
        p[[i, j]] = p[[j, i]]
        m = p @ m
    c = grid.center()
    to_c, back = np.eye(4), np.eye(4)
    to_c[:3, 3], back[:3, 3] = -c, c
    return back @ m @ to_c


# ---------------------------------------------------------------------------------------------------------------
# Sets
# ---------------------------------------------------------------------------------------------------------------
def paper_cases(real_ct_dir: Path, cts: list[str]) -> Iterator[CalCase]:
    """``paper``, ``paper_regression``, ``partial`` (paper pairs cut), ``swapped`` and ``damaged`` from the paper
    protocol's datalists ``<real_ct_dir>/<ct>/dataset.json``."""
    from monai_rigidreg.core.geometry import params_to_matrix
    from monai_rigidreg.evaluation.evaluate import iter_cases, load_datalist

    for ct in cts:
        datalist = real_ct_dir / ct / "dataset.json"
        if not datalist.is_file():
            continue
        items, _ = load_datalist(datalist)
        for i, case in enumerate(iter_cases(items)):
            truth = params_to_matrix(case.truth, case.center)
            score = _matrix_tre(case.points, truth)
            base = f"{ct}/{case.case_id}"
            meta = {"label": case.item.get("label", ""), "group": case.item.get("group", "")}
            yield CalCase(f"paper/{base}", "paper", ct, case.fixed, case.moving, case.fov, score, {}, meta)
            yield CalCase(f"paper_regression/{base}", "paper_regression", ct, case.fixed, case.moving, case.fov,
                          score, {"fine_stage": False}, meta)
            # the CT cut across one axis near the CBCT centre: 25-75 % of the CBCT's extent covered
            axis = (2, 2, 1, 0)[i % 4]
            keep = ("lower", "upper")[(i // 4) % 2]
            offset = (-32.0, 0.0, 32.0)[i % 3]
            plane = float(case.center[axis] + offset)
            cut = _cut(case.fixed, axis, plane, keep)
            inside = case.points[_inside_image(cut, case.points)]
            yield CalCase(f"partial/{base}/{'xyz'[axis]}_{keep}_{offset:+.0f}", "partial", ct, cut, case.moving,
                          case.fov, _matrix_tre(inside, truth), {}, {**meta, "cut": f"{'xyz'[axis]} {keep} "
                                                                     f"{offset:+.0f} mm"})
            if i % 4 == 0:  # swapped inputs: the CBCT as fixed, the CT as moving; scored against the intended T
                yield CalCase(f"swapped/{base}", "swapped", ct, case.moving, case.fixed, None,
                              _swapped_score(case.points, truth), {}, meta)
            if i % 7 == 0:
                yield from _damaged(base, ct, case.fixed, case.moving, case.fov, score, meta)


def _swapped_score(points: np.ndarray, truth: np.ndarray) -> Callable[[np.ndarray, np.ndarray], tuple[float, bool]]:
    """A swapped result read as the CT -> CBCT transform it claims to be: the distance to the true one over the CT
    points (never a success: its couch shifts come out inverted)."""
    score = _matrix_tre(points, truth)

    def swapped(params: np.ndarray, center: np.ndarray) -> tuple[float, bool]:
        err, _ = score(params, center)
        return err, False

    return swapped


def _damaged(base: str, ct: str, fixed: sitk.Image, moving: sitk.Image, fov: sitk.Image | None,
             score: Callable[..., tuple[float, bool]], meta: dict[str, Any]) -> Iterator[CalCase]:
    """``damaged``: the CBCT without its rescale intercept (+1024), with a quarter of its slices blank (-1000), with
    Gaussian noise of 300 HU."""
    yield CalCase(f"damaged/{base}/no_intercept", "damaged", ct, fixed, moving + 1024.0, fov, score, {}, meta)
    arr = sitk.GetArrayFromImage(moving)
    n = arr.shape[0]
    arr[n // 2: n // 2 + n // 4] = -1000.0
    blank = sitk.GetImageFromArray(arr)
    blank.CopyInformation(moving)
    yield CalCase(f"damaged/{base}/blank_slices", "damaged", ct, fixed, blank, fov, score, {}, meta)
    rng = np.random.default_rng(35)
    noisy = sitk.GetImageFromArray((sitk.GetArrayFromImage(moving) + rng.normal(0, 300, arr.shape)).astype(np.float32))
    noisy.CopyInformation(moving)
    yield CalCase(f"damaged/{base}/noise300", "damaged", ct, fixed, noisy, fov, score, {}, meta)


def clinical_cases(pairs_dirs: list[Path], cts: list[str] | None) -> Iterator[CalCase]:
    """``clinical``, ``clinical_no_search``, ``partial`` (the CT cut across z near the isocentre) and ``swapped`` from
    the clinical-geometry pairs cached in ``<pairs_dir>/<ct>/<group>_<nnn>/``."""
    from benchmarks.accuracy.bench_clinical_geometry import cached_pairs, case_errors, roi_box
    from benchmarks.bench_common import Tee
    from monai_rigidreg.simulation.clinical import tre_points

    for pairs_dir in pairs_dirs:
        if not pairs_dir.is_dir():
            continue
        tag = pairs_dir.name
        for i, (ct_name, pair_name, ct, case) in enumerate(cached_pairs(pairs_dir, ("small", "large", "deformed"),
                                                                        Tee())):
            if cts and ct_name not in cts:
                continue
            rec = case.record
            deformed = rec["deformation"] is not None
            points = tre_points(ct, case.matrix, case.fov)
            floor = float(rec["rigid_floor_mm"]) if deformed else 0.0

            def score(params: np.ndarray, center: np.ndarray, rec: dict = rec, points: np.ndarray = points,
                      deformed: bool = deformed, floor: float = floor) -> tuple[float, bool]:
                from monai_rigidreg.core.geometry import recenter_params

                p = recenter_params(params, center, np.asarray(rec["center"]))
                e = case_errors(p, rec, points)
                err = e["landmark"] if deformed else e["tre"]
                return float(err), bool((err - floor) < SUCCESS_MM)

            options = {"roi": roi_box(rec)} if deformed else {}
            base = f"{ct_name}/{tag}/{pair_name}"
            meta = {"group": rec["group"], "isocenter_distance_mm": rec["isocenter_distance_mm"],
                    "floor_mm": floor if deformed else None}
            yield CalCase(f"clinical/{base}", "clinical", ct_name, ct.image, case.cbct, case.fov, score, options,
                          meta)
            yield CalCase(f"clinical_no_search/{base}", "clinical_no_search", ct_name, ct.image, case.cbct, case.fov,
                          score, {**options, "global_init": False}, meta)
            if not deformed:
                iso = np.asarray(rec["isocenter"], dtype=np.float64)
                keep = ("lower", "upper")[i % 2]
                offset = (-40.0, 0.0, 40.0)[i % 3]
                cut = _cut(ct.image, 2, float(iso[2] + offset), keep)
                inside = points[_inside_image(cut, points)]
                if len(inside) >= 100:
                    yield CalCase(f"partial/{base}/z_{keep}_{offset:+.0f}", "partial", ct_name, cut, case.cbct,
                                  case.fov, _matrix_tre(inside, case.matrix), {},
                                  {**meta, "cut": f"z {keep} {offset:+.0f} mm from the isocentre"})
                if i % 5 == 0:
                    yield CalCase(f"swapped/{base}", "swapped", ct_name, case.cbct, ct.image, None,
                                  _swapped_score(points, case.matrix), {}, meta)


def negative_cases(real_ct_dir: Path, pairs_dir: Path) -> Iterator[CalCase]:
    """``negative``: pairs with no right answer the registration can reach (another patient, another body region;
    the opposite head/feet orientation and a 90-degree rotation, scored against their truth), and an empty field of
    view (refused)."""
    from benchmarks.bench_common import Tee, find_cts
    from monai_rigidreg.core.geometry import params_to_matrix
    from monai_rigidreg.evaluation.evaluate import iter_cases, load_datalist
    from monai_rigidreg.io import load_volume
    from monai_rigidreg.simulation.clinical import load_clinical_case

    def first_paper(ct: str) -> Any:
        path = real_ct_dir / ct / "dataset.json"
        if not path.is_file():
            return None
        items, _ = load_datalist(path)
        return next(iter_cases(items[1:2]))

    def first_clinical(ct: str) -> Any:
        return load_clinical_case(pairs_dir / ct / "small_000")

    def other_cbcts(source: str) -> list[tuple[str, sitk.Image, sitk.Image | None]]:
        """The CBCTs of ``source``: its first paper pair's and its first clinical pair's, each where its data is
        there (``(variant, cbct, fov)``). Both are cases of their own, so that what a collection contains does not
        depend on which clinical pairs happen to be cached."""
        out = []
        paper = first_paper(source)
        if paper is not None:
            out.append(("paper", paper.moving, paper.fov))
        clinical = first_clinical(source)
        if clinical is not None:
            out.append(("clinical", clinical.cbct, clinical.fov))
        return out

    none = None
    for ct, other_region, other_patient in NEGATIVE_PARTNERS:
        paper = first_paper(ct)
        paths = find_cts([ct], Tee(), (ct,))
        if paper is None and not paths:
            continue
        ct_img = paper.fixed if paper is not None else load_volume(paths[0])
        for kind, source in (("other_region", other_region), ("other_patient", other_patient)):
            for variant, cbct, fov in other_cbcts(source) if source else []:
                yield CalCase(f"negative/{ct}/{kind}_{source}/{variant}", "negative", ct, ct_img,
                              _recentred(cbct, ct_img), None if fov is None else _recentred(fov, ct_img), none, {},
                              {"kind": kind, "cbct_of": source, "cbct": variant})
        paper = first_paper(ct)
        if paper is None:
            continue
        truth = params_to_matrix(paper.truth, paper.center)
        for kind, flips, transpose in (("head_feet", (0, 2), None), ("rot90", (0,), (0, 1))):
            moved = _content_rotated(paper.moving, (), flips, transpose)
            fov = _content_rotated(paper.fov, (), flips, transpose) if paper.fov is not None else None
            true = _content_matrix(paper.moving, flips, transpose) @ truth
            yield CalCase(f"negative/{ct}/{paper.case_id}/{kind}", "negative", ct, paper.fixed, moved, fov,
                          _matrix_tre(paper.points, true), {}, {"kind": kind})
        rng = np.random.default_rng(0)
        empty = sitk.GetImageFromArray((-1000.0 + rng.normal(0, 20, sitk.GetArrayViewFromImage(paper.moving).shape))
                                       .astype(np.float32))
        empty.CopyInformation(paper.moving)
        yield CalCase(f"negative/{ct}/{paper.case_id}/empty_fov", "negative", ct, paper.fixed, empty, paper.fov,
                      none, {}, {"kind": "empty_fov"})
