"""Output layouts of a simulated drive: KITTI odometry (plus SemanticKITTI labels) and Argoverse 1 tracking.

Both are read back by `dmlo.datasets.open_sequence`, ground-truth poses included.

- ``kitti``: `velodyne/NNNNNN.bin` (float32 x y z reflectance), `labels/NNNNNN.label`, `poses.txt` (camera
  frame, `Tr · T_world_lidar · Tr⁻¹`), `calib.txt` (`Tr:` and placeholder P0..P3), `times.txt`.
- ``argoverse``: `lidar/PC_<ns>.ply` (binary: float x y z, uchar intensity, ushort laser_number, as real
  AV1 sweeps), `poses/city_SE3_egovehicle_<ns>.json` (`rotation` quaternion w x y z, `translation`),
  `vehicle_calibration_info.json` with the units' mounts (`vehicle_SE3_up_lidar_`,
  `vehicle_SE3_down_lidar_`), and — a dmlo addition, AV1 has no point labels — `labels/PC_<ns>.label`
  (SemanticKITTI uint32). Sweep `k` is stamped `k · 100 ms` (nanoseconds), so the reader's timestamps are
  the KITTI layout's `times.txt`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Protocol

import numpy as np
import numpy.typing as npt

from dmlo.poses import matrix_to_quaternion
from dmlo.simulator.sensor import LidarModel
from dmlo.simulator.trajectory import lidar_to_camera_poses

# Camera matrices of KITTI sequences 00–02, written as placeholders so readers expecting P0..P3 work.
_KITTI_P = {
    "P0": [718.856, 0.0, 607.1928, 0.0, 0.0, 718.856, 185.2157, 0.0, 0.0, 0.0, 1.0, 0.0],
    "P1": [718.856, 0.0, 607.1928, -386.1448, 0.0, 718.856, 185.2157, 0.0, 0.0, 0.0, 1.0, 0.0],
    "P2": [718.856, 0.0, 607.1928, 45.38225, 0.0, 718.856, 185.2157, -0.1130887, 0.0, 0.0, 1.0, 0.003779761],
    "P3": [718.856, 0.0, 607.1928, -337.2877, 0.0, 718.856, 185.2157, 2.369057, 0.0, 0.0, 1.0, 0.004915215],
}

# Velodyne's calibrated reflectivity: 0–100 for diffuse surfaces of 0–100 % reflectance (and 101–255 for
# retro-reflectors), as the uint8 intensity of AV1 sweeps.
_DIFFUSE_INTENSITY_SCALE = 100.0
_RETROREFLECTIVE = 0.9  # simulated reflectance from which a return counts as retro-reflective
SWEEP_PERIOD_NS = 100_000_000


class Layout(Protocol):
    """Writes one simulated drive in some dataset layout."""

    def existing_scans(self, out: Path) -> list[Path]:
        """Scan and label files of this layout already in `out` (replaced by a new simulation)."""
        ...

    def remove_leftovers(self, out: Path) -> None:
        """Deletes this layout's metadata files and emptied folders (after its scans were deleted)."""
        ...

    def prepare(self, out: Path) -> None: ...

    def write_frame(
        self,
        out: Path,
        index: int,
        points: npt.NDArray[np.float32],
        labels: npt.NDArray[np.uint32],
        lasers: npt.NDArray[np.uint16],
    ) -> None: ...

    def finish(
        self, out: Path, lidar_poses: npt.NDArray[np.float64], times: npt.NDArray[np.float64]
    ) -> None: ...


class KittiLayout:
    """KITTI odometry sequence folder with SemanticKITTI labels."""

    def __init__(self, tr: npt.NDArray[np.float64]) -> None:
        self.tr = tr

    def existing_scans(self, out: Path) -> list[Path]:
        return sorted((out / "velodyne").glob("*.bin")) + sorted((out / "labels").glob("*.label"))

    def remove_leftovers(self, out: Path) -> None:
        _remove(out, files=("poses.txt", "calib.txt", "times.txt"), folders=("velodyne", "labels"))

    def prepare(self, out: Path) -> None:
        (out / "velodyne").mkdir(parents=True, exist_ok=True)
        (out / "labels").mkdir(parents=True, exist_ok=True)

    def write_frame(
        self,
        out: Path,
        index: int,
        points: npt.NDArray[np.float32],
        labels: npt.NDArray[np.uint32],
        lasers: npt.NDArray[np.uint16],
    ) -> None:
        points.tofile(out / "velodyne" / f"{index:06d}.bin")
        labels.tofile(out / "labels" / f"{index:06d}.label")

    def finish(self, out: Path, lidar_poses: npt.NDArray[np.float64], times: npt.NDArray[np.float64]) -> None:
        camera_poses = lidar_to_camera_poses(lidar_poses, self.tr)
        with open(out / "poses.txt", "w") as f:
            f.writelines(" ".join(f"{v:.12e}" for v in pose[:3, :].ravel()) + "\n" for pose in camera_poses)
        with open(out / "calib.txt", "w") as f:
            f.writelines(
                f"{name}: " + " ".join(f"{v:.12e}" for v in values) + "\n"
                for name, values in _KITTI_P.items()
            )
            f.write("Tr: " + " ".join(f"{v:.12e}" for v in self.tr[:3, :].ravel()) + "\n")
        with open(out / "times.txt", "w") as f:
            f.writelines(f"{t:.6e}\n" for t in times)


def reflectance_to_intensity(reflectance: npt.NDArray[np.floating]) -> npt.NDArray[np.uint8]:
    """Simulated reflectance in [0, 1] → Velodyne uint8 intensity: diffuse returns 0–100, retro-reflective
    ones (reflectance ≥ 0.9: signs, lane paint) 101–255."""
    r = np.clip(np.asarray(reflectance, dtype=np.float64), 0.0, 1.0)
    retro = 101.0 + (r - _RETROREFLECTIVE) / (1.0 - _RETROREFLECTIVE) * 154.0
    intensity = np.where(r >= _RETROREFLECTIVE, retro, r * _DIFFUSE_INTENSITY_SCALE)
    return np.round(intensity).astype(np.uint8)


def _pose_record(pose: npt.NDArray[np.float64]) -> dict[str, list[float]]:
    x, y, z, w = matrix_to_quaternion(pose[:3, :3])[0]
    return {
        "rotation": [float(w), float(x), float(y), float(z)],
        "translation": [float(v) for v in pose[:3, 3]],
    }


class Argoverse1Layout:
    """Argoverse 1 tracking log folder (what `dmlo.datasets.Argoverse1Sequence` reads)."""

    _PLY_HEADER = (
        "ply\nformat binary_little_endian 1.0\nelement vertex {count}\nproperty float x\nproperty float y\n"
        "property float z\nproperty uchar intensity\nproperty ushort laser_number\nend_header\n"
    )
    _RECORD = np.dtype(
        [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "u1"), ("laser_number", "<u2")]
    )
    _UNIT_KEYS = ("vehicle_SE3_up_lidar_", "vehicle_SE3_down_lidar_")

    def __init__(self, model: LidarModel) -> None:
        self.model = model

    @staticmethod
    def stamp(index: int) -> int:
        return index * SWEEP_PERIOD_NS

    def existing_scans(self, out: Path) -> list[Path]:
        return (
            sorted((out / "lidar").glob("PC_*.ply"))
            + sorted((out / "labels").glob("PC_*.label"))
            + sorted((out / "poses").glob("city_SE3_egovehicle_*.json"))
        )

    def remove_leftovers(self, out: Path) -> None:
        _remove(out, files=("vehicle_calibration_info.json",), folders=("lidar", "labels", "poses"))

    def prepare(self, out: Path) -> None:
        for folder in ("lidar", "labels", "poses"):
            (out / folder).mkdir(parents=True, exist_ok=True)

    def write_frame(
        self,
        out: Path,
        index: int,
        points: npt.NDArray[np.float32],
        labels: npt.NDArray[np.uint32],
        lasers: npt.NDArray[np.uint16],
    ) -> None:
        records = np.empty(len(points), dtype=self._RECORD)
        records["x"], records["y"], records["z"] = points[:, 0], points[:, 1], points[:, 2]
        records["intensity"] = reflectance_to_intensity(points[:, 3])
        records["laser_number"] = lasers
        stamp = self.stamp(index)
        with open(out / "lidar" / f"PC_{stamp}.ply", "wb") as f:
            f.write(self._PLY_HEADER.format(count=len(points)).encode("ascii"))
            f.write(records.tobytes())
        labels.astype("<u4").tofile(out / "labels" / f"PC_{stamp}.label")

    def finish(self, out: Path, lidar_poses: npt.NDArray[np.float64], times: npt.NDArray[np.float64]) -> None:
        for index, pose in enumerate(lidar_poses):
            path = out / "poses" / f"city_SE3_egovehicle_{self.stamp(index)}.json"
            path.write_text(json.dumps(_pose_record(pose)) + "\n")
        mounts = self.model.unit_mounts()
        calibration = {}
        for key, mount in zip(self._UNIT_KEYS, mounts):
            record = _pose_record(np.eye(4) if mount is None else mount)
            calibration[key] = {
                "rotation": {"coefficients": record["rotation"]},
                "translation": record["translation"],
            }
        (out / "vehicle_calibration_info.json").write_text(json.dumps(calibration, indent=2) + "\n")


def _remove(out: Path, files: tuple[str, ...], folders: tuple[str, ...]) -> None:
    for name in files:
        (out / name).unlink(missing_ok=True)
    for name in folders:
        folder = out / name
        if folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()


LAYOUTS = ("kitti", "argoverse")


def make_layout(name: str, model: LidarModel, tr: npt.NDArray[np.float64]) -> Layout:
    if name == "kitti":
        return KittiLayout(tr)
    if name == "argoverse":
        return Argoverse1Layout(model)
    raise ValueError(f"layout: unknown {name!r}; known: {', '.join(LAYOUTS)}")
