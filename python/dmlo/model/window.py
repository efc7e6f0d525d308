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
    """Decodes (B, D·D, H, W) logits whose channel ``d = row·D + col`` indexes the window cell.

    Written for onnxruntime on the CPU, where reductions over the channel axis (ReduceMax, ReduceSum,
    ArgMax) cost several times an elementwise pass over the same tensor; at the refine stage
    (D = 7, 64×1792) this version runs in under half the time of four slices, three adds and channel-axis
    reductions, with the same values (float rounding apart) and the same first-maximum tie-breaking.
    """
    batch, channels, height, width = logits.shape
    radius = window // 2
    weights = torch.exp(logits - _channel_max(logits))  # (B, D², H, W), the largest is 1
    flat = weights.reshape(batch, channels, height * width)
    # Sums over the channel axis as MatMuls: in onnxruntime ~10× faster than a ReduceSum over that axis.
    total = torch.matmul(torch.ones(1, channels, dtype=logits.dtype, device=logits.device), flat)
    # 2×2 window masses laid out (B, H·W, (D−1)²): the window axis last, where onnxruntime's ArgMax is ~4×
    # faster than along the channel axis.
    if window <= _MATMUL_MAX_WINDOW:
        # One MatMul with the 0/1 window-membership matrix sums the four corners and transposes for free;
        # (D−1)²·D² multiply-adds per cell are cheap for a small window.
        window_sums_last = torch.matmul(flat.transpose(1, 2), _window_membership(window, logits).t())
    else:
        # A wide window (the wide-window graph's D = 41) would make that matrix huge: sum adjacent columns,
        # then adjacent rows of those pairs (2 adds instead of 3), and transpose.
        cells = flat.view(batch, window, window, height, width)
        column_pairs = cells[:, :, :-1] + cells[:, :, 1:]
        window_sums = (column_pairs[:, :-1] + column_pairs[:, 1:]).view(batch, -1, height * width)
        window_sums_last = window_sums.transpose(1, 2)
    best_last = window_sums_last.argmax(dim=2, keepdim=True)  # (B, H·W, 1), the first maximum
    best_sum = window_sums_last.gather(2, best_last).view(batch, height, width)
    best = best_last.view(batch, 1, height, width)
    # Row and column of the winning window's top-left cell, computed in float (exports as plain arithmetic).
    best_float = best.squeeze(1).to(logits.dtype)
    best_row = torch.floor(best_float / (window - 1))
    best_col = best_float - best_row * (window - 1)
    # Channel of that cell: best_row·D + best_col = best + best_row. Only three cells are needed for the
    # centroid: the bottom pair (bottom left + bottom right) and the right pair (top right + bottom right).
    top_left = best + best_row.unsqueeze(1).to(best.dtype)

    def pick(channel: Tensor) -> Tensor:
        return weights.gather(1, channel).squeeze(1)

    top_right, bottom_left, bottom_right = pick(top_left + 1), pick(top_left + window), pick(top_left + window + 1)
    row = best_row + (bottom_left + bottom_right) / best_sum - radius
    col = best_col + (top_right + bottom_right) / best_sum - radius
    window_sums = window_sums_last.transpose(1, 2).view(batch, -1, height, width)
    return WindowDecoding(torch.stack((row, col), dim=1), best_sum / total.view(batch, height, width), window_sums)


# Up to this window the membership MatMul is the faster way to the window-last sums in onnxruntime (measured:
# ~20 % faster than separable adds + Transpose at D = 5 and 7, a tie at D = 11; at D = 41 its 1,600 × 1,681
# matrix would cost ~10 G multiply-adds per frame).
_MATMUL_MAX_WINDOW = 9


def _window_membership(window: int, like: Tensor) -> Tensor:
    """((D−1)², D²) 0/1 matrix whose row ``row·(D−1) + col`` marks the four cells of that window (channels
    ``r·D + c``). Built per call (a few tiny ops; constants in the exported graph) rather than cached, so
    that no tensor outlives a ``torch.inference_mode`` block or a device."""
    eye = torch.eye(window, dtype=like.dtype, device=like.device)
    pairs = eye[:-1] + eye[1:]  # pairs[i, j] = 1 for j ∈ {i, i + 1}
    return torch.kron(pairs, pairs)


def _channel_max(values: Tensor) -> Tensor:
    """``values.amax(dim=1, keepdim=True)`` as pairwise maxima of channel halves (exact): in onnxruntime a
    handful of elementwise Max ops take about half the time of one ReduceMax over the channel axis."""
    leftovers = []
    while values.shape[1] > 1:
        half = values.shape[1] // 2
        if values.shape[1] % 2:
            leftovers.append(values[:, 2 * half:])
        values = torch.maximum(values[:, :half], values[:, half: 2 * half])
    for leftover in leftovers:
        values = torch.maximum(values, leftover)
    return values


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
