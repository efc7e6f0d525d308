"""Pose loss: the motion error a rigid solve would make from the predicted matches (beyond the paper).

The flow loss (Eq. 10) treats every cell's error alone. The odometry, though, solves one motion from a
thousand matches: independent errors average out, while errors that look like a small rigid motion pass
straight into the pose and drift the trajectory. To first order the flow of a motion exp(ξ)·T is
``flow_gt + J ξ`` (J from `dmlo.train.dataset.flow_pose_jacobian`), so the weighted least-squares motion
error implied by the predicted flow is

    ξ̂ = (Σ w Jᵀ J)⁻¹ Σ w Jᵀ (flow − flow_gt),

with the network's confidence as the weights over cells whose match is roughly right (RANSAC removes the
others at run time). The loss is the size of ξ̂, and it trains the flow only: the weights are held fixed.
Letting it reach the confidence too was tried and hurt: it lowered the confidence of the matches near
their truth, which the flow loss does not see (it ignores cells beyond 2 px), so NMS then kept more
outliers (a third of the top 1000 within 2 px of the truth fell to a tenth after one epoch, RANSAC
inliers ~200 → ~100, pair rotation error 0.09 → 0.16°).
"""

from __future__ import annotations

import torch
from torch import Tensor

# ξ is in (mrad, mm), which at ~1 m per frame both read as mm of position error per metre driven. A
# rotation error, though, keeps turning every later step of a KITTI segment (100–800 m), while a
# translation error is added once; the rotation part is weighted up accordingly.
ROTATION_WEIGHT = 10.0


def pose_error(
    flow: Tensor,
    confidence: Tensor,
    gt_flow: Tensor,
    valid: Tensor,
    jacobian: Tensor,
    inlier_px: float = 2.0,
    damping: float = 1e-3,
) -> tuple[Tensor, Tensor]:
    """First-order motion error ξ̂ (B, 6) — (ω mrad, t mm) — implied by the predicted flow, and (B,) bool
    whether the sample had enough usable cells (at least 6) to define it.

    ``flow``/``gt_flow`` (B, 2, H, W) pixels, ``confidence``/``valid`` (B, H, W), ``jacobian``
    (B, 6, 2, H, W) pixels per unit of ξ (NaN where undefined). Cells count when valid, with a finite
    Jacobian and a flow error below ``inlier_px``; ``damping`` (relative to the mean diagonal of the normal
    matrix) keeps directions a cropped scan hardly constrains from blowing up.
    """
    if jacobian.dim() != 5 or jacobian.shape[1] != 6 or jacobian.shape[2:] != flow.shape[1:]:
        raise ValueError(f"jacobian must have shape (B, 6, 2, H, W) matching flow {tuple(flow.shape)}, got {tuple(jacobian.shape)}")
    residual = flow - gt_flow
    usable = valid.bool() & torch.isfinite(jacobian).all(dim=(1, 2)) & torch.isfinite(residual).all(dim=1)
    with torch.no_grad():
        usable = usable & (residual.norm(dim=1) < inlier_px)
    weight = torch.where(usable, confidence.detach(), torch.zeros_like(confidence))
    jacobian = torch.where(usable[:, None, None], jacobian, torch.zeros_like(jacobian))
    residual = torch.where(usable[:, None], residual, torch.zeros_like(residual))
    defined = usable.sum(dim=(1, 2)) >= 6
    total = weight.sum(dim=(1, 2)).clamp(min=1e-12)
    normal = torch.einsum("bkchw,blchw,bhw->bkl", jacobian, jacobian, weight) / total[:, None, None]
    gradient = torch.einsum("bkchw,bchw,bhw->bk", jacobian, residual, weight) / total[:, None]
    eye = torch.eye(6, dtype=normal.dtype, device=normal.device)
    # An undefined sample solves the identity system instead: no NaN may reach the gradient of the others.
    normal = torch.where(defined[:, None, None], normal, eye)
    gradient = torch.where(defined[:, None], gradient, torch.zeros_like(gradient))
    scale = normal.diagonal(dim1=1, dim2=2).mean(dim=1).detach().clamp(min=1e-12)
    error = torch.linalg.solve(normal + damping * scale[:, None, None] * eye, gradient.unsqueeze(-1)).squeeze(-1)
    return error, defined


def pose_loss(
    flow: Tensor, confidence: Tensor, gt_flow: Tensor, valid: Tensor, jacobian: Tensor, inlier_px: float = 2.0
) -> tuple[Tensor, Tensor]:
    """Mean over the samples with a defined error of |ξ̂| (rotation weighted by `ROTATION_WEIGHT`), and the
    per-sample (B, 6) errors for logging (NaN rows where undefined). Zero (still in the graph) when no
    sample counts."""
    error, defined = pose_error(flow, confidence, gt_flow, valid, jacobian, inlier_px)
    weights = torch.tensor([ROTATION_WEIGHT] * 3 + [1.0] * 3, dtype=error.dtype, device=error.device)
    size = torch.sqrt(((error * weights) ** 2).sum(dim=1) + 1e-12)
    loss = torch.where(defined, size, torch.zeros_like(size)).sum() / defined.sum().clamp(min=1)
    return loss, torch.where(defined[:, None], error.detach(), torch.full_like(error, float("nan")))
