"""Where the time of one registration goes: reading, preprocessing, network, confidence (CPU, shipped weights).

Runs on cases of a datalist (default: the Shepp-Logan set that ``bench_registration.py`` simulates) and prints the
median seconds per case of every stage of :class:`monai_rigidreg.registration.RigidRegistrar`, each next to the
slower way it replaced, so the figures quoted in the code and docs/results.md can be rerun:

* reading the CT as stored (the simulator writes int16 HU) and a float32 ``.nii.gz`` copy, with the NaN check
  (a second read with nibabel) after SimpleITK's read or overlapped with it, as ``load_volume`` does;
* the network-grid preprocessing: MONAI's transforms on a ``MetaTensor`` (``sitk_to_metatensor``,
  ``ResampleToNetworkGrid``, ``NormalizeHU``) versus the registrar's path (no whole-volume transpose);
* the anti-aliasing filter on the cropped CT: MONAI ``GaussianSmooth`` versus ``gaussian_smooth``;
* the network forward (regression + Gauss-Newton fine stage) on plain tensors versus ``MetaTensor`` inputs;
* the confidence signals (edge check + swapped-input estimate) and the whole call with and without reading.

Usage::

    python -m benchmarks.accuracy.bench_registration --cases 14 --max-cases 7 --output-dir bench_out   # makes the data
    python -m benchmarks.speed.bench_inference_speed --datalist bench_out/shepp_logan_paper/subset.json
"""

from __future__ import annotations

import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import SimpleITK as sitk
import torch
from monai.data import MetaTensor
from monai.transforms import GaussianSmooth

from benchmarks.bench_common import median_time, script_parser
from monai_rigidreg.core.geometry import Grid
from monai_rigidreg.core.image_ops import gaussian_smooth
from monai_rigidreg.evaluation.evaluate import load_datalist
from monai_rigidreg.io.prefetch import check_nifti_complete, check_nifti_finite
from monai_rigidreg.io.volumes import load_volume, sitk_to_metatensor
from monai_rigidreg.registration.confidence import cylindrical_fov_mask
from monai_rigidreg.registration.registrar import RigidRegistrar
from monai_rigidreg.transforms import NormalizeHU, ResampleToNetworkGrid
from monai_rigidreg.transforms.grid import antialias_sigmas, crop_to_grid


def _time_case(reg: RigidRegistrar, it: dict, k: int, tmp: Path, repeats: int,
               add: Callable[[str, float], None]) -> None:
    """Time every stage on one datalist item; ``add(name, seconds)`` collects the medians."""
    fixed, moving = load_volume(it["fixed"]), load_volume(it["moving"])
    stored = sitk.ReadImage(str(it["fixed"]))
    f32 = tmp / f"ct{k}_float32.nii.gz"
    sitk.WriteImage(sitk.Cast(stored, sitk.sitkFloat32), str(f32), True)
    ct_type = stored.GetPixelIDTypeAsString()
    add(f"read CT as stored ({ct_type}), load_volume", median_time(lambda: load_volume(it["fixed"]), repeats))
    add("read CBCT as stored, load_volume", median_time(lambda: load_volume(it["moving"]), repeats))

    def sequential_read(path: Path = f32) -> None:
        sitk.ReadImage(str(path))
        check_nifti_finite(path)
        check_nifti_complete(path)

    add("read CT float32 .nii.gz, NaN and completeness checks after the read", median_time(sequential_read, repeats))
    add("read CT float32 .nii.gz, the same checks overlapped (load_volume)",
        median_time(lambda: load_volume(f32), repeats))

    grid = reg.network_grid(fixed, moving)
    resampler = ResampleToNetworkGrid(reg.network_size, reg.network_spacing)
    normalize = NormalizeHU(*reg.hu_range)

    def monai_path() -> None:
        for img in (fixed, moving):
            normalize(resampler(sitk_to_metatensor(img), grid=grid))

    add("preprocess both, MONAI transforms on MetaTensor", median_time(monai_path, repeats))
    add("preprocess both, registrar path", median_time(
        lambda: (reg.preprocess(fixed, grid), reg.preprocess(moving, grid)), repeats))

    in_grid = Grid.from_sitk(fixed)
    sig = antialias_sigmas(in_grid, grid)
    raw = torch.from_numpy(sitk.GetArrayFromImage(fixed)).permute(2, 1, 0)[None]
    crop = crop_to_grid(raw, in_grid, grid, int(np.ceil(4 * max(sig))) + 1)[0].contiguous()
    add(f"anti-alias CT crop {tuple(crop.shape[1:])}, MONAI GaussianSmooth",
        median_time(lambda: GaussianSmooth(sigma=sig)(crop), repeats))
    add(f"anti-alias CT crop {tuple(crop.shape[1:])}, gaussian_smooth",
        median_time(lambda: gaussian_smooth(crop, sig), repeats))

    f_t, m_t = reg.preprocess(fixed, grid), reg.preprocess(moving, grid)
    aff = torch.as_tensor(grid.affine("RAS"))
    f_mt, m_mt = MetaTensor(f_t, affine=aff), MetaTensor(m_t, affine=aff)
    reg.estimate(m_t, f_t, grid)  # warm-up
    add("network forward, MetaTensor inputs", median_time(lambda: reg.estimate(m_mt, f_mt, grid), repeats))
    add("network forward, plain tensors", median_time(lambda: reg.estimate(m_t, f_t, grid), repeats))
    params = reg.estimate(m_t, f_t, grid)
    fov_t = reg._on_grid(cylindrical_fov_mask(moving), grid, "nearest", 0.0)[0]
    add("confidence (edge check + swapped estimate)",
        median_time(lambda: reg.assess(m_t, f_t, grid, params, fov_t), repeats))
    add("register call, volumes in memory (with confidence)",
        median_time(lambda: reg(fixed, moving, resample_moving=False), repeats))
    add("register call from files (with confidence)",
        median_time(lambda: reg(it["fixed"], it["moving"], resample_moving=False), repeats))
    f32.unlink()


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--datalist", type=Path, default=Path("bench_out/shepp_logan_paper/subset.json"))
    ap.add_argument("--cases", type=int, default=4, help="cases of the datalist to time")
    ap.add_argument("--repeats", type=int, default=3, help="runs per stage and case (median)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--bundle", type=Path, default=None)
    args = ap.parse_args()

    torch.set_num_threads(args.threads)
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(args.threads)
    if not args.datalist.is_file():
        sys.exit(f"{args.datalist} not found: run benchmarks/accuracy/bench_registration.py first (see --help)")
    items, _ = load_datalist(args.datalist)
    items = items[: args.cases]
    reg = RigidRegistrar.from_bundle(args.bundle, device="cpu")
    rows: dict[str, list[float]] = {}

    def add(name: str, value: float) -> None:
        rows.setdefault(name, []).append(value)

    tmp = Path(tempfile.mkdtemp(prefix="bench_speed_"))
    for k, it in enumerate(items):
        _time_case(reg, it, k, tmp, args.repeats, add)
    tmp.rmdir()

    print(f"# {len(items)} cases of {args.datalist}, {args.threads} CPU threads, median of {args.repeats} runs each\n")
    print("| stage | median s per case |")
    print("|---|---|")
    for name, vals in rows.items():
        print(f"| {name} | {np.median(vals):.3f} |")


if __name__ == "__main__":
    main()
