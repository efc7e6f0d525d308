"""The one interface every dataset reader implements: a sequence of :class:`Frame`."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "DatasetError",
    "Frame",
    "ScanSequence",
    "SequenceBase",
    "check_plausible_scan",
    "moving_mask",
    "MAX_SENSOR_RANGE_M",
    "MIN_RETURN_RANGE_M",
    "MOVING_CLASSES",
]


class DatasetError(ValueError):
    """A data file that is missing, truncated, malformed or holds no plausible scan; the message names the
    file and the problem."""


# A return farther than this from the sensor is not a LiDAR measurement: no automotive sensor reaches
# a kilometre, so such coordinates come from garbage bytes or the wrong unit or frame.
MAX_SENSOR_RANGE_M = 1000.0
# Closer than this a point is no return either (sensors see nothing within decimetres); points exactly
# at the origin are the no-return markers some drivers write and are left out of the count.
MIN_RETURN_RANGE_M = 0.01


def check_plausible_scan(path: Path, points: NDArray[np.floating]) -> None:
    """Raises :class:`DatasetError` naming ``path`` when ``points`` (``N×3`` or more columns, the sensor
    frame, metres) cannot be a LiDAR scan: no point at all, or fewer than half of its returns (finite
    points other than the origin) between :data:`MIN_RETURN_RANGE_M` and :data:`MAX_SENSOR_RANGE_M`
    from the sensor — what bytes that are not a scan, or a scan in millimetres, read as."""
    xyz = np.asarray(points[:, :3], dtype=np.float64)
    if len(xyz) == 0:
        raise DatasetError(f"{path}: the scan holds no point")
    with np.errstate(over="ignore", invalid="ignore"):
        ranges = np.linalg.norm(xyz, axis=1)
    returns = np.isfinite(ranges) & (ranges > 0.0)
    plausible = returns & (ranges >= MIN_RETURN_RANGE_M) & (ranges <= MAX_SENSOR_RANGE_M)
    if 2 * int(plausible.sum()) < max(int(returns.sum()), 1):
        raise DatasetError(
            f"{path}: not a plausible LiDAR scan: {int(plausible.sum())} of its {len(xyz)} points lie "
            f"{MIN_RETURN_RANGE_M:g} m to {MAX_SENSOR_RANGE_M:g} m from the sensor "
            f"({len(xyz) - int(returns.sum())} non-finite or at the origin); garbage data, or coordinates "
            "not in metres in the sensor's frame?"
        )


@dataclass(frozen=True, eq=False)
class Frame:
    """One LiDAR scan with what the dataset knows about it.

    - ``points``: ``(N, 4)`` float32 ``x, y, z, reflectance`` (reflectance in [0, 1]) in the sensor frame.
    - ``pose``: ``(4, 4)`` float64 ``T_world_lidar``, or None when the dataset has no ground truth.
    - ``labels``: ``(N,)`` uint32 per-point labels (SemanticKITTI: lower 16 bits class, upper 16 bits
      instance), or None.
    - ``timestamp``: seconds (float), or None.
    - ``path``: the scan file.
    """

    points: NDArray[np.float32]
    pose: NDArray[np.float64] | None
    labels: NDArray[np.uint32] | None
    timestamp: float | None
    path: Path


@runtime_checkable
class ScanSequence(Protocol):
    """An indexable sequence of frames; ``poses`` is every ground-truth pose ``(N, 4, 4)`` or None."""

    @property
    def name(self) -> str: ...

    @property
    def poses(self) -> NDArray[np.float64] | None: ...

    def __len__(self) -> int: ...

    def __getitem__(self, index: int) -> Frame: ...


class SequenceBase:
    """Shared plumbing for readers: index checks, iteration and the per-frame assembly.

    Subclasses set ``name``, ``_paths`` (one scan file per frame), ``_poses``, ``_timestamps`` and
    implement ``_read_points(i)`` and ``_read_labels(i)``.
    """

    name: str
    _paths: list[Path]
    _poses: NDArray[np.float64] | None = None
    _timestamps: NDArray[np.float64] | None = None

    @property
    def poses(self) -> NDArray[np.float64] | None:
        return None if self._poses is None else self._poses.copy()

    @property
    def timestamps(self) -> NDArray[np.float64] | None:
        """Every frame's timestamp in seconds, or None."""
        return None if self._timestamps is None else self._timestamps.copy()

    @property
    def paths(self) -> list[Path]:
        """The scan file of every frame, in order."""
        return list(self._paths)

    def __len__(self) -> int:
        return len(self._paths)

    def __getitem__(self, index: int) -> Frame:
        if not isinstance(index, (int, np.integer)):
            raise TypeError(f"frame index must be an integer, got {type(index).__name__}")
        count = len(self._paths)
        if not -count <= index < count:
            raise IndexError(f"frame index {index} out of range for {count} frames in {self.name}")
        i = int(index) % count
        points = self._read_points(i)
        # Bytes that parse but hold no scan are as unreadable as a truncated file: refused here, so a run
        # skips the frame instead of matching the next scan against them.
        check_plausible_scan(self._paths[i], points)
        labels = self._read_labels(i)
        if labels is not None and len(labels) != len(points):
            raise DatasetError(
                f"{self._paths[i]}: {len(labels)} labels for {len(points)} points"
            )
        return Frame(
            points=points,
            pose=None if self._poses is None else self._poses[i].copy(),
            labels=labels,
            timestamp=None if self._timestamps is None else float(self._timestamps[i]),
            path=self._paths[i],
        )

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, frames={len(self)})"

    def _read_points(self, index: int) -> NDArray[np.float32]:
        raise NotImplementedError

    def _read_labels(self, index: int) -> NDArray[np.uint32] | None:
        return None


# SemanticKITTI "moving-*" classes 252–259: car, bicyclist, person, motorcyclist, on-rails, bus, truck,
# other-vehicle.
MOVING_CLASSES = np.arange(252, 260, dtype=np.uint32)


def moving_mask(labels: NDArray[np.integer]) -> NDArray[np.bool_]:
    """True for points whose SemanticKITTI class (lower 16 bits of the label) is a moving class 252–259."""
    array = np.asarray(labels)
    if array.ndim != 1:
        raise ValueError(f"labels must be one-dimensional, got shape {array.shape}")
    if not np.issubdtype(array.dtype, np.integer):
        raise TypeError(f"labels must be integers, got dtype {array.dtype}")
    semantic = array.astype(np.uint32) & np.uint32(0xFFFF)
    return (semantic >= 252) & (semantic <= 259)
