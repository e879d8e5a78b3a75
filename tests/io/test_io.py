"""SimpleITK I/O: formats, DICOM series, transforms, MetaTensor conversion and clear errors for bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from conftest import oblique_direction, smooth_random_image, write_dicom_series

from monai_rigidreg.core.errors import InputError, OutputExistsError
from monai_rigidreg.core.geometry import Grid, params_to_sitk, sitk_to_params
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


def _with_voxel(image: sitk.Image, zyx: tuple[int, int, int], value: float) -> sitk.Image:
    """A copy of ``image`` with the voxel at array index ``zyx`` set to ``value`` (e.g. NaN)."""
    arr = sitk.GetArrayFromImage(image)
    arr[zyx] = value
    out = sitk.GetImageFromArray(arr)
    out.CopyInformation(image)
    return out


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
    nan_img = _with_voxel(volume, (2, 3, 4), np.nan)
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


# ---------------------------------------------------------------------------------------------------------------
# DICOM series with uneven slice positions: read at their true positions, or refused
# ---------------------------------------------------------------------------------------------------------------
def _series_files(d, uid):
    return list_dicom_series(d)[uid]


@pytest.mark.parametrize("damage", ["deleted", "unreadable"])
def test_dicom_series_with_a_missing_slice_is_read_at_its_true_positions(tmp_path, volume, caplog, damage):
    """A slice gone (deleted, or a file GDCM cannot parse) leaves a double gap: the series comes back on the complete
    series' grid, every other slice unchanged and the missing one interpolated from its neighbours, with a warning
    naming the gap (ITK alone would spread 15 slices over the 16-slice extent at the mean spacing)."""
    uid = "1.2.826.0.1.3680043.2.1125.7"
    d = tmp_path / "dicom"
    write_dicom_series(volume, d, uid, shuffle_seed=2)
    complete = load_volume(d)
    gone = _series_files(d, uid)[7]
    if damage == "deleted":
        Path(gone).unlink()
    else:
        Path(gone).write_bytes(b"\x00not a DICOM file" * 40)
    with caplog.at_level("WARNING", logger="monai_rigidreg.io"):
        img = load_volume(d)
    assert "4 mm between slices 6 and 7" in caplog.text and "missing or unreadable slice" in caplog.text
    assert "resampled from 15 slices onto a regular grid of 16 slices at 2 mm" in caplog.text
    assert img.GetSize() == complete.GetSize()
    np.testing.assert_allclose(img.GetSpacing(), complete.GetSpacing(), atol=1e-6)
    np.testing.assert_allclose(img.GetOrigin(), complete.GetOrigin(), atol=1e-6)
    np.testing.assert_allclose(img.GetDirection(), complete.GetDirection(), atol=1e-9)
    a, b = sitk.GetArrayFromImage(complete), sitk.GetArrayFromImage(img)  # [z, y, x]
    keep = [k for k in range(16) if k != 7]
    np.testing.assert_allclose(b[keep], a[keep], atol=1e-2)
    np.testing.assert_allclose(b[7], 0.5 * (a[6] + a[8]), atol=1e-2)


def test_dicom_series_with_mixed_slice_spacing_is_resampled_onto_a_regular_grid(tmp_path, caplog):
    """2 mm slices, then 4 mm slices (every other file of the upper half gone): each voxel lands at its true
    position; ITK's own reading (19 slices at the mean gap) would put slices up to 6.7 mm off."""
    from conftest import smooth_random_image

    uid = "1.2.3.4.77"
    vol = sitk.Cast(smooth_random_image((12, 10, 24), (1.5, 1.5, 2.0), (3.0, -4.0, 10.0), (1, 0, 0, 0, 1, 0, 0, 0, 1))
                    * 1000, sitk.sitkFloat32)
    d = tmp_path / "dicom"
    write_dicom_series(vol, d, uid)
    complete = load_volume(d)
    files = _series_files(d, uid)
    for k in range(13, 23, 2):  # keeps 0..12, then 14, 16, ..., 22, and 23 (a last gap of 2 mm)
        Path(files[k]).unlink()
    naive = sitk.ReadImage(_series_files(d, uid))
    assert abs(naive.GetSpacing()[2] - 46.0 / 18) < 1e-3  # what ITK alone reports: 19 slices spread evenly
    with caplog.at_level("WARNING", logger="monai_rigidreg.io"):
        img = load_volume(d)
    assert "unevenly spaced" in caplog.text and "4 mm between slices 12 and 13" in caplog.text
    assert "and 2 more" in caplog.text and "regular grid of 24 slices at 2 mm" in caplog.text
    assert img.GetSize() == complete.GetSize() and img.GetSpacing() == pytest.approx(complete.GetSpacing())
    np.testing.assert_allclose(img.GetOrigin(), complete.GetOrigin(), atol=1e-6)
    a, b = sitk.GetArrayFromImage(complete), sitk.GetArrayFromImage(img)
    kept = list(range(13)) + list(range(14, 23, 2)) + [23]
    np.testing.assert_allclose(b[kept], a[kept], atol=1e-2)
    for k in range(13, 23, 2):
        np.testing.assert_allclose(b[k], 0.5 * (a[k - 1] + a[k + 1]), atol=1e-2)


def test_dicom_series_with_duplicate_or_sheared_slices_is_refused(tmp_path, volume):
    import shutil

    uid = "1.2.3.4.88"
    dup = tmp_path / "dup"
    write_dicom_series(volume, dup, uid)
    shutil.copy(_series_files(dup, uid)[5], dup / "zz_copy.dcm")
    with pytest.raises(InputError, match=r"two slices lie at the same position .* zz_copy.dcm") as info:
        load_volume(dup)
    assert str(dup) in str(info.value)
    # slice origins moving sideways by 0.5 mm per slice (a tilted gantry): the grid cannot hold it
    tilt = tmp_path / "tilt"
    write_dicom_series(volume, tilt, uid)
    row = np.asarray(volume.GetDirection()).reshape(3, 3)[:, 0]
    reader, writer = sitk.ImageFileReader(), sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    for k, f in enumerate(_series_files(tilt, uid)):
        reader.SetFileName(f)
        sl = reader.Execute()
        ipp = np.array([float(v) for v in sl.GetMetaData("0020|0032").split("\\")]) + 0.5 * k * row
        sl.SetMetaData("0020|0032", "\\".join(f"{v:.6f}" for v in ipp))
        writer.SetFileName(f)
        writer.Execute(sl)
    with pytest.raises(InputError, match="drift sideways by up to 7.50 mm"):
        load_volume(tilt)


def _same_image(a: sitk.Image, b: sitk.Image) -> None:
    assert a.GetPixelID() == b.GetPixelID() and a.GetSize() == b.GetSize()
    np.testing.assert_array_equal(sitk.GetArrayViewFromImage(a), sitk.GetArrayViewFromImage(b))
    np.testing.assert_allclose(a.GetOrigin(), b.GetOrigin())
    np.testing.assert_allclose(a.GetSpacing(), b.GetSpacing())
    np.testing.assert_allclose(a.GetDirection(), b.GetDirection())


def test_prefetched_reads_are_what_load_volume_reads_and_go_through_its_checks(tmp_path, volume):
    """The register command's reads started before torch is imported (monai_rigidreg.io.prefetch): load_volume takes
    them (once), gives the image it reads itself, re-reads a file changed since, and reports a corrupt file or NaN
    voxels with the same errors."""
    import os

    from monai_rigidreg.io.prefetch import drop_prefetched, needs_nan_check, prefetch_volumes, take_prefetched

    int_path = tmp_path / "ct.nii.gz"
    sitk.WriteImage(sitk.Cast(volume * 100.0, sitk.sitkInt16), str(int_path))
    float_path = tmp_path / "cbct.nii.gz"
    sitk.WriteImage(volume, str(float_path))
    assert prefetch_volumes([int_path, float_path, None, tmp_path, tmp_path / "missing.nii.gz"]) == 2
    assert prefetch_volumes([int_path]) == 0  # already pending
    for path in (int_path, float_path):
        loaded = load_volume(path)
        assert take_prefetched(path) is None  # taken by load_volume
        _same_image(loaded, load_volume(path))  # the second load reads the file itself
    _same_image(load_volume(int_path, pixel_type=None), sitk.ReadImage(str(int_path)))  # int16 kept on request
    # a file rewritten after its read started is read again
    assert prefetch_volumes([int_path]) == 1
    pending = take_prefetched(int_path)
    assert pending is not None and pending[1] is None  # stored integers: no NaN check (no nibabel import)
    pending[0].result()
    prefetch_volumes([int_path])
    sitk.WriteImage(sitk.Cast(volume * -7.0, sitk.sitkInt16), str(int_path))
    os.utime(int_path, ns=(1_000_000_000, 1_000_000_000))  # a distinct modification time whatever the clock
    _same_image(load_volume(int_path), sitk.Cast(sitk.Cast(volume * -7.0, sitk.sitkInt16), sitk.sitkFloat32))
    # a file replaced by one of the same size and modification time (cp -p, rsync -t) is read again too
    plain, other = tmp_path / "plain.nii", tmp_path / "other.nii"  # uncompressed: the same size for the same shape
    sitk.WriteImage(sitk.Cast(volume * 100.0, sitk.sitkInt16), str(plain))
    sitk.WriteImage(sitk.Cast(volume * 3.0, sitk.sitkInt16), str(other))
    assert plain.stat().st_size == other.stat().st_size
    stamp = plain.stat().st_mtime_ns
    os.utime(other, ns=(stamp, stamp))
    prefetch_volumes([plain])
    take = take_prefetched(plain)
    take[0].result()
    prefetch_volumes([plain])
    os.replace(other, plain)
    assert plain.stat().st_mtime_ns == stamp
    _same_image(load_volume(plain), sitk.Cast(sitk.Cast(volume * 3.0, sitk.sitkInt16), sitk.sitkFloat32))
    # the same errors as an own read
    corrupt = tmp_path / "corrupt.nii.gz"
    corrupt.write_bytes(b"not an image at all")
    prefetch_volumes([corrupt])
    with pytest.raises(InputError, match="unreadable or corrupt image file"):
        load_volume(corrupt)
    bad_path = tmp_path / "inf.nii.gz"
    sitk.WriteImage(_with_voxel(volume, (1, 2, 3), np.inf), str(bad_path))
    prefetch_volumes([bad_path])
    with pytest.raises(InputError, match="1 NaN or infinite voxel"):
        load_volume(bad_path)
    # which files need the NIfTI NaN check: floats, scaled integers, unreadable headers; not integers, not .mha
    assert needs_nan_check(float_path) and needs_nan_check(corrupt) and not needs_nan_check(int_path)
    mha = tmp_path / "v.mha"
    sitk.WriteImage(volume, str(mha))
    assert not needs_nan_check(mha)
    import nibabel as nib

    scaled = nib.Nifti1Image(np.zeros((4, 4, 4), np.int16), np.eye(4))
    scaled.header.set_slope_inter(0.5, 10.0)
    nib.save(scaled, str(tmp_path / "scaled.nii.gz"))
    assert needs_nan_check(tmp_path / "scaled.nii.gz")
    # a read nobody takes can be dropped (the register command drops its own when it fails first)
    assert prefetch_volumes([int_path, float_path]) == 2
    assert drop_prefetched([int_path, float_path, None]) == 2
    assert take_prefetched(int_path) is None and take_prefetched(float_path) is None


def test_a_truncated_float_nifti_is_reported_as_corrupt(tmp_path, volume):
    """ITK reads a truncated float .nii.gz without complaint; the NaN check's read of the voxels fails, and that is
    an InputError naming the file (was a bare EOFError)."""
    import gzip

    path = tmp_path / "cut.nii.gz"
    sitk.WriteImage(volume, str(path))
    raw = gzip.decompress(path.read_bytes())
    path.write_bytes(gzip.compress(raw[: len(raw) * 2 // 3]))
    with pytest.raises(InputError, match="unreadable or corrupt image file") as info:
        load_volume(path)
    assert "cut.nii.gz" in str(info.value)


def test_register_command_starts_reading_both_inputs_before_importing_the_stack():
    """``register`` with one pair calls prefetch_volumes with --fixed and --moving before it imports the registration
    modules (a subprocess, so that nothing is imported yet)."""
    import subprocess
    import sys

    code = ("import sys, monai_rigidreg.io.prefetch as pf; seen = []; "
            "pf.prefetch_volumes = lambda paths: seen.append(([str(p) for p in paths], 'torch' in sys.modules)) or 0; "
            "from monai_rigidreg.cli import main; "
            "main(['register', '--fixed', 'nofixed.nii.gz', '--moving', 'nomoving.nii.gz', '--output-dir', 'o', "
            "'-q']); print(seen)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "[(['nofixed.nii.gz', 'nomoving.nii.gz'], False)]"


def test_a_register_run_that_fails_first_leaves_no_pending_read(tmp_path, volume):
    """The output folder is refused after the reads started: the run ends with the usual error and drops them."""
    from monai_rigidreg.cli import main
    from monai_rigidreg.io.prefetch import _PENDING

    fixed, moving = tmp_path / "ct.nii.gz", tmp_path / "cbct.nii.gz"
    sitk.WriteImage(volume, str(fixed))
    sitk.WriteImage(volume, str(moving))
    taken = tmp_path / "out"
    taken.mkdir()
    (taken / "keep.txt").write_text("not ours")
    assert main(["register", "--fixed", str(fixed), "--moving", str(moving), "--output-dir", str(taken), "-q"]) == 2
    assert not [k for k in _PENDING if k[0] in (str(fixed.resolve()), str(moving.resolve()))]
    assert (taken / "keep.txt").read_text() == "not ours"


def test_nifti_completeness_check(tmp_path, volume):
    """check_nifti_complete: the voxel bytes a NIfTI-1 or NIfTI-2 header declares must all be there and a gzip
    stream must be whole with its checksums right; several gzip members and zero padding after the last one are
    fine (gzip reads them)."""
    import gzip

    import nibabel as nib

    from monai_rigidreg.io.prefetch import check_nifti_complete

    whole = tmp_path / "whole.nii.gz"
    sitk.WriteImage(sitk.Cast(volume * 100.0, sitk.sitkInt16), str(whole))
    check_nifti_complete(whole)
    raw = gzip.decompress(whole.read_bytes())
    members = tmp_path / "members.nii.gz"
    members.write_bytes(gzip.compress(raw[:500]) + gzip.compress(raw[500:]))
    check_nifti_complete(members)
    padded = tmp_path / "padded.nii.gz"
    padded.write_bytes(whole.read_bytes() + bytes(64))
    check_nifti_complete(padded)
    short = tmp_path / "short.nii.gz"  # a whole gzip stream of too few voxel bytes (written short, not cut)
    short.write_bytes(gzip.compress(raw[:-10]))
    with pytest.raises(InputError, match="truncated: .* bytes of voxel data where its header declares"):
        check_nifti_complete(short)
    cut = tmp_path / "cut.nii.gz"
    cut.write_bytes(whole.read_bytes()[:-20])
    with pytest.raises(InputError, match="compressed data ends early"):
        check_nifti_complete(cut)
    damaged = bytearray(whole.read_bytes())
    damaged[-6] ^= 0xFF  # the stored CRC-32 (bytes -8..-5): the stream decodes, its trailer disagrees
    (tmp_path / "damaged.nii.gz").write_bytes(bytes(damaged))
    with pytest.raises(InputError, match="its compressed data: Error -3"):
        check_nifti_complete(tmp_path / "damaged.nii.gz")
    # uncompressed NIfTI-1 and NIfTI-2 (nibabel writes both): the file size against the header
    data = np.arange(4 * 5 * 6, dtype=np.int16).reshape(4, 5, 6)
    for cls, name in ((nib.Nifti1Image, "v1.nii"), (nib.Nifti2Image, "v2.nii")):
        path = tmp_path / name
        nib.save(cls(data, np.eye(4)), str(path))
        check_nifti_complete(path)
        path.write_bytes(path.read_bytes()[:-1])
        with pytest.raises(InputError, match="truncated: 239 bytes of voxel data where its header declares 240"):
            check_nifti_complete(path)
    # not a NIfTI header (ITK decides about it): no opinion
    other = tmp_path / "other.nii"
    other.write_bytes(b"not a header" * 100)
    check_nifti_complete(other)


def test_grid_within_is_containment_of_a_smaller_box():
    from monai_rigidreg.core.geometry import Grid
    from monai_rigidreg.io import grid_within

    ct = Grid((256, 256, 141), (1.95, 1.95, 2.0), (-249.0, -249.0, -140.0))
    cbct = Grid.centered((128, 128, 128), (1.5, 1.5, 1.5), (10.0, -20.0, 5.0))
    assert grid_within(cbct, ct) and not grid_within(ct, cbct)
    assert not grid_within(Grid.centered((128, 128, 128), (1.5, 1.5, 1.5), (0.0, 0.0, 90.0)), ct)  # sticks out in z
    big = Grid.centered((200, 200, 120), (2.4, 2.4, 2.3), (0.0, 0.0, 0.0))  # inside, more than half the volume
    assert not grid_within(big, ct)
    assert grid_within(big, ct, max_share=0.95)  # 92 % of its volume


def _nifti1_bytes(data: np.ndarray, datatype: int, bitpix: int, vox_offset: float) -> bytes:
    """A single-file NIfTI-1 (little-endian) with a hand-set datatype, bitpix and vox_offset (nibabel would fix
    them)."""
    import struct

    hdr = bytearray(348)
    struct.pack_into("<i", hdr, 0, 348)
    struct.pack_into("<8h", hdr, 40, 3, *data.shape, 1, 1, 1, 1)
    struct.pack_into("<hh", hdr, 70, datatype, bitpix)
    struct.pack_into("<8f", hdr, 76, 1, 1, 1, 1, 0, 0, 0, 0)
    struct.pack_into("<f", hdr, 108, vox_offset)
    struct.pack_into("<f", hdr, 112, 1.0)  # scl_slope
    struct.pack_into("<h", hdr, 252, 1)  # qform_code: scanner
    hdr[344:348] = b"n+1\0"
    return bytes(hdr) + bytes(4) + np.ascontiguousarray(data.transpose(2, 1, 0)).tobytes()


def test_nifti_completeness_check_reads_the_header_as_the_readers_do(tmp_path):
    """The voxel bytes come from the datatype (a wrong bitpix is ignored, as ITK ignores it), the data starts at
    least after the header (nifti1_io's rule for a vox_offset below it), a vox_offset that is not a finite number
    gives no opinion, and an uncompressed file named .nii.gz is sized as a plain file (ITK reads it)."""
    import gzip

    from monai_rigidreg.io.prefetch import check_nifti_complete

    data = np.arange(6 * 5 * 4, dtype=np.int16).reshape(6, 5, 4)
    wrong_bitpix = tmp_path / "bitpix.nii"
    wrong_bitpix.write_bytes(_nifti1_bytes(data, 4, 32, 352.0))  # int16 (datatype 4) with bitpix 32
    assert sitk.ReadImage(str(wrong_bitpix)).GetSize() == (6, 5, 4)
    check_nifti_complete(wrong_bitpix)
    zero_offset = tmp_path / "offset0.nii"
    zero_offset.write_bytes(_nifti1_bytes(data, 4, 16, 0.0)[:-100])  # cut by 100 bytes; data really starts at 352
    with pytest.raises(InputError, match="truncated: 140 bytes of voxel data where its header declares 240"):
        check_nifti_complete(zero_offset)
    for bad in (float("nan"), float("inf")):
        odd = tmp_path / "odd.nii"
        odd.write_bytes(_nifti1_bytes(data, 4, 16, bad)[:-100])
        check_nifti_complete(odd)  # no opinion: no ValueError / OverflowError escapes
    named_gz = tmp_path / "plain.nii.gz"
    named_gz.write_bytes(_nifti1_bytes(data, 4, 16, 352.0))
    check_nifti_complete(named_gz)
    named_gz.write_bytes(_nifti1_bytes(data, 4, 16, 352.0)[:-2])
    with pytest.raises(InputError, match="truncated: 238 bytes"):
        check_nifti_complete(named_gz)
    whole_gz = tmp_path / "whole.nii.gz"
    whole_gz.write_bytes(gzip.compress(_nifti1_bytes(data, 4, 16, 352.0)))
    check_nifti_complete(whole_gz)


def test_a_truncated_integer_nifti_is_refused_by_a_plain_load(tmp_path, volume, monkeypatch):
    """load_volume's own read (no prefetch: the Python API, --datalist, ROI masks) runs the completeness check too,
    also where no thread can be started (then in line)."""
    import concurrent.futures

    path = tmp_path / "cut.nii.gz"
    sitk.WriteImage(sitk.Cast(volume * 100.0, sitk.sitkInt16), str(path))
    path.write_bytes(path.read_bytes()[:-40])
    assert sitk.ReadImage(str(path)).GetSize() == volume.GetSize()  # ITK alone: no error
    with pytest.raises(InputError, match="compressed data ends early: the file is truncated"):
        load_volume(path)

    def no_thread(*args, **kwargs):
        raise RuntimeError("can't start new thread")

    monkeypatch.setattr(concurrent.futures.ThreadPoolExecutor, "submit", no_thread)
    with pytest.raises(InputError, match="compressed data ends early: the file is truncated"):
        load_volume(path)
    whole = tmp_path / "whole.nii.gz"
    sitk.WriteImage(sitk.Cast(volume * 100.0, sitk.sitkInt16), str(whole))
    assert load_volume(whole).GetSize() == volume.GetSize()


def test_unreadable_metaimage_messages_name_the_real_problem(tmp_path, volume):
    """ITK ends a failed MetaImage read with an errno text of its own ("No such file or directory") whatever the
    cause: a .mhd whose data file is missing says so, a truncated .mha says its data ends early."""
    mhd = tmp_path / "v.mhd"
    sitk.WriteImage(volume, str(mhd))
    raw = next(tmp_path.glob("v.*raw"))
    raw.unlink()
    with pytest.raises(InputError, match=f"its voxel data file .*{raw.name} does not exist"):
        load_volume(mhd)
    mha = tmp_path / "v.mha"
    sitk.WriteImage(volume, str(mha))
    mha.write_bytes(mha.read_bytes()[:-100])
    with pytest.raises(InputError, match="its voxel data could not be read: the file ends early or is damaged"):
        load_volume(mha)
