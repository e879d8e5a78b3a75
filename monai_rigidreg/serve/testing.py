"""Parts for testing the service against real DICOM nodes, for the test suite, ``benchmarks/bench_service.py`` and an
installation check: a CT volume written as a DICOM CT Image Storage series (:func:`write_ct_series`), a console
that sends files (:func:`send_files` with pynetdicom, :func:`dcmtk_storescu` for dcmtk's), and a throw-away Orthanc
PACS on free loopback ports with its own storage (:class:`Orthanc`).
"""

from __future__ import annotations

import contextlib
import json
import shutil
import socket
import subprocess
import time
import urllib.error
import urllib.request
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["write_ct_series", "send_files", "SendResult", "free_port", "Orthanc", "orthanc_binary", "dcmtk_storescu",
           "wait_for"]

CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"
RESERVED_PORTS = frozenset({104, 4242, 8042, 11112})
"""Ports a system service may hold (Orthanc's Debian defaults, DICOM's); :func:`free_port` never returns them."""


def free_port() -> int:
    """A TCP port free on the loopback interface now (not one of :data:`RESERVED_PORTS`)."""
    while True:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        if port not in RESERVED_PORTS:
            return port


def write_ct_series(image: Any, directory: str | Path, *, patient_id: str, study_uid: str, series_uid: str,
                    frame_of_reference_uid: str, series_description: str = "", patient_name: str = "TEST^PATIENT",
                    series_number: int = 1, station_name: str = "", image_type: Sequence[str] = ("ORIGINAL",
                    "PRIMARY", "AXIAL"), patient_position: str = "HFS", study_date: str = "20260101",
                    series_time: str = "120000", images_in_acquisition: bool = True) -> list[Path]:
    """Write a ``SimpleITK.Image`` (HU) as a CT Image Storage series: one file per slice (``CT0001.dcm``, ...), signed
    16-bit HU (rescale 1, 0), the image's geometry in Image Position / Orientation (Patient), one Frame of Reference,
    SOP Instance UIDs derived from the series UID (so a rewrite gives the same instances). Returns the files in
    slice order.

    ``images_in_acquisition`` writes Images in Acquisition (0020,1002), the number of slices, which lets the service
    tell a truncated series.
    """
    import pydicom
    import SimpleITK as sitk
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import PYDICOM_IMPLEMENTATION_UID, ExplicitVRLittleEndian, generate_uid

    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    arr = np.clip(np.rint(sitk.GetArrayFromImage(image)), -1024, 3071).astype(np.int16)  # [z, y, x]
    direction = np.asarray(image.GetDirection(), dtype=np.float64).reshape(3, 3)
    spacing = image.GetSpacing()
    iop = [*direction[:, 0], *direction[:, 1]]
    files = []
    for k in range(arr.shape[0]):
        sop_uid = generate_uid(entropy_srcs=[series_uid, str(k)])
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CT_IMAGE_STORAGE
        meta.MediaStorageSOPInstanceUID = sop_uid
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
        path = out / f"CT{k + 1:04d}.dcm"
        ds = FileDataset(str(path), {}, file_meta=meta, preamble=b"\x00" * 128)
        ds.SOPClassUID, ds.SOPInstanceUID = CT_IMAGE_STORAGE, sop_uid
        ds.PatientName, ds.PatientID, ds.PatientBirthDate, ds.PatientSex = patient_name, patient_id, "", "O"
        ds.StudyInstanceUID, ds.StudyDate, ds.StudyTime = study_uid, study_date, "100000"
        ds.ReferringPhysicianName, ds.StudyID, ds.AccessionNumber = "", "1", ""
        ds.Modality, ds.SeriesInstanceUID, ds.SeriesNumber = "CT", series_uid, str(series_number)
        ds.SeriesDate, ds.SeriesTime = study_date, series_time
        ds.SeriesDescription = series_description
        ds.PatientPosition = patient_position
        ds.FrameOfReferenceUID, ds.PositionReferenceIndicator = frame_of_reference_uid, ""
        ds.Manufacturer = "monai-rigidreg test"
        if station_name:
            ds.StationName = station_name
        ds.ImageType = list(image_type)
        ds.InstanceNumber = str(k + 1)
        ds.AcquisitionNumber = "1"
        if images_in_acquisition:
            ds.ImagesInAcquisition = str(arr.shape[0])
        ds.ImagePositionPatient = [f"{v:.6f}" for v in image.TransformIndexToPhysicalPoint((0, 0, k))]
        ds.ImageOrientationPatient = [f"{v:.8f}" for v in iop]
        ds.PixelSpacing = [f"{spacing[1]:.6f}", f"{spacing[0]:.6f}"]  # row spacing (y), column spacing (x)
        ds.SliceThickness = f"{spacing[2]:.6f}"
        ds.SliceLocation = f"{float(np.dot(image.TransformIndexToPhysicalPoint((0, 0, k)), direction[:, 2])):.6f}"
        ds.KVP = ""
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.Rows, ds.Columns = arr.shape[1], arr.shape[2]
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.RescaleIntercept, ds.RescaleSlope, ds.RescaleType = "0", "1", "HU"
        ds.WindowCenter, ds.WindowWidth = "40", "400"
        ds.PixelData = arr[k].tobytes()
        if int(pydicom.__version__.split(".")[0]) >= 3:
            pydicom.dcmwrite(str(path), ds, enforce_file_format=True)
        else:  # pragma: no cover - pydicom 2.4
            ds.is_little_endian, ds.is_implicit_VR = True, False
            pydicom.dcmwrite(str(path), ds, write_like_original=False)
        files.append(path)
    return files


@dataclass
class SendResult:
    """What :func:`send_files` achieved: ``established`` (the association was accepted), ``rejected``, the C-STORE
    status of each file sent (``None``: no response)."""

    established: bool
    rejected: bool
    statuses: list[int | None]

    @property
    def all_stored(self) -> bool:
        return self.established and bool(self.statuses) and all(s == 0 for s in self.statuses)


def _wait_for_reactor(assoc: Any, seconds: float = 10.0) -> None:
    """Wait until the association's reactor has resumed from the pause of the last request.

    pynetdicom (2.x-3.0) pauses the reactor thread for each request and takes ``_is_paused`` for proof that it is
    paused. A reactor that was released after the previous response but has not run since still shows ``True``: the
    next request then goes out unpaused, the reactor takes its response for an unexpected message and the request
    times out ("Received unexpected C-STORE service message"; seen in CI on a loaded machine). Between requests of
    one association, waiting for the flag to fall closes that window."""
    deadline = time.monotonic() + seconds
    while getattr(assoc, "_is_paused", False) and assoc.is_established and time.monotonic() < deadline:
        time.sleep(0.001)


def send_files(files: Sequence[str | Path], port: int, called_ae: str, calling_ae: str, host: str = "127.0.0.1",
               abort_after: int | None = None) -> SendResult:
    """Send ``files`` in one association with pynetdicom, as a console does. ``abort_after``: abort the association
    after that many files (a sender that stops mid-series)."""
    from pydicom import dcmread
    from pynetdicom import AE

    ae = AE(ae_title=calling_ae)
    ae.acse_timeout = ae.dimse_timeout = ae.network_timeout = 60.0  # the service's own timeouts
    sop_classes = {str(dcmread(str(f), stop_before_pixels=True).SOPClassUID) for f in files[:1]} or {CT_IMAGE_STORAGE}
    for sop in sop_classes:
        ae.add_requested_context(sop, ["1.2.840.10008.1.2.1", "1.2.840.10008.1.2"])
    assoc = ae.associate(host, port, ae_title=called_ae)
    if not assoc.is_established:
        return SendResult(False, bool(assoc.is_rejected), [])
    statuses: list[int | None] = []
    for k, f in enumerate(files):
        if abort_after is not None and k >= abort_after:
            assoc.abort()
            return SendResult(True, False, statuses)
        status = assoc.send_c_store(dcmread(str(f)), msg_id=k + 1)  # each request its own Message ID
        statuses.append(int(status.Status) if status is not None and "Status" in status else None)
        _wait_for_reactor(assoc)
    assoc.release()
    return SendResult(True, False, statuses)


def dcmtk_storescu() -> str | None:
    """dcmtk's ``storescu`` (Debian ``dcmtk``), not pynetdicom's command of the same name; ``None`` if absent."""
    for candidate in ("/usr/bin/storescu", "/usr/local/bin/storescu", shutil.which("storescu")):
        if candidate and Path(candidate).is_file():
            try:
                out = subprocess.run([candidate, "--version"], capture_output=True, text=True, timeout=20)
            except (OSError, subprocess.TimeoutExpired):
                continue
            if "dcmtk" in (out.stdout + out.stderr).lower():
                return candidate
    return None


def orthanc_binary() -> str | None:
    """The Orthanc server (Debian ``orthanc``: ``/usr/sbin/Orthanc``), or ``None``."""
    for candidate in (shutil.which("Orthanc"), "/usr/sbin/Orthanc", "/usr/bin/Orthanc"):
        if candidate and Path(candidate).is_file():
            return candidate
    return None


def wait_for(predicate: Any, timeout: float, interval: float = 0.05, what: str = "condition") -> Any:
    """Call ``predicate`` until it returns something true (returned) or ``timeout`` seconds pass
    (``TimeoutError``)."""
    end = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > end:
            raise TimeoutError(f"{what}: not reached within {timeout:g} s")
        time.sleep(interval)


class Orthanc:
    """A throw-away Orthanc with its own configuration and storage under ``folder``, on free ports: DICOM
    ``dicom_port`` (AE ``ae_title``), HTTP (REST) on ``http_port`` for the loopback interface only, no
    authentication. ``modalities`` (``{name: (ae_title, host, port)}``) are the DICOM nodes it knows; every AE may
    store to it (``DicomAlwaysAllowStore``).

    Use as a context manager; :meth:`instances` and :meth:`file` read its REST API.
    """

    def __init__(self, folder: str | Path, ae_title: str = "ORTHANC",
                 modalities: dict[str, tuple[str, str, int]] | None = None) -> None:
        self.folder = Path(folder)
        self.ae_title = ae_title
        self.dicom_port, self.http_port = free_port(), free_port()
        while self.http_port == self.dicom_port:
            self.http_port = free_port()
        self.modalities = modalities or {}
        self.process: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.http_port}"

    def start(self, timeout: float = 60.0) -> Orthanc:
        exe = orthanc_binary()
        if exe is None:
            raise FileNotFoundError("Orthanc is not installed (Debian package orthanc)")
        self.folder.mkdir(parents=True, exist_ok=True)
        config = {
            "Name": "monai-rigidreg-test", "StorageDirectory": str(self.folder / "storage"),
            "IndexDirectory": str(self.folder / "index"), "Plugins": [], "ConcurrentJobs": 1,
            "HttpServerEnabled": True, "HttpPort": self.http_port, "RemoteAccessAllowed": False,
            "AuthenticationEnabled": False, "DicomServerEnabled": True, "DicomAet": self.ae_title,
            "DicomPort": self.dicom_port, "DicomCheckCalledAet": False, "DicomAlwaysAllowStore": True,
            "DicomAlwaysAllowEcho": True, "UnknownSopClassAccepted": False, "StorageCompression": False,
            "DicomModalities": {k: list(v) for k, v in self.modalities.items()}, "SaveJobs": False,
            "HttpThreadsCount": 4, "DicomThreadsCount": 2, "LuaScripts": [], "StableAge": 3600,
        }
        path = self.folder / "orthanc.json"
        path.write_text(json.dumps(config, indent=2))
        self._log = open(self.folder / "orthanc.log", "ab")  # noqa: SIM115 - closed in stop()
        self.process = subprocess.Popen([exe, str(path)], stdout=self._log, stderr=subprocess.STDOUT,
                                        cwd=self.folder)
        try:
            wait_for(self._answers, timeout, 0.1, "Orthanc's REST API")
        except TimeoutError:
            self.stop()
            raise RuntimeError(f"Orthanc did not start; its log: {(self.folder / 'orthanc.log').read_text()[-2000:]}"
                               ) from None
        return self

    def _answers(self) -> bool:
        if self.process is not None and self.process.poll() is not None:
            raise RuntimeError(f"Orthanc exited with {self.process.returncode}; its log: "
                               f"{(self.folder / 'orthanc.log').read_text()[-2000:]}")
        try:
            self.get("/system")
            return True
        except (urllib.error.URLError, ConnectionError, OSError):
            return False

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(20)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(10)
        self.process = None
        with contextlib.suppress(AttributeError):
            self._log.close()

    def __enter__(self) -> Orthanc:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()

    def get(self, path: str) -> Any:
        with urllib.request.urlopen(self.url + path, timeout=10) as r:  # noqa: S310 - loopback URL we built
            data = r.read()
        return json.loads(data) if data[:1] in (b"{", b"[") else data

    def instances(self) -> list[str]:
        """The Orthanc ids of every instance held."""
        return self.get("/instances")

    def instance_tags(self, instance_id: str) -> dict[str, Any]:
        return self.get(f"/instances/{instance_id}/simplified-tags")

    def file(self, instance_id: str) -> bytes:
        return self.get(f"/instances/{instance_id}/file")

    def reg_instances(self) -> dict[str, dict[str, Any]]:
        """``{orthanc id: simplified tags}`` of every instance of modality REG held."""
        out = {}
        for i in self.instances():
            tags = self.instance_tags(i)
            if tags.get("Modality") == "REG":
                out[i] = tags
        return out


@contextlib.contextmanager
def running(obj: Any) -> Iterator[Any]:
    """``with running(service):`` start, yield, stop."""
    obj.start()
    try:
        yield obj
    finally:
        obj.stop()
