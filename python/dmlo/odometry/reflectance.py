"""What the odometry does with the scans' reflectance.

The bundled model was trained on KITTI's reflectance, in [0, 1]; most sensors and drivers give 0–255
(some 0–65535), and N×3 clouds or PLY/PCD files without an intensity field give none. Fed such scans as
they are, a reflectance model sees images unlike any it was trained on, and its poses go wrong (issue 25:
a real drive reported standing still). So every scan's reflectance is brought to [0, 1] by one scale, and scans with
no usable reflectance run a range-only model (`range_only/` beside the model, trained with the channel
zeroed) with zeros in the channel.

The scale is decided once per sequence (per `Odometry`), from the first scan: a sensor's scale is a
property of its driver, and deciding per scan would let one dark 0–255 scan (every value ≤ 1) be read as
[0, 1] mid-drive and change the network's input scale from one scan to the next. A later scan without
usable reflectance still moves the odometry to the range-only model (for good: every later pair then
runs it), and a later scan beyond the chosen scale is clipped to 1, each with a notice.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

# Reflectance settings (`OdometryConfig.reflectance`, whose schema lists the same): the divisor of each scale,
# and the two others.
SCALES: dict[str, float] = {"unit": 1.0, "0-255": 255.0, "0-65535": 65535.0}
NONE = "none"
MODES: tuple[str, ...] = ("auto", *SCALES, NONE)
RANGE_ONLY_DIR = "range_only"  # the range-only model's folder inside a model's folder


class ReflectanceNotice(UserWarning):
    """What the odometry does with the scans' reflectance when they are not already on the model's [0, 1]
    scale: the scale it chose or the range-only model, once per `Odometry` (again only when a later scan
    moves it to the range-only model, or first exceeds the chosen scale)."""


@dataclass(frozen=True)
class Choice:
    mode: str  # one of SCALES or NONE
    reason: str  # what the values looked like, or that the config said so


def detect(reflectance: npt.NDArray[np.float32] | None) -> Choice:
    """The scale a scan's reflectance column looks like; None: the scan had no such column (N×3)."""
    if reflectance is None:
        return Choice(NONE, "the scans have no reflectance (N×3 points)")
    values = reflectance if np.isfinite(reflectance).all() else reflectance[np.isfinite(reflectance)]
    if values.size == 0:
        return Choice(NONE, "no point has a finite reflectance")
    low, high = float(values.min()), float(values.max())
    if low == high:
        return Choice(NONE, f"every point's reflectance is {high:g}")
    if low < 0:
        return Choice(NONE, f"reflectance from {low:g} to {high:g} is on no known scale")
    for mode, divisor in SCALES.items():
        if high <= divisor:
            scale = "[0, 1]" if mode == "unit" else mode.replace("-", "–")
            return Choice(mode, f"values up to {high:g} look like {scale}")
    return Choice(NONE, f"reflectance up to {high:g} is on no known scale")


def usable(reflectance: npt.NDArray[np.float32] | None) -> bool:
    """Whether a later scan has reflectance to match on (not absent, not one value everywhere)."""
    return detect(reflectance).mode != NONE


def normalise(cloud: npt.NDArray[np.float32], mode: str) -> tuple[npt.NDArray[np.float32], float]:
    """`cloud` (N×4) with its reflectance divided by the scale's divisor and clipped to [0, 1] (zeros with
    "none"), and the largest finite value before clipping. Non-finite values stay NaN, so the odometry leaves
    their points out as before. A new array when values change, else `cloud` itself."""
    column = cloud[:, 3]
    finite = np.isfinite(column)
    every = bool(finite.all())
    values = column if every else column[finite]
    if mode == NONE:
        if not values.any() and every:
            return cloud, 0.0
        out = cloud.copy()
        out[:, 3] = np.where(finite, np.float32(0), np.float32(np.nan))
        return out, 0.0
    divisor = np.float32(SCALES[mode])
    low, high = (float(values.min() / divisor), float(values.max() / divisor)) if values.size else (0.0, 0.0)
    if divisor == 1 and 0.0 <= low and high <= 1.0:
        return cloud, high  # already the model's scale (non-finite values left out later): no copy
    out = cloud.copy()
    out[:, 3] = np.where(finite, np.clip(column / divisor, 0.0, 1.0), np.float32(np.nan))
    return out, high


def range_only_model(model_path: Path) -> Path | None:
    """The range-only model beside a model (`<model folder>/range_only/frame.onnx`), if there is one."""
    folder = model_path if model_path.is_dir() else model_path.parent
    graph = folder / RANGE_ONLY_DIR / "frame.onnx"
    return graph if graph.is_file() else None
