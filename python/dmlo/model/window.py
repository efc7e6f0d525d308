"""From D×D similarities to a sub-pixel offset and a confidence: softmax (Eq. 3) and the best 2×2 window (Eq. 11).

The softmax is never normalised in full (ONNX-NOTES item 4): ``e = exp(l − max l)``; the winning window's
mass ``Q* = Σ_W e / Σ e`` and the in-window weights ``e / Σ_W e`` are ratios that do not need it.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor


class WindowDecoding(NamedTuple):
    offset: Tensor
    """(B, 2, H, W) sub-pixel (Δrow, Δcol) of the match relative to the window centre, in window cells."""
    confidence: Tensor
    """(B, H, W) Q*: the softmax mass of the winning 2×2 window."""
    window_sums: Tensor
    """(B, (D−1)², H, W) unnormalised 2×2 window masses (for tie checks)."""


def decode_window(logits: Tensor, window: int) -> WindowDecoding:
    """Decodes (B, D·D, H, W) logits whose channel ``d = row·D + col`` indexes the window cell."""
    batch, _, height, width = logits.shape
    radius = window // 2
    weights = torch.exp(logits - logits.amax(dim=1, keepdim=True)).view(batch, window, window, height, width)
    total = weights.sum(dim=(1, 2))
    # The four corners of every 2×2 window, indexed by the window's top-left cell.
    top_left = weights[:, :-1, :-1].reshape(batch, -1, height, width)
    top_right = weights[:, :-1, 1:].reshape(batch, -1, height, width)
    bottom_left = weights[:, 1:, :-1].reshape(batch, -1, height, width)
    bottom_right = weights[:, 1:, 1:].reshape(batch, -1, height, width)
    sums = top_left + top_right + bottom_left + bottom_right
    best = sums.argmax(dim=1, keepdim=True)

    def pick(values: Tensor) -> Tensor:
        return values.gather(1, best).squeeze(1)

    best_sum = pick(sums)
    # Row and column of the winning window's top-left cell, computed in float (exports as plain arithmetic).
    best_float = best.squeeze(1).to(logits.dtype)
    best_row = torch.floor(best_float / (window - 1))
    best_col = best_float - best_row * (window - 1)
    row = best_row + (pick(bottom_left) + pick(bottom_right)) / best_sum - radius
    col = best_col + (pick(top_right) + pick(bottom_right)) / best_sum - radius
    return WindowDecoding(torch.stack((row, col), dim=1), best_sum / total, sums)


def peak_centroid(logits: Tensor, window: int) -> Tensor:
    """Sub-pixel offset (B, 2, H, W), in window cells from the window centre: the softmax-weighted centroid
    of the 3×3 cells around the most likely cell (moved inside the window when that cell is on its edge).

    Beyond the paper, whose Eq. 11 takes the centroid of the best 2×2 window. A 2×2 window always
    straddles a cell border, so when the network spreads its mass over the neighbours of the true cell
    (it does) that centroid is pulled towards the border: held out, the predicted fractional parts pile
    up near ±0.5 px, where the truth lies ~0.1–0.2 px closer to the cell centres. The 3×3 centroid around
    the peak has no such pull.
    """
    batch, _, height, width = logits.shape
    radius = window // 2
    weights = torch.exp(logits - logits.amax(dim=1, keepdim=True)).view(batch, window, window, height, width)
    best = logits.argmax(dim=1).to(logits.dtype)  # (B, H, W); float arithmetic exports as plain ops
    best_row = torch.floor(best / window)
    best_col = best - best_row * window
    best_row = best_row.clamp(1, window - 2).unsqueeze(1).unsqueeze(1)
    best_col = best_col.clamp(1, window - 2).unsqueeze(1).unsqueeze(1)
    cells = torch.arange(window, dtype=logits.dtype, device=logits.device)
    rows = cells.view(1, window, 1, 1, 1)
    cols = cells.view(1, 1, window, 1, 1)
    near = ((rows - best_row).abs() <= 1).to(logits.dtype) * ((cols - best_col).abs() <= 1).to(logits.dtype)
    mass = weights * near
    total = mass.sum(dim=(1, 2))
    row = (mass * rows).sum(dim=(1, 2)) / total - radius
    col = (mass * cols).sum(dim=(1, 2)) / total - radius
    return torch.stack((row, col), dim=1)
