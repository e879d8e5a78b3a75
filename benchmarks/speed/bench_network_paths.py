"""The speed-ups of the registration path since 0.4.6, each next to the way it replaced (CPU, shipped weights).

Prints the median seconds of:

* one kernel-3 convolution of a single volume, and one network run (learned regression + Gauss-Newton fine stage)
  on one volume, with the encoder's kernel-3
  convolutions as ``OneDNNConv3d`` (oneDNN directly) and as plain ``nn.Conv3d`` (PyTorch's batch-1 path);
* the network from three starts one by one and as one batch (``RigidRegistrar._runs_from``);
* the learned network's local cost volume (``correlation_net.local_cost_volume``, 16^3 cells, radius 2) on
  channel-last maps with its own backward (0.6.3) and as the einsum over unfolded windows it replaced (autograd's
  backward): 32 channels at batch 1, the inference size, and forward plus backward at the context network's
  training size (batch 4);
* the 4 mm level's cost volume at its selected cells (``context_net.sparse_cost_volume``, 4096 of 32^3 cells, 16
  channels, radius 1, batch 1) as a product and channel sum (0.6.3) and as the einsum it replaced;
* the networks' unit feature vectors (``correlation_net.unit_channels``, a 4 mm level's ``[4, 16, 32^3]`` maps) as a
  sum of squares over the channels (0.6.3) and as ``F.normalize``'s vector norm;
* the sampling points of every warp (``core.warp.affine_grid``) on the last level's ``102^3`` grid and the network's
  ``64^3`` as per-axis sums (0.6.3) and as ``F.affine_grid``'s batched product;
* the 4 mm level's match-weight head with its backward at training size, at 1 thread and at torch's count
  (``networks.blocks.pointwise_columns``) as ``conv1d`` on the selected cells' columns (0.6.3) and as a kernel-1
  ``Conv3d`` on a ``[B, C, N, 1, 1]`` volume;
* a kernel-3 convolution of the context network's training size with its backward, at 1 thread and at torch's
  count: ``OneDNNConv3d``'s weight gradient as one swapped convolution (0.6.3) and ``nn.Conv3d``'s (oneDNN's
  weight-gradient kernel);
* the Gauss-Newton Jacobian on the last level's grid (about 1M voxels, two feature channels): from index ramps
  (``fixed_jacobian``) and through the ``[6, 3, N]`` parameter flow it replaced;
* the masked NCC maps of the global search's 27 rotation templates: one batched FFT (``masked_ncc_maps``) and one
  template at a time (``masked_ncc_map``);
* the CT's body mask (``coarse_body_mask``, what the registration computes once per CT) with the binary opening,
  closing and dilation as numpy shifted ORs / ANDs of the ball (0.4.7) and as ITK's filters;
* the key of the body-mask cache (``body.image_key``, a digest of the CT's voxels) with SHA-256 (0.4.8) and with
  BLAKE2b;
* the last level's support erosion (``image_ops.erode``, a 102^3 mask, radius 4 voxels) as sliding-window minima
  (0.4.7) and as ``max_pool3d`` of the negated mask;
* the last level's Gauss-Newton steps (``precision.refine_native``'s four, from 1 mm / 1 degree off the
  registration's estimate) over the candidate voxels (``support_reach``: the field of view, 0.4.8) and over the
  whole grid, with the largest difference of the two estimates (mm at the grid's corners): on the pair, and on a
  paper-protocol pair of ``bench_real_ct.py`` (``bench_out/real_ct``) whose field of view fills its grid, where the
  dense steps are cheaper (``precision.CANDIDATE_SHARE_MAX``);
* the command's two slowest outputs, ``registered.nii.gz`` and the QC figure: the volume written in a worker thread
  while the figure is drawn (``outputs.write_outputs``, 0.4.7) and one after the other.

Usage::

    python -m benchmarks.speed.bench_network_paths          # a bench_speed pair if there is one, else a phantom
    python -m benchmarks.speed.bench_network_paths --pair bench_out/speed/case_1 --ct ../shared/data/<ct>.nii.gz

Run it alone on the machine: a second CPU-bound process distorts every row.
"""

from __future__ import annotations

import argparse
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import SimpleITK as sitk

import monai_rigidreg  # before torch: its thread policy applies before torch loads
from benchmarks.bench_common import median_time as _median


def median_time(fn: Callable[[], object], repeats: int) -> float:
    return _median(fn, repeats, warm_up=True)


def load_pair(args: argparse.Namespace) -> tuple[sitk.Image, sitk.Image, str]:
    from monai_rigidreg.io.volumes import load_volume

    if args.pair is not None and args.ct is not None:
        return load_volume(args.ct), load_volume(args.pair / "cbct.nii.gz"), f"{args.ct.name} / {args.pair}"
    ct = Path("../shared/data/thorax_4dct_phase00_itkelastix.nii.gz")
    pair = Path("bench_out/speed/case_1")
    if ct.is_file() and (pair / "cbct.nii.gz").is_file():
        return load_volume(ct), load_volume(pair / "cbct.nii.gz"), f"{ct.name} / {pair}"
    from monai_rigidreg.simulation import simulate_pair

    out = simulate_pair(Path(tempfile.mkdtemp()), phantom="shepp-logan-asym", params=(8, -5, 6, 4, -3, 7), seed=4)
    return load_volume(out["fixed"]), load_volume(out["moving"]), "simulated phantom pair (fast preset)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pair", type=Path, default=None, help="a folder with cbct.nii.gz (with --ct)")
    ap.add_argument("--ct", type=Path, default=None, help="the pair's planning CT")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()

    import torch

    from monai_rigidreg.core.geometry import Grid, params_to_matrix
    from monai_rigidreg.networks import blocks
    from monai_rigidreg.networks.gauss_newton import fixed_jacobian, parameter_flow
    from monai_rigidreg.registration.registrar import RigidRegistrar
    from monai_rigidreg.registration.search import masked_ncc_map, masked_ncc_maps

    fixed, moving, source = load_pair(args)
    reg = RigidRegistrar.from_bundle(device="cpu")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, OMP_WAIT_POLICY="
          f"{os.environ.get('OMP_WAIT_POLICY')}, monai-rigidreg {monai_rigidreg.__version__}; pair: {source}")
    print(f"median of {args.repeats} runs after a warm-up, seconds\n")
    rows: list[tuple[str, float, float]] = []

    body = reg._bodies(fixed)
    center = Grid.from_sitk(moving).center()
    starts = [params_to_matrix(p, center) for p in
              ([0.0] * 6, [12.0, -6.0, 4.0, 0.0, 10.0, 0.0], [-8.0, 0.0, 9.0, -15.0, 0.0, 5.0])]
    prepared = [reg._start_tensors(fixed, moving, s, body) for s in starts]
    mov = torch.stack([p[2] for p in prepared])
    fix = torch.stack([p[1] for p in prepared])
    grid = reg.grid_spec.canonical()

    def one_run() -> None:
        reg.estimate_batch(mov[:1], fix[:1], grid)

    conv = blocks.OneDNNConv3d(16, 16, 3, 1, 1)
    x = torch.rand(1, 16, 32, 32, 32, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        rows.append(("one kernel-3 convolution [1, 16, 32^3]: oneDNN | nn.Conv3d",
                     median_time(lambda: conv(x), args.repeats),
                     median_time(lambda: torch.nn.Conv3d._conv_forward(conv, x, conv.weight, conv.bias),
                                 args.repeats)))

    fast = median_time(one_run, args.repeats)
    onednn = blocks.OneDNNConv3d._conv_forward
    blocks.OneDNNConv3d._conv_forward = torch.nn.Conv3d._conv_forward  # PyTorch's own dispatch
    try:
        slow = median_time(one_run, args.repeats)
    finally:
        blocks.OneDNNConv3d._conv_forward = onednn
    rows.append(("network run, one volume: OneDNNConv3d | nn.Conv3d", fast, slow))

    batched = median_time(lambda: reg.estimate_batch(mov, fix, grid), args.repeats)
    singles = median_time(lambda: [reg.estimate_batch(mov[i:i + 1], fix[i:i + 1], grid) for i in range(3)],
                          args.repeats)
    rows.append(("network from three starts: one batch | one by one", batched, singles))

    native = Grid.centered((102, 102, 102), (1.875,) * 3, tuple(float(v) for v in center))
    feats = torch.rand(1, 2, *native.size, generator=torch.Generator().manual_seed(0))

    def through_flow() -> torch.Tensor:
        g_idx = torch.gradient(feats, dim=(2, 3, 4))
        inv_t = np.linalg.inv(native.index_to_physical()[:3, :3]).T
        g_phys = [sum(float(inv_t[a, i]) * g_idx[i] for i in range(3) if inv_t[a, i] != 0.0) for a in range(3)]
        flow = parameter_flow(native, torch.float32)  # as before 0.4.6, for the grid of each case's last level
        return torch.stack([sum(g_phys[a] * flow[k, a] for a in range(3)) for k in range(6)], 1)

    from monai_rigidreg.networks.correlation_net import local_cost_volume

    cells = torch.randn(2, 1, 32, 16, 16, 16, generator=torch.Generator().manual_seed(5))

    def cost_einsum(feat_moving: torch.Tensor, feat_fixed: torch.Tensor, r: int) -> torch.Tensor:
        fm_n, ff_n = torch.nn.functional.normalize(feat_moving, dim=1), torch.nn.functional.normalize(feat_fixed, dim=1)
        x, y, z = ff_n.shape[2:]
        padded = torch.nn.functional.pad(fm_n, (r,) * 6)
        k = 2 * r + 1
        return torch.cat([torch.einsum("bcxyz,bcxykz->bkxyz", ff_n, padded[:, :, dx:dx + x, dy:dy + y].unfold(4, z, 1))
                          for dx in range(k) for dy in range(k)], dim=1)

    rows.append(("local cost volume [1, 32, 16^3], radius 2: channel-last | einsum (before 0.6.3)",
                 median_time(lambda: local_cost_volume(cells[0], cells[1], 2), args.repeats),
                 median_time(lambda: cost_einsum(cells[0], cells[1], 2), args.repeats)))
    train_cells = torch.randn(2, 4, 32, 16, 16, 16, generator=torch.Generator().manual_seed(6)).requires_grad_(True)
    upstream = torch.randn(4, 125, 16, 16, 16, generator=torch.Generator().manual_seed(7))

    def cost_with_grad(fn: Callable[..., torch.Tensor]) -> tuple[torch.Tensor, ...]:
        return torch.autograd.grad((fn(train_cells[0], train_cells[1], 2) * upstream).sum(), (train_cells,))

    rows.append(("local cost volume + backward [4, 32, 16^3] (training): channel-last | einsum",
                 median_time(lambda: cost_with_grad(local_cost_volume), args.repeats),
                 median_time(lambda: cost_with_grad(cost_einsum), args.repeats)))

    from monai_rigidreg.networks.context_net import sparse_cost_volume
    from monai_rigidreg.networks.correlation_net import unit_channels

    fine = torch.randn(2, 1, 16, 32, 32, 32, generator=torch.Generator().manual_seed(9))
    picked = torch.randperm(32 ** 3, generator=torch.Generator().manual_seed(10))[:4096][None]

    def sparse_einsum(feat_moving: torch.Tensor, feat_fixed: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        # the windows gathered as sparse_cost_volume gathers them, then the einsum of before 0.6.3
        fm_n, ff_n = unit_channels(feat_moving), unit_channels(feat_fixed)
        b, c, x, y, z = ff_n.shape
        padded = torch.nn.functional.pad(fm_n, (1,) * 6).flatten(2)
        ax = torch.arange(3)
        offsets = ((ax[:, None, None] * (y + 2) + ax[None, :, None]) * (z + 2) + ax[None, None, :]).reshape(-1)
        start = ((index // (y * z)) * (y + 2) + (index // z) % y) * (z + 2) + index % z
        windows = (start[..., None] + offsets).reshape(b, -1)
        win = padded.gather(2, windows[:, None].expand(b, c, -1)).view(b, c, -1, 27)
        sel = ff_n.flatten(2).gather(2, index[:, None].expand(b, c, -1))
        return torch.einsum("bcn,bcnk->bnk", sel, win)

    rows.append(("4 mm level's cost volume at 4096 of 32^3 cells [1, 16], radius 1: product-sum | einsum",
                 median_time(lambda: sparse_cost_volume(fine[0], fine[1], picked, 1), args.repeats),
                 median_time(lambda: sparse_einsum(fine[0], fine[1], picked), args.repeats)))

    maps = torch.randn(4, 16, 32, 32, 32, generator=torch.Generator().manual_seed(8))
    rows.append(("unit channel vectors [4, 16, 32^3]: sum of squares | F.normalize",
                 median_time(lambda: unit_channels(maps), args.repeats),
                 median_time(lambda: torch.nn.functional.normalize(maps, dim=1), args.repeats)))

    from monai_rigidreg.core.warp import affine_grid
    from monai_rigidreg.networks.blocks import OneDNNConv3d, pointwise_columns

    theta = torch.randn(1, 3, 4, generator=torch.Generator().manual_seed(9))
    for n in (102, 64):  # the last level's grid, the network's grid
        rows.append((f"sampling points, {n}^3: per-axis sums | F.affine_grid",
                     median_time(lambda n=n: affine_grid(theta, (n, n, n)), args.repeats),
                     median_time(lambda n=n: torch.nn.functional.affine_grid(theta, [1, 1, n, n, n],
                                                                             align_corners=True), args.repeats)))

    head = torch.nn.Sequential(torch.nn.Conv3d(32, 16, 1), torch.nn.PReLU(), torch.nn.Conv3d(16, 1, 1))
    torch.nn.init.normal_(head[-1].weight)
    columns = torch.randn(4, 32, 4096, generator=torch.Generator().manual_seed(10), requires_grad=True)
    volume16 = torch.randn(4, 16, 32, 32, 32, generator=torch.Generator().manual_seed(11), requires_grad=True)
    plain_conv = torch.nn.Conv3d(16, 16, 3, 1, 1)
    swapped_conv = OneDNNConv3d(16, 16, 3, 1, 1)
    swapped_conv.load_state_dict(plain_conv.state_dict())
    threads = torch.get_num_threads()
    for n in sorted({1, threads}):  # a CPU training run beside other work runs at 1 thread (engine.ThreadTuner)
        torch.set_num_threads(n)
        rows.append((f"4 mm weight head + backward [4, 32, 4096] (training), {n} thread(s): conv1d columns | "
                     "Conv3d [.., 1, 1]",
                     median_time(lambda: pointwise_columns(head, columns).sum().backward(), args.repeats),
                     median_time(lambda: head(columns[..., None, None]).sum().backward(), args.repeats)))
        rows.append((f"kernel-3 conv + backward [4, 16, 32^3] 16 -> 16 (training), {n} thread(s): swapped-convolution "
                     "weight gradient | oneDNN's",
                     median_time(lambda: swapped_conv(volume16).sum().backward(), args.repeats),
                     median_time(lambda: plain_conv(volume16).sum().backward(), args.repeats)))
    torch.set_num_threads(threads)

    ramps = median_time(lambda: fixed_jacobian(feats, native), args.repeats)
    flows = median_time(through_flow, args.repeats)
    rows.append(("Jacobian, 102^3 x 2 channels: index ramps | [6, 3, N] flow", ramps, flows))

    gen = torch.Generator().manual_seed(1)
    volume = torch.rand(42, 42, 42, generator=gen)
    templates = torch.rand(27, 24, 24, 24, generator=gen)
    masks = (torch.rand(27, 24, 24, 24, generator=gen) > 0.2).float()
    spectra = (torch.fft.rfftn(volume), torch.fft.rfftn(volume * volume))
    batched_ncc = median_time(lambda: masked_ncc_maps(volume, templates, masks, fft_dtype=torch.float32,
                                                      spectra=spectra), args.repeats)
    single_ncc = median_time(lambda: [masked_ncc_map(volume, templates[k], masks[k], fft_dtype=torch.float32,
                                                     spectra=spectra) for k in range(27)], args.repeats)
    rows.append(("search NCC maps, 27 templates 24^3 in 42^3: batched | one by one", batched_ncc, single_ncc))

    from monai_rigidreg.registration import body as body_module

    def itk_filter(fn: Callable[..., sitk.Image], **kw: object) -> Callable[[np.ndarray, list[int]], np.ndarray]:
        return lambda arr, radius: sitk.GetArrayFromImage(
            fn(sitk.GetImageFromArray(arr.astype(np.uint8)), kernelRadius=radius, kernelType=sitk.sitkBall, **kw)) != 0

    def itk_dilate(mask: sitk.Image, radius_mm: float) -> sitk.Image:
        return sitk.BinaryDilate(sitk.Cast(mask, sitk.sitkUInt8), kernelRadius=body_module._radius_vox(
            radius_mm, mask.GetSpacing()), kernelType=sitk.sitkBall, backgroundValue=0, foregroundValue=1)

    ours = median_time(lambda: body_module.coarse_body_mask(fixed), args.repeats)
    saved = body_module._opening, body_module._closing, body_module._dilate
    body_module._opening = itk_filter(sitk.BinaryMorphologicalOpening, foregroundValue=1)
    body_module._closing = itk_filter(sitk.BinaryMorphologicalClosing, foregroundValue=1, safeBorder=True)
    body_module._dilate = itk_dilate
    try:
        itk = median_time(lambda: body_module.coarse_body_mask(fixed), args.repeats)
    finally:
        body_module._opening, body_module._closing, body_module._dilate = saved
    rows.append((f"CT body mask {fixed.GetSize()}: numpy ball morphology | ITK filters", ours, itk))

    import hashlib

    from monai_rigidreg.registration.body import image_key

    voxels = np.ascontiguousarray(sitk.GetArrayViewFromImage(fixed)).data
    rows.append((f"CT image key (body-mask cache) {fixed.GetSize()}: SHA-256 | BLAKE2b",
                 median_time(lambda: image_key(fixed), args.repeats),
                 median_time(lambda: hashlib.blake2b(voxels, digest_size=16).hexdigest(), args.repeats)))

    from monai_rigidreg.core.image_ops import erode

    support = (torch.rand(1, 1, 102, 102, 102, generator=torch.Generator().manual_seed(3)) > 0.1).float()

    def erode_by_pooling(mask: torch.Tensor, radius: int) -> torch.Tensor:
        for axis in range(3):
            kernel = [1, 1, 1]
            kernel[axis] = 2 * radius + 1
            mask = -torch.nn.functional.max_pool3d(-mask, tuple(kernel), 1, tuple(k // 2 for k in kernel))
        return mask

    rows.append(("support erosion, 102^3, radius 4: sliding-window minima | max_pool3d",
                 median_time(lambda: erode(support, (4, 4, 4)), args.repeats),
                 median_time(lambda: erode_by_pooling(support, 4), args.repeats)))

    from monai_rigidreg.core.grid_sampling import normalize_hu, sitk_on_grid
    from monai_rigidreg.networks.gauss_newton import alignment_features, gauss_newton_align
    from monai_rigidreg.registration import last_level as precision
    from monai_rigidreg.registration.confidence import cylindrical_fov_mask
    from monai_rigidreg.registration.match_region import weight_on_grid

    def last_level_row(ct: sitk.Image, cbct: sitk.Image, fov_image: sitk.Image, label: str) -> None:
        result = reg(ct, cbct, assess=False, resample_moving=False, moving_fov=fov_image)
        start = params_to_matrix(result.params, result.center) @ params_to_matrix([1.0, -1.0, 1.0, 1.0, -1.0, 1.0],
                                                                                  result.center)
        stage = reg.network.fine_stage
        level = precision.native_grid(ct, cbct, start)
        lo, hi = -1200.0, 2000.0
        fixed_t = normalize_hu(sitk_on_grid(ct, level, "bilinear", lo), lo, hi)[None]
        moving_t = normalize_hu(sitk_on_grid(cbct, level, "bilinear", lo, matrix=start), lo, hi)[None]
        fov = (sitk_on_grid(fov_image, level, "nearest", 0.0, matrix=start) > 0).float()[None]
        radius = [max(1, round(stage.support_erosion_mm / s)) for s in level.spacing]
        weight = weight_on_grid([reg._bodies(ct)], level)[None]
        feats = alignment_features(torch.cat([moving_t, fixed_t]), level.spacing, 1e-3, stage.highpass_sigma_mm,
                                   stage.highpass_weight)
        eye = torch.eye(4, dtype=torch.float64)[None]
        kwargs = dict(iterations=4, weight=weight, moving_support=erode(fov, radius),
                      bias_degree=reg.native_bias_degree, tolerance=getattr(stage, "tolerance", None),
                      secant=getattr(stage, "secant", False))
        cand, reach = precision.support_reach(fov, radius, level.spacing, weight)
        estimates = {}

        def steps(subset: bool) -> None:
            extra = {"candidates": cand, "reach_mm": reach} if subset else {}
            estimates[subset] = gauss_newton_align(feats[:1], feats[1:], level, eye, **kwargs, **extra)[0].numpy()

        timed = median_time(lambda: steps(True), args.repeats), median_time(lambda: steps(False), args.repeats)
        corners = np.concatenate([level.corners(), np.ones((8, 1))], 1)
        apart = np.abs(corners @ (estimates[True] - estimates[False]).T)[:, :3].max()
        rows.append((f"last level's steps, {label}, {level.size[0]}^3, {100 * float(cand.float().mean()):.0f}% "
                     f"candidates (estimates {apart:.0e} mm apart): candidate voxels | whole grid", *timed))

    last_level_row(fixed, moving, cylindrical_fov_mask(moving), "this pair")
    paper = Path("bench_out/real_ct/head_tigre_ct")
    if (paper / "dataset.json").is_file():  # a paper-protocol pair (64^3 CBCT): its field of view fills the grid
        import json

        item = json.loads((paper / "dataset.json").read_text())["training"][3]
        last_level_row(sitk.ReadImage(str(paper / item["fixed"]), sitk.sitkFloat32),
                       sitk.ReadImage(str(paper / item["moving"]), sitk.sitkFloat32),
                       sitk.ReadImage(str(paper / item["moving_fov"])), f"paper protocol {item['case_id']}")
    else:
        print(f"(no {paper}/dataset.json: python -m benchmarks.accuracy.bench_real_ct makes it; its last-level "
              "row skipped)")

    from concurrent.futures import ThreadPoolExecutor

    from monai_rigidreg.export.qc_figure import qc_figure
    from monai_rigidreg.io.volumes import resample, save_volume

    registered = resample(moving, fixed, sitk.Euler3DTransform())
    scratch = Path(tempfile.mkdtemp(prefix="bench_outputs_"))

    def outputs(overlap: bool) -> None:
        for name in ("registered.nii.gz", "qc.png"):
            (scratch / name).unlink(missing_ok=True)
        if overlap:
            with ThreadPoolExecutor(max_workers=1) as pool:
                saving = pool.submit(save_volume, registered, scratch / "registered.nii.gz")
                qc_figure(fixed, moving, registered, scratch / "qc.png", title="bench")
                saving.result()
        else:
            save_volume(registered, scratch / "registered.nii.gz")
            qc_figure(fixed, moving, registered, scratch / "qc.png", title="bench")

    rows.append(("registered.nii.gz + QC figure: overlapped | one after the other",
                 median_time(lambda: outputs(True), args.repeats), median_time(lambda: outputs(False), args.repeats)))

    width = max(len(r[0]) for r in rows)
    print(f"{'':{width}s}  {'new s':>8s}  {'old s':>8s}  speed-up")
    for name, new, old in rows:
        print(f"{name:{width}s}  {new:8.4f}  {old:8.4f}  {old / new:5.2f}x")


if __name__ == "__main__":
    main()
