"""SimpleITK I/O: formats, DICOM series, transforms, MetaTensor conversion and clear errors for bad input."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from conftest import oblique_direction, smooth_random_image, write_dicom_series

from monai_rigidreg.errors import InputError, OutputExistsError
from monai_rigidreg.geometry import Grid, params_to_sitk, sitk_to_params
from monai_rigidreg.io import (
    grids_overlap,
    list_dicom_series,
    load_volume,
    metatensor_to_sitk,
    read_transform,
    resample,
    save_volume,
    sitk_to_metatensor,
    write_transform,
)


@pytest.fixture(scope="module")
def volume():
    img = smooth_random_image((20, 18, 16), (1.0, 1.5, 2.0), (-10.0, 5.0, 3.0), oblique_direction(0, 0, 15))
    return sitk.Cast(img * 1000, sitk.sitkFloat32)


@pytest.mark.parametrize("suffix", [".nii.gz", ".nii", ".mha", ".nrrd"])
def test_save_load_roundtrip(tmp_path, volume, suffix):
    path = save_volume(volume, tmp_path / f"vol{suffix}")
    back = load_volume(path)
    assert back.GetSize() == volume.GetSize()
    np.testing.assert_allclose(back.GetSpacing(), volume.GetSpacing(), atol=1e-5)
    np.testing.assert_allclose(back.GetOrigin(), volume.GetOrigin(), atol=1e-4)
    np.testing.assert_allclose(back.GetDirection(), volume.GetDirection(), atol=1e-5)
    np.testing.assert_allclose(sitk.GetArrayFromImage(back), sitk.GetArrayFromImage(volume), atol=1e-3)
    with pytest.raises(OutputExistsError, match="already exists"):
        save_volume(volume, path)
    save_volume(volume, path, overwrite=True)


def test_dicom_series_with_shuffled_files(tmp_path, volume):
    d = tmp_path / "dicom"
    write_dicom_series(volume, d, "1.2.826.0.1.3680043.2.1125.2", shuffle_seed=3)
    series = list_dicom_series(d)
    assert list(series) == ["1.2.826.0.1.3680043.2.1125.2"]
    img = load_volume(d)
    assert img.GetSize() == volume.GetSize()
    np.testing.assert_allclose(img.GetSpacing(), volume.GetSpacing(), atol=1e-4)
    np.testing.assert_allclose(img.GetOrigin(), volume.GetOrigin(), atol=1e-3)
    np.testing.assert_allclose(img.GetDirection(), volume.GetDirection(), atol=1e-5)
    expected = sitk.GetArrayFromImage(sitk.Cast(sitk.RescaleIntensity(volume, -1000, 2000), sitk.sitkInt16))
    np.testing.assert_array_equal(sitk.GetArrayFromImage(img), expected.astype(np.float32))


def test_dicom_picks_largest_series_or_named_one(tmp_path, volume):
    d = tmp_path / "dicom"
    write_dicom_series(volume, d, "1.2.3.100", shuffle_seed=1)
    sub = sitk.Image(volume[:, :, :6])
    write_dicom_series(sub, d / "tmp", "1.2.3.200", shuffle_seed=2)
    for f in (d / "tmp").iterdir():
        f.rename(d / f"b_{f.name}")
    (d / "tmp").rmdir()
    assert sorted(len(v) for v in list_dicom_series(d).values()) == [6, 16]
    assert load_volume(d).GetSize()[2] == 16
    assert load_volume(d, series_uid="1.2.3.200").GetSize()[2] == 6
    with pytest.raises(InputError, match="no DICOM series with UID"):
        load_volume(d, series_uid="9.9.9")


def test_load_errors_are_clear(tmp_path, volume):
    with pytest.raises(InputError, match="no such file"):
        load_volume(tmp_path / "missing.nii.gz")
    corrupt = tmp_path / "corrupt.nii.gz"
    corrupt.write_bytes(b"this is not a NIfTI file at all" * 10)
    with pytest.raises(InputError, match=r"corrupt.nii.gz: unreadable or corrupt"):
        load_volume(corrupt)
    empty = tmp_path / "empty_dir"
    empty.mkdir()
    with pytest.raises(InputError, match="no DICOM image series"):
        load_volume(empty)
    two_d = tmp_path / "slice.nii.gz"
    sitk.WriteImage(volume[:, :, 3], str(two_d))
    with pytest.raises(InputError, match="expected a 3D volume, got a 2D image"):
        load_volume(two_d)
    four_d = tmp_path / "series.nii.gz"
    sitk.WriteImage(sitk.JoinSeries([volume, volume]), str(four_d))
    with pytest.raises(InputError, match="expected a 3D volume, got a 4D image"):
        load_volume(four_d)
    arr = sitk.GetArrayFromImage(volume)
    arr[2, 3, 4] = np.nan
    nan_img = sitk.GetImageFromArray(arr)
    nan_img.CopyInformation(volume)
    nan_path = tmp_path / "nan.nii.gz"
    sitk.WriteImage(nan_img, str(nan_path))
    with pytest.raises(InputError, match="1 NaN or infinite voxel"):
        load_volume(nan_path)
    mha_path = tmp_path / "nan.mha"
    sitk.WriteImage(nan_img, str(mha_path))
    with pytest.raises(InputError, match="nan.mha: volume has 1 NaN"):
        load_volume(mha_path)


@pytest.mark.parametrize("suffix", [".tfm", ".h5"])
def test_transform_file_roundtrip_read_by_plain_sitk(tmp_path, suffix):
    params, center = [3.5, -2.0, 7.25, 12.0, -8.0, 25.0], (10.0, -20.0, 5.0)
    tfm = params_to_sitk(params, center)
    path = write_transform(tfm, tmp_path / f"t{suffix}")
    plain = sitk.ReadTransform(str(path))
    pts = np.random.default_rng(0).uniform(-100, 100, (20, 3))
    for p in pts:
        np.testing.assert_allclose(plain.TransformPoint(tuple(p)), tfm.TransformPoint(tuple(p)), atol=1e-9)
    back = read_transform(path)
    assert back.GetName() == "Euler3DTransform"
    np.testing.assert_allclose(sitk_to_params(back), params, atol=1e-9)
    with pytest.raises(OutputExistsError):
        write_transform(tfm, path)
    if suffix == ".tfm":
        text = path.read_text()
        assert "Euler3DTransform_double_3_3" in text
        assert "FixedParameters: 10 -20 5" in text


def test_read_transform_rejects_other_types(tmp_path):
    bspline = sitk.BSplineTransformInitializer(sitk.Image(8, 8, 8, sitk.sitkFloat32), (3, 3, 3))
    p = tmp_path / "bspline.tfm"
    sitk.WriteTransform(bspline, str(p))
    with pytest.raises(InputError, match="expected a rigid transform, got BSplineTransform"):
        read_transform(p)
    aff = sitk.AffineTransform(3)
    aff.Scale(1.2)
    p2 = tmp_path / "affine.tfm"
    sitk.WriteTransform(aff, str(p2))
    with pytest.raises(InputError, match="scaling or shear"):
        read_transform(p2)
    two_d = tmp_path / "euler2d.tfm"
    sitk.WriteTransform(sitk.Euler2DTransform(), str(two_d))
    with pytest.raises(InputError, match="3D transform"):
        read_transform(two_d)
    bad = tmp_path / "garbage.tfm"
    bad.write_text("#Insight Transform File V1.0\nnonsense\n")
    with pytest.raises(InputError, match="garbage.tfm"):
        read_transform(bad)
    with pytest.raises(InputError, match="no such transform file"):
        read_transform(tmp_path / "none.tfm")


def test_metatensor_conversion_keeps_geometry(volume):
    mt = sitk_to_metatensor(volume)
    assert tuple(mt.shape) == (1, *volume.GetSize())
    assert mt.meta["space"] == "RAS"
    # voxel (i, j, k) of the MetaTensor is SimpleITK index (i, j, k); its affine is RAS
    i, j, k = 3, 5, 7
    assert float(mt[0, i, j, k]) == pytest.approx(volume[i, j, k])
    lps = np.array(volume.TransformIndexToPhysicalPoint((i, j, k)))
    ras = (mt.affine.numpy() @ [i, j, k, 1])[:3]
    np.testing.assert_allclose(ras, lps * [-1, -1, 1], atol=1e-9)
    back = metatensor_to_sitk(mt)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(back), sitk.GetArrayFromImage(volume))
    np.testing.assert_allclose(Grid.from_sitk(back).index_to_physical(), Grid.from_sitk(volume).index_to_physical(),
                               atol=1e-12)


def test_monai_loadimage_agrees_with_our_converter(tmp_path, volume):
    from monai.transforms import LoadImage

    path = save_volume(volume, tmp_path / "v.nii.gz")
    loaded = LoadImage(image_only=True, ensure_channel_first=True)(str(path))
    ours = sitk_to_metatensor(load_volume(path))
    np.testing.assert_allclose(loaded.affine.numpy(), ours.affine.numpy(), atol=1e-4)
    np.testing.assert_allclose(loaded.numpy(), ours.numpy(), atol=1e-3)
    np.testing.assert_allclose(Grid.from_metatensor(loaded).center(), Grid.from_sitk(volume).center(), atol=1e-4)


def test_resample_default_and_overlap(volume):
    grid = Grid.centered((10, 10, 10), (2.0, 2.0, 2.0), Grid.from_sitk(volume).center())
    out = resample(volume, grid, params_to_sitk([100, 0, 0, 0, 0, 0]))
    stats = sitk.StatisticsImageFilter()
    stats.Execute(volume)
    assert np.all(sitk.GetArrayFromImage(out) == pytest.approx(stats.GetMinimum()))
    assert grids_overlap(Grid.from_sitk(volume), grid)
    assert not grids_overlap(Grid.from_sitk(volume), Grid.centered((10, 10, 10), (1, 1, 1), (500, 0, 0)))
    with pytest.raises(ValueError, match="interpolator"):
        resample(volume, grid, interpolator="cubic")
