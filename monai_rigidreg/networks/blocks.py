"""The residual encoder stage of :class:`~monai_rigidreg.networks.CorrelationRigidNet`, without MONAI.

:class:`ResidualStage3d` is the subset of MONAI's :class:`monai.networks.blocks.ResidualUnit` that the shipped
network uses (3D, kernel 3, ``"NDA"`` ordering, PReLU, instance or batch norm, no dropout), built from torch modules
with the same module tree, so its ``state_dict`` keys are MONAI's (``conv.unit0.conv.weight``,
``conv.unit0.adn.A.weight``, ``residual.weight``, ...): checkpoints load either way and
``tests/test_networks.py`` checks both give the same output with the same weights.

Why not MONAI's block: every ``monai.*`` import runs MONAI's ``__init__``, which imports all its submodules (ignite
and ``torch.distributed`` among them): about 6 s on 2 cores (``python -X importtime -c "import monai"``), where
``monai-rigidreg register`` has a budget of 1.5 s for the whole command (the speed issue). The register path
therefore imports no MONAI module (``tests/test_threads_and_startup.py``); training, the transforms and the bundle
still use MONAI.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["NORMS", "OneDNNConv3d", "ResidualStage3d", "pointwise_columns"]

NORMS = ("INSTANCE", "BATCH", "NONE")
"""Normalisation layers :class:`ResidualStage3d` builds (MONAI's names; a ``(name, kwargs)`` pair passes keyword
arguments such as ``{"affine": True}`` to the torch layer, as MONAI's factories do; ``"NONE"``: no normalisation,
for features that must not depend on the extent of the volume they were computed on)."""


def _norm(norm: str | tuple, channels: int) -> nn.Module:
    name, kwargs = (norm, {}) if isinstance(norm, str) else (norm[0], dict(norm[1]) if len(norm) > 1 else {})
    name = str(name).upper()
    if name == "INSTANCE":
        return nn.InstanceNorm3d(channels, **kwargs)
    if name == "BATCH":
        return nn.BatchNorm3d(channels, **kwargs)
    if name == "NONE":
        return nn.Identity()
    raise ValueError(f"norm must be one of {NORMS} (or a (name, kwargs) pair), got {norm!r}")


def _conv3d(input: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, stride: tuple[int, ...],
            padding: tuple[int, ...], dilation: tuple[int, ...] = (1, 1, 1), groups: int = 1) -> torch.Tensor:
    """``F.conv3d`` (zero padding), a single float32 CPU volume sent to oneDNN directly (``torch.mkldnn_convolution``;
    :class:`OneDNNConv3d` says why)."""
    if (input.shape[0] == 1 and input.device.type == "cpu" and input.dtype == torch.float32
            and weight.dtype == torch.float32 and torch.backends.mkldnn.is_available()
            and torch.backends.mkldnn.enabled):
        return torch.mkldnn_convolution(input.contiguous(), weight, bias, padding, stride, dilation, groups)
    return nn.functional.conv3d(input, weight, bias, stride, padding, dilation, groups)


class _SwappedWeightGradConv3d(torch.autograd.Function):
    """``F.conv3d`` (groups 1, dilation 1, zero padding) whose weight gradient is itself one convolution.

    ``dW[o, i, k] = sum_b sum_x g[b, o, x] * x_pad[b, i, stride * x + k]`` is the convolution of the padded input
    with the batch as its channels and its channels as its batch (``[C_in, B, ...]``) by the output gradient taken
    as ``C_out`` filters of ``B`` channels, dilated by the stride, cut to the kernel's size. On CPU oneDNN runs this
    forward convolution faster than its own weight-gradient kernel: a training step's ``[4, 16, 32^3]`` 16 -> 16
    kernel-3 convolution with its backward 1.56x faster at 1 thread, 1.83x at 2
    (``benchmarks/speed/bench_network_paths.py``); a whole context-network step beside a busy process at 2 threads
    3.83 -> 2.12 s (``benchmarks/speed/bench_training_threads.py``). The input gradient is PyTorch's own
    (``aten.convolution_backward``), the bias gradient the output gradient's sum.

    Under autocast (the context network's ``train_autocast``) the convolution runs in autocast's precision, as
    ``F.conv3d`` would: the inputs are saved cast to the output's dtype, the backward computes in that dtype and
    returns each gradient in the dtype of the tensor it belongs to (as ``F.conv3d``'s casts do).
    """

    @staticmethod
    def forward(ctx, input, weight, bias, stride, padding):  # noqa: ANN001, ANN205 (autograd.Function)
        out = _conv3d(input, weight, bias, stride, padding)  # autocast, where on, casts inside F.conv3d
        ctx.dtypes = (input.dtype, weight.dtype, None if bias is None else bias.dtype)
        if out.dtype != input.dtype or out.dtype != weight.dtype:
            input, weight = input.to(out.dtype), weight.to(out.dtype)
        ctx.save_for_backward(input, weight)
        ctx.stride, ctx.padding, ctx.has_bias = stride, padding, bias is not None
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):  # noqa: ANN001, ANN205
        input, weight = ctx.saved_tensors
        input_dtype, weight_dtype, bias_dtype = ctx.dtypes
        grad_input = grad_weight = grad_bias = None
        with torch.autocast(grad.device.type, enabled=False):
            compute = grad.to(input.dtype)
            if ctx.needs_input_grad[0]:
                grad_input = torch.ops.aten.convolution_backward(
                    compute, input, weight, None, list(ctx.stride), list(ctx.padding), [1, 1, 1], False, [0, 0, 0],
                    1, [True, False, False])[0].to(input_dtype)
            if ctx.needs_input_grad[1]:
                px, py, pz = ctx.padding
                padded = nn.functional.pad(input, (pz, pz, py, py, px, px)) if px or py or pz else input
                full = nn.functional.conv3d(padded.transpose(0, 1), compute.transpose(0, 1), dilation=ctx.stride)
                kx, ky, kz = weight.shape[2:]
                grad_weight = full[:, :, :kx, :ky, :kz].transpose(0, 1).to(weight_dtype)
            if ctx.has_bias and ctx.needs_input_grad[2]:
                grad_bias = grad.sum((0, 2, 3, 4), dtype=torch.promote_types(grad.dtype, bias_dtype)).to(bias_dtype)
        return grad_input, grad_weight, grad_bias, None, None


class OneDNNConv3d(nn.Conv3d):
    """``nn.Conv3d`` with two CPU paths of its own: a single volume sent to oneDNN directly, and a weight gradient
    computed as a convolution.

    * PyTorch 2.x runs a convolution of a single CPU volume (batch 1, float32, kernel larger than 1) on its slow
      reference path instead of oneDNN (MKL-DNN): on 2 cores a kernel-3 convolution of ``[1, 16, 32, 32, 32]`` took
      24 ms instead of 1.8 ms through ``torch.mkldnn_convolution`` (``benchmarks/speed/bench_network_paths.py``,
      torch 2.13; a batch of 2 already goes to oneDNN). The registration runs the network on one volume at a time,
      and the regression's fine passes re-encode the warped CBCT alone, so this was a quarter of a network run (one
      run 0.24 s instead of 0.32 s, the same script).
    * Where the weight needs a gradient (training) on CPU, the weight gradient is one forward convolution
      (:class:`_SwappedWeightGradConv3d`) instead of oneDNN's weight-gradient kernel, which was the largest item of
      a context-network training step.

    Same weights, same ``state_dict``; the result and the gradients agree with ``nn.Conv3d``'s to float rounding
    (``tests/networks/test_correlation_net.py``). Elsewhere it is ``nn.Conv3d``: on CUDA, for kernel 1, dilation or
    groups, and without a weight gradient for batches, float64 or oneDNN disabled.

    Example:
        >>> conv = OneDNNConv3d(2, 4, 3, 2, 1)
        >>> conv(torch.randn(3, 2, 9, 8, 8)).shape
        torch.Size([3, 4, 5, 4, 4])
    """

    def _conv_forward(self, input: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
        if self.padding_mode != "zeros" or isinstance(self.padding, str) or max(self.kernel_size) == 1:
            return super()._conv_forward(input, weight, bias)
        if (self.groups == 1 and tuple(self.dilation) == (1, 1, 1) and input.device.type == "cpu"
                and weight.requires_grad and torch.is_grad_enabled()):
            return _SwappedWeightGradConv3d.apply(input, weight, bias, tuple(self.stride), tuple(self.padding))
        return _conv3d(input, weight, bias, tuple(self.stride), tuple(self.padding), tuple(self.dilation),
                       self.groups)


class _ConvNormAct(nn.Sequential):
    """``conv`` (3D, kernel 3, padding 1) then ``adn`` (``N``: norm, ``A``: PReLU): MONAI's ``Convolution``."""

    def __init__(self, in_channels: int, out_channels: int, stride: int, norm: str | tuple) -> None:
        super().__init__()
        self.add_module("conv", OneDNNConv3d(in_channels, out_channels, 3, stride, 1))
        adn = nn.Sequential()
        adn.add_module("N", _norm(norm, out_channels))
        adn.add_module("A", nn.PReLU())
        self.add_module("adn", adn)


class ResidualStage3d(nn.Module):
    """A residual stage: ``subunits`` conv-norm-PReLU units (the first with ``stride``) plus a residual branch.

    ``out = conv(x) + residual(x)``; the residual is the identity when the shape is kept, a kernel-3 convolution
    with ``stride`` when it is not (a kernel-1 one when only the channels change): MONAI's ``ResidualUnit`` with
    ``spatial_dims=3, kernel_size=3, act="PRELU", adn_ordering="NDA"``, no dropout.

    Args:
        in_channels: input channels ``C_in``.
        out_channels: output channels ``C_out``.
        stride: stride of the first unit and of the residual branch (2 halves every spatial size, rounding up).
        subunits: conv-norm-PReLU units (at least 1).
        norm: ``"INSTANCE"``, ``"BATCH"``, ``"NONE"`` or ``(name, kwargs)`` (see :data:`NORMS`).

    Shapes: ``[B, C_in, x, y, z]`` -> ``[B, C_out, ceil(x / stride), ceil(y / stride), ceil(z / stride)]``.
    """

    def __init__(self, in_channels: int, out_channels: int, stride: int = 2, subunits: int = 2,
                 norm: str | tuple = "INSTANCE") -> None:
        super().__init__()
        self.conv = nn.Sequential()
        c_in, s = int(in_channels), int(stride)
        for i in range(max(1, int(subunits))):
            self.conv.add_module(f"unit{i:d}", _ConvNormAct(c_in, int(out_channels), s, norm))
            c_in, s = int(out_channels), 1
        self.residual: nn.Module = nn.Identity()
        if int(stride) != 1:
            self.residual = OneDNNConv3d(int(in_channels), int(out_channels), 3, int(stride), 1)
        elif int(in_channels) != int(out_channels):
            self.residual = nn.Conv3d(int(in_channels), int(out_channels), 1, 1, 0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(x) + self.residual(x)


def pointwise_columns(head: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    """``head`` (kernel-1 ``nn.Conv3d`` layers between elementwise ones, e.g. a match-weight head) on columns.

    Each kernel-1 ``Conv3d`` runs as ``conv1d`` with its own weights, so the module and its ``state_dict`` stay those
    of a volume head. Why: the same ``Conv3d`` on the columns viewed as a ``[B, C, N, 1, 1]`` volume takes a slow
    backward at one thread, 143 ms forward and backward at ``[4, 32, 4096]`` against 5.8 ms as ``conv1d`` (7.0 ms
    either way at 2 threads; torch 2.13, ``benchmarks/speed/bench_network_paths.py``).

    Args:
        head: the layers, applied in order; every ``nn.Conv3d`` among them has kernel size 1.
        x: ``[B, C, N]`` features of ``N`` cells.

    Returns:
        ``[B, C_out, N]``: what ``head(x[..., None, None])[..., 0, 0]`` gives.

    Example:
        >>> head = nn.Sequential(nn.Conv3d(8, 4, 1), nn.PReLU(), nn.Conv3d(4, 1, 1))
        >>> x = torch.randn(2, 8, 10)
        >>> bool(torch.allclose(pointwise_columns(head, x), head(x[..., None, None])[..., 0, 0], atol=1e-6))
        True
    """
    for layer in head:
        if isinstance(layer, nn.Conv3d):
            if tuple(layer.kernel_size) != (1, 1, 1):
                raise ValueError(f"pointwise_columns needs kernel-1 convolutions, got {tuple(layer.kernel_size)}")
            x = nn.functional.conv1d(x, layer.weight.flatten(2), layer.bias)
        else:
            x = layer(x)
    return x
