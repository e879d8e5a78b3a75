"""The register API and command: outputs, convention round trip, DICOM input, bad input, known-motion recovery."""

from __future__ import annotations

import json

import numpy as np
import pytest
import SimpleITK as sitk
import torch
from conftest import KNOWN_MOTION, TINY_SIM, small_registrar_for_tests, write_dicom_series

from monai_rigidreg.cli import main
from monai_rigidreg.core.errors import InputError, OutputExistsError
from monai_rigidreg.core.geometry import Grid, params_to_matrix, target_registration_error, transform_points
from monai_rigidreg.export.outputs import write_outputs
from monai_rigidreg.export.transform_files import read_transform
from monai_rigidreg.io import load_volume
from monai_rigidreg.networks import DualEncoderRigidNet
from monai_rigidreg.registration import RigidRegistrar, register
from monai_rigidreg.registration.confidence import confidence_score

MOTION = KNOWN_MOTION


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    from monai_rigidreg.simulation import simulate_pair

    out = tmp_path_factory.mktemp("pair")
    return simulate_pair(out, phantom="shepp-logan-asym", params=MOTION, seed=3,
                         **{k: v for k, v in TINY_SIM.items() if k != "preset"})


@pytest.fixture(scope="module")
def small_registrar():
    return small_registrar_for_tests(cascade_steps=2)


def test_refine_recovers_known_motion_and_outputs_are_consistent(pair, small_registrar, tmp_path):
    fixed, moving = load_volume(pair["fixed"]), load_volume(pair["moving"])
    res = small_registrar(fixed, moving, refine=True)
    center = Grid.from_sitk(fixed).center()
    np.testing.assert_allclose(res.center, center)
    pts = np.stack(np.meshgrid(*[np.linspace(-60, 60, 5)] * 3, indexing="ij"), -1).reshape(-1, 3)
    assert target_registration_error(res.params, MOTION, pts, center=center) < 2.0
    assert {"preprocess", "network", "refine", "confidence", "resample", "total"} <= set(res.timings)
    assert "change_tre_mm" in res.details["refine"]
    paths = write_outputs(res, fixed, moving, tmp_path / "out")
    assert set(paths) == {"transform.tfm", "TransformParameters.txt", "registered.nii.gz", "result.json", "qc.png"}
    # the transform file, read by plain SimpleITK and applied with sitk.Resample, reproduces registered.nii.gz
    tfm = sitk.ReadTransform(str(paths["transform.tfm"]))
    again = sitk.Resample(moving, fixed, tfm, sitk.sitkLinear, float(sitk.GetArrayViewFromImage(moving).min()))
    np.testing.assert_allclose(sitk.GetArrayFromImage(again), sitk.GetArrayFromImage(load_volume(
        paths["registered.nii.gz"])), atol=1e-3)
    result = json.loads(paths["result.json"].read_text())
    np.testing.assert_allclose([result["params"][k] for k in ("tx", "ty", "tz", "rx", "ry", "rz")], res.params)
    np.testing.assert_allclose(np.array(result["matrix"]), res.matrix, atol=1e-12)
    with pytest.raises(OutputExistsError):
        write_outputs(res, fixed, moving, tmp_path / "out")


def test_clinical_geometry_oblique_and_smaller_cbct(pair, small_registrar):
    """A CBCT on an oblique, anisotropic, cropped grid: same physical content, so the same answer."""
    fixed, moving = load_volume(pair["fixed"]), load_volume(pair["moving"])
    base = small_registrar(fixed, moving, refine=True, assess=False).params
    from monai_rigidreg.core.geometry import rotation_matrix

    d = rotation_matrix(*np.deg2rad([4.0, -3.0, 10.0])).ravel()
    cg = Grid.centered((20, 18, 16), (9.0, 10.0, 11.0), Grid.from_sitk(moving).center())
    oblique = Grid(cg.size, cg.spacing, cg.origin, d)
    # put the centre back where it was after the rotation of the direction
    shift = Grid.from_sitk(moving).center() - oblique.center()
    oblique = Grid(cg.size, cg.spacing, tuple(np.asarray(cg.origin) + shift), d)
    from monai_rigidreg.io import resample

    moving2 = resample(moving, oblique, None, default_value=-1000.0)
    res = small_registrar(fixed, moving2, refine=True, assess=False)
    pts = np.stack(np.meshgrid(*[np.linspace(-50, 50, 5)] * 3, indexing="ij"), -1).reshape(-1, 3)
    assert target_registration_error(res.params, base, pts, center=res.center) < 3.0


def test_bad_inputs_give_clear_errors(pair, small_registrar, tmp_path):
    fixed = load_volume(pair["fixed"])
    with pytest.raises(InputError, match="no such file"):
        small_registrar(tmp_path / "missing.nii.gz", fixed)
    far = sitk.Image(fixed)
    far.SetOrigin(tuple(np.asarray(fixed.GetOrigin()) + 5000.0))
    with pytest.raises(InputError, match="do not overlap"):
        small_registrar(fixed, far)
    with pytest.raises(InputError, match="2D"):
        small_registrar(fixed, fixed[:, :, 3])
    arr = sitk.GetArrayFromImage(fixed)
    arr[1, 2, 3] = np.nan
    nan_img = sitk.GetImageFromArray(arr)
    nan_img.CopyInformation(fixed)
    with pytest.raises(InputError, match="NaN"):
        small_registrar(fixed, nan_img)


def test_preprocess_matches_the_training_transforms_on_a_large_oblique_ct(small_registrar):
    """The registrar's fast path (no whole-volume transpose, plain tensors) equals the MONAI training transforms
    (``ResampleToNetworkGrid`` + ``NormalizeHU`` on a ``MetaTensor``), including the crop of a CT larger than the
    grid, an oblique direction, an int16 input and the nearest-neighbour field-of-view mask."""
    from monai_rigidreg.io import sitk_to_metatensor
    from monai_rigidreg.transforms import NormalizeHU, ResampleToNetworkGrid
    from monai_rigidreg.transforms.grid import crop_to_grid

    rng = np.random.default_rng(0)
    ct = sitk.GetImageFromArray(rng.integers(-1000, 1500, size=(70, 90, 80)).astype(np.int16))  # [z, y, x]
    ct.SetSpacing((3.0, 2.5, 3.5))
    ct.SetOrigin((-110.0, -100.0, -120.0))
    c, s_ = np.cos(0.2), np.sin(0.2)
    ct.SetDirection((c, -s_, 0.0, s_, c, 0.0, 0.0, 0.0, 1.0))
    grid = Grid.centered((32, 32, 32), (5.0, 5.0, 5.0), Grid.from_sitk(ct).center() + np.array([5.0, -3.0, 2.0]))
    fast = small_registrar.preprocess(ct, grid)
    assert type(fast) is torch.Tensor and fast.shape == (1, 32, 32, 32) and fast.dtype == torch.float32
    mt = sitk_to_metatensor(sitk.Cast(ct, sitk.sitkFloat32))
    assert crop_to_grid(mt, Grid.from_sitk(ct), grid, 2)[0].numel() < 0.8 * mt.numel()  # the crop path runs
    ref = NormalizeHU()(ResampleToNetworkGrid((32, 32, 32), (8.0, 8.0, 8.0))(mt, grid=grid))
    np.testing.assert_allclose(fast.numpy(), torch.as_tensor(ref).numpy(), atol=1e-6)
    mask = sitk.Cast(ct > 0, sitk.sitkUInt8)
    fast_m = small_registrar._on_grid(mask, grid, "nearest", 0.0)
    ref_m = ResampleToNetworkGrid((32, 32, 32), (8.0, 8.0, 8.0))(sitk_to_metatensor(mask), grid=grid, mode="nearest",
                                                                   padding_value=0.0)
    np.testing.assert_array_equal(fast_m.numpy(), torch.as_tensor(ref_m).numpy())


def test_confidence_flags_deliberately_failed_registrations(pair, small_registrar):
    """The failure flag: right transforms pass, deliberately wrong ones (10-20 mm / 10-15 deg off) are flagged."""
    fixed, moving = load_volume(pair["fixed"]), load_volume(pair["moving"])
    grid = small_registrar.network_grid(fixed)
    f_t = small_registrar.preprocess(fixed, grid)
    m_t = small_registrar.preprocess(moving, grid)
    fov = torch.ones_like(f_t[0])
    good = small_registrar.assess(m_t, f_t, grid, np.asarray(MOTION), fov, swap=False)
    wrong = [np.asarray(MOTION) + d for d in ([12, 0, 0, 0, 0, 0], [0, -15, 8, 0, 0, 0], [0, 0, 0, 12, 0, 0],
                                              [5, 5, 0, 0, 0, 15])]
    bad = [small_registrar.assess(m_t, f_t, grid, w, fov, swap=False) for w in wrong]
    assert good["edge_ncc"] > max(b["edge_ncc"] for b in bad)
    assert good["confidence"] >= 0.5
    assert all(b["confidence"] < 0.5 for b in bad), [round(b["local_gain"], 4) for b in bad]
    # swapped-input disagreement alone also flags
    assert confidence_score(0.0, 8.0) < 0.5 and confidence_score(0.0, 0.5) > 0.5
    # and so does tissue on deep air alone (tissue_air.DEEP_LIMIT 0.015 scores 0.5); not measured (NaN): no effect
    assert confidence_score(0.0, 0.5, tissue_on_air_share=0.04) < 0.01
    assert confidence_score(0.0, 0.5, tissue_on_air_share=0.0) == pytest.approx(confidence_score(0.0, 0.5))
    assert confidence_score(0.0, 0.5, tissue_on_air_share=0.015) == pytest.approx(0.5, abs=0.02)
    assert confidence_score(0.0, 0.5, tissue_on_air_share=float("nan")) == confidence_score(0.0, 0.5)
    # the edge gain counts only where the edge optimum lies beyond one probe step (EDGE_OFFSET_LIMIT)
    assert confidence_score(0.05, 0.5) < 0.01
    assert confidence_score(0.05, 0.5, edge_offset_steps=0.6) == pytest.approx(confidence_score(0.0, 0.5))
    assert confidence_score(0.05, 0.5, edge_offset_steps=1.4) < 0.01
    assert confidence_score(0.05, 0.5, edge_offset_steps=float("nan")) < 0.01  # not measured: the gain counts
    assert good["edge_offset"] <= 1.0 and all(b["edge_offset"] > 1.0 for b in bad), [b["edge_offset"] for b in bad]


def test_edge_offset_is_the_parabola_vertex_in_probe_steps():
    """Per parameter the vertex of the parabola through the scores at minus one, zero and plus one step: a score
    curve ``1 - (x - v)^2`` sampled there gives back ``|v|``; the largest over the six parameters counts; a
    parameter along which the scores do not curve down has no optimum (infinite)."""
    from monai_rigidreg.registration.confidence import edge_offset

    def scores(vertices):
        out = [0.0]  # the estimate's score; each parameter's curve -(x - v)^2 taken relative to it
        for v in vertices:
            out += [-((-1.0 - v) ** 2) + v**2, -((1.0 - v) ** 2) + v**2]
        return out

    assert edge_offset(scores([0.0, 0.3, -0.2, 0.0, 0.7, 0.1])) == pytest.approx(0.7)
    assert edge_offset(scores([0.0, 0.0, 0.0, -1.6, 0.0, 0.0])) == pytest.approx(1.6)
    flat = scores([0.0] * 6)
    flat[5], flat[6] = 0.01, 0.02  # the third parameter: both neighbours better
    assert edge_offset(flat) == float("inf")
    assert np.isnan(edge_offset([0.0] * 12 + [float("nan")])) and np.isnan(edge_offset([0.0] * 5))


def test_register_command_with_dicom_and_overwrite_rules(pair, tmp_path, monkeypatch, small_registrar):
    monkeypatch.setattr(RigidRegistrar, "from_bundle", classmethod(lambda cls, *a, **k: small_registrar))
    fixed = load_volume(pair["fixed"])
    dicom = tmp_path / "ct_dicom"
    write_dicom_series(fixed, dicom, "1.2.3.4.5")
    out = tmp_path / "out"
    assert main(["register", "--fixed", str(dicom), "--moving", pair["moving"], "--output-dir", str(out),
                 "--refine"]) == 0
    assert (out / "transform.tfm").is_file() and (out / "qc.png").is_file()
    t = read_transform(out / "transform.tfm")
    assert t.GetName() == "Euler3DTransform"
    # an existing output directory is refused (exit code 2, nothing changed), and replaced with --overwrite
    before = (out / "result.json").read_text()
    assert main(["register", "--fixed", pair["fixed"], "--moving", pair["moving"], "--output-dir", str(out)]) == 2
    assert (out / "result.json").read_text() == before
    assert main(["register", "--fixed", pair["fixed"], "--moving", pair["moving"], "--output-dir", str(out),
                 "--overwrite"]) == 0
    # corrupt input: exit code 2 and no output directory at all
    bad = tmp_path / "corrupt.nii.gz"
    bad.write_bytes(b"\x00" * 100)
    assert main(["register", "--fixed", str(bad), "--moving", pair["moving"], "--output-dir",
                 str(tmp_path / "never")]) == 2
    assert not (tmp_path / "never").exists()
    four_d = tmp_path / "4d.nii.gz"
    sitk.WriteImage(sitk.JoinSeries([fixed, fixed]), str(four_d))
    assert main(["register", "--fixed", str(four_d), "--moving", pair["moving"], "--output-dir",
                 str(tmp_path / "never")]) == 2


def test_shipped_model_recovers_known_motion(fast_pair):
    """The shipped bundle weights on a simulated pair (network, then with refinement)."""
    pair = fast_pair
    try:
        res = register(pair["fixed"], pair["moving"], device="cpu", resample_moving=False)
    except InputError as exc:
        pytest.fail(f"shipped bundle unusable: {exc}")
    fixed = load_volume(pair["fixed"])
    from monai_rigidreg.evaluation.evaluate import body_points

    pts = body_points(fixed)
    tre_net = target_registration_error(res.params, MOTION, pts, center=res.center)
    res_r = register(pair["fixed"], pair["moving"], device="cpu", refine=True, resample_moving=False)
    tre_ref = target_registration_error(res_r.params, MOTION, pts, center=res_r.center)
    initial = target_registration_error(np.zeros(6), MOTION, pts, center=res.center)
    assert initial > 10.0
    assert tre_net < 2.0  # measured about 0.9 mm on this coarse pair (CT 4 mm, CBCT 5 mm voxels)
    assert not res.flagged  # a right answer is not flagged
    assert tre_ref < 2.0


def test_package_register_is_the_function_and_takes_a_registrar_built_once(fast_pair):
    """The README's call: ``monai_rigidreg.register(ct, cbct, model=registrar)`` with a registrar from the bundle."""
    import monai_rigidreg
    from monai_rigidreg import registration

    assert monai_rigidreg.register is registration.register and callable(monai_rigidreg.register)
    registrar = monai_rigidreg.RigidRegistrar.from_bundle(device="cpu")
    a = monai_rigidreg.register(fast_pair["fixed"], fast_pair["moving"], model=registrar, resample_moving=False)
    b = registrar(fast_pair["fixed"], fast_pair["moving"], resample_moving=False)
    np.testing.assert_array_equal(a.params, b.params)
    # `import monai_rigidreg.registration` (done above) must not shadow the function
    assert monai_rigidreg.register is registration.register


def test_network_grid_comes_from_the_bundle_and_its_two_placements():
    from monai_rigidreg.core.network_grid import NetworkGridSpec
    from monai_rigidreg.networks import GaussNewtonStage, TwoStageRigidNet

    shipped = NetworkGridSpec.from_bundle()
    assert shipped.spacing == (2.0, 2.0, 2.0) and shipped.size == (64, 64, 64)
    # a bare network gets the shipped bundle's grid, not a literal of its own
    reg = RigidRegistrar(DualEncoderRigidNet(channels=(4, 8, 8, 8), pool_size=2), device="cpu")
    assert reg.grid_spec == shipped
    # a fine stage built for another spacing is refused rather than run on the wrong grid
    net = TwoStageRigidNet(DualEncoderRigidNet(channels=(4, 8, 8, 8), pool_size=2), GaussNewtonStage((4.0,) * 3))
    with pytest.raises(InputError, match="fine stage works at"):
        RigidRegistrar(net, device="cpu")
    # training placement on the CT centre, inference placement on the CBCT centre
    ct = Grid.centered((100, 100, 50), (1.0, 1.0, 3.0), (10.0, -20.0, 30.0))
    cbct = Grid.centered((64, 64, 64), (1.0, 1.0, 1.0), (40.0, 5.0, 0.0))
    spec = NetworkGridSpec(16, 4.0)
    np.testing.assert_allclose(spec.on_fixed(ct).center(), [10.0, -20.0, 30.0])
    np.testing.assert_allclose(spec.on_moving(cbct).center(), [40.0, 5.0, 0.0])
    np.testing.assert_allclose(spec.canonical().center(), [0.0, 0.0, 0.0])
    assert spec.on_moving(cbct).size == (16, 16, 16) and spec.on_moving(cbct).spacing == (4.0, 4.0, 4.0)
    assert spec.pooled(2) == NetworkGridSpec(8, 8.0)
    with pytest.raises(InputError, match="spacing"):
        NetworkGridSpec(16, 0.0)


@pytest.mark.parametrize("steps", [0, -1, 1.5, "2"])
def test_bad_cascade_steps_are_refused(small_registrar, steps):
    with pytest.raises(InputError, match="cascade_steps"):
        RigidRegistrar(small_registrar.network, network_size=(32, 32, 32), network_spacing=(8.0, 8.0, 8.0),
                       cascade_steps=steps, device="cpu")


def test_a_folder_with_both_series_is_refused_until_the_series_are_named(pair, tmp_path, monkeypatch, capsys,
                                                                        small_registrar):
    """A DICOM folder holding the CT and the CBCT series, given as --fixed and --moving: both sides would pick the
    largest series and register the CT to itself; refused with the series listed, accepted once they are named."""
    monkeypatch.setattr(RigidRegistrar, "from_bundle", classmethod(lambda cls, *a, **k: small_registrar))
    both = tmp_path / "both"
    both.mkdir()
    for name, uid in (("fixed", "1.2.3.4.100"), ("moving", "1.2.3.4.200")):
        single = tmp_path / name
        write_dicom_series(load_volume(pair[name]), single, uid)
        for f in single.iterdir():
            f.rename(both / f"{name}_{f.name}")
    out = tmp_path / "out"
    assert main(["register", "--fixed", str(both), "--moving", str(both), "--output-dir", str(out)]) == 2
    err = capsys.readouterr().err
    assert "same DICOM series 1.2.3.4.100" in err and "1.2.3.4.200" in err and "--moving-series-uid" in err
    assert "slices" in err and "Traceback" not in err
    assert not out.exists()
    assert main(["register", "--fixed", str(both), "--moving", str(both), "--output-dir", str(out),
                 "--fixed-series-uid", "1.2.3.4.100", "--moving-series-uid", "1.2.3.4.200", "--no-qc"]) == 0
    prov = json.loads((out / "result.json").read_text())["provenance"]
    assert prov["inputs"]["fixed"]["series_uid"] == "1.2.3.4.100" and prov["inputs"]["fixed"]["format"] == "dicom"
    assert prov["inputs"]["moving"]["series_uid"] == "1.2.3.4.200"
    assert prov["inputs"]["fixed"]["study_uid"] == "1.2.826.0.1.3680043.2.1125.1"
    # the same file on both sides, through the Python API too
    with pytest.raises(InputError, match="same file"):
        register(pair["fixed"], pair["fixed"], model=small_registrar)


def test_result_json_audit_trail_and_inverse_matrices(fast_pair, tmp_path):
    """``result.json`` of a CLI run with the shipped bundle: inputs, bundle version and weights' SHA-256, software
    versions, time, command line; the moving->fixed matrix (LPS and RAS) is the inverse of the fixed->moving one."""
    import hashlib

    from monai_rigidreg.bundle import default_bundle_path

    out = tmp_path / "out"
    assert main(["register", "--fixed", str(fast_pair["fixed"]), "--moving", str(fast_pair["moving"]),
                 "--output-dir", str(out), "--no-qc", "--device", "cpu"]) == 0
    result = json.loads((out / "result.json").read_text())
    prov = result["provenance"]
    weights = default_bundle_path() / "models" / "model.pt"
    assert prov["bundle"]["weights_sha256"] == hashlib.sha256(weights.read_bytes()).hexdigest()
    assert prov["bundle"]["version"] == json.loads((default_bundle_path() / "configs" / "metadata.json")
                                                   .read_text())["version"]
    assert prov["inputs"]["fixed"]["path"].endswith(str(fast_pair["fixed"]).split("/")[-1])
    assert {"monai_rigidreg", "torch", "monai", "SimpleITK"} <= set(prov["software"])
    assert prov["device"] == "cpu" and prov["timestamp_utc"].endswith("+00:00") and prov["command_line"]
    m = np.array(result["matrix"])
    np.testing.assert_allclose(np.array(result["matrix_moving_to_fixed"]) @ m, np.eye(4), atol=1e-9)
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])
    np.testing.assert_allclose(np.array(result["matrix_moving_to_fixed_ras"]),
                               flip @ np.linalg.inv(m) @ flip, atol=1e-9)


def test_fine_stage_switch_returns_the_regressions_own_estimate(fast_pair, tmp_path):
    """``register(..., fine_stage=False)`` (also with a registrar built once) and ``--no-fine-stage``: the learned
    regression's estimate itself, re-expressed about the CT centre; the registrar's network is left as it was."""
    import torch

    from monai_rigidreg.core.geometry import recenter_params

    registrar = RigidRegistrar.from_bundle(device="cpu")
    fixed, moving = load_volume(fast_pair["fixed"]), load_volume(fast_pair["moving"])
    alone = register(fixed, moving, model=registrar, fine_stage=False, resample_moving=False)
    full = register(fixed, moving, model=registrar, resample_moving=False)
    assert registrar.network.fine_stage_enabled  # restored
    assert alone.details["fine_stage"] is False and full.details["fine_stage"] is True
    grid = registrar.network_grid(fixed, moving)
    m_t, f_t = registrar.preprocess(moving, grid), registrar.preprocess(fixed, grid)
    # the shipped regression (ContextCorrelationNet) also reads the CT on its wider context grid, same centre
    context = registrar._context(fixed, grid, None)
    with torch.no_grad():
        own = registrar.network.regression.forward_pair(m_t[None], f_t[None], context[None])[0].double().numpy()
    np.testing.assert_allclose(alone.params, recenter_params(own, grid.center(), alone.center), atol=1e-4)
    assert np.abs(alone.params - full.params).max() > 0.01  # the fine stage does move the estimate
    out = tmp_path / "out"
    assert main(["register", "--fixed", str(fast_pair["fixed"]), "--moving", str(fast_pair["moving"]),
                 "--output-dir", str(out), "--no-qc", "--no-fine-stage", "--device", "cpu"]) == 0
    result = json.loads((out / "result.json").read_text())
    assert result["details"]["fine_stage"] is False
    np.testing.assert_allclose([result["params"][k] for k in ("tx", "ty", "tz", "rx", "ry", "rz")], alone.params,
                               atol=1e-4)


def test_the_default_path_runs_the_bundle_s_lead_passes_and_the_network_alone_its_own(fast_pair, monkeypatch):
    """``lead_passes`` (the bundle's ``[2, 1]``): the learned levels' passes while the fine stage follows; the learned
    network alone (``fine_stage=False``) keeps the regression's own (``network_def.regression.passes``, ``[4, 1]``),
    and the regression's setting is restored after every call."""
    registrar = RigidRegistrar.from_bundle(device="cpu")
    regression = registrar.network.regression
    assert registrar.lead_passes == (2, 1) and regression.passes == (4, 1)
    seen = []
    levels = regression.forward_levels

    def spy(*args, **kwargs):
        seen.append(regression.passes)
        return levels(*args, **kwargs)

    monkeypatch.setattr(regression, "forward_levels", spy)
    fixed, moving = load_volume(fast_pair["fixed"]), load_volume(fast_pair["moving"])
    register(fixed, moving, model=registrar, resample_moving=False)
    assert seen and set(seen) == {(2, 1)} and regression.passes == (4, 1)
    seen.clear()
    register(fixed, moving, model=registrar, fine_stage=False, resample_moving=False)
    assert seen and set(seen) == {(4, 1)} and regression.passes == (4, 1)
    with pytest.raises(InputError, match="lead_passes"):
        RigidRegistrar(registrar.network, lead_passes=(2,))


def test_the_network_alone_is_flagged_where_the_last_level_would_move_it_far(fast_pair, monkeypatch):
    """``fine_stage=False``: the last level runs from the learned estimate as a probe (the estimate is kept), and how
    far it would move it, ``details.signals.polish_probe_mm``, is about the estimate's error: an estimate 4 mm and
    3 degrees off the true motion (the network's output replaced, so the test does not depend on how good the shipped
    weights are on this small phantom) is probed at about its error and flagged ``"unpolished"``; an estimate at the
    true motion is moved a fraction of a millimetre and not flagged for it; the default path runs no probe."""
    from monai_rigidreg.core.geometry import recenter_params
    from monai_rigidreg.registration.calibration import POLISH_PROBE_LIMIT_MM

    registrar = RigidRegistrar.from_bundle(device="cpu")
    fixed, moving = load_volume(fast_pair["fixed"]), load_volume(fast_pair["moving"])
    truth = np.asarray(MOTION, dtype=np.float64)  # about the CT centre
    center = Grid.from_sitk(fixed).center()  # the result's centre (RegistrationResult.center)

    def network_at(params):
        def estimate(moving_t, fixed_t, grid, *args, **kwargs):
            return np.stack([recenter_params(params, center, grid.center())] * len(moving_t))
        return estimate

    off = truth + np.array([4.0, 0.0, 0.0, 0.0, 3.0, 0.0])
    monkeypatch.setattr(registrar, "estimate_batch", network_at(off))
    alone = register(fixed, moving, model=registrar, fine_stage=False, resample_moving=False)
    np.testing.assert_allclose(alone.center, center)
    np.testing.assert_allclose(alone.params, off, atol=1e-3)  # the estimate is kept as it came
    tre = _fast_pair_tre(fast_pair, alone)
    probe = alone.details["signals"]["polish_probe_mm"]
    # the probe under-reads the error a little (0.54-0.96 of it over the calibration cases, docs/trust.md)
    assert tre > POLISH_PROBE_LIMIT_MM and 0.5 * tre < probe < 1.05 * tre
    assert "unpolished" in alone.details["flag_reasons"] and alone.flagged and alone.timings["polish_probe"] > 0

    monkeypatch.setattr(registrar, "estimate_batch", network_at(truth))
    right = register(fixed, moving, model=registrar, fine_stage=False, resample_moving=False)
    np.testing.assert_allclose(right.params, truth, atol=1e-3)
    assert right.details["signals"]["polish_probe_mm"] < 1.0 and "unpolished" not in right.details["flag_reasons"]
    monkeypatch.undo()
    full = register(fixed, moving, model=registrar, resample_moving=False)
    assert "polish_probe_mm" not in full.details["signals"] and "polish_probe" not in full.timings


# -- the swapped-input estimate as a third candidate (confidence.SWAP_AGREE_MM) -------------------------------------


@pytest.fixture(scope="module")
def shipped_registrar():
    return RigidRegistrar.from_bundle(device="cpu")


def _fast_pair_tre(fast_pair, res) -> float:
    from monai_rigidreg.evaluation.evaluate import body_points

    return float(target_registration_error(res.params, MOTION, body_points(load_volume(fast_pair["fixed"])),
                                           center=res.center))


def _last_level_spoiled_once(real):
    """A ``refine_native`` stand-in whose first result is moved 12 mm along x, and the list its calls append to."""
    calls: list[int] = []

    def spoiled_once(fixed, moving, matrix, *args, **kwargs):
        out, grid = real(fixed, moving, matrix, *args, **kwargs)
        calls.append(1)
        if len(calls) == 1:
            out = out @ params_to_matrix([12.0, 0.0, 0.0, 0.0, 0.0, 0.0], np.zeros(3))
        return out, grid

    return spoiled_once, calls


@pytest.mark.parametrize("broken", ["refine_native", "assess_estimate", "global_search"])
def test_a_failing_stage_leaves_no_worker_thread_running(fast_pair, shipped_registrar, monkeypatch, broken):
    """The global search and the swapped-input estimate run in worker threads: when a stage raises (the last level,
    the confidence check before it takes the twin, the search itself), the error reaches the caller and every
    worker has finished (none left using the network); the next registration runs normally."""
    import threading

    from monai_rigidreg.registration import confidence, last_level, search

    def failing(*args, **kwargs):
        raise RuntimeError(f"{broken} broke")

    with monkeypatch.context() as m:
        m.setattr({"refine_native": last_level, "assess_estimate": confidence, "global_search": search}[broken], broken,
                  failing)
        with pytest.raises(RuntimeError, match=f"{broken} broke"):
            shipped_registrar(fast_pair["fixed"], fast_pair["moving"], resample_moving=False, thorough=True)
    assert not [t for t in threading.enumerate() if t.name.startswith("monai-rigidreg-")]
    res = shipped_registrar(fast_pair["fixed"], fast_pair["moving"], resample_moving=False, thorough=True,
                            global_init=False)
    assert res.timings["swap_estimate"] > 0 and "swap_tre_mm" in res.details["signals"]
    assert res.details["swap_estimate"] == "beside the last level"
    assert _fast_pair_tre(fast_pair, res) < 2.0


def test_a_stale_early_twin_is_computed_again_after_the_last_level(fast_pair, shipped_registrar, monkeypatch):
    """Where the last level moves the estimate by more than EARLY_SWAP_MAX_CHANGE_MM, the twin started beside it
    (its CT masked for the network's estimate) is dropped and the confidence check computes its own from the refined
    estimate: the same signals as a registration that never started one early."""
    import monai_rigidreg.registration.confidence as conf_mod
    import monai_rigidreg.registration.last_level as reg_mod

    real = conf_mod.assess_estimate
    seen = []

    def spy(*args, swapped=None, **kwargs):
        seen.append(swapped is not None)
        return real(*args, swapped=swapped, **kwargs)

    monkeypatch.setattr(conf_mod, "assess_estimate", spy)
    monkeypatch.setattr(reg_mod, "EARLY_SWAP_MAX_CHANGE_MM", -1.0)  # every change counts as stale
    res = shipped_registrar(fast_pair["fixed"], fast_pair["moving"], resample_moving=False, thorough=True,
                            global_init=False)
    assert seen == [False] and res.details["swap_estimate"] == "after the last level"
    assert "swap_estimate" not in res.timings
    monkeypatch.setattr(reg_mod, "EARLY_SWAP_MAX_CHANGE_MM", 1e9)
    early = shipped_registrar(fast_pair["fixed"], fast_pair["moving"], resample_moving=False, thorough=True,
                              global_init=False)
    assert seen == [False, True] and early.details["swap_estimate"] == "beside the last level"
    # the last level moved this estimate by a fraction of a millimetre: both twins agree with it alike
    assert abs(early.details["signals"]["swap_tre_mm"] - res.details["signals"]["swap_tre_mm"]) < 0.2
    assert early.details["native_level"]["change_mm"] < reg_mod.EARLY_SWAP_MAX_CHANGE_MM


def test_registrar_lowers_its_threads_while_other_work_is_busy_and_restores_them(fast_pair, shipped_registrar,
                                                                                monkeypatch):
    """adapt_threads: a call starting while other work keeps cores busy runs with fewer torch and SimpleITK threads
    (its worker threads too) and restores the caller's counts afterwards; details.cpu_threads says how many;
    adapt_threads=False (``--threads N``) keeps the counts as set."""
    import SimpleITK as sitk_

    import monai_rigidreg.registration.last_level as reg_mod

    seen = []
    real_native = reg_mod.refine_native

    def watching(*args, **kwargs):
        seen.append((torch.get_num_threads(), sitk_.ProcessObject.GetGlobalDefaultNumberOfThreads()))
        return real_native(*args, **kwargs)

    torch_before, itk_before = torch.get_num_threads(), sitk_.ProcessObject.GetGlobalDefaultNumberOfThreads()
    monkeypatch.setattr(reg_mod, "refine_native", watching)
    import monai_rigidreg.core.device as device_mod

    monkeypatch.setattr(device_mod, "adaptive_threads", lambda current: 1)  # as if other work kept the rest busy
    try:
        torch.set_num_threads(2)
        sitk_.ProcessObject.SetGlobalDefaultNumberOfThreads(2)
        res = shipped_registrar(fast_pair["fixed"], fast_pair["moving"], resample_moving=False, global_init=False)
        assert res.details["cpu_threads"] == 1 and seen and set(seen) == {(1, 1)}  # every pass of the last level
        assert torch.get_num_threads() == 2 and sitk_.ProcessObject.GetGlobalDefaultNumberOfThreads() == 2
        assert _fast_pair_tre(fast_pair, res) < 2.0
        shipped_registrar.adapt_threads = False
        res = shipped_registrar(fast_pair["fixed"], fast_pair["moving"], resample_moving=False, global_init=False)
        assert res.details["cpu_threads"] == 2 and seen[-1] == (2, 2)
    finally:
        shipped_registrar.adapt_threads = True
        torch.set_num_threads(torch_before)
        sitk_.ProcessObject.SetGlobalDefaultNumberOfThreads(itk_before)


def test_starts_run_in_one_batch_give_each_starts_own_estimate(fast_pair, shipped_registrar):
    """The global search's candidates go through the network as one batch (RigidRegistrar._runs_from): each start's
    grid, tensors and total are its own, and its estimate that of the start run alone (the fine stage's early stop,
    shared by the batch, may add a step: agreement to 0.05 mm / degrees; a mixed-up case would be millimetres off)."""
    fixed = load_volume(fast_pair["fixed"])
    moving = load_volume(fast_pair["moving"])
    center = Grid.from_sitk(moving).center()
    starts = [params_to_matrix(p, center) for p in
              ([0.0, 0.0, 0.0, 0.0, 0.0, 0.0], [12.0, -6.0, 4.0, 0.0, 10.0, 0.0], [-8.0, 0.0, 9.0, -15.0, 0.0, 5.0])]
    timings: dict = {}
    batched = shipped_registrar._runs_from(fixed, moving, starts, None, [], timings)
    assert timings["network"] > 0
    alone = [shipped_registrar._run_from(fixed, moving, start, None, [], {}) for start in starts]
    for one, many in zip(alone, batched):
        assert one.grid == many.grid
        np.testing.assert_allclose(many.residual, one.residual, atol=0.05)
        np.testing.assert_allclose(many.total, one.total, atol=0.05)
    # the starts differ, and so do the estimates' residuals
    assert np.abs(batched[1].residual - batched[2].residual).max() > 1.0


def _fake_search(matrices):
    """A global_search stand-in returning these fixed -> moving candidates, best first."""
    from monai_rigidreg.registration.search import SearchCandidate

    def search(*args, **kwargs):
        return [SearchCandidate(np.asarray(m), 0.9 - 0.01 * k, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
                for k, m in enumerate(matrices)]

    return search


def test_further_search_starts_run_only_where_the_best_one_leads_elsewhere(fast_pair, shipped_registrar,
                                                                           monkeypatch):
    """The search's best candidate 12 mm from the identity's estimate (beyond SEARCH_AGREE_MM): the network from
    it comes back to the same pose, so the next candidates are not run; where the best candidate's run ends 20 mm
    away (its estimate moved, as a wrong basin would leave it), the other three run too and the right pose wins."""
    import dataclasses

    import monai_rigidreg.registration.search as reg_mod

    fixed, moving = load_volume(fast_pair["fixed"]), load_volume(fast_pair["moving"])
    alone = shipped_registrar(fixed, moving, resample_moving=False, thorough=True, global_init=False, assess=False)
    c = Grid.from_sitk(moving).center()
    near = alone.matrix @ params_to_matrix([12.0, 0.0, 0.0, 0.0, 0.0, 0.0], c)
    monkeypatch.setattr(reg_mod, "global_search", _fake_search([near, near, near, near]))
    res = shipped_registrar(fixed, moving, resample_moving=False, thorough=True, assess=False)
    search = res.details["global_search"]
    assert search["distance_to_identity_start_mm"] > reg_mod.SEARCH_AGREE_MM
    assert search["best_start_to_identity_estimate_mm"] < reg_mod.SAME_POSE_MM
    assert search["starts_run"] == 1 and len(search["search_start_ncc"]) == 1
    assert _fast_pair_tre(fast_pair, res) < 2.0

    real = shipped_registrar._runs_from
    calls = []

    def first_run_elsewhere(fixed_img, moving_img, starts, *args, **kwargs):
        runs = real(fixed_img, moving_img, starts, *args, **kwargs)
        calls.append(len(starts))
        if len(calls) == 2:  # the identity's run, then the best candidate's
            runs[0] = dataclasses.replace(runs[0], total=runs[0].total @ params_to_matrix([20.0, 0, 0, 0, 0, 0], c))
        return runs

    monkeypatch.setattr(shipped_registrar, "_runs_from", first_run_elsewhere)
    res = shipped_registrar(fixed, moving, resample_moving=False, thorough=True, assess=False)
    search = res.details["global_search"]
    assert calls == [1, 1, 3]  # the identity's run, the best candidate's, the other three in one batch
    assert search["best_start_to_identity_estimate_mm"] > reg_mod.SAME_POSE_MM
    assert search["starts_run"] == 4 and len(search["search_start_ncc"]) == 4
    assert search.get("start_rank", 1) != 0  # the moved estimate does not win
    assert _fast_pair_tre(fast_pair, res) < 2.0


def test_the_global_search_runs_beside_the_network_and_its_errors_reach_the_caller(fast_pair, shipped_registrar,
                                                                                    monkeypatch):
    """The search runs in a worker thread beside the network from the identity: its candidates are those of a direct
    call, its own time and the wait are recorded, and an exception in it is raised to the caller (not lost in the
    thread, no result written)."""
    import threading

    import monai_rigidreg.registration.search as reg_mod
    from monai_rigidreg.registration.confidence import cylindrical_fov_mask
    from monai_rigidreg.registration.search import global_search

    fixed, moving = load_volume(fast_pair["fixed"]), load_volume(fast_pair["moving"])
    threads = []
    real = reg_mod.global_search

    def recording(*args, **kwargs):
        threads.append(threading.current_thread().name)
        return real(*args, **kwargs)

    monkeypatch.setattr(reg_mod, "global_search", recording)
    res = shipped_registrar(fixed, moving, resample_moving=False, thorough=True, assess=False)
    assert threads == ["monai-rigidreg-search"]
    body = shipped_registrar._bodies(fixed)
    direct = global_search(fixed, moving, cylindrical_fov_mask(moving), hu_range=shipped_registrar.hu_range,
                           fixed_body=body)
    assert res.details["global_search"]["candidates"] == [c.to_dict() for c in direct]
    assert res.timings["global_search"] > 0 and 0 <= res.timings["global_search_wait"] <= res.timings["total"]

    def failing(*args, **kwargs):
        raise MemoryError("search out of memory")

    monkeypatch.setattr(reg_mod, "global_search", failing)
    with pytest.raises(MemoryError, match="search out of memory"):
        shipped_registrar(fixed, moving, resample_moving=False, thorough=True, assess=False)


def test_a_better_swapped_estimate_replaces_a_wrong_one(fast_pair, shipped_registrar, monkeypatch):
    """The last level is made to return an estimate 12 mm off (once); the swapped-input estimate disagrees, matches
    the images better, and replaces it after its own last level: the result is right again, in the right frame
    (a composition in the wrong order or direction would leave it centimetres off)."""
    import monai_rigidreg.registration.last_level as reg_mod

    spoiled_once, calls = _last_level_spoiled_once(reg_mod.refine_native)
    monkeypatch.setattr(reg_mod, "refine_native", spoiled_once)
    monkeypatch.setattr(reg_mod, "NATIVE_MAX_PASSES", 1)  # one pass, so the spoiled result stays (test_last_level)
    res = shipped_registrar(fast_pair["fixed"], fast_pair["moving"], resample_moving=False, thorough=True,
                            global_init=False)
    assert len(calls) == 2  # the spoiled estimate, then the swapped one's last level
    # details.native_level describes the swapped estimate's own last level (a small correction), not the spoiled one
    assert res.details["native_level"]["change_mm"] < 5.0
    check = res.details["swap_check"]
    assert check["replaced"] and check["swap_tre_mm"] > 8.0 and check["swapped_ncc"] > check["estimate_ncc"]
    assert res.details["start"] == "swapped"
    assert _fast_pair_tre(fast_pair, res) < 2.0
    assert not res.flagged


def _offset_twin(monkeypatch, offset) -> None:
    """The swapped-input estimate moved by ``offset`` (params, mm / degrees), wherever it is made: started beside
    the last level (``swapped``) or computed in the check (``estimate``)."""
    import monai_rigidreg.registration.confidence as conf_mod

    real, offset = conf_mod.assess_estimate, np.asarray(offset, dtype=np.float64)

    def moved(moving_t, fixed_t, grid, params, fov, estimate=None, swapped=None, **kwargs):
        assert swapped is not None  # the thorough path starts it early
        spoiled = None if estimate is None else (lambda m, f: estimate(m, f) + offset)
        return real(moving_t, fixed_t, grid, params, fov, spoiled, swapped=lambda: swapped() + offset, **kwargs)

    monkeypatch.setattr(conf_mod, "assess_estimate", moved)


def test_a_worse_swapped_estimate_does_not_count_against_a_right_one(fast_pair, shipped_registrar, monkeypatch):
    """The swapped-input estimate is made 15 mm wrong: it disagrees, matches the images worse, so the estimate
    stays (right) and the disagreement does not flag it; the same disagreement counted would."""
    _offset_twin(monkeypatch, [0.0, 15.0, 0, 0, 0, 0])
    res = shipped_registrar(fast_pair["fixed"], fast_pair["moving"], resample_moving=False, thorough=True,
                            global_init=False)
    check = res.details["swap_check"]
    assert not check["replaced"] and check["swap_tre_mm"] > 10.0 and check["swapped_ncc"] < check["estimate_ncc"]
    assert res.details["signals"]["swap_counted"] is False and res.details["start"] == "identity"
    # the images chose clearly between the two: not ambiguous (calibration.AMBIGUOUS_NCC_GAP)
    gap = res.details["signals"]["alternative_ncc_gap"]
    assert gap == pytest.approx(abs(check["estimate_ncc"] - check["swapped_ncc"]), abs=2e-4) and gap > 0.1
    assert _fast_pair_tre(fast_pair, res) < 2.0
    assert not res.flagged
    assert confidence_score(res.details["signals"]["local_gain"], check["swap_tre_mm"]) < 0.5
    assert confidence_score(0.0, 8.0, swap_counted=False) > 0.5


def test_a_twin_a_few_mm_away_is_not_a_distinct_pose(fast_pair, shipped_registrar, monkeypatch):
    """The swapped-input estimate (the network's, unpolished) is moved 4.5 mm: it disagrees (over SWAP_AGREE_MM)
    but lies within AMBIGUOUS_TWIN_MM of the polished estimate, so however close their image match, it is not
    recorded as a distinct pose and does not flag the result ``ambiguous``."""
    import monai_rigidreg.registration.confidence as conf_mod

    _offset_twin(monkeypatch, [0.0, 4.5, 0, 0, 0, 0])
    res = shipped_registrar(fast_pair["fixed"], fast_pair["moving"], resample_moving=False, thorough=True,
                            global_init=False)
    check = res.details["swap_check"]
    assert conf_mod.SWAP_AGREE_MM < check["swap_tre_mm"] < conf_mod.AMBIGUOUS_TWIN_MM
    assert not check["replaced"] and "alternative_ncc_gap" not in res.details["signals"]
    assert "ambiguous" not in res.details["flag_reasons"]
    assert _fast_pair_tre(fast_pair, res) < 2.0


def test_a_replacing_twin_that_disagrees_with_its_own_twin_is_flagged(fast_pair, shipped_registrar, monkeypatch):
    """The last level returns an estimate 12 mm off once, so the swapped estimate replaces it (as above); that
    replacement's own twin is then made 15 mm wrong: it matches worse, but after a replacement the two directions
    kept disagreeing, so the disagreement counts and the result is flagged (not so without the replacement, see
    the test above)."""
    import monai_rigidreg.registration.confidence as conf_mod
    import monai_rigidreg.registration.last_level as reg_mod

    real_assess = conf_mod.assess_estimate
    spoiled_once, _ = _last_level_spoiled_once(reg_mod.refine_native)
    monkeypatch.setattr(reg_mod, "NATIVE_MAX_PASSES", 1)  # one pass, so the spoiled result stays (test_last_level)
    assess_calls = []

    def wrong_second_swap(moving_t, fixed_t, grid, params, fov, estimate=None, **kwargs):
        assess_calls.append(1)
        if estimate is not None and len(assess_calls) > 1:
            estimate_ = estimate

            def estimate(m, f):
                return estimate_(m, f) + np.array([0.0, 15.0, 0, 0, 0, 0])
        return real_assess(moving_t, fixed_t, grid, params, fov, estimate, **kwargs)

    monkeypatch.setattr(reg_mod, "refine_native", spoiled_once)
    monkeypatch.setattr(conf_mod, "assess_estimate", wrong_second_swap)
    res = shipped_registrar(fast_pair["fixed"], fast_pair["moving"], resample_moving=False, thorough=True,
                            global_init=False)
    check = res.details["swap_check"]
    assert check["replaced"] and res.details["start"] == "swapped" and len(assess_calls) == 2
    after = check["after_replacement"]
    assert after["swap_tre_mm"] > 10.0 and after["swapped_ncc"] < after["estimate_ncc"]
    assert res.details["signals"]["swap_counted"] is True
    assert _fast_pair_tre(fast_pair, res) < 2.0  # the estimate itself is right; the flag says it is unsettled
    assert res.flagged


def test_swapped_estimate_started_early_gives_the_same_signals(fast_pair, shipped_registrar):
    """swap_inputs builds exactly what assess_estimate hands its estimator (the CT masked by the field of view as
    the estimate places it): a swapped estimate computed from them ahead of time gives the same signals; one from
    inputs masked by another estimate (12 mm away) gives a different twin."""
    from monai_rigidreg.registration.confidence import swap_inputs

    fixed, moving = load_volume(fast_pair["fixed"]), load_volume(fast_pair["moving"])
    grid = shipped_registrar.network_grid(fixed)
    f_t = shipped_registrar.preprocess(fixed, grid)
    m_t = shipped_registrar.preprocess(moving, grid)
    fov = torch.zeros_like(f_t[0])
    n = grid.size[0]
    fov[n // 6: n - n // 6, n // 6: n - n // 6] = 1.0  # a truncated view: the mask placement matters
    p = np.asarray(MOTION, dtype=np.float64)
    inline = shipped_registrar.assess(m_t, f_t, grid, p, fov)
    twin = shipped_registrar.estimate(*swap_inputs(m_t, f_t, grid, p, fov), grid)
    early = shipped_registrar.assess(m_t, f_t, grid, p, fov, swapped=lambda: twin)
    for key in ("swap_tre_mm", "local_gain", "edge_ncc", "tissue_on_air"):
        assert early[key] == inline[key], key
    np.testing.assert_array_equal(early["swap_params"], inline["swap_params"])
    other = shipped_registrar.estimate(*swap_inputs(m_t, f_t, grid, p + np.array([12.0, 0, 0, 0, 0, 0]), fov), grid)
    assert not np.allclose(other, twin, atol=1e-3)


def test_edge_test_looks_inside_the_match_region_only(pair, small_registrar):
    """A CBCT whose half beyond x = centre moved 6 mm further: over the whole field of view the right estimate for
    the other half loses edge alignment to a perturbation (gain above the limit); restricted to that half (the
    region the estimate was asked to match) it sits at the optimum."""
    from monai_rigidreg.core.warp import warp_volume_params
    from monai_rigidreg.registration.confidence import LOCAL_GAIN_LIMIT

    fixed, moving = load_volume(pair["fixed"]), load_volume(pair["moving"])
    grid = small_registrar.network_grid(fixed)
    f_t = small_registrar.preprocess(fixed, grid)
    m_t = small_registrar.preprocess(moving, grid)
    shifted = warp_volume_params(m_t[None], torch.tensor([[6.0, 0, 0, 0, 0, 0]]), grid)[0]
    half = torch.zeros_like(m_t[0])
    half[grid.size[0] // 2:] = 1.0  # x index >= centre: the moved half (LPS +x, in the moving frame)
    mixed = m_t * (1 - half) + shifted * half
    fov = torch.ones_like(f_t[0])
    region = 1.0 - half  # the other half; the motion is small, so the fixed-frame half is about the same voxels
    whole = small_registrar.assess(mixed, f_t, grid, np.asarray(MOTION), fov, swap=False)
    inside = small_registrar.assess(mixed, f_t, grid, np.asarray(MOTION), fov, swap=False, region=region)
    assert whole["local_gain"] > LOCAL_GAIN_LIMIT, whole["local_gain"]
    assert inside["local_gain"] < LOCAL_GAIN_LIMIT / 2, inside["local_gain"]


def test_tissue_on_air_separates_right_and_grossly_wrong_poses(pair, small_registrar):
    """The gross-failure signal: at the true pose almost none of the CT's tissue in view lies on CBCT air; shifted
    30 mm along x or turned 40 degrees about z (the phantom beside itself), a large share does (0.31, 0.19). An exact
    computation on toy volumes pins the levels and the field-of-view restriction."""
    from monai_rigidreg.core.warp import warp_volume_params
    from monai_rigidreg.registration.confidence import AIR_HU, TISSUE_HU, tissue_on_air

    fixed, moving = load_volume(pair["fixed"]), load_volume(pair["moving"])
    grid = small_registrar.network_grid(fixed)
    f_t = small_registrar.preprocess(fixed, grid)[0]
    m_t = small_registrar.preprocess(moving, grid)[0]
    fov = torch.ones_like(f_t)

    def at(params):
        moved = warp_volume_params(m_t[None, None], torch.tensor([params], dtype=torch.float32), grid)[0, 0]
        return tissue_on_air(f_t, moved, fov)

    right = at(list(MOTION))
    shifted = at([MOTION[0] + 30.0, *MOTION[1:]])
    turned = at([*MOTION[:5], MOTION[5] + 40.0])
    assert right < 0.02, right
    assert shifted > 0.2 and turned > 0.1, (shifted, turned)
    # toy volumes: 1000 tissue voxels in view, 250 of them on air; tissue outside the view does not count
    lo, hi = -1000.0, 2000.0
    norm = lambda hu: (hu - lo) / (hi - lo)  # noqa: E731
    ct = torch.full((20, 10, 10), norm(TISSUE_HU - 100))
    ct[:10] = norm(TISSUE_HU + 100)
    cb = torch.full((20, 10, 10), norm(0.0))
    cb[:10, :, :] = norm(0.0)
    cb[:10, :5, :5] = norm(AIR_HU - 100)  # 250 voxels of air under tissue
    view = torch.zeros(20, 10, 10)
    view[:10] = 1.0
    assert tissue_on_air(ct, cb, view) == pytest.approx(0.25)
    # tissue on air outside the view does not count
    ct_out, cb_out = ct.clone(), cb.clone()
    ct_out[10:] = norm(TISSUE_HU + 100)
    cb_out[10:, :, :5] = norm(AIR_HU - 100)
    assert tissue_on_air(ct_out, cb_out, view) == pytest.approx(0.25)
    # another normalization window: the levels follow it
    lo2, hi2 = -1200.0, 3000.0
    renorm = lambda t: ((t * (hi - lo) + lo) - lo2) / (hi2 - lo2)  # noqa: E731
    assert tissue_on_air(renorm(ct), renorm(cb), view, (lo2, hi2)) == pytest.approx(0.25)
    assert tissue_on_air(renorm(ct), renorm(cb), view) != pytest.approx(0.25)
    cb[:10, :5, :5] = norm(AIR_HU + 100)  # just above the air level: no longer air
    assert tissue_on_air(ct, cb, view) == 0.0
    view[:] = 0.0
    assert np.isnan(tissue_on_air(ct, cb, view))  # nothing in view: no signal


def test_deep_air_leaves_out_the_band_along_the_cbcts_body_outline():
    """``tissue_on_air_deep`` (the rule's signal): tissue on a two-voxel band of CBCT air along its body (an outline
    that moved, a millimetre of error) does not count; tissue on air that reaches deeper than
    :data:`~monai_rigidreg.registration.tissue_air.DEEP_AIR_MM` does, voxel for voxel where the air's box is all
    air. On the 2 mm network grid the radius is two voxels; on a 4 mm one, one."""
    from monai_rigidreg.registration.tissue_air import AIR_HU, TISSUE_HU, deep_air_radius, tissue_on_air

    lo, hi = -1000.0, 2000.0
    norm = lambda hu: (hu - lo) / (hi - lo)  # noqa: E731
    assert deep_air_radius((2.0, 2.0, 2.0)) == [2, 2, 2] and deep_air_radius((4.0, 1.0, 2.5)) == [1, 4, 2]
    ct = torch.full((30, 12, 12), norm(TISSUE_HU + 100))  # tissue everywhere in view
    cb = torch.full((30, 12, 12), norm(0.0))
    view = torch.ones(30, 12, 12)
    radius = deep_air_radius((2.0, 2.0, 2.0))
    cb[:, :2, :] = norm(AIR_HU - 100)  # a two-voxel band of air along one face: an outline 4 mm off
    band = tissue_on_air(ct, cb, view)
    assert band == pytest.approx(2 / 12)
    assert tissue_on_air(ct, cb, view, air_radius=radius) == 0.0
    cb[:, :, :] = norm(0.0)
    cb[:10, :, :] = norm(AIR_HU - 100)  # a block of 10 of 30 slices: the volume's own edge does not erode it
    deep = tissue_on_air(ct, cb, view, air_radius=radius)
    assert deep == pytest.approx((10 - 2) / 30)  # all but the two slices next to the CBCT's tissue
    assert tissue_on_air(ct, cb, view) == pytest.approx(10 / 30)


def test_the_last_level_bias_degree_follows_the_match_region(fast_pair, shipped_registrar, monkeypatch):
    """Without a match region the last level fits a constant bias (the bundle's native_bias_degree, 0), with
    ``roi=`` the quadratic (native_bias_degree_roi, 2); details.native_level says which it used."""
    import monai_rigidreg.registration.last_level as reg_mod

    real = reg_mod.refine_native
    seen = []

    def record(*args, **kwargs):
        seen.append(kwargs["bias_degree"])
        return real(*args, **kwargs)

    monkeypatch.setattr(reg_mod, "refine_native", record)
    whole = shipped_registrar(fast_pair["fixed"], fast_pair["moving"], resample_moving=False, global_init=False)
    c = Grid.from_sitk(load_volume(fast_pair["fixed"])).center()
    box = [*(c - 60.0), *(c + 60.0)]
    boxed = shipped_registrar(fast_pair["fixed"], fast_pair["moving"], resample_moving=False, global_init=False,
                              roi=box)
    # the registrar scores its estimate with the tissue-on-air signal too (the hand-set rule's score; the confidence
    # itself is the calibrated one, test_calibration.py)
    sig = whole.details["signals"]
    assert 0.0 <= sig["tissue_on_air"] < 0.02
    assert {"bone_share", "bone_agreement"} <= set(sig)  # recorded for the calibration (registration.bone_check)
    assert sig["rule_score"] == pytest.approx(confidence_score(sig["local_gain"], sig["swap_tre_mm"],
                                                              swap_counted=sig.get("swap_counted", True),
                                                              tissue_on_air_share=sig["tissue_on_air_deep"],
                                                              edge_offset_steps=sig["edge_offset"]))
    assert whole.details["native_level"]["bias_degree"] == 0 and seen[0] == 0
    assert boxed.details["native_level"]["bias_degree"] == 2 and seen[-1] == 2
    assert _fast_pair_tre(fast_pair, whole) < 2.0 and _fast_pair_tre(fast_pair, boxed) < 2.0



def test_result_json_is_strict_json_with_unmeasured_signals_as_null():
    """A signal that was not measured (NaN: no tissue in view, a check that did not run) is written as null, so
    strict JSON readers (allow_nan=False here) accept result.json; finite values and numpy scalars pass as numbers."""
    from monai_rigidreg.registration import RegistrationResult

    res = RegistrationResult(np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]), np.zeros(3), None, {"total": 1.5},
                             float("nan"), False,
                             {"signals": {"tissue_on_air": float("nan"), "local_gain": np.float32(0.002),
                                          "swap_tre_mm": np.float64(np.inf)}, "grid": np.array([64, 64, 64])})
    text = json.dumps(res.to_dict(), allow_nan=False)
    back = json.loads(text)
    assert back["confidence"] is None
    assert back["details"]["signals"]["tissue_on_air"] is None and back["details"]["signals"]["swap_tre_mm"] is None
    assert back["details"]["signals"]["local_gain"] == pytest.approx(0.002)
    assert back["details"]["grid"] == [64, 64, 64]
    assert back["params"]["tx"] == 1.0


COUCH_KEYS = {"6dof", "3dof", "isocentre_lps_mm", "patient_position", "patient_position_assumed",
              "isocentre_source", "patient_position_source"}


def _couch_keys(record: dict) -> set:
    return {k for k in COUCH_KEYS if k in record}


def _input_dependent_registrar():
    """The small untrained registrar with its output layer drawn at random (seeded): its estimate depends on the
    inputs and moves every axis. The untrained network's is exactly the identity whatever the inputs, under which
    two ways of reading them give equal parameters, and couch shifts are zero at any isocentre."""
    registrar = small_registrar_for_tests()
    head = registrar.network.head.weight
    with torch.no_grad():
        head.copy_(0.05 * torch.randn(head.shape, generator=torch.Generator().manual_seed(0)))
    return registrar


def test_every_entry_point_gives_couch_shifts_and_an_audit_trail(pair, tmp_path):
    """``register()`` (paths or images), a bare registrar's result written by ``write_outputs`` (the demo's way) and
    ``register_files`` all carry ``couch_shift`` and ``provenance``: they were absent or empty outside the command.
    The couch shifts are at the CBCT's centre, here 20 mm from the CT's (the rotation centre), under an estimate
    that moves every axis, so an isocentre placed elsewhere, a swapped or a flipped axis shows."""
    from monai_rigidreg.registration.files import register_files

    registrar = _input_dependent_registrar()
    fixed = load_volume(pair["fixed"])
    moving = load_volume(pair["moving"])[:, :, 4:]  # (the pair's CBCT shares the CT's centre)
    cbct = tmp_path / "cbct.nii.gz"
    sitk.WriteImage(moving, str(cbct))
    iso = Grid.from_sitk(moving).center()
    assert np.linalg.norm(iso - Grid.from_sitk(fixed).center()) > 10.0
    by_path = register(pair["fixed"], cbct, model=registrar)
    by_image = register(fixed, moving, model=registrar)
    for result in (by_path, by_image):
        assert _couch_keys(result.couch_shift) == COUCH_KEYS
        assert result.couch_shift["patient_position"] == "HFS" and result.couch_shift["patient_position_assumed"]
        assert result.couch_shift["isocentre_source"] == "CBCT centre (default)"
        np.testing.assert_allclose(result.couch_shift["isocentre_lps_mm"], iso, atol=1e-4)
        # HFS: the correction undoes the displacement of the anatomy at the isocentre (LPS x, y, z: IEC X, -Z, Y)
        d = transform_points(result.matrix, iso[None])[0] - iso
        assert np.abs(d).min() > 0.5 and np.abs(d - result.params[:3]).max() > 0.5  # the rotation moves it too
        np.testing.assert_allclose([result.couch_shift["3dof"][k] for k in ("lateral", "longitudinal", "vertical")],
                                   [-d[0], -d[2], d[1]], atol=1e-4)
        assert {"inputs", "bundle", "software", "device", "timestamp_utc"} <= set(result.provenance)
        assert result.timings["load"] <= result.timings["total"]
    assert by_path.provenance["inputs"]["moving"]["path"].endswith("cbct.nii.gz")
    assert by_image.provenance["inputs"]["moving"] == {"path": None, "format": "image in memory"}
    assert np.abs(by_path.params).min() > 0.5  # an estimate of its inputs, on every axis
    np.testing.assert_allclose(by_path.params, by_image.params, atol=1e-4)  # reading it first changes nothing
    bare = registrar(fixed, moving)
    assert bare.couch_shift == {} and bare.provenance == {}
    write_outputs(bare, fixed, moving, tmp_path / "bare", qc=False, names=("ct.nii.gz", "cbct.nii.gz"))
    files = register_files(registrar, pair["fixed"], cbct, tmp_path / "files", qc=False)
    records = [json.loads((tmp_path / "bare" / "result.json").read_text()),
               json.loads(files["result.json"].read_text())]
    for record in records:
        assert _couch_keys(record["couch_shift"]) == COUCH_KEYS and record["provenance"]["inputs"]
    assert records[0]["provenance"]["inputs"]["fixed"] == {"path": None, "format": "image in memory",
                                                           "name": "ct.nii.gz"}
    shifts = [list(r["couch_shift"]["6dof"].values()) for r in records]
    assert np.abs(shifts[0]).min() > 0.5, shifts[0]
    np.testing.assert_allclose(shifts[0], shifts[1], atol=1e-4)  # the same defaults as the command's
