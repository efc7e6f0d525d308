"""3×3 deformable convolution (Dai et al. 2017, DCN v1) that trains in PyTorch and exports to ONNX ``DeformConv``.

Offsets follow torchvision's and ONNX's layout: ``offset[:, 2k]`` is Δrow and ``offset[:, 2k + 1]`` is Δcol
of tap ``k = kh·3 + kw``; samples outside the image read zero. In PyTorch the samples come from one
``grid_sample`` call; during ``torch.onnx.export`` (TorchScript exporter, opset ≥ 19) the same call is
written as the ONNX ``DeformConv`` operator, which onnxruntime runs natively on the CPU.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

KERNEL = 3
TAPS = KERNEL * KERNEL


def _sample_taps(x: Tensor, offset: Tensor) -> Tensor:
    """Bilinear samples of ``x`` (B, C, H, W) at every tap → (B, C, 9, H, W)."""
    batch, _, height, width = x.shape
    rows = torch.arange(height, dtype=x.dtype, device=x.device).view(1, 1, height, 1)
    cols = torch.arange(width, dtype=x.dtype, device=x.device).view(1, 1, 1, width)
    taps = torch.arange(TAPS, device=x.device)
    tap_rows = (taps // KERNEL - 1).to(x.dtype).view(1, TAPS, 1, 1)
    tap_cols = (taps % KERNEL - 1).to(x.dtype).view(1, TAPS, 1, 1)
    offset = offset.view(batch, TAPS, 2, height, width)
    sample_rows = rows + tap_rows + offset[:, :, 0]  # (B, 9, H, W)
    sample_cols = cols + tap_cols + offset[:, :, 1]
    # align_corners=True maps pixel centres 0 and size-1 to -1 and 1; zeros padding gives torchvision's
    # "outside corners read zero" bilinear rule.
    grid = torch.stack(
        (sample_cols * (2.0 / max(width - 1, 1)) - 1.0, sample_rows * (2.0 / max(height - 1, 1)) - 1.0), dim=-1
    ).view(batch, TAPS * height, width, 2)
    samples = F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    return samples.view(batch, x.shape[1], TAPS, height, width)


def deform_conv2d_reference(x: Tensor, offset: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
    """Deformable 3×3 convolution, stride 1, padding 1, one offset group, in plain PyTorch ops."""
    batch, channels, height, width = x.shape
    columns = _sample_taps(x, offset).reshape(batch, channels * TAPS, height * width)
    out = torch.matmul(weight.reshape(weight.shape[0], channels * TAPS), columns)
    out = out.view(batch, weight.shape[0], height, width)
    if bias is not None:
        out = out + bias.view(1, -1, 1, 1)
    return out


class _DeformConvOnnx(torch.autograd.Function):
    """Forward only: stands in for the deformable convolution while the TorchScript exporter traces."""

    @staticmethod
    def forward(ctx, x: Tensor, offset: Tensor, weight: Tensor, bias: Tensor) -> Tensor:  # type: ignore[override]
        return deform_conv2d_reference(x, offset, weight, bias)

    @staticmethod
    def symbolic(g, x, offset, weight, bias):  # type: ignore[no-untyped-def]
        return g.op(
            "DeformConv",
            x,
            weight,
            offset,
            bias,
            kernel_shape_i=[KERNEL, KERNEL],
            pads_i=[1, 1, 1, 1],
            strides_i=[1, 1],
            dilations_i=[1, 1],
            group_i=1,
            offset_group_i=1,
        )


def deform_conv2d(x: Tensor, offset: Tensor, weight: Tensor, bias: Tensor) -> Tensor:
    if torch.onnx.is_in_onnx_export():
        return _DeformConvOnnx.apply(x, offset, weight, bias)
    return deform_conv2d_reference(x, offset, weight, bias)


class DeformConv2d(nn.Module):
    """A 3×3 deformable convolution whose offsets come from a plain 3×3 convolution of the same input.

    The offset convolution starts at zero, so an untrained layer is exactly a plain 3×3 convolution.
    """

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.offset = nn.Conv2d(in_channels, 2 * TAPS, KERNEL, padding=1)
        conv = nn.Conv2d(in_channels, out_channels, KERNEL, padding=1)
        assert self.offset.bias is not None and conv.bias is not None  # both built with bias=True
        nn.init.zeros_(self.offset.weight)
        nn.init.zeros_(self.offset.bias)
        self.weight = conv.weight
        self.bias = conv.bias

    def forward(self, x: Tensor) -> Tensor:
        return deform_conv2d(x, self.offset(x), self.weight, self.bias)
