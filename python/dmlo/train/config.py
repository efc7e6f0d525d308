"""Training settings (paper §IV-B defaults), saved as ``train.json`` beside the checkpoints."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class TrainConfig:
    data: list[str] = field(default_factory=list)
    """Training sequences (folders `dmlo.datasets.open_sequence` reads)."""
    val: list[str] = field(default_factory=list)
    """Held-out sequences for the validation pass after every epoch."""
    out: str = "run"
    epochs: int = 60
    batch_size: int = 4
    """Per process."""
    optimizer: str = "sgd"
    """``sgd`` (the paper's) or ``adam`` (for short runs on small compute)."""
    lr: float = 5e-4
    momentum: float = 0.9
    weight_decay: float = 1e-5
    lr_step_epochs: int = 20
    lr_gamma: float = 0.1
    crop_height: int | None = None
    crop_width: int | None = 448
    yaw_roll: bool = True
    mirror: bool = False
    """Also train on the mirror world (half of the samples flipped left–right)."""
    laser_gain_spread: float = 0.0
    """Per-row reflectance gains of up to ± this, the same in both scans (`Augmentation`); 0: off."""
    row_dropout: float = 0.0
    """Rows losing up to this share of their cells (`Augmentation`); 0: off."""
    reflectance_dropout: float = 0.0
    """Share of the pairs trained without their reflectance (`Augmentation`); 0: off."""
    reflectance_remap: float = 0.0
    """Share of the pairs whose reflectance passes through a random monotone curve (`Augmentation`); 0: off."""
    reflectance_falloff: float = 0.0
    """Share of the pairs whose reflectance fades with range (`Augmentation`); 0: off."""
    reflectance_zeros: float = 0.0
    """Largest share of cells whose reflectance is zeroed in each scan (`Augmentation`); 0: off."""
    max_gap: int = 2
    """Pairs 1 … max_gap frames apart (2: the paper's triplets)."""
    val_max_pairs: int = 64
    val_width: int | None = None
    """Centred crop for validation; None: full width."""
    seed: int = 0
    workers: int = 0
    device: str = "auto"
    checkpoint_every: int = 50
    """Also checkpoint every this many steps inside an epoch (resume loses at most this many)."""
    max_steps: int | None = None
    """Stop after this many optimiser steps in total (tests, smoke runs)."""
    pose_loss_weight: float = 0.0
    """Weight of the pose loss (`dmlo.model.pose_loss`, beyond the paper) next to the flow loss; 0: off.
    When on, the best checkpoint is the one with the smallest validation pose error instead of EPE."""
    confidence_loss_weight: float = 0.0
    """Weight of the confidence loss (`dmlo.model.confidence_loss`, beyond the paper): Q* trained as the
    probability that the match lies within 1 px of the truth; 0: off."""
    init: str | None = None
    """A checkpoint whose weights (and model config) a new run starts from: fine-tuning."""
    no_reflectance: bool = False
    """Train a range-only model (``MatcherConfig.use_reflectance`` False, also over the config of ``init``):
    the network sees the reflectance channel zeroed in every sample."""

    def __post_init__(self) -> None:
        positive = ("epochs", "batch_size", "lr_step_epochs", "checkpoint_every", "max_gap")
        for name in positive:
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.optimizer not in ("sgd", "adam"):
            raise ValueError(f"optimizer must be 'sgd' or 'adam', got {self.optimizer!r}")
        for name in ("pose_loss_weight", "confidence_loss_weight"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.lr <= 0:
            raise ValueError(f"lr must be > 0, got {self.lr}")
        if self.val_width is not None and (self.val_width <= 0 or self.val_width % 8):
            raise ValueError(f"val_width must be a positive multiple of 8, got {self.val_width}")

    def augmentation(self) -> Any:
        """The training pairs' `Augmentation` these settings describe."""
        from dmlo.train.dataset import Augmentation

        return Augmentation(
            self.crop_height, self.crop_width, self.yaw_roll, mirror=self.mirror,
            laser_gain_spread=self.laser_gain_spread, row_dropout=self.row_dropout,
            reflectance_dropout=self.reflectance_dropout, reflectance_remap=self.reflectance_remap,
            reflectance_falloff=self.reflectance_falloff, reflectance_zeros=self.reflectance_zeros,
        )

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> TrainConfig:
        known = {f.name for f in dataclasses.fields(cls)}
        return cls(**{key: value for key, value in values.items() if key in known})

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=2, sort_keys=True) + "\n")
