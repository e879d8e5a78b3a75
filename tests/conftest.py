"""Shared fixtures and helpers: small deterministic volumes, a DICOM series writer, seeds, the real-data directory."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
import torch

from monai_rigidreg.core.geometry import rotation_matrix
from monai_rigidreg.io.shared_data import shared_data_dir

torch.set_num_threads(max(1, min(2, torch.get_num_threads())))


def oblique_direction(rx: float, ry: float, rz: float) -> tuple[float, ...]:
    """Row-major direction cosines of a rotation given in degrees."""
    return tuple(rotation_matrix(*np.deg2rad([rx, ry, rz])).ravel())


def smooth_random_image(size_xyz, spacing, origin, direction, seed=0, sigma_mm=3.0) -> sitk.Image:
    """A smooth random float32 volume (structure at every scale of a few mm) with the given geometry."""
    rng = np.random.default_rng(seed)
    img = sitk.GetImageFromArray(rng.normal(size=tuple(size_xyz)[::-1]).astype(np.float32))
    img.SetSpacing(spacing)
    img = sitk.SmoothingRecursiveGaussian(img, sigma_mm)
    img.SetOrigin(origin)
    img.SetDirection(direction)
    return img


def write_dicom_series(image: sitk.Image, directory: str | Path, series_uid: str, shuffle_seed: int = 0,
                       frame_of_reference_uid: str | None = None, study_uid: str | None = None,
                       modality: str = "CT", patient_id: str | None = None, issuer: str | None = None) -> None:
    """Write ``image`` as a CT DICOM series into ``directory``, one file per slice, file names in random order.

    A plain function, so that any test builds its DICOM input with ``from conftest import write_dicom_series``.
    ``frame_of_reference_uid`` (0020|0052) is written only when given; ``study_uid`` (0020|000d) defaults to a
    fixed UID shared by every series written here; ``modality`` (0008|0060) defaults to ``"CT"``; ``patient_id``
    (0010|0020) and ``issuer`` (0010|0021) are written only when given.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    img16 = sitk.Cast(sitk.RescaleIntensity(image, -1000, 2000), sitk.sitkInt16)
    direction = img16.GetDirection()
    iop = "\\".join(f"{v:.10f}" for v in (direction[0], direction[3], direction[6], direction[1], direction[4],
                                          direction[7]))
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    order = np.random.default_rng(shuffle_seed).permutation(img16.GetDepth())
    for k in range(img16.GetDepth()):
        sl = img16[:, :, k]
        for tag, value in [
            ("0008|0060", modality),
            ("0008|0021", time.strftime("%Y%m%d")),
            ("0020|000d", "1.2.826.0.1.3680043.2.1125.1" if study_uid is None else study_uid),
            ("0020|000e", series_uid),
            ("0020|0037", iop),
            ("0020|0032", "\\".join(f"{v:.6f}" for v in img16.TransformIndexToPhysicalPoint((0, 0, k)))),
            ("0020|0013", str(k + 1)),
            ("0018|0050", str(img16.GetSpacing()[2])),
            *([] if frame_of_reference_uid is None else [("0020|0052", frame_of_reference_uid)]),
            *([] if patient_id is None else [("0010|0020", patient_id)]),
            *([] if issuer is None else [("0010|0021", issuer)]),
        ]:
            sl.SetMetaData(tag, value)
        writer.SetFileName(str(directory / f"img_{order[k]:04d}.dcm"))
        writer.Execute(sl)


@pytest.fixture
def real_data_dir():
    d = shared_data_dir()
    if d is None:
        pytest.skip("real CT volumes not found: set MONAI_RIGIDREG_DATA or place them in ../shared/data")
    return d


TINY_SIM = dict(
    preset="fast",
    simct_size=(32, 32, 32),
    simct_spacing=(8.0, 8.0, 8.0),
    cbct_size=(24, 24, 24),
    cbct_spacing=(10.0, 10.0, 10.0),
    simct_views=60,
    cbct_views=60,
)
"""Simulation settings small enough for the default test suite (a few seconds per case on a 2-core CPU)."""


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """Three simulated CBCT/Sim-CT pairs (asymmetric Shepp-Logan, random motion) and their datalist."""
    from monai_rigidreg.simulation import simulate_dataset

    out = tmp_path_factory.mktemp("tiny_sim")
    return simulate_dataset(out, phantom="shepp-logan-asym", protocol="random", num_cases=3, seed=1, progress=False,
                            **TINY_SIM)


KNOWN_MOTION = [6.0, -4.0, 5.0, 3.0, -2.0, 4.0]
"""Ground truth of :func:`fast_pair` (mm, degrees, fixed -> moving about the CT centre)."""


@pytest.fixture(scope="session")
def fast_pair(tmp_path_factory):
    """A pair at the ``fast`` preset (Sim-CT 64^3 at 4 mm, CBCT 48^3 at 5 mm) under :data:`KNOWN_MOTION`."""
    from monai_rigidreg.simulation import simulate_pair

    return simulate_pair(tmp_path_factory.mktemp("fast_pair"), phantom="shepp-logan-asym", params=KNOWN_MOTION,
                         seed=4)


DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
"""Devices every device-generic test runs on: the CPU always, CUDA where present."""


@pytest.fixture(params=[(d, t) for d in DEVICES for t in (torch.float32, torch.float64)],
                ids=lambda p: f"{p[0]}-{str(p[1]).split('.')[-1]}")
def device_dtype(request) -> tuple[torch.device, torch.dtype]:
    """``(device, dtype)`` for the network, warp, loss and fine-stage tests: CPU and CUDA, float32 and float64."""
    return torch.device(request.param[0]), request.param[1]


def small_registrar_for_tests(cascade_steps: int = 1):
    """An untrained, small network (seeded) in a registrar on a 32^3 grid at 8 mm: fast API/CLI tests that do not
    depend on the shipped weights."""
    from monai_rigidreg.networks import DualEncoderRigidNet
    from monai_rigidreg.registration import RigidRegistrar

    torch.manual_seed(0)
    net = DualEncoderRigidNet(channels=(4, 8, 8, 8), pool_size=2)
    return RigidRegistrar(net, network_size=(32, 32, 32), network_spacing=(8.0, 8.0, 8.0),
                          cascade_steps=cascade_steps, device="cpu")


def true_motion_registrar(registrar, motion):
    """``registrar`` (e.g. :func:`small_registrar_for_tests`) with its estimate replaced by a pair's true motion.

    The untrained test network's estimate is exactly the identity, under which a missing or doubled inverse, a
    flipped sign or a swapped axis in what the outputs re-express (result.json's matrices, transform.tfm, the REG,
    the couch shifts, transformix's parameters, registered.nii.gz) would not show. ``motion``: six numbers (mm,
    degrees, fixed -> moving about the CT centre), or ``motion(fixed, moving)`` giving them per pair. The result's
    ``registered`` (made under the network's estimate) is left as it is: the outputs see that the parameters changed
    and resample the CBCT under the motion (``RegistrationResult.registered_is_current``). The returned object is a
    ``RigidRegistrar`` (a subclass sharing the registrar's state), so ``register(model=...)`` takes it.
    """
    motion_for = motion if callable(motion) else (lambda fixed, moving: motion)

    class TrueMotion(type(registrar)):
        def __call__(self, fixed, moving, *args, **kwargs):
            result = super().__call__(fixed, moving, *args, **kwargs)
            result.params = np.asarray(motion_for(fixed, moving), dtype=np.float64).copy()
            return result

    wrapped = object.__new__(TrueMotion)
    wrapped.__dict__.update(vars(registrar))
    return wrapped


def resampled_with_truth(fixed, moving, fov, transform):
    """``(fixed, registered, raw, mask)`` arrays for checking a simulated pair's ground truth: the CBCT resampled on
    the CT grid with the true transform and with the identity, and the voxels both place inside the CBCT's FOV."""
    def on_fixed(image, tfm, interpolator, fill):
        return sitk.GetArrayFromImage(sitk.Resample(image, fixed, tfm, interpolator, fill))

    reg = on_fixed(moving, transform, sitk.sitkLinear, -1000.0)
    raw = on_fixed(moving, sitk.Transform(), sitk.sitkLinear, -1000.0)
    mask = (on_fixed(fov, transform, sitk.sitkNearestNeighbor, 0) > 0) & (
        on_fixed(fov, sitk.Transform(), sitk.sitkNearestNeighbor, 0) > 0)
    return sitk.GetArrayFromImage(fixed), reg, raw, mask


def synth_ct(grid, seed: int, radius_mm: float | None = None) -> sitk.Image:
    """A synthetic-anatomy CT (HU, float32) on ``grid`` (:mod:`monai_rigidreg.simulation.synth`)."""
    from monai_rigidreg.simulation.synth import synth_hu_volume, synth_label_map

    labels = synth_label_map(grid, seed, radius_mm=radius_mm)
    hu = synth_hu_volume(labels, seed, grid, radius_mm=radius_mm).numpy()
    img = sitk.GetImageFromArray(np.ascontiguousarray(hu.transpose(2, 1, 0)).astype(np.float32))
    img.SetSpacing(grid.spacing)
    img.SetOrigin(grid.origin)
    img.SetDirection(grid.direction)
    return img


@pytest.fixture(scope="module")
def one_torch_thread():
    """One torch thread for a module (``pytestmark = pytest.mark.usefixtures("one_torch_thread")``): the CPU is
    shared, and OpenMP spinning on a busy machine is very slow."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


# ---------------------------------------------------------------------------------------------------------------
# The boundary tests' pair, small network and helpers (the command line, the output folders, the bundle's entry points)
# ---------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="session")
def pair(tmp_path_factory):
    from monai_rigidreg.simulation import simulate_pair

    return simulate_pair(tmp_path_factory.mktemp("pair"), phantom="shepp-logan-asym", params=[4, -3, 2, 2, -1, 3],
                         seed=3, device="cpu", **{k: v for k, v in TINY_SIM.items() if k != "preset"})


@pytest.fixture(scope="module")
def small_registrar():
    return small_registrar_for_tests(cascade_steps=1)


@pytest.fixture
def with_small_network(monkeypatch, small_registrar):
    """The register command with the small network instead of the shipped bundle."""
    from monai_rigidreg.registration import RigidRegistrar

    monkeypatch.setattr(RigidRegistrar, "from_bundle", classmethod(lambda cls, *a, **k: small_registrar))


def listing(root: Path) -> list[str]:
    """Every path under ``root`` (hidden ones included), relative, sorted."""
    return sorted(str(p.relative_to(root)) for p in Path(root).rglob("*"))


def run_cli(capsys, args: list[str]) -> tuple[int, str]:
    """``monai-rigidreg ARGS`` in this process: its exit status and what it wrote to stderr."""
    from monai_rigidreg.cli import main

    code = main([str(a) for a in args])
    return code, capsys.readouterr().err


def last_line(err: str) -> str:
    lines = err.strip().splitlines()
    return lines[-1] if lines else ""


def constant_like(image: sitk.Image, value: float = 0.0) -> sitk.Image:
    out = sitk.Image(image.GetSize(), sitk.sitkFloat32)
    out.CopyInformation(image)
    return out + value


def in_main_thread() -> None:
    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signals reach the main thread only")
