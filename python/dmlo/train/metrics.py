"""EPE and Fl-all accumulated over batches, with `dmlo.metrics.flow_errors`' definitions.

EPE: mean ‖f − f̄‖ in pixels over valid cells; Fl-all: % of valid cells with EPE > 3 px and > 5 % of ‖f̄‖.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class FlowErrorSums:
    epe_sum: float = 0.0
    outliers: int = 0
    cells: int = 0

    def add(self, flow: Tensor, gt_flow: Tensor, valid: Tensor) -> None:
        valid = valid.bool() & torch.isfinite(gt_flow).all(dim=1)
        error = (flow - torch.nan_to_num(gt_flow)).norm(dim=1)
        magnitude = torch.nan_to_num(gt_flow).norm(dim=1)
        self.epe_sum += float(error[valid].sum())
        self.outliers += int(((error > 3.0) & (error > 0.05 * magnitude) & valid).sum())
        self.cells += int(valid.sum())

    def merge(self, other: FlowErrorSums) -> None:
        self.epe_sum += other.epe_sum
        self.outliers += other.outliers
        self.cells += other.cells

    @property
    def epe(self) -> float:
        return self.epe_sum / self.cells if self.cells else float("nan")

    @property
    def fl_all(self) -> float:
        return 100.0 * self.outliers / self.cells if self.cells else float("nan")


@dataclass
class PoseErrorSums:
    """Mean size of the motion errors (B, 6) — (ω mrad, t mm) — that `dmlo.model.pose_loss` implies."""

    rotation_sum: float = 0.0
    translation_sum: float = 0.0
    pairs: int = 0

    def add(self, errors: Tensor) -> None:
        finite = torch.isfinite(errors).all(dim=1)
        self.rotation_sum += float(errors[finite, :3].norm(dim=1).sum())
        self.translation_sum += float(errors[finite, 3:].norm(dim=1).sum())
        self.pairs += int(finite.sum())

    @property
    def rotation(self) -> float:
        return self.rotation_sum / self.pairs if self.pairs else float("nan")

    @property
    def translation(self) -> float:
        return self.translation_sum / self.pairs if self.pairs else float("nan")
