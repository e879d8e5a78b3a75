"""elastix TransformParameters.txt of a rigid result (monai_rigidreg.export.elastix_params): transformix reproduces
``sitk.Resample(moving, fixed, T, sitkLinear, fill)`` on an oblique, anisotropic CT grid; the numbers round-trip."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from conftest import oblique_direction, smooth_random_image

from monai_rigidreg.core.errors import InputError, OutputExistsError
from monai_rigidreg.core.geometry import Grid, params_to_matrix, params_to_sitk
from monai_rigidreg.export.elastix_params import (
    elastix_parameter_map,
    format_parameter_map,
    read_elastix_transform,
    write_elastix_transform,
    write_transform_h5,
)

PARAMS = np.array([4.0, -3.0, 5.5, 6.0, -8.0, 10.0])  # rotations on all three axes, about the CT centre
FILL = -7.0  # a non-zero fill, so that DefaultPixelValue is checked too


def _fixed() -> sitk.Image:
    return smooth_random_image((40, 36, 30), (2.0, 2.5, 3.0), (-40.0, -45.0, -45.0), oblique_direction(20, -15, 30),
                               seed=1)


def _moving() -> sitk.Image:
    # another oblique grid, about the CT centre but not covering the whole CT (a border where the fill shows)
    return smooth_random_image((44, 40, 34), (2.2, 2.2, 2.8), (-83.9, -66.9, 6.8), oblique_direction(-10, 25, 5),
                               seed=2)


def _itk():
    itk = pytest.importorskip("itk", reason="itk-elastix (the optional 'elastix' extra) is not installed")
    if not hasattr(itk, "transformix_filter") or not hasattr(itk, "ParameterObject"):
        pytest.skip("itk is installed without itk-elastix (no transformix_filter / ParameterObject)")
    return itk


def _to_itk(itk, image: sitk.Image):
    out = itk.image_view_from_array(sitk.GetArrayFromImage(image).copy())
    out.SetOrigin(image.GetOrigin())
    out.SetSpacing(image.GetSpacing())
    out.SetDirection(itk.matrix_from_array(np.asarray(image.GetDirection()).reshape(3, 3)))
    return out


def _transformix(itk, path, moving: sitk.Image) -> np.ndarray:
    pobj = itk.ParameterObject.New()
    pobj.ReadParameterFile(str(path))
    out = itk.transformix_filter(_to_itk(itk, moving), transform_parameter_object=pobj, log_to_console=False)
    return itk.array_from_image(out), out


def test_transformix_reproduces_sitk_resample_on_an_oblique_grid(tmp_path):
    itk = _itk()
    fixed, moving = _fixed(), _moving()
    center = Grid.from_sitk(fixed).center()
    tfm = params_to_sitk(PARAMS, center)
    expected = sitk.GetArrayFromImage(sitk.Resample(moving, fixed, tfm, sitk.sitkLinear, FILL))
    ones = sitk.Image(moving.GetSize(), sitk.sitkFloat32) + 1.0
    ones.CopyInformation(moving)
    coverage = sitk.GetArrayFromImage(sitk.Resample(ones, fixed, tfm, sitk.sitkLinear, 0.0))
    inside, outside = coverage > 0.999, coverage == 0.0
    assert 0.3 < inside.mean() < 0.95  # a real overlap with a border outside it

    path = write_elastix_transform(tmp_path / "TransformParameters.txt", PARAMS, center, fixed, FILL)
    got, out = _transformix(itk, path, moving)
    assert got.shape == expected.shape
    np.testing.assert_allclose(got[inside], expected[inside], atol=1e-4)
    np.testing.assert_array_equal(got[outside], FILL)
    np.testing.assert_allclose(tuple(out.GetOrigin()), fixed.GetOrigin(), atol=1e-9)
    np.testing.assert_allclose(tuple(out.GetSpacing()), fixed.GetSpacing(), atol=1e-9)
    np.testing.assert_allclose(itk.array_from_matrix(out.GetDirection()).ravel(), fixed.GetDirection(), atol=1e-9)


@pytest.mark.parametrize("change", ["direction row by row", "ComputeZYX true", "parameters tx first"])
def test_the_checked_choices_matter(tmp_path, change):
    """Negative controls: each choice verified above, made the other way, breaks the agreement."""
    itk = _itk()
    fixed, moving = _fixed(), _moving()
    center = Grid.from_sitk(fixed).center()
    expected = sitk.GetArrayFromImage(sitk.Resample(moving, fixed, params_to_sitk(PARAMS, center), sitk.sitkLinear,
                                                    FILL))
    pmap = elastix_parameter_map(PARAMS, center, fixed, FILL)
    if change == "direction row by row":
        pmap["Direction"] = tuple(repr(v) for v in fixed.GetDirection())
    elif change == "ComputeZYX true":
        pmap["ComputeZYX"] = ("true",)
    else:
        pmap["TransformParameters"] = pmap["TransformParameters"][3:] + pmap["TransformParameters"][:3]
    path = tmp_path / "TransformParameters.txt"
    path.write_text(format_parameter_map(pmap))
    got, _ = _transformix(itk, path, moving)
    assert np.abs(got - expected).max() > 1.0


def test_file_numbers_round_trip_to_our_params(tmp_path):
    fixed = _fixed()
    center = Grid.from_sitk(fixed).center()
    path = write_elastix_transform(tmp_path / "a.txt", PARAMS, None, fixed, FILL)  # None: the CT centre
    params, c = read_elastix_transform(path)
    np.testing.assert_allclose(params, PARAMS, rtol=0, atol=1e-12)
    np.testing.assert_allclose(c, center, rtol=0, atol=1e-12)
    text = path.read_text()
    expected_tp = " ".join(repr(v) for v in params_to_sitk(PARAMS, center).GetParameters())
    assert f"(TransformParameters {expected_tp})" in text  # rx ry rz (radians) tx ty tz (mm), full precision
    assert '(Transform "EulerTransform")' in text and '(ResampleInterpolator "FinalLinearInterpolator")' in text
    assert '(ResultImagePixelType "float")' in text and "(DefaultPixelValue -7.0)" in text
    assert '(InitialTransformParametersFileName "NoInitialTransform")' in text
    # a matrix, or the SimpleITK transform, about the same centre writes the same numbers
    m_path = write_elastix_transform(tmp_path / "m.txt", params_to_matrix(PARAMS, center), center, fixed, FILL)
    t_path = write_elastix_transform(tmp_path / "t.txt", params_to_sitk(PARAMS, center), center, fixed, FILL)
    for other in (m_path, t_path):
        p2, c2 = read_elastix_transform(other)
        np.testing.assert_allclose(p2, PARAMS, atol=1e-9)
        np.testing.assert_allclose(c2, center, atol=1e-12)


def test_elastix_reads_the_same_numbers(tmp_path):
    itk = _itk()
    fixed = _fixed()
    path = write_elastix_transform(tmp_path / "TransformParameters.txt", PARAMS, None, fixed, FILL)
    pobj = itk.ParameterObject.New()
    pobj.ReadParameterFile(str(path))
    pm = pobj.GetParameterMap(0)
    tfm = params_to_sitk(PARAMS, Grid.from_sitk(fixed).center())
    np.testing.assert_array_equal([float(v) for v in pm["TransformParameters"]], tfm.GetParameters())
    np.testing.assert_array_equal([float(v) for v in pm["CenterOfRotationPoint"]], tfm.GetCenter())
    np.testing.assert_array_equal([int(v) for v in pm["Size"]], fixed.GetSize())
    d = np.asarray(fixed.GetDirection()).reshape(3, 3)
    np.testing.assert_array_equal([float(v) for v in pm["Direction"]], d.T.ravel())
    assert pm["Transform"] == ("EulerTransform",) and pm["UseDirectionCosines"] == ("true",)


def test_bad_input_and_existing_file(tmp_path):
    fixed = _fixed()
    with pytest.raises(InputError, match="rigid"):
        write_elastix_transform(tmp_path / "x.txt", np.diag([2.0, 1.0, 1.0, 1.0]), None, fixed, 0.0)
    with pytest.raises(InputError, match="3D"):
        write_elastix_transform(tmp_path / "x.txt", PARAMS, None, sitk.Image(4, 4, sitk.sitkFloat32), 0.0)
    with pytest.raises(InputError, match="interpolator"):
        write_elastix_transform(tmp_path / "x.txt", PARAMS, None, fixed, 0.0, interpolator="cubic")
    path = write_elastix_transform(tmp_path / "x.txt", PARAMS, None, fixed, 0.0)
    with pytest.raises(OutputExistsError):
        write_elastix_transform(path, PARAMS, None, fixed, 0.0)
    write_elastix_transform(path, PARAMS, None, fixed, 0.0, overwrite=True, interpolator="bspline")
    assert '(FinalBSplineInterpolationOrder 3)' in path.read_text()
    path.write_text(path.read_text().replace('(ComputeZYX "false")', '(ComputeZYX "true")'))
    with pytest.raises(InputError, match="ComputeZYX"):
        read_elastix_transform(path)


def test_write_transform_h5_reads_back_equal(tmp_path):
    tfm = params_to_sitk(PARAMS, (1.0, -2.0, 3.0))
    path = write_transform_h5(tfm, tmp_path / "transform.h5")
    back = sitk.ReadTransform(str(path))
    assert back.GetName() == "Euler3DTransform"
    assert back.GetParameters() == tfm.GetParameters()
    assert back.GetFixedParameters() == tfm.GetFixedParameters()
    pt = (10.0, -20.0, 30.0)
    assert back.TransformPoint(pt) == tfm.TransformPoint(pt)
    with pytest.raises(InputError, match=r"\.h5"):
        write_transform_h5(tfm, tmp_path / "transform.tfm")
    with pytest.raises(OutputExistsError):
        write_transform_h5(tfm, path)
