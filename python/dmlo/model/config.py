"""The matching network's settings: one small typed dataclass, saved as JSON beside every checkpoint."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class MatcherConfig:
    """Architecture and loss switches of the DMLO matcher (paper §III-C, ablation of Table V).

    The defaults are the paper's structure: a 9-layer coarse net with strides 4 (rows) × 8 (cols) and a
    refine net of 2 plain + 3 deformable 3×3 convolutions. ``refine_channels`` and the plain/deformable
    split are the knobs that trade accuracy for speed (BENCHMARKS.md, "Network").
    """

    coarse_channels: int = 32
    """Width C of the coarse features (the last of the 9 coarse convolutions)."""
    coarse_window: int = 11
    """D of the coarse correlation, odd: ±5 coarse cells = ±20 rows, ±40 columns (the paper's 40×80)."""
    refine_channels: int = 16
    """Width of every refine convolution."""
    refine_plain_layers: int = 2
    refine_deformable_layers: int = 3
    refine_window: int = 5
    """D of the refine correlation, odd, in full-resolution pixels around the coarse offset."""
    normalize_features: bool = True
    """L2-normalise features before the correlation (Table V "FN")."""
    similarity_scale: float = 10.0
    """Initial value of the learned factor applied to the similarities before the softmax; cosine
    similarities lie in [-1, 1], too flat for a softmax over 121 cells without it."""
    subpixel_loss: bool = True
    """Bilinear sub-pixel cross entropy (Eq. 9–10, Table V "S"); False: one-hot on the nearest cell."""
    coarse_loss_weight: float = 1.0
    refine_loss_weight: float = 1.0
    refine_offset: str = "window"
    """How the refine window's distribution becomes a sub-pixel flow: ``window`` is the paper's Eq. 11 (the
    centroid of the best 2×2 window, which pulls matches towards cell borders), ``peak_centroid`` (beyond
    the paper) the centroid of the 3×3 cells around the most likely one (`dmlo.model.window.peak_centroid`).
    Q* is the best 2×2 window's mass either way, and the loss does not depend on it, so a trained model can
    be exported with either. Measured with the bundled weights: held-out pair rotation error 0.079 → 0.062°,
    but no gain on the bench drives (docs/measurements.md), so the paper's stays the default."""
    range_scale_m: float = 80.0
    """The range channel enters the network divided by this (metres); reflectance enters as is."""
    use_reflectance: bool = True
    """False: a range-only model (beyond the paper, for sensors without a usable reflectance): the
    reflectance channel is multiplied by 0 where it enters the network, in training and in the exported
    graphs alike, so the model sees the same zeros whatever a scan's reflectance holds."""
    leaky_slope: float = 0.1

    def __post_init__(self) -> None:
        for name in ("coarse_window", "refine_window"):
            value = getattr(self, name)
            if value < 3 or value % 2 == 0:
                raise ValueError(f"{name} must be odd and >= 3, got {value}")
        for name in ("coarse_channels", "refine_channels"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.refine_plain_layers < 0 or self.refine_deformable_layers < 0:
            raise ValueError("refine_plain_layers and refine_deformable_layers must be >= 0")
        if self.refine_plain_layers + self.refine_deformable_layers < 1:
            raise ValueError("the refine net needs at least one layer")
        if self.refine_offset not in ("window", "peak_centroid"):
            raise ValueError(f"refine_offset must be 'window' or 'peak_centroid', got {self.refine_offset!r}")
        if not isinstance(self.use_reflectance, bool):
            raise ValueError(f"use_reflectance must be true or false, got {self.use_reflectance!r}")
        if self.similarity_scale <= 0 or self.range_scale_m <= 0:
            raise ValueError("similarity_scale and range_scale_m must be > 0")

    @classmethod
    def preset(cls, name: str) -> MatcherConfig:
        """Named variants: ``paper`` (2 plain + 3 deformable, 16 ch), ``fast`` (5 plain, 8 ch),
        ``light`` (4 plain + 1 deformable, 8 ch)."""
        presets = {
            "paper": cls(),
            "fast": cls(refine_channels=8, refine_plain_layers=5, refine_deformable_layers=0),
            "light": cls(refine_channels=8, refine_plain_layers=4, refine_deformable_layers=1),
        }
        if name not in presets:
            raise ValueError(f"unknown model preset {name!r}; choose one of {sorted(presets)}")
        return presets[name]

    # Strides of the coarse net: each coarse cell covers this many rows and columns.
    @property
    def coarse_stride(self) -> tuple[int, int]:
        return (4, 8)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> MatcherConfig:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown MatcherConfig fields: {unknown}")
        return cls(**values)

    @classmethod
    def load(cls, path: str | Path) -> MatcherConfig:
        return cls.from_dict(json.loads(Path(path).read_text()))

    def save(self, path: str | Path) -> None:
        Path(path).write_text(self.to_json() + "\n")
