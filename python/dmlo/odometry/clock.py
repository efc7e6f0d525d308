"""The scans' timestamps as `Odometry.register` takes them. The crate's clock (`odometry::clock`, run by
`dmlo_rs.Odometry`) counts the frames — a scan two sensor periods after the previous one comes after one
missing scan, though no file is missing; this checks what Python hands it and warns."""

from __future__ import annotations

import math
import warnings

import numpy as np


class TimestampWarning(UserWarning):
    """A scan's timestamp is not after the previous scan's: it is taken for the next frame."""


class TimestampCheck:
    """Refuses a timestamp that is not a finite number, and warns once when one is not after the previous."""

    def __init__(self) -> None:
        self._last: float | None = None
        self._warned = False

    def check(self, timestamp: object) -> float | None:
        """`timestamp` as a float (None stays None)."""
        if timestamp is None:
            return None
        numeric = isinstance(timestamp, (int, float, np.floating, np.integer)) and not isinstance(timestamp, bool)
        if not numeric or not math.isfinite(timestamp):  # type: ignore[arg-type]
            raise ValueError(f"timestamp: expected a finite number (seconds), got {timestamp!r}")
        time = float(timestamp)  # type: ignore[arg-type]
        if self._last is not None and time <= self._last and not self._warned:
            self._warned = True
            warnings.warn(
                f"scan timestamp {timestamp!r} is not after the previous scan's {self._last!r}: taken for the "
                "next frame (warned once)",
                TimestampWarning,
                stacklevel=3,
            )
        self._last = time
        return time
