"""Sub-pixel bilinear cross entropy (Eq. 9–10) over a D×D correlation window, and its one-hot ablation."""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor


class WindowTarget(NamedTuple):
    probability: Tensor
    """(B, D·D, H, W) ground-truth distribution P over the window cells (Eq. 9)."""
    inside: Tensor
    """(B, H, W) bool: the ground truth lies in the window (cells outside get no loss)."""


def window_target(gt_offset: Tensor, window: int, subpixel: bool = True) -> WindowTarget:
    """Target distribution for ground-truth offsets (B, 2, H, W) relative to the window centre, in cells.

    Sub-pixel: the bilinear weights of the GT location on the four surrounding cells (Eq. 9); a GT lying
    exactly on the last row/column puts its weight on that row/column. One-hot: weight 1 on the nearest
    cell. A GT outside [−r, r]² has no complete support in the window and is marked outside.
    """
    batch, _, height, width = gt_offset.shape
    radius = window // 2
    position = gt_offset + radius  # window-cell coordinates, 0 … D−1 inside
    finite = torch.isfinite(position).all(dim=1)
    inside = finite & (position >= 0).all(dim=1) & (position <= window - 1).all(dim=1)
    position = torch.where(inside.unsqueeze(1), position, torch.zeros_like(position))
    probability = torch.zeros(batch, window * window, height, width, dtype=gt_offset.dtype, device=gt_offset.device)
    if subpixel:
        first = torch.clamp(torch.floor(position), 0, window - 2)
        fraction = position - first
        first = first.long()
        for d_row in (0, 1):
            for d_col in (0, 1):
                weight_row = fraction[:, 0] if d_row else 1 - fraction[:, 0]
                weight_col = fraction[:, 1] if d_col else 1 - fraction[:, 1]
                cell = (first[:, 0] + d_row) * window + first[:, 1] + d_col
                probability.scatter_add_(1, cell.unsqueeze(1), (weight_row * weight_col).unsqueeze(1))
    else:
        nearest = torch.round(position).long()
        cell = nearest[:, 0] * window + nearest[:, 1]
        probability.scatter_(1, cell.unsqueeze(1), 1.0)
    probability = probability * inside.unsqueeze(1)
    return WindowTarget(probability, inside)


def window_cross_entropy(logits: Tensor, gt_offset: Tensor, valid: Tensor, window: int, subpixel: bool = True) -> tuple[Tensor, Tensor]:
    """Mean over valid cells with the GT inside the window of −Σ P log Q (Eq. 10).

    Returns ``(loss, cells)``: the loss (0 when no cell counts, still part of the graph) and the number of
    cells it averages over.
    """
    target = window_target(gt_offset, window, subpixel)
    counted = target.inside & valid
    per_cell = -(target.probability * F.log_softmax(logits, dim=1)).sum(dim=1)
    cells = counted.sum()
    loss = torch.where(counted, per_cell, torch.zeros_like(per_cell)).sum() / cells.clamp(min=1)
    return loss, cells
