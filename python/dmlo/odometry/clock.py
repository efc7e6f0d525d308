"""Frame numbers from scan timestamps: a scan that arrives two sensor periods after the previous one comes
after one missing scan, though no file is missing (a dropped frame of the driver or the log)."""

from __future__ import annotations

import math
import warnings
from collections import deque

import numpy as np

RECENT_INTERVALS = 50  # the sensor period is the median of this many intervals between consecutive scans


class TimestampWarning(UserWarning):
    """A scan's timestamp is not after the previous scan's: it is taken for the next frame."""


class FrameClock:
    """Counts frames: one per scan, or as many sensor periods as a scan's timestamp lies after the last
    timestamped one (the period measured as the median interval between consecutive scans)."""

    def __init__(self) -> None:
        self.frame = -1  # the newest scan's frame number
        self._last: tuple[float, int] | None = None  # timestamp and frame of the newest timestamped scan
        self._intervals: deque[float] = deque(maxlen=RECENT_INTERVALS)
        self._warned = False

    @property
    def period(self) -> float | None:
        """The sensor period in the timestamps' unit, once two consecutive scans had timestamps."""
        return float(np.median(self._intervals)) if self._intervals else None

    def advance(self, timestamp: float | None = None) -> int:
        """The frame number of the next scan, `timestamp` its time (any unit, increasing) or None."""
        frames = 1
        if timestamp is not None:
            numeric = isinstance(timestamp, (int, float, np.floating, np.integer)) and not isinstance(timestamp, bool)
            if not numeric or not math.isfinite(timestamp):
                raise ValueError(f"timestamp: expected a finite number (seconds), got {timestamp!r}")
            if self._last is not None:
                frames = self._frames_since_last(float(timestamp))
        self.frame += frames
        if timestamp is not None:
            self._last = (float(timestamp), self.frame)
        return self.frame

    def _frames_since_last(self, timestamp: float) -> int:
        """How far this scan's frame lies after the newest one: the frames since the last timestamped scan
        are at least those counted (one per scan), more when the time says more periods passed."""
        assert self._last is not None
        last_time, last_frame = self._last
        counted = self.frame + 1 - last_frame
        interval = timestamp - last_time
        if interval <= 0:
            if not self._warned:
                self._warned = True
                warnings.warn(
                    f"scan timestamp {timestamp!r} is not after the previous scan's {last_time!r}: taken for the next "
                    "frame (warned once)",
                    TimestampWarning,
                    stacklevel=4,
                )
            return 1
        period = self.period
        frames = counted if period is None else max(counted, round(interval / period))
        if frames == 1:  # only intervals between consecutive scans measure the period
            self._intervals.append(interval)
        return last_frame + frames - self.frame
