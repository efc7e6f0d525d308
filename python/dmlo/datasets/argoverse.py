"""Argoverse 1 tracking logs and Argoverse 2 sensor logs.

Both give sweeps in the **ego-vehicle frame** (the two VLP-32 merged), so a frame's pose is
``city_SE3_egovehicle`` (``T_world_lidar`` with the ego frame as "LiDAR" frame). Reflectance is the
sensor's 8-bit intensity divided by 255.

- Argoverse 1: ``LOG/lidar/PC_<ts>.ply`` (x y z intensity laser_number), poses
  ``LOG/poses/city_SE3_egovehicle_<ts>.json`` (``rotation`` quaternion ``w x y z``, ``translation``).
  Per-point labels are read from ``LOG/labels/PC_<ts>.label`` (SemanticKITTI uint32) when that folder
  exists: AV1 has none, ``dmlo simulate --sensor argoverse`` writes them.
- Argoverse 2: ``LOG/sensors/lidar/<ts>.feather`` (float16 x y z, uint8 intensity, laser_number,
  offset_ns), poses ``LOG/city_SE3_egovehicle.feather`` (timestamp_ns, qw qx qy qz, tx_m ty_m tz_m). Needs
  pyarrow (the ``argoverse2`` extra).

Timestamps are the nanosecond stamps in the file names, as seconds.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dmlo.datasets.base import DatasetError, SequenceBase
from dmlo.datasets.scan_files import read_labels, read_ply
from dmlo.poses import quaternion_to_matrix

__all__ = ["Argoverse1Sequence", "Argoverse2Sequence"]

PathLike = str | os.PathLike[str]

_AV1_SWEEP = re.compile(r"^PC_(\d+)\.ply$")
_AV2_SWEEP = re.compile(r"^(\d+)\.feather$")


def _pose_from_quaternion_wxyz(
    path: Path, rotation: Any, translation: Any
) -> NDArray[np.float64]:
    try:
        q_wxyz = np.asarray(rotation, dtype=np.float64).reshape(4)
        t = np.asarray(translation, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: rotation must be 4 numbers and translation 3") from None
    if not (np.all(np.isfinite(q_wxyz)) and np.all(np.isfinite(t))) or np.linalg.norm(q_wxyz) < 1e-9:
        raise DatasetError(f"{path}: non-finite or zero pose values")
    pose = np.eye(4)
    pose[:3, :3] = quaternion_to_matrix(q_wxyz[[1, 2, 3, 0]])[0]
    pose[:3, 3] = t
    return pose


class Argoverse1Sequence(SequenceBase):
    """An Argoverse 1 tracking log folder (``lidar/PC_<ts>.ply`` and ``poses/city_SE3_egovehicle_<ts>.json``)."""

    def __init__(self, log_dir: PathLike, name: str | None = None) -> None:
        self.directory = Path(log_dir)
        lidar_dir = self.directory / "lidar"
        if not lidar_dir.is_dir():
            raise DatasetError(f"{self.directory}: no lidar/ folder (not an Argoverse 1 log)")
        sweeps = []
        for path in lidar_dir.iterdir():
            match = _AV1_SWEEP.match(path.name)
            if match and path.is_file():
                sweeps.append((int(match.group(1)), path))
        if not sweeps:
            raise DatasetError(f"{lidar_dir}: no PC_<timestamp>.ply sweeps")
        sweeps.sort()
        stamps_ns = [stamp for stamp, _ in sweeps]
        self._paths = [path for _, path in sweeps]
        self._timestamps = np.asarray(stamps_ns, dtype=np.float64) * 1e-9
        self.name = name or self.directory.name

        pose_dir = self.directory / "poses"
        if pose_dir.is_dir():
            poses = []
            for stamp in stamps_ns:
                pose_path = pose_dir / f"city_SE3_egovehicle_{stamp}.json"
                if not pose_path.is_file():
                    raise DatasetError(f"{pose_path}: missing pose for sweep PC_{stamp}.ply")
                try:
                    record = json.loads(pose_path.read_text(encoding="utf-8"))
                    rotation, translation = record["rotation"], record["translation"]
                except (json.JSONDecodeError, UnicodeDecodeError) as err:
                    raise DatasetError(f"{pose_path}: not valid JSON ({err})") from None
                except (KeyError, TypeError):
                    raise DatasetError(f"{pose_path}: needs 'rotation' and 'translation' keys") from None
                poses.append(_pose_from_quaternion_wxyz(pose_path, rotation, translation))
            self._poses = np.stack(poses)

    def _read_points(self, index: int) -> NDArray[np.float32]:
        return read_ply(self._paths[index])

    def _read_labels(self, index: int) -> NDArray[np.uint32] | None:
        label_dir = self.directory / "labels"
        if not label_dir.is_dir():
            return None
        return read_labels(label_dir / f"{self._paths[index].stem}.label")


def _import_feather() -> Any:
    try:
        import pyarrow.feather as feather
    except ImportError:
        raise DatasetError(
            "reading Argoverse 2 needs pyarrow: pip install 'dmlo[argoverse2]' (or pip install pyarrow)"
        ) from None
    return feather


def _read_feather_columns(path: Path, required: tuple[str, ...]) -> dict[str, NDArray[Any]]:
    feather = _import_feather()
    try:
        table = feather.read_table(path)
    except Exception as err:  # pyarrow raises its own ArrowInvalid/OSError family for bad files
        raise DatasetError(f"{path}: cannot read Feather file ({err})") from None
    missing = [name for name in required if name not in table.column_names]
    if missing:
        raise DatasetError(
            f"{path}: missing column(s) {', '.join(missing)} (has {', '.join(table.column_names)})"
        )
    return {name: table.column(name).to_numpy() for name in table.column_names}


class Argoverse2Sequence(SequenceBase):
    """An Argoverse 2 sensor log folder (``sensors/lidar/<ts>.feather``, ``city_SE3_egovehicle.feather``)."""

    def __init__(self, log_dir: PathLike, name: str | None = None) -> None:
        self.directory = Path(log_dir)
        lidar_dir = self.directory / "sensors" / "lidar"
        if not lidar_dir.is_dir():
            raise DatasetError(f"{self.directory}: no sensors/lidar/ folder (not an Argoverse 2 log)")
        sweeps = []
        for path in lidar_dir.iterdir():
            match = _AV2_SWEEP.match(path.name)
            if match and path.is_file():
                sweeps.append((int(match.group(1)), path))
        if not sweeps:
            raise DatasetError(f"{lidar_dir}: no <timestamp_ns>.feather sweeps")
        sweeps.sort()
        stamps_ns = np.asarray([stamp for stamp, _ in sweeps], dtype=np.int64)
        self._paths = [path for _, path in sweeps]
        self._timestamps = stamps_ns.astype(np.float64) * 1e-9
        self.name = name or self.directory.name

        pose_path = self.directory / "city_SE3_egovehicle.feather"
        if pose_path.is_file():
            columns = _read_feather_columns(
                pose_path, ("timestamp_ns", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")
            )
            pose_stamps = np.asarray(columns["timestamp_ns"], dtype=np.int64)
            row_of = {int(stamp): row for row, stamp in enumerate(pose_stamps)}
            missing = [int(s) for s in stamps_ns if int(s) not in row_of]
            if missing:
                raise DatasetError(f"{pose_path}: no pose at sweep timestamp {missing[0]} ns")
            rows = np.asarray([row_of[int(s)] for s in stamps_ns])
            quaternion_xyzw = np.stack(
                [np.asarray(columns[k], dtype=np.float64)[rows] for k in ("qx", "qy", "qz", "qw")], axis=1
            )
            translation = np.stack(
                [np.asarray(columns[k], dtype=np.float64)[rows] for k in ("tx_m", "ty_m", "tz_m")], axis=1
            )
            if not (np.all(np.isfinite(quaternion_xyzw)) and np.all(np.isfinite(translation))):
                raise DatasetError(f"{pose_path}: non-finite pose values")
            poses = np.tile(np.eye(4), (len(rows), 1, 1))
            poses[:, :3, :3] = quaternion_to_matrix(quaternion_xyzw)
            poses[:, :3, 3] = translation
            self._poses = poses

    def _read_points(self, index: int) -> NDArray[np.float32]:
        path = self._paths[index]
        columns = _read_feather_columns(path, ("x", "y", "z", "intensity"))
        points = np.empty((len(columns["x"]), 4), dtype=np.float32)
        for axis, key in enumerate(("x", "y", "z")):
            points[:, axis] = columns[key]
        points[:, 3] = np.asarray(columns["intensity"], dtype=np.float32) / 255.0
        return points
