"""The street a scene is built along, apart from what stands on it: the ego trajectory as a street axis
(`StreetPath`, extended 150 m past both ends), the street's cross-section (`StreetLayout`) and the cars
that drive along the axis (`MovingCar`). The scene (`dmlo.simulator.scene`), its highway roadside
(`dmlo.simulator.highway`) and its cross traffic (`dmlo.simulator.traffic`) all place things by them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from dmlo.simulator.trajectory import FRAME_RATE_HZ

PATH_SPACING = 2.0
PATH_EXTENSION = 150.0


class StreetPath:
    """The ego trajectory as a street axis: positions, ground height and heading by arc length."""

    def __init__(self, lidar_poses: npt.NDArray[np.float64], mount_height: float) -> None:
        positions = lidar_poses[:, :3, 3]
        steps = np.linalg.norm(np.diff(positions[:, :2], axis=0), axis=1)
        keep = np.concatenate([[True], steps > 1e-3])
        positions = positions[keep]
        forward_first = lidar_poses[0, :2, 0] / np.linalg.norm(lidar_poses[0, :2, 0])
        forward_last = lidar_poses[-1, :2, 0] / np.linalg.norm(lidar_poses[-1, :2, 0])
        ground = positions[:, 2] - mount_height
        ext = np.linspace(PATH_EXTENSION, PATH_SPACING, int(PATH_EXTENSION / PATH_SPACING))
        before = np.column_stack(
            [positions[0, :2] - ext[:, None] * forward_first, np.full(len(ext), ground[0])]
        )
        after = np.column_stack(
            [positions[-1, :2] + ext[::-1, None] * forward_last, np.full(len(ext), ground[-1])]
        )
        points = np.vstack([before, np.column_stack([positions[:, :2], ground]), after])
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points[:, :2], axis=0), axis=1))])
        self.length = float(arc[-1])
        self.s = np.arange(0.0, self.length + 1e-9, PATH_SPACING)
        self.xy = np.column_stack(
            [np.interp(self.s, arc, points[:, 0]), np.interp(self.s, arc, points[:, 1])]
        )
        self.ground_z = _smooth(np.interp(self.s, arc, points[:, 2]), 5)
        tangent = np.gradient(self.xy, axis=0)
        tangent = np.column_stack([_smooth(tangent[:, 0], 2), _smooth(tangent[:, 1], 2)])
        self.heading = np.unwrap(np.arctan2(tangent[:, 1], tangent[:, 0]))
        # Arc length of the real trajectory's start (the extension comes first), and of every frame's pose.
        self.start_s = float(arc[len(before)])
        self.frame_s = arc[len(before) + np.cumsum(keep) - 1]

    def ego_s(self, time: float) -> float:
        """Arc length of the ego at `time` seconds (frames at 10 Hz, linear between them)."""
        frame = time * FRAME_RATE_HZ
        return float(np.interp(frame, np.arange(len(self.frame_s)), self.frame_s))

    def at(
        self, s: npt.ArrayLike
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """(xy (…,2), ground z, heading) at arc lengths `s`."""
        s = np.asarray(s, dtype=np.float64)
        xy = np.stack([np.interp(s, self.s, self.xy[:, 0]), np.interp(s, self.s, self.xy[:, 1])], axis=-1)
        return xy, np.interp(s, self.s, self.ground_z), np.interp(s, self.s, self.heading)

    def place(self, s: float, u: float) -> tuple[npt.NDArray[np.float64], float, float]:
        """(xy, ground z, heading) of the point at lateral offset `u` (left positive) from the axis at `s`."""
        xy, z, heading = self.at(s)
        normal = np.array([-np.sin(heading), np.cos(heading)])
        return xy + u * normal, float(z), float(heading)

    def grade(self, s: float) -> float:
        """Longitudinal slope dz/ds of the ground at `s`."""
        _, z0, _ = self.at(s - 1.0)
        _, z1, _ = self.at(s + 1.0)
        return float(z1 - z0) / 2.0

    def distance(self, xy: npt.ArrayLike) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]]:
        """Distance from each point (…,2) to the nearest axis sample, and that sample's index."""
        xy = np.asarray(xy, dtype=np.float64)
        flat = xy.reshape(-1, 2)
        best = np.empty(len(flat))
        index = np.empty(len(flat), dtype=np.int64)
        for start in range(0, len(flat), 2048):
            chunk = flat[start : start + 2048]
            d2 = ((chunk[:, None, :] - self.xy[None, :, :]) ** 2).sum(-1)
            index[start : start + 2048] = d2.argmin(1)
            best[start : start + 2048] = np.sqrt(d2.min(1))
        return best.reshape(xy.shape[:-1]), index.reshape(xy.shape[:-1])


def _smooth(values: npt.NDArray[np.float64], half_width: int) -> npt.NDArray[np.float64]:
    if len(values) < 2 * half_width + 1:
        return values
    padded = np.pad(values, half_width, mode="edge")
    kernel = np.ones(2 * half_width + 1) / (2 * half_width + 1)
    return np.convolve(padded, kernel, mode="valid")


@dataclass(frozen=True)
class StreetLayout:
    """Cross-section of the street, drawn once per scene."""

    road_left: float
    road_right: float
    sidewalk_left: float
    sidewalk_right: float
    kerb: float

    def road(self, side: int) -> float:
        return self.road_left if side > 0 else self.road_right

    def outer(self, side: int) -> float:
        """Distance from the axis to the outer edge of the sidewalk on `side` (+1 left, −1 right)."""
        return self.road(side) + (self.sidewalk_left if side > 0 else self.sidewalk_right)


@dataclass(frozen=True)
class MovingCar:
    """A car driving along the street axis at constant speed: `s(t) = s0 + direction·speed·t`."""

    instance: int
    s0: float
    speed: float
    direction: int
    lateral: float
    length: float
    width: float
    height: float
    albedo: float
