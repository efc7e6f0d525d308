"""Frame numbers from scan timestamps: a scan that arrives two sensor periods after the previous one comes
after one missing scan, though no file is missing (a dropped frame of the driver or the log). The counting is
the crate's (`dmlo_rs.FrameClock`); this wrapper checks the timestamps Python hands it and warns."""

from __future__ import annotations

import math
import warnings

import numpy as np

import dmlo_rs


class TimestampWarning(UserWarning):
    """A scan's timestamp is not after the previous scan's: it is taken for the next frame."""


class FrameClock:
    """Counts frames: one per scan, or as many sensor periods as a scan's timestamp lies after the last
    timestamped one (the period measured as the median interval between consecutive scans)."""

    def __init__(self) -> None:
        self._clock = dmlo_rs.FrameClock()
        self._last_time: float | None = None  # the newest timestamp, for the warning
        self._warned = False

    @property
    def frame(self) -> int:
        """The newest scan's frame number, −1 before the first."""
        return self._clock.frame

    @property
    def period(self) -> float | None:
        """The sensor period in the timestamps' unit, once two consecutive scans had timestamps."""
        return self._clock.period

    def advance(self, timestamp: float | None = None) -> int:
        """The frame number of the next scan, `timestamp` its time (any unit, increasing) or None."""
        if timestamp is not None:
            numeric = isinstance(timestamp, (int, float, np.floating, np.integer)) and not isinstance(timestamp, bool)
            if not numeric or not math.isfinite(timestamp):
                raise ValueError(f"timestamp: expected a finite number (seconds), got {timestamp!r}")
            timestamp = float(timestamp)
        frame, out_of_order = self._clock.advance(timestamp)
        if out_of_order and not self._warned:
            self._warned = True
            warnings.warn(
                f"scan timestamp {timestamp!r} is not after the previous scan's {self._last_time!r}: taken for the "
                "next frame (warned once)",
                TimestampWarning,
                stacklevel=3,
            )
        if timestamp is not None:
            self._last_time = timestamp
        return frame
