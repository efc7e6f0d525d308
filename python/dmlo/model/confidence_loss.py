"""Confidence loss: Q* as the probability that the match is right (beyond the paper).

The odometry keeps the 1000 most confident matches after NMS, so what matters of Q* is how it ranks the
cells. The flow loss (Eq. 10) never asks for that: a cell whose ground truth lies outside its refine
window gets no loss at all, so its Q* is whatever the softmax happens to give, and a confidently wrong
match costs nothing. Measured on the held-out drives with the stage-2 model, only a fifth of the kept
matches lay within 1 px of the truth; choosing the kept cells by their true error instead would halve the
pair rotation error (0.082° → 0.034°). The loss here is the binary cross entropy of Q* against "the
predicted match lies within ``inlier_px`` of the truth", over every cell with a ground truth.

Tried for one epoch from the bundled model (docs/measurements.md, "Confidence loss"): weight 0.5 barely moved the ranking
(kept matches within 1 px 21.0 → 21.8 %), weight 5 bent the flow itself and raised the pair error; Q* shares
its softmax with the flow, so the option stays off by default.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

# Q* is a ratio of softmax masses in float32 and reaches 0 and 1. It is squeezed into [ε, 1 − ε] by an
# affine map rather than a clamp, so a confidently wrong cell (Q* ≈ 1) still gets a gradient; ε bounds a
# single cell's loss (log 1/ε) and gradient (1/ε).
_EPSILON = 1e-3


def confidence_target(flow: Tensor, gt_flow: Tensor, valid: Tensor, inlier_px: float = 1.0) -> tuple[Tensor, Tensor]:
    """``(target, counted)``, both (B, H, W): 1.0 where the predicted flow is within ``inlier_px`` of the
    ground truth, and the cells that count (valid, finite ground truth). No gradient flows through either."""
    with torch.no_grad():
        counted = valid.bool() & torch.isfinite(gt_flow).all(dim=1)
        error = torch.where(counted.unsqueeze(1), flow - gt_flow, torch.zeros_like(flow)).norm(dim=1)
        target = (counted & (error < inlier_px)).to(flow.dtype)
    return target, counted


def confidence_loss(confidence: Tensor, flow: Tensor, gt_flow: Tensor, valid: Tensor, inlier_px: float = 1.0) -> Tensor:
    """Mean binary cross entropy of ``confidence`` (B, H, W) in (0, 1] over the counted cells; 0 (still in
    the graph) when none counts. ``flow``/``gt_flow`` (B, 2, H, W) pixels, ``valid`` (B, H, W)."""
    if confidence.shape != valid.shape or flow.shape != gt_flow.shape or flow.shape[2:] != confidence.shape[1:]:
        raise ValueError(
            f"confidence {tuple(confidence.shape)}, flow {tuple(flow.shape)}, gt_flow {tuple(gt_flow.shape)} and "
            f"valid {tuple(valid.shape)} must describe the same (B, H, W) cells"
        )
    target, counted = confidence_target(flow, gt_flow, valid, inlier_px)
    probability = _EPSILON + (1 - 2 * _EPSILON) * confidence
    per_cell = F.binary_cross_entropy(probability, target, reduction="none")
    return torch.where(counted, per_cell, torch.zeros_like(per_cell)).sum() / counted.sum().clamp(min=1)
