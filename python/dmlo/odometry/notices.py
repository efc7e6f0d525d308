"""The crate's notices about the scans (`dmlo_rs::odometry::pipeline::Notice`) as Python warnings: each kind
has its warning class, so that a caller can filter or raise on one kind."""

from __future__ import annotations

import warnings
from collections.abc import Iterable


class ReflectanceNotice(UserWarning):
    """What the odometry does with the scans' reflectance when they are not already on the model's [0, 1]
    scale: the scale it chose or the range-only model, once per `Odometry` (again only when a later scan
    moves it to the range-only model, or first exceeds the chosen scale)."""


class SensorMismatchWarning(UserWarning):
    """The scans fill far less of the model's cylinder image than the sensor it was trained for."""


class PairWarning(UserWarning):
    """A pair registered (`register_pair`) with fewer RANSAC inliers than a motion needs: its motion is not to
    be trusted (the identity when RANSAC found none)."""


class TimestampWarning(UserWarning):
    """A scan's timestamp is not after the previous scan's: it is taken for the next frame."""


CATEGORIES: dict[str, type[UserWarning]] = {
    "reflectance_scaled": ReflectanceNotice,
    "range_only_model": ReflectanceNotice,
    "zero_reflectance": ReflectanceNotice,
    "reflectance_unused": ReflectanceNotice,
    "reflectance_clipped": ReflectanceNotice,
    "reflectance_rescaled": ReflectanceNotice,
    "too_few_inliers": PairWarning,
    "timestamp_not_after": TimestampWarning,
    "sensor_mismatch": SensorMismatchWarning,
}


def warn(notices: Iterable[tuple[str, str]], stacklevel: int) -> None:
    """Each `(kind, message)` the crate said, as a warning of its kind's class (`stacklevel` as
    `warnings.warn` counts it from the caller of this function)."""
    for kind, message in notices:
        warnings.warn(message, CATEGORIES.get(kind, UserWarning), stacklevel=stacklevel + 1)
