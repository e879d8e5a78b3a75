"""What damaged or unusual inputs do to a registration, and what the package's input checks make of them.

On one ``bench_speed.py`` pair (the held-out thorax CT and a simulated 128^3 CBCT with known motion; run
``python -m benchmarks.speed.bench_speed`` first to make ``bench_out/speed``), each variant is

* read as ITK reads it alone (``SimpleITK.ReadImage``, what ``io.load_volume`` did for integer NIfTI files before
  0.4.9) and registered in-process with the shipped bundle: TRE against the ground truth, confidence, flag;
* read by ``io.load_volume`` (the package's checks): the error it raises, if any.

Variants: the pair as it is; the CBCT ``.nii.gz`` cut to half its bytes; the CT cut to 75 %; the CBCT as uint8
(-1000..530 HU mapped to 0..255); the two images swapped (``--fixed`` the CBCT). The swapped row's TRE compares the
estimate with the true CT -> CBCT motion: an inverted transform is what a swapped input gives a user. Last, the
swapped-inputs warning's rule over the benchmark pairs in ``bench_out`` in the usual order (false warnings).

Usage::

    python -m benchmarks.accuracy.bench_damaged_inputs [--pairs bench_out/speed] [--case case_0] \
        [--results benchmarks/results/bench_damaged_inputs_<version>_<date>.txt] [--tree CHECKOUT]

``--tree`` measures another checkout's package with this script (its own ``io.load_volume`` and registrar), e.g.
the release before the checks.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import SimpleITK as sitk

import monai_rigidreg
from benchmarks.bench_common import REPO, Tee, script_parser


def _module(new: str, old: str):
    """A module of the package measured: its path since 0.5 (``new``) or, in an older checkout (``--tree``), the path
    it had there."""
    try:
        return importlib.import_module(new)
    except ModuleNotFoundError:
        return importlib.import_module(old)


def _rerun_with(tree: Path, args: argparse.Namespace) -> int:
    """This script again in a child process that imports ``tree``'s package (its folder first on the path: the
    child runs in it) and this checkout's ``benchmarks`` (``PYTHONPATH``); paths made absolute first."""
    argv = ["--pairs", str(args.pairs.resolve()), "--case", args.case, "--scan", *[str(p.resolve()) for p in args.scan]]
    if args.results is not None:
        argv += ["--results", str(args.results.resolve())]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tree), str(REPO)])}
    return subprocess.call([sys.executable, "-m", "benchmarks.accuracy.bench_damaged_inputs", *argv], cwd=tree, env=env)


def cut(src: Path, dst: Path, fraction: float) -> Path:
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * fraction)])
    return dst


def _grid(path: Path):
    from monai_rigidreg import Grid

    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    reader.ReadImageInformation()
    return Grid(reader.GetSize(), reader.GetSpacing(), reader.GetOrigin(), reader.GetDirection())


def scan_swap_rule(out: Tee, folders: list[Path]) -> None:
    """The swapped-inputs warning's rule (``io.grid_within``, where this checkout has it) over every simulated CBCT
    under ``folders`` against its CT (the real CT named in its path, and its own Sim-CT where one lies beside it), in
    the usual order: each hit would be a false warning."""
    try:
        from monai_rigidreg.io import grid_within
    except ImportError:
        out("\n(no io.grid_within in this checkout: the swapped-inputs rule is not scanned)")
        return
    shared_data_dir = _module("monai_rigidreg.io.shared_data", "monai_rigidreg.data").shared_data_dir

    data = shared_data_dir()
    cts = {} if data is None else {p.name.split(".")[0]: p for p in Path(data).glob("*.nii.gz")}
    checked, hits = 0, []
    for folder in folders:
        for cbct in sorted(Path(folder).rglob("*cbct*.nii.gz")):
            if "fov" in cbct.name:
                continue
            names = [k for k in cts if k in str(cbct)]
            refs = [cts[names[0]]] if names else []
            sim = cbct.with_name(cbct.name.replace("cbct", "simct"))
            refs += [sim] if sim.exists() else []
            for ref in refs:
                checked += 1
                if grid_within(_grid(ref), _grid(cbct)):
                    hits.append(f"{ref.name} / {cbct}")
    out(f"\nswapped-inputs rule in the usual order (CT fixed, CBCT moving) over {', '.join(map(str, folders))}: "
        f"{checked} pairs checked, {len(hits)} would warn{': ' + '; '.join(hits[:10]) if hits else ''}")


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--pairs", type=Path, default=Path("bench_out/speed"))
    ap.add_argument("--case", default="case_0")
    ap.add_argument("--results", type=Path, default=None)
    ap.add_argument("--tree", default=None, help="a checkout whose monai_rigidreg to measure (default: this one)")
    ap.add_argument("--scan", type=Path, nargs="*", default=[Path("bench_out/clinical"),
                                                              Path("bench_out/clinical_seed2500"),
                                                              Path("bench_out/real_ct"), Path("bench_out/speed")],
                    help="folders of simulated pairs to run the swapped-inputs rule over")
    args = ap.parse_args()
    if args.tree is not None and Path(monai_rigidreg.__file__).resolve().parents[1] != Path(args.tree).resolve():
        sys.exit(_rerun_with(Path(args.tree).resolve(), args))

    InputError = _module("monai_rigidreg.core.errors", "monai_rigidreg.errors").InputError
    matrix_distance_mm = _module("monai_rigidreg.registration.search", "monai_rigidreg.global_init").matrix_distance_mm
    from monai_rigidreg import params_to_matrix
    from monai_rigidreg.io import load_volume

    out = Tee()
    case_dir = args.pairs / args.case
    if not (case_dir / "case.json").is_file():
        out(f"no pair at {case_dir}: run `python -m benchmarks.speed.bench_speed --output-dir {args.pairs}` first")
        return
    record = json.loads((case_dir / "case.json").read_text())
    ct_path, cbct_path = Path(record["fixed"]), case_dir / "cbct.nii.gz"
    points = np.load(case_dir / "tre_points.npy")
    truth = np.asarray(record["matrix"])
    out(f"command: python {' '.join(sys.argv)}")
    out(f"date: {time.strftime('%Y-%m-%dT%H:%M:%S%z')}; monai-rigidreg {monai_rigidreg.__version__} from "
        f"{Path(monai_rigidreg.__file__).parent}; pair: "
        f"{ct_path.name} / {cbct_path}")
    registrar = monai_rigidreg.RigidRegistrar.from_bundle()
    tmp = Path(tempfile.mkdtemp(prefix="bench_damaged_"))
    u8 = tmp / "cbct_uint8.nii.gz"
    window = sitk.IntensityWindowing(sitk.ReadImage(str(cbct_path), sitk.sitkFloat32), -1000.0, 530.0, 0.0, 255.0)
    sitk.WriteImage(sitk.Cast(window, sitk.sitkUInt8), str(u8))
    variants = [("as it is", ct_path, cbct_path),
                ("CBCT .nii.gz cut to 50 % of its bytes", ct_path, cut(cbct_path, tmp / "cbct_half.nii.gz", 0.5)),
                ("CT .nii.gz cut to 75 % of its bytes", cut(ct_path, tmp / "ct_75.nii.gz", 0.75), cbct_path),
                ("CBCT as uint8 (0..255)", ct_path, u8),
                ("swapped: the CBCT as fixed, the CT as moving", cbct_path, ct_path)]
    out("\n| variant | ITK alone: TRE mm | confidence | flagged | warnings | io.load_volume |")
    out("|---|---|---|---|---|---|")
    for name, fixed_path, moving_path in variants:
        fixed = sitk.ReadImage(str(fixed_path), sitk.sitkFloat32)
        moving = sitk.ReadImage(str(moving_path), sitk.sitkFloat32)
        r = monai_rigidreg.register(fixed, moving, model=registrar)
        tre = matrix_distance_mm(params_to_matrix(r.params, r.center), truth, points)
        warned = len(r.details.get("warnings", []))
        try:
            load_volume(fixed_path)
            load_volume(moving_path)
            checked = "read"
        except InputError as exc:
            # (a checkout before 0.4.9 has no InputError.reason: its message after the path)
            checked = f"InputError: {getattr(exc, 'reason', str(exc).split(': ', 1)[-1])}"
        out(f"| {name} | {tre:.2f} | {r.confidence:.2f} | {r.flagged} | {warned} | {checked} |")
    out("\nITK alone: the variant read by SimpleITK.ReadImage and registered (monai_rigidreg.register, shipped "
        "bundle); warnings: details.warnings entries (non-HU range, swapped-looking inputs)")
    scan_swap_rule(out, args.scan)
    out.write(args.results)


if __name__ == "__main__":
    main()
