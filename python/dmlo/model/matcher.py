"""The full DMLO matcher: coarse correlation at stride 4×8, then refine correlation at full resolution.

Shapes: a scan is (B, 2, H, W) float32 — channel 0 range in metres (0 where empty), channel 1
reflectance — with H divisible by 4 and W by 8. For every reference cell p the matcher predicts the flow
(Δrow, Δcol) in full-resolution pixels (the match lies at p + flow in the target scan) and the confidence
Q* of §III-C-d.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from dmlo.model.config import MatcherConfig
from dmlo.model.correlation import block_window_correlation, clamp_origin, local_correlation
from dmlo.model.features import CoarseEncoder, RefineEncoder
from dmlo.model.loss import window_cross_entropy
from dmlo.model.window import decode_window, peak_centroid


class Features(NamedTuple):
    """What the matcher needs of one scan; cached per frame by the odometry."""

    coarse: Tensor
    """(B, C, H/4, W/8), L2-normalised when the config says so."""
    refine: Tensor
    """(B, Cr, H, W), L2-normalised when the config says so."""


class MatchOutput(NamedTuple):
    flow: Tensor
    """(B, 2, H, W) (Δrow, Δcol) in full-resolution pixels."""
    confidence: Tensor
    """(B, H, W) Q* of the refine window."""
    coarse_logits: Tensor
    """(B, Dc², H/4, W/8) scaled similarities of the coarse window (origin 0)."""
    coarse_flow: Tensor
    """(B, 2, H/4, W/8) (Δrow, Δcol) in coarse cells."""
    coarse_confidence: Tensor
    refine_logits: Tensor
    """(B, Dr², H, W) scaled similarities of the refine window."""
    refine_origin: Tensor
    """(B, 2, H, W) integer refine window centre relative to each cell (clamped into the image)."""


def check_scan(scan: Tensor, name: str = "scan") -> None:
    if scan.dim() != 4 or scan.shape[1] != 2:
        raise ValueError(f"{name} must have shape (B, 2, H, W), got {tuple(scan.shape)}")
    if scan.shape[2] % 4 or scan.shape[3] % 8:
        raise ValueError(f"{name} height must be divisible by 4 and width by 8, got {tuple(scan.shape[2:])}")
    if not scan.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got {scan.dtype}")


def upsample_coarse_flow(coarse_flow: Tensor, stride: tuple[int, int]) -> Tensor:
    """Coarse-cell flow (B, 2, h, w) → full-resolution pixel flow (B, 2, h·sr, w·sc), nearest neighbour."""
    batch, _, height, width = coarse_flow.shape
    rows, cols = stride
    scale = torch.tensor([rows, cols], dtype=coarse_flow.dtype, device=coarse_flow.device).view(1, 2, 1, 1)
    pixels = (coarse_flow * scale).view(batch, 2, height, 1, width, 1)
    return pixels.expand(batch, 2, height, rows, width, cols).reshape(batch, 2, height * rows, width * cols)


class Matcher(nn.Module):
    """Siamese coarse-to-fine matcher of §III-C."""

    def __init__(self, config: MatcherConfig | None = None) -> None:
        super().__init__()
        self.config = config or MatcherConfig()
        self.coarse_encoder = CoarseEncoder(self.config)
        self.refine_encoder = RefineEncoder(self.config)
        # Learned softmax temperatures, one per stage, started at config.similarity_scale.
        initial = math.log(self.config.similarity_scale)
        self.coarse_log_scale = nn.Parameter(torch.tensor(initial))
        self.refine_log_scale = nn.Parameter(torch.tensor(initial))

    def encode(self, scan: Tensor) -> Features:
        check_scan(scan)
        reflectance = 1.0 if self.config.use_reflectance else 0.0  # 0: a range-only model
        scale = torch.tensor([1.0 / self.config.range_scale_m, reflectance], dtype=scan.dtype, device=scan.device)
        scan = scan * scale.view(1, 2, 1, 1)
        coarse = self.coarse_encoder(scan)
        refine = self.refine_encoder(scan)
        if self.config.normalize_features:
            coarse = F.normalize(coarse, dim=1, eps=1e-6)
            refine = F.normalize(refine, dim=1, eps=1e-6)
        return Features(coarse, refine)

    def match(self, ref: Features, tgt: Features) -> MatchOutput:
        config = self.config
        coarse_window, refine_window = config.coarse_window, config.refine_window
        coarse_logits = local_correlation(ref.coarse, tgt.coarse, coarse_window)  # origin 0
        coarse_logits = coarse_logits * self.coarse_log_scale.exp()
        coarse = decode_window(coarse_logits, coarse_window)

        # The refine window is centred on the upsampled coarse match rounded to a pixel; no gradient flows
        # through the argmax-based coarse decision.
        height, width = ref.refine.shape[2:]
        stride = config.coarse_stride
        unclamped = torch.round(upsample_coarse_flow(coarse.offset.detach(), stride))
        origin = clamp_origin(unclamped, height, width)
        # Every cell of a coarse cell's block shares its unclamped origin: one patch per block suffices.
        block_origin = unclamped[:, :, :: stride[0], :: stride[1]]
        refine_logits = block_window_correlation(ref.refine, tgt.refine, block_origin, stride, refine_window)
        refine_logits = refine_logits * self.refine_log_scale.exp()
        refine = decode_window(refine_logits, refine_window)
        offset = refine.offset if config.refine_offset == "window" else peak_centroid(refine_logits, refine_window)
        return MatchOutput(
            flow=origin + offset,
            confidence=refine.confidence,
            coarse_logits=coarse_logits,
            coarse_flow=coarse.offset,
            coarse_confidence=coarse.confidence,
            refine_logits=refine_logits,
            refine_origin=origin,
        )

    def forward(self, ref_scan: Tensor, tgt_scan: Tensor) -> MatchOutput:
        check_scan(tgt_scan, "tgt_scan")
        if ref_scan.shape != tgt_scan.shape:
            raise ValueError(f"ref_scan {tuple(ref_scan.shape)} and tgt_scan {tuple(tgt_scan.shape)} differ in shape")
        # One batch through the Siamese encoders: both scans share weights and BatchNorm statistics.
        both = self.encode(torch.cat((ref_scan, tgt_scan), dim=0))
        batch = ref_scan.shape[0]
        ref = Features(both.coarse[:batch], both.refine[:batch])
        tgt = Features(both.coarse[batch:], both.refine[batch:])
        return self.match(ref, tgt)


def coarse_ground_truth(flow: Tensor, valid: Tensor, stride: tuple[int, int], min_fraction: float = 0.25) -> tuple[Tensor, Tensor]:
    """Ground truth of a coarse cell: the mean flow of its valid pixels, in coarse cells.

    A coarse cell (i, j) stands for the patch of rows 4i…4i+3 and columns 8j…8j+7; moving its match by one
    coarse cell moves the patch by (4, 8) pixels. The cell counts when at least ``min_fraction`` of its
    pixels have a valid ground truth. Returns ``(flow (B, 2, h, w), valid (B, h, w))``.
    """
    weight = valid.to(flow.dtype).unsqueeze(1)
    flow = torch.where(valid.unsqueeze(1), flow, torch.zeros_like(flow))
    fraction = F.avg_pool2d(weight, stride, stride)
    mean_flow = F.avg_pool2d(flow * weight, stride, stride) / fraction.clamp(min=1e-6)
    scale = torch.tensor(stride, dtype=flow.dtype, device=flow.device).view(1, 2, 1, 1)
    return mean_flow / scale, fraction.squeeze(1) >= min_fraction


def matching_loss(output: MatchOutput, gt_flow: Tensor, valid: Tensor, config: MatcherConfig) -> tuple[Tensor, dict[str, float]]:
    """Loss of both stages (Eq. 10, each a mean over its valid cells) and logging metrics.

    ``gt_flow`` (B, 2, H, W) in pixels and ``valid`` (B, H, W) bool come from the ground truth of §III-C-c.
    """
    if gt_flow.shape != output.flow.shape or valid.shape != output.confidence.shape:
        raise ValueError(
            f"gt_flow {tuple(gt_flow.shape)} / valid {tuple(valid.shape)} do not match the prediction "
            f"{tuple(output.flow.shape)}"
        )
    valid = valid.bool() & torch.isfinite(gt_flow).all(dim=1)
    gt_flow = torch.where(valid.unsqueeze(1), gt_flow, torch.zeros_like(gt_flow))
    coarse_flow, coarse_valid = coarse_ground_truth(gt_flow, valid, config.coarse_stride)
    coarse_loss, coarse_cells = window_cross_entropy(
        output.coarse_logits, coarse_flow, coarse_valid, config.coarse_window, config.subpixel_loss
    )
    refine_loss, refine_cells = window_cross_entropy(
        output.refine_logits, gt_flow - output.refine_origin, valid, config.refine_window, config.subpixel_loss
    )
    loss = config.coarse_loss_weight * coarse_loss + config.refine_loss_weight * refine_loss
    metrics = {
        "loss": float(loss.detach()),
        "coarse_loss": float(coarse_loss.detach()),
        "refine_loss": float(refine_loss.detach()),
        "refine_coverage": float(refine_cells) / max(int(valid.sum()), 1),
    }
    return loss, metrics
