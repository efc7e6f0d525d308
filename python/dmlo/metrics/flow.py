"""Matching metrics of the paper's Table V: end-point error (EPE) and Fl-all.

Flows are ``(2, H, W)`` (or batched ``(B, 2, H, W)``) pixel displacements — the channel order does not
matter — with a ``(H, W)`` / ``(B, H, W)`` boolean mask of pixels that have ground truth.

- **EPE**: mean over valid pixels of ``‖f − f̄‖₂`` in pixels.
- **Fl-all**: the KITTI 2015 flow definition the paper's table caption quotes ("percentage of outliers
  averaged over all ground truth pixels"): a pixel is an outlier when its EPE is above 3 px **and** above
  5 % of the ground-truth flow's magnitude; reported in %.

Both are averaged over all valid pixels of all images together (not per image), as KITTI does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "FLOW_OUTLIER_ABSOLUTE",
    "FLOW_OUTLIER_RELATIVE",
    "FlowErrors",
    "end_point_error",
    "fl_all",
    "flow_errors",
]

FLOW_OUTLIER_ABSOLUTE = 3.0  # pixels
FLOW_OUTLIER_RELATIVE = 0.05  # of the ground-truth magnitude


@dataclass(frozen=True)
class FlowErrors:
    """EPE (px) and Fl-all (%) over ``valid_pixels`` pixels; ``outliers`` counts the Fl outliers."""

    epe: float
    fl_all: float
    valid_pixels: int
    outliers: int


def _flow_arrays(
    flow_pred: ArrayLike, flow_gt: ArrayLike, valid: ArrayLike | None
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    pred = np.asarray(flow_pred, dtype=np.float64)
    gt = np.asarray(flow_gt, dtype=np.float64)
    if pred.ndim == 3 and gt.ndim == 3:
        pred, gt = pred[None], gt[None]
    if pred.ndim != 4 or pred.shape[1] != 2:
        raise ValueError(f"flow_pred must be (2, H, W) or (B, 2, H, W), got {np.shape(flow_pred)}")
    if gt.shape != pred.shape:
        raise ValueError(f"flow_gt has shape {np.shape(flow_gt)} but flow_pred has {np.shape(flow_pred)}")
    if valid is None:
        mask = np.ones((pred.shape[0], *pred.shape[2:]), dtype=bool)
    else:
        mask = np.asarray(valid)
        if mask.dtype != np.bool_:
            raise TypeError(f"valid must be a boolean mask, got dtype {mask.dtype}")
        if mask.ndim == 2:
            mask = mask[None]
        if mask.shape != (pred.shape[0], *pred.shape[2:]):
            raise ValueError(
                f"valid has shape {np.shape(valid)}, expected {(pred.shape[0], *pred.shape[2:])}"
            )
    return pred, gt, mask


def flow_errors(
    flow_pred: ArrayLike, flow_gt: ArrayLike, valid: ArrayLike | None = None
) -> FlowErrors:
    """EPE and Fl-all of a predicted flow against the ground truth over the valid pixels."""
    pred, gt, mask = _flow_arrays(flow_pred, flow_gt, valid)
    count = int(mask.sum())
    if count == 0:
        raise ValueError("no valid pixels: EPE and Fl-all are undefined")
    pred_valid = pred.transpose(0, 2, 3, 1)[mask]
    gt_valid = gt.transpose(0, 2, 3, 1)[mask]
    if not np.all(np.isfinite(pred_valid)):
        raise ValueError("flow_pred has NaN or infinite values at valid pixels")
    if not np.all(np.isfinite(gt_valid)):
        raise ValueError("flow_gt has NaN or infinite values at valid pixels")
    epe = np.linalg.norm(pred_valid - gt_valid, axis=1)
    magnitude = np.linalg.norm(gt_valid, axis=1)
    outlier = (epe > FLOW_OUTLIER_ABSOLUTE) & (epe > FLOW_OUTLIER_RELATIVE * magnitude)
    outliers = int(outlier.sum())
    return FlowErrors(
        epe=float(epe.mean()), fl_all=100.0 * outliers / count, valid_pixels=count, outliers=outliers
    )


def end_point_error(flow_pred: ArrayLike, flow_gt: ArrayLike, valid: ArrayLike | None = None) -> float:
    """Mean end-point error in pixels over the valid pixels."""
    return flow_errors(flow_pred, flow_gt, valid).epe


def fl_all(flow_pred: ArrayLike, flow_gt: ArrayLike, valid: ArrayLike | None = None) -> float:
    """Percentage of valid pixels that are KITTI flow outliers (EPE > 3 px and > 5 % of |GT|)."""
    return flow_errors(flow_pred, flow_gt, valid).fl_all
