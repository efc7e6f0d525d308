"""Correlation of reference features with a D×D window of target features around a per-position origin (Eq. 2).

For the reference position p = (i, j) the window is centred on c(p) = clamp(p + origin(p)) (clamped into
the image) and holds the target features at c(p) + (h, w), h, w ∈ [−r, r], r = (D − 1)/2; positions
outside the image read zero features. This is the exact window of the paper's Eq. 2 at every position
(ONNX-NOTES item 6), not a warp of the target by the upsampled flow, and the same code runs in training
and in the exported graph.

Two implementations of that one definition:

- `window_correlation` takes any per-position origin: it gathers the D² target rows of every cell and
  does a batched MatMul (D²·C values moved per cell).
- `block_window_correlation` is what the matcher uses: its origin is the upsampled coarse flow, constant
  over every stride-sized block (4×8) before clamping. All window centres of a block's cells then lie in
  a stride-sized rectangle starting at the clamped centre of its first cell (clamping is monotone and
  moves neighbours at most as far apart as they were), so one (4 + D − 1)×(8 + D − 1) target patch per
  block holds every cell's window, clamped or not. One MatMul per block gives the similarities of its 32
  cells with all patch cells (~2.9× the products needed at D = 7, but in one well-shaped MatMul), and
  one GatherElements picks each cell's D×D window from them at the offset of its own clamped centre in
  the patch: ~11× fewer target rows gathered than per-cell windows, no per-cell MatMul, and border
  cells need no special case; in onnxruntime it runs faster than `window_correlation` (the figures are in
  docs/measurements.md). Picking the windows with static skews (Pad, Slice, Transpose) instead of a gather
  was slower than either: those operators are slow on such shapes.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def clamp_origin(origin: Tensor, height: int, width: int) -> Tensor:
    """Moves each window centre p + origin(p) into the image; returns the clamped origin (B, 2, H, W)."""
    rows = torch.arange(height, dtype=origin.dtype, device=origin.device).view(1, height, 1)
    cols = torch.arange(width, dtype=origin.dtype, device=origin.device).view(1, 1, width)
    centre_rows = torch.clamp(rows + origin[:, 0], 0, height - 1)
    centre_cols = torch.clamp(cols + origin[:, 1], 0, width - 1)
    return torch.stack((centre_rows - rows, centre_cols - cols), dim=1)


def window_correlation(ref: Tensor, tgt: Tensor, origin: Tensor, window: int) -> Tensor:
    """Similarities (B, D·D, H, W) of ``ref`` (B, C, H, W) with ``tgt`` around ``origin``.

    ``origin`` (B, 2, H, W) holds integer-valued (Δrow, Δcol) already clamped by `clamp_origin`; channel
    ``d = (h + r)·D + (w + r)`` of the result is the similarity with the target at c(p) + (h, w).
    """
    batch, channels, height, width = ref.shape
    radius = window // 2
    padded_height, padded_width = height + 2 * radius, width + 2 * radius
    # Channels-last rows of the zero-padded target: one Gather picks any window cell.
    tgt_rows = F.pad(tgt, (radius, radius, radius, radius)).permute(0, 2, 3, 1)
    tgt_rows = tgt_rows.reshape(batch * padded_height * padded_width, channels)

    rows = torch.arange(height, device=ref.device).view(1, height, 1)
    cols = torch.arange(width, device=ref.device).view(1, 1, width)
    centre_rows = rows + origin[:, 0].round().long() + radius  # (B, H, W) in padded coordinates
    centre_cols = cols + origin[:, 1].round().long() + radius
    image_start = (torch.arange(batch, device=ref.device) * (padded_height * padded_width)).view(batch, 1, 1)
    centres = image_start + centre_rows * padded_width + centre_cols
    steps = torch.arange(-radius, radius + 1, device=ref.device)
    window_steps = (steps.view(window, 1) * padded_width + steps.view(1, window)).view(1, 1, window * window)
    index = centres.view(batch, height * width, 1) + window_steps  # (B, H·W, D·D)

    windows = tgt_rows.index_select(0, index.reshape(-1)).view(batch, height * width, window * window, channels)
    ref_rows = ref.permute(0, 2, 3, 1).reshape(batch, height * width, channels, 1)
    # A batched MatMul: in onnxruntime ~40 % faster than a broadcast Mul + ReduceSum over channels.
    similarity = torch.matmul(windows, ref_rows).view(batch, height * width, window * window)
    return similarity.permute(0, 2, 1).reshape(batch, window * window, height, width)


def local_correlation(ref: Tensor, tgt: Tensor, window: int) -> Tensor:
    """`window_correlation` with origin 0, computed without any gather (the coarse stage).

    For each of the D row displacements one MatMul gives the similarity of every reference cell with every
    cell of the displaced target row, (B, H, W, W + 2r); the D column displacements are the band around its
    diagonal, read by a skew: padding each flattened row by W and viewing it with rows of W + 2r + 1 puts
    target column j + t − r of reference column j at (j, t). Only reshapes and slices, no gather: ~10× less
    memory traffic than gathering D² feature rows per cell.
    """
    batch, channels, height, width = ref.shape
    radius = window // 2
    padded_width = width + 2 * radius
    ref_rows = ref.permute(0, 2, 3, 1)  # (B, H, W, C)
    tgt_rows = F.pad(tgt, (radius, radius, radius, radius)).permute(0, 2, 1, 3)  # (B, H + 2r, C, W + 2r)
    bands = []
    for row_step in range(window):
        similarity = torch.matmul(ref_rows, tgt_rows[:, row_step : row_step + height])  # (B, H, W, W + 2r)
        skewed = F.pad(similarity.reshape(batch, height, width * padded_width), (0, width))
        bands.append(skewed.view(batch, height, width, padded_width + 1)[..., :window])  # (B, H, W, D)
    return torch.stack(bands, dim=1).permute(0, 1, 4, 2, 3).reshape(batch, window * window, height, width)


def block_window_correlation(ref: Tensor, tgt: Tensor, block_origin: Tensor, stride: tuple[int, int], window: int) -> Tensor:
    """`window_correlation` for an origin that is constant over ``stride``-sized blocks before clamping.

    ``block_origin`` (B, 2, H/sr, W/sc) holds the integer-valued, *unclamped* (Δrow, Δcol) of each block;
    the result equals ``window_correlation(ref, tgt, clamp_origin(origin, H, W), window)`` where
    ``origin`` repeats each block's value over its sr × sc cells. H must be divisible by sr and W by sc.
    """
    batch, _, height, width = ref.shape
    block_rows, block_cols = stride
    blocks_down, blocks_across = height // block_rows, width // block_cols
    if height % block_rows or width % block_cols:
        raise ValueError(f"features {height}×{width} do not split into {block_rows}×{block_cols} blocks")
    if block_origin.shape != (batch, 2, blocks_down, blocks_across):
        expected = (batch, 2, blocks_down, blocks_across)
        raise ValueError(f"block_origin must have shape {expected}, got {tuple(block_origin.shape)}")
    origin = block_origin.round().long()
    # Unclamped window centre of each block's first cell, (B, h, w).
    first_row = torch.arange(blocks_down, device=ref.device).view(1, blocks_down, 1) * block_rows + origin[:, 0]
    first_col = torch.arange(blocks_across, device=ref.device).view(1, 1, blocks_across) * block_cols + origin[:, 1]
    patch_size = (block_rows + window - 1, block_cols + window - 1)
    patches = _target_patches(tgt, first_row.clamp(0, height - 1), first_col.clamp(0, width - 1), patch_size, window // 2)
    # (blocks, patch cells, C) × (blocks, C, block cells): every cell of a block against every patch cell,
    # one row per block row so that the gather below runs in parallel over rows in onnxruntime.
    products = torch.matmul(patches, _block_cells(ref, stride)).reshape(batch * blocks_down, -1)
    index = _window_index(first_row, first_col, (height, width), stride, window)
    windows = products.gather(1, index)
    # (B, h, D², sr·W) → (B, D², H, W): a transpose of whole image-row runs.
    windows = windows.view(batch, blocks_down, window * window, block_rows * width).transpose(1, 2)
    return windows.reshape(batch, window * window, height, width)


def _window_index(first_row: Tensor, first_col: Tensor, size: tuple[int, int], stride: tuple[int, int], window: int) -> Tensor:
    """(B·h, D²·sr·W): where each cell's window lies in its block row of products, in image order.

    A block row of products is (w, patch rows, patch cols, sr, sc); cell (k, l) of a block reads its
    window at the offset of its own clamped centre from the block's patch corner (the clamped centre of
    the first cell, ``first_row`` / ``first_col`` clamped), so clamped border cells need no special case.
    """
    height, width = size
    block_rows, block_cols = stride
    batch, blocks_down, blocks_across = first_row.shape
    patch_rows, patch_cols = block_rows + window - 1, block_cols + window - 1
    block_cells = block_rows * block_cols
    first_row = first_row.view(batch, blocks_down, 1, blocks_across, 1)
    first_col = first_col.view(batch, blocks_down, 1, blocks_across, 1)
    cell_rows = torch.arange(block_rows, device=first_row.device).view(1, 1, block_rows, 1, 1)
    cell_cols = torch.arange(block_cols, device=first_row.device).view(1, 1, 1, 1, block_cols)
    window_top = (first_row + cell_rows).clamp(0, height - 1) - first_row.clamp(0, height - 1)
    window_left = (first_col + cell_cols).clamp(0, width - 1) - first_col.clamp(0, width - 1)
    block = torch.arange(blocks_across, device=first_row.device).view(1, 1, 1, blocks_across, 1)
    # Product of each cell with its window's top-left target cell, (B, h, sr, w, sc).
    window_start = (block * patch_rows * patch_cols + window_top * patch_cols + window_left) * block_cells
    window_start = window_start + cell_rows * block_cols + cell_cols
    steps = torch.arange(window, device=first_row.device)
    window_steps = (steps.view(window, 1) * patch_cols + steps.view(1, window)) * block_cells
    index = window_start.view(batch * blocks_down, 1, block_rows * width) + window_steps.view(1, window * window, 1)
    return index.view(batch * blocks_down, -1)


def _target_patches(tgt: Tensor, top: Tensor, left: Tensor, size: tuple[int, int], radius: int) -> Tensor:
    """(B·h·w, rows·cols, C) channels-last target patches, one per block.

    ``top``, ``left`` (B, h, w) are the window centre (inside the image) of the patch's top-left window:
    the patch spans target rows top − r … top + rows − 1 − r and the same for columns. The target is
    zero-padded so that such a patch never leaves the padded image and reads zeros outside the image.
    """
    batch, channels, height, width = tgt.shape
    rows, cols = size
    padded_height, padded_width = height + rows - 1, width + cols - 1
    padded = F.pad(tgt, (radius, cols - 1 - radius, radius, rows - 1 - radius))
    tgt_rows = padded.permute(0, 2, 3, 1).reshape(batch * padded_height * padded_width, channels)
    image_start = (torch.arange(batch, device=tgt.device) * (padded_height * padded_width)).view(batch, 1, 1)
    corner = image_start + top * padded_width + left  # the patch's first cell, in padded coordinates
    steps = torch.arange(rows, device=tgt.device).view(rows, 1) * padded_width + torch.arange(cols, device=tgt.device)
    index = corner.unsqueeze(-1) + steps.view(1, 1, 1, rows * cols)
    return tgt_rows.index_select(0, index.reshape(-1)).view(-1, rows * cols, channels)


def _block_cells(ref: Tensor, stride: tuple[int, int]) -> Tensor:
    """(B·h·w, C, sr·sc): the reference features of each block, its cells in row-major order."""
    batch, channels, height, width = ref.shape
    block_rows, block_cols = stride
    blocks = ref.view(batch, channels, height // block_rows, block_rows, width // block_cols, block_cols)
    return blocks.permute(0, 2, 4, 1, 3, 5).reshape(-1, channels, block_rows * block_cols)
