"""KITTI odometry sequences (and SemanticKITTI labels), and the side files shared with plain folders.

Layouts read:

- the odometry tree ``ROOT/sequences/XX/velodyne/*.bin`` with ``ROOT/sequences/XX/calib.txt``,
  ``times.txt``, optional SemanticKITTI ``labels/*.label``, and ground truth in ``ROOT/poses/XX.txt``
  (found whether ``ROOT`` or ``ROOT/sequences/XX`` is opened);
- a bare sequence folder ``velodyne/`` with optional ``poses.txt``, ``calib.txt``, ``times.txt`` and
  ``labels/`` (the layout the simulator writes).

Ground-truth poses in KITTI files are left-camera poses; with a ``calib.txt`` holding ``Tr:`` they become
``T_world_lidar = Tr⁻¹ · P_cam · Tr``. Without a calibration the poses are used as given, i.e. taken to be
LiDAR poses already, and a ``UserWarning`` says so; pass ``tr_cam_lidar`` to supply the calibration.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from dmlo import poses as pose_files
from dmlo.datasets.base import DatasetError, SequenceBase
from dmlo.datasets.scan_files import in_scan_order, read_bin, read_labels

__all__ = ["KittiSequence", "read_timestamps", "load_side_files"]

PathLike = str | os.PathLike[str]


def read_timestamps(path: PathLike) -> NDArray[np.float64]:
    """Timestamps in seconds from ``times.txt`` (one float a line) or KITTI raw ``timestamps.txt``.

    KITTI raw lines (``2011-09-26 14:30:15.002263428``) become seconds since the Unix epoch (UTC) with
    their nanoseconds kept.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: timestamp file not found")
    stamps = []
    with path.open("r", encoding="utf-8", errors="replace") as handle:
        for number, line in enumerate(handle, start=1):
            text = line.strip()
            if not text:
                continue
            try:
                seconds = float(text)
            except ValueError:
                pass
            else:
                # The odometry counts missing scans from the intervals: a NaN would count nothing.
                if not np.isfinite(seconds):
                    raise DatasetError(f"{path}:{number}: timestamp {text!r} is not a finite number")
                stamps.append(seconds)
                continue
            try:
                moment = np.datetime64(text.replace(" ", "T"), "ns")
            except ValueError:
                raise DatasetError(f"{path}:{number}: {text!r} is neither seconds nor a date-time") from None
            nanoseconds = int(moment.astype(np.int64))
            stamps.append(nanoseconds // 1_000_000_000 + (nanoseconds % 1_000_000_000) * 1e-9)
    return np.asarray(stamps, dtype=np.float64)


def load_side_files(
    directory: Path,
    frame_count: int,
    poses_path: Path | None = None,
    calib_path: Path | None = None,
    tr_cam_lidar: ArrayLike | None = None,
) -> tuple[NDArray[np.float64] | None, NDArray[np.float64] | None]:
    """Ground-truth LiDAR poses and timestamps for a sequence of ``frame_count`` scans in ``directory``.

    Poses come from ``poses_path`` or ``directory/poses.txt`` (KITTI camera-frame), converted with
    ``tr_cam_lidar`` or the ``Tr:`` line of ``calib_path`` / ``directory/calib.txt``; timestamps from
    ``times.txt`` or ``timestamps.txt``. Counts must match the scans.
    """
    if poses_path is None and (directory / "poses.txt").is_file():
        poses_path = directory / "poses.txt"
    if calib_path is None and (directory / "calib.txt").is_file():
        calib_path = directory / "calib.txt"

    poses = None
    if poses_path is not None:
        try:
            poses_cam = pose_files.read_kitti_poses(poses_path)
            if tr_cam_lidar is None and calib_path is not None:
                tr_cam_lidar = pose_files.read_kitti_calib(calib_path)["Tr"]
        except (pose_files.PoseFileError, FileNotFoundError) as err:
            raise DatasetError(str(err)) from None
        if len(poses_cam) != frame_count:
            raise DatasetError(f"{poses_path}: {len(poses_cam)} poses but {frame_count} scans")
        if tr_cam_lidar is None:
            warnings.warn(
                f"{poses_path}: no calib.txt with a 'Tr:' line beside it; the poses are used as given "
                "(assumed to be LiDAR poses, not KITTI camera poses)",
                UserWarning,
                stacklevel=3,
            )
            poses = poses_cam
        else:
            poses = pose_files.camera_to_lidar(poses_cam, tr_cam_lidar)

    timestamps = None
    for candidate in ("times.txt", "timestamps.txt"):
        if (directory / candidate).is_file():
            timestamps = read_timestamps(directory / candidate)
            if len(timestamps) != frame_count:
                raise DatasetError(
                    f"{directory / candidate}: {len(timestamps)} timestamps but {frame_count} scans"
                )
            break
    return poses, timestamps


class KittiSequence(SequenceBase):
    """A KITTI odometry sequence folder (``velodyne/*.bin``, optional labels, poses, calib, times). Scans
    run in file-name order, or numerically when every name is a number (``1.bin, 2.bin, 10.bin``)."""

    def __init__(
        self,
        sequence_dir: PathLike,
        poses_path: PathLike | None = None,
        calib_path: PathLike | None = None,
        tr_cam_lidar: ArrayLike | None = None,
        name: str | None = None,
    ) -> None:
        self.directory = Path(sequence_dir)
        scan_dir = self.directory / "velodyne"
        if not scan_dir.is_dir():
            raise DatasetError(f"{self.directory}: no velodyne/ folder (not a KITTI sequence)")
        self._paths = in_scan_order(scan_dir.glob("*.bin"))
        if not self._paths:
            raise DatasetError(f"{scan_dir}: no .bin scans")
        self.name = name or self.directory.name

        label_dir = self.directory / "labels"
        self._label_paths: list[Path] | None = None
        if label_dir.is_dir():
            self._label_paths = [label_dir / f"{p.stem}.label" for p in self._paths]
            missing = [p for p in self._label_paths if not p.is_file()]
            if missing:
                raise DatasetError(
                    f"{label_dir}: {len(missing)} scans have no label file, first {missing[0].name}"
                )

        if poses_path is None and not (self.directory / "poses.txt").is_file():
            # Opened as ROOT/sequences/XX directly: the ground truth is ROOT/poses/XX.txt.
            tree_poses = self.directory.parent.parent / "poses" / f"{self.directory.name}.txt"
            if self.directory.parent.name == "sequences" and tree_poses.is_file():
                poses_path = tree_poses
        self._poses, self._timestamps = load_side_files(
            self.directory,
            len(self._paths),
            Path(poses_path) if poses_path is not None else None,
            Path(calib_path) if calib_path is not None else None,
            tr_cam_lidar,
        )

    @classmethod
    def from_root(
        cls, root: PathLike, sequence: str | int, tr_cam_lidar: ArrayLike | None = None
    ) -> KittiSequence:
        """Sequence ``XX`` of the odometry tree ``ROOT/sequences/XX`` with poses ``ROOT/poses/XX.txt``."""
        root = Path(root)
        key = f"{int(sequence):02d}" if str(sequence).isdigit() else str(sequence)
        directory = root / "sequences" / key
        if not directory.is_dir():
            available = sorted(p.name for p in (root / "sequences").glob("*") if p.is_dir())
            raise DatasetError(
                f"{root}: no sequence {key!r} under sequences/ (available: {', '.join(available) or 'none'})"
            )
        poses_path = root / "poses" / f"{key}.txt"
        return cls(
            directory,
            poses_path=poses_path if poses_path.is_file() else None,
            tr_cam_lidar=tr_cam_lidar,
            name=key,
        )

    def _read_points(self, index: int) -> NDArray[np.float32]:
        return read_bin(self._paths[index])

    def _read_labels(self, index: int) -> NDArray[np.uint32] | None:
        if self._label_paths is None:
            return None
        return read_labels(self._label_paths[index])
