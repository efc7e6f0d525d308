"""Pose files and frame conversions.

Two text formats are read and written:

- **KITTI**: one pose a line, the first three rows of the 4×4 matrix as 12 floats, row-major.
- **TUM**: ``timestamp tx ty tz qx qy qz qw`` a line (Hamilton quaternion, scalar last); lines starting
  with ``#`` are comments.

Poses are ``(N, 4, 4)`` float64 arrays. KITTI odometry ground truth is given in the left camera frame;
``camera_to_lidar`` turns it into ``T_world_lidar = Tr⁻¹ · P_cam · Tr`` with ``Tr`` (LiDAR → camera) from
the ``Tr:`` line of ``calib.txt``.

Writers are safe against interruption: :func:`write_kitti_poses` / :func:`write_tum_poses` write a
temporary file and rename it over the target, and :class:`PoseWriter` appends one complete line per pose
and flushes it, so a run cut short leaves a valid file holding every pose written so far.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable
from pathlib import Path
from types import TracebackType
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

PoseFormat = Literal["kitti", "tum"]
POSE_FORMATS: tuple[PoseFormat, ...] = ("kitti", "tum")

__all__ = [
    "POSE_FORMATS",
    "ROTATION_TOLERANCE",
    "PoseFileError",
    "PoseFormat",
    "PoseWriter",
    "accumulate_motions",
    "camera_to_lidar",
    "detect_pose_format",
    "lidar_to_camera",
    "matrix_to_quaternion",
    "quaternion_to_matrix",
    "read_kitti_calib",
    "read_kitti_poses",
    "read_poses",
    "read_tum_poses",
    "relative_motions",
    "write_kitti_poses",
    "write_poses",
    "write_tum_poses",
]


class PoseFileError(ValueError):
    """A pose or calibration file that cannot be read: the message names the file, line and problem."""


# ----------------------------------------------------------------------------------------------------
# Checks


def as_poses(poses: ArrayLike, name: str = "poses") -> NDArray[np.float64]:
    """Return ``poses`` as a C-contiguous ``(N, 4, 4)`` float64 array, or raise ``ValueError``."""
    array = np.asarray(poses, dtype=np.float64)
    if array.ndim == 2 and array.shape == (4, 4):
        array = array[None]
    if array.ndim != 3 or array.shape[1:] != (4, 4):
        raise ValueError(f"{name} must have shape (N, 4, 4), got {np.shape(poses)}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return np.ascontiguousarray(array)


def _as_transform(matrix: ArrayLike, name: str) -> NDArray[np.float64]:
    array = np.asarray(matrix, dtype=np.float64)
    if array.shape != (4, 4):
        raise ValueError(f"{name} must have shape (4, 4), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return array


def _rigid_inverse(transforms: NDArray[np.float64]) -> NDArray[np.float64]:
    """Inverse of rigid transforms ``(..., 4, 4)`` without a general matrix inverse."""
    rotation_t = np.swapaxes(transforms[..., :3, :3], -1, -2)
    inverse = np.zeros_like(transforms)
    inverse[..., :3, :3] = rotation_t
    inverse[..., :3, 3] = -np.einsum("...ij,...j->...i", rotation_t, transforms[..., :3, 3])
    inverse[..., 3, 3] = 1.0
    return inverse


# ----------------------------------------------------------------------------------------------------
# Quaternions (Hamilton, stored x y z w as in TUM files)


def midpoint_motion(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rigid motion halfway between two: the rotation is the projection of R_a + R_b onto SO(3)
    (for two rotations their geodesic midpoint), the translation the mean. With `a` the identity: half
    of `b` (half its angle about the same axis, half its translation)."""
    u, _, vt = np.linalg.svd(a[:3, :3] + b[:3, :3])
    fix = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    middle = np.eye(4)
    middle[:3, :3] = u @ fix @ vt
    middle[:3, 3] = (a[:3, 3] + b[:3, 3]) / 2
    return middle


def quaternion_to_matrix(quaternions_xyzw: ArrayLike) -> NDArray[np.float64]:
    """Rotation matrices ``(N, 3, 3)`` from quaternions ``(N, 4)`` ordered ``x y z w`` (normalised here)."""
    q = np.asarray(quaternions_xyzw, dtype=np.float64).reshape(-1, 4)
    norm = np.linalg.norm(q, axis=1)
    if np.any(norm < 1e-12) or not np.all(np.isfinite(norm)):
        raise ValueError("quaternions must be finite and non-zero")
    x, y, z, w = (q / norm[:, None]).T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def matrix_to_quaternion(rotations: ArrayLike) -> NDArray[np.float64]:
    """Quaternions ``(N, 4)`` ordered ``x y z w`` with ``w ≥ 0`` from rotation matrices ``(N, 3, 3)``.

    Uses the numerically stable branch (largest diagonal term) per matrix.
    """
    r = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    trace = np.trace(r, axis1=1, axis2=2)
    diagonal = np.stack([r[:, 0, 0], r[:, 1, 1], r[:, 2, 2], trace], axis=1)
    branch = np.argmax(diagonal, axis=1)
    q = np.empty((len(r), 4))
    for index, (m, b) in enumerate(zip(r, branch, strict=True)):
        if b == 3:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] + m[1, 1] + m[2, 2])
            q[index] = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
        elif b == 0:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
            q[index] = [s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
        elif b == 1:
            s = 2.0 * np.sqrt(1.0 - m[0, 0] + m[1, 1] - m[2, 2])
            q[index] = [(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 - m[0, 0] - m[1, 1] + m[2, 2])
            q[index] = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1.0
    return q


# ----------------------------------------------------------------------------------------------------
# Reading


def _read_rows(path: Path, what: str) -> list[tuple[int, list[str]]]:
    """Non-empty, non-comment lines of ``path`` split on whitespace, with their 1-based line numbers."""
    if not path.is_file():
        raise FileNotFoundError(f"{what} file not found: {path}")
    rows = []
    with path.open("r", encoding="utf-8", errors="replace") as handle:
        for number, line in enumerate(handle, start=1):
            stripped = line.strip()
            if stripped and not stripped.startswith("#"):
                rows.append((number, stripped.replace(",", " ").split()))
    return rows


def _parse_floats(path: Path, number: int, fields: list[str], expected: int, what: str) -> list[float]:
    if len(fields) != expected:
        raise PoseFileError(
            f"{path}:{number}: expected {expected} numbers on a {what} line, found {len(fields)}"
        )
    try:
        values = [float(field) for field in fields]
    except ValueError:
        bad = next(field for field in fields if not _is_float(field))
        raise PoseFileError(f"{path}:{number}: {bad!r} is not a number") from None
    if not all(np.isfinite(values)):
        raise PoseFileError(f"{path}:{number}: NaN or infinite value")
    return values


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def read_kitti_poses(path: str | os.PathLike[str]) -> NDArray[np.float64]:
    """Read a KITTI pose file (12 floats a line) into ``(N, 4, 4)`` float64 poses.

    Raises ``FileNotFoundError`` for a missing file and :class:`PoseFileError` for an empty file, a line
    without exactly 12 numbers, a non-number, or a rotation that is not one (not orthonormal within
    :data:`ROTATION_TOLERANCE`, or a reflection).
    """
    path = Path(path)
    rows = _read_rows(path, "pose")
    if not rows:
        raise PoseFileError(f"{path}: no poses in file")
    values = np.array([_parse_floats(path, n, f, 12, "KITTI pose") for n, f in rows])
    poses = np.zeros((len(values), 4, 4))
    poses[:, :3, :] = values.reshape(-1, 3, 4)
    poses[:, 3, 3] = 1.0
    _check_rotations(path, [number for number, _ in rows], poses[:, :3, :3])
    return poses


# Largest |RᵀR − I| entry accepted as a rotation: pose files print 6 to 9 significant digits, whose
# rounding is far below this, while a scaled, sheared or garbled matrix is far above it.
ROTATION_TOLERANCE = 1e-3


def _check_rotations(path: Path, line_numbers: list[int], rotations: NDArray[np.float64]) -> None:
    """Raises :class:`PoseFileError` naming the first line whose 3×3 block is not a rotation."""
    deviation = np.abs(np.einsum("nji,njk->nik", rotations, rotations) - np.eye(3)).max(axis=(1, 2))
    determinants = np.linalg.det(rotations)
    bad = np.flatnonzero((deviation > ROTATION_TOLERANCE) | (determinants <= 0.0))
    if bad.size:
        first = int(bad[0])
        raise PoseFileError(
            f"{path}:{line_numbers[first]}: the rotation is not orthonormal with determinant +1 "
            f"(|RᵀR − I| = {deviation[first]:.2e}, det = {determinants[first]:.4f}); "
            f"{bad.size} of {len(rotations)} poses are not rigid"
        )


def read_tum_poses(path: str | os.PathLike[str]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Read a TUM pose file into ``(timestamps (N,), poses (N, 4, 4))``."""
    path = Path(path)
    rows = _read_rows(path, "pose")
    if not rows:
        raise PoseFileError(f"{path}: no poses in file")
    values = np.array([_parse_floats(path, n, f, 8, "TUM pose") for n, f in rows])
    for (number, _), quaternion in zip(rows, values[:, 4:], strict=True):
        if np.linalg.norm(quaternion) < 1e-6:
            raise PoseFileError(f"{path}:{number}: zero quaternion")
    poses = np.zeros((len(values), 4, 4))
    poses[:, :3, :3] = quaternion_to_matrix(values[:, 4:])
    poses[:, :3, 3] = values[:, 1:4]
    poses[:, 3, 3] = 1.0
    return values[:, 0].copy(), poses


def detect_pose_format(path: str | os.PathLike[str]) -> PoseFormat:
    """``"kitti"`` if the first data line has 12 numbers, ``"tum"`` if it has 8; otherwise an error."""
    path = Path(path)
    rows = _read_rows(path, "pose")
    if not rows:
        raise PoseFileError(f"{path}: no poses in file")
    number, fields = rows[0]
    if len(fields) == 12:
        return "kitti"
    if len(fields) == 8:
        return "tum"
    raise PoseFileError(
        f"{path}:{number}: cannot tell the pose format: {len(fields)} numbers "
        "(KITTI has 12 a line, TUM has 8)"
    )


def read_poses(
    path: str | os.PathLike[str], format: PoseFormat | None = None
) -> tuple[NDArray[np.float64] | None, NDArray[np.float64]]:
    """Read poses in either format (detected from the column count when ``format`` is None).

    Returns ``(timestamps or None, poses)``; KITTI files carry no timestamps.
    """
    fmt = detect_pose_format(path) if format is None else format
    if fmt == "kitti":
        return None, read_kitti_poses(path)
    if fmt == "tum":
        return read_tum_poses(path)
    raise ValueError(f"format must be one of {POSE_FORMATS}, got {format!r}")


def read_kitti_calib(path: str | os.PathLike[str]) -> dict[str, NDArray[np.float64]]:
    """Read a KITTI ``calib.txt`` (``KEY: 12 floats`` lines) into 4×4 matrices keyed ``P0``…``Tr``.

    Every 12-number entry becomes a 4×4 matrix with ``[0, 0, 0, 1]`` as last row. ``Tr`` maps LiDAR
    (Velodyne) points into the left camera frame.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"calibration file not found: {path}")
    matrices: dict[str, NDArray[np.float64]] = {}
    with path.open("r", encoding="utf-8", errors="replace") as handle:
        for number, line in enumerate(handle, start=1):
            if not line.strip():
                continue
            key, sep, rest = line.partition(":")
            if not sep:
                raise PoseFileError(f"{path}:{number}: expected 'KEY: values', found {line.strip()!r}")
            values = _parse_floats(path, number, rest.split(), 12, f"calibration {key.strip()!r}")
            matrix = np.eye(4)
            matrix[:3, :] = np.reshape(values, (3, 4))
            matrices[key.strip()] = matrix
    if "Tr" not in matrices:
        raise PoseFileError(f"{path}: no 'Tr:' line (LiDAR → camera transform)")
    return matrices


# ----------------------------------------------------------------------------------------------------
# Frames and motions


def camera_to_lidar(poses_cam: ArrayLike, tr_cam_lidar: ArrayLike) -> NDArray[np.float64]:
    """KITTI camera-frame poses → LiDAR-frame poses: ``T_world_lidar = Tr⁻¹ · P_cam · Tr``.

    The world frame becomes the LiDAR frame of the first scan when ``P_cam[0]`` is the identity.
    """
    poses = as_poses(poses_cam, "poses_cam")
    tr = _as_transform(tr_cam_lidar, "tr_cam_lidar")
    return np.linalg.inv(tr) @ poses @ tr


def lidar_to_camera(poses_lidar: ArrayLike, tr_cam_lidar: ArrayLike) -> NDArray[np.float64]:
    """Inverse of :func:`camera_to_lidar`: ``P_cam = Tr · T_world_lidar · Tr⁻¹``."""
    poses = as_poses(poses_lidar, "poses_lidar")
    tr = _as_transform(tr_cam_lidar, "tr_cam_lidar")
    return tr @ poses @ np.linalg.inv(tr)


def relative_motions(poses: ArrayLike) -> NDArray[np.float64]:
    """Pair motions ``T_tgt_ref`` between consecutive poses, ``(N-1, 4, 4)``.

    With ``p_t = T p_{t-1}`` (the pipeline's convention), ``T[i] = T_world_{i+1}⁻¹ · T_world_i``.
    """
    array = as_poses(poses)
    return _rigid_inverse(array[1:]) @ array[:-1]


def accumulate_motions(
    motions: ArrayLike, initial: ArrayLike | None = None
) -> NDArray[np.float64]:
    """Chain pair motions ``T_tgt_ref`` into poses: ``T_world_t = T_world_{t-1} · T⁻¹``.

    Returns ``(N+1, 4, 4)`` poses starting at ``initial`` (identity by default); inverse of
    :func:`relative_motions`.
    """
    steps = as_poses(motions, "motions") if np.size(motions) else np.zeros((0, 4, 4))
    start = np.eye(4) if initial is None else _as_transform(initial, "initial")
    poses = np.empty((len(steps) + 1, 4, 4))
    poses[0] = start
    inverse_steps = _rigid_inverse(steps)
    for index, step in enumerate(inverse_steps):
        poses[index + 1] = poses[index] @ step
    return poses


# ----------------------------------------------------------------------------------------------------
# Writing


def _format_kitti(pose: NDArray[np.float64]) -> str:
    return " ".join(f"{value:.9e}" for value in pose[:3, :].reshape(-1)) + "\n"


def _format_tum(timestamp: float, pose: NDArray[np.float64]) -> str:
    quaternion = matrix_to_quaternion(pose[:3, :3])[0]
    values = [timestamp, *pose[:3, 3], *quaternion]
    return " ".join(f"{value:.9f}" if i == 0 else f"{value:.9e}" for i, value in enumerate(values)) + "\n"


def _atomic_write(path: Path, lines: Iterable[str]) -> None:
    """Write to a temporary file beside ``path`` and rename it over ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    descriptor, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(descriptor, "w", encoding="utf-8") as handle:
            handle.writelines(lines)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def _timestamps_for(poses: NDArray[np.float64], timestamps: ArrayLike | None) -> NDArray[np.float64]:
    if timestamps is None:
        return np.arange(len(poses), dtype=np.float64)
    stamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if len(stamps) != len(poses):
        raise ValueError(f"timestamps has {len(stamps)} entries but there are {len(poses)} poses")
    return stamps


def write_kitti_poses(path: str | os.PathLike[str], poses: ArrayLike) -> None:
    """Write ``(N, 4, 4)`` poses as a KITTI file (atomically: temporary file, then rename)."""
    array = as_poses(poses)
    _atomic_write(Path(path), (_format_kitti(pose) for pose in array))


def write_tum_poses(
    path: str | os.PathLike[str], poses: ArrayLike, timestamps: ArrayLike | None = None
) -> None:
    """Write poses as a TUM file; timestamps default to the frame index (atomic like the KITTI writer)."""
    array = as_poses(poses)
    stamps = _timestamps_for(array, timestamps)
    _atomic_write(Path(path), (_format_tum(t, pose) for t, pose in zip(stamps, array, strict=True)))


def write_poses(
    path: str | os.PathLike[str],
    poses: ArrayLike,
    format: PoseFormat = "kitti",
    timestamps: ArrayLike | None = None,
) -> None:
    """Write poses in ``format`` (``"kitti"`` ignores ``timestamps``)."""
    if format == "kitti":
        write_kitti_poses(path, poses)
    elif format == "tum":
        write_tum_poses(path, poses, timestamps)
    else:
        raise ValueError(f"format must be one of {POSE_FORMATS}, got {format!r}")


class PoseWriter:
    """Append poses to a file one complete line at a time, flushed after each.

    For odometry that writes as it goes: if the run stops, the file holds every pose appended so far and
    reads back with :func:`read_poses`. The file is truncated when opened unless ``append=True``.

    >>> with PoseWriter("poses.txt", "kitti") as writer:  # doctest: +SKIP
    ...     writer.append(pose)
    """

    def __init__(
        self, path: str | os.PathLike[str], format: PoseFormat = "kitti", append: bool = False
    ) -> None:
        if format not in POSE_FORMATS:
            raise ValueError(f"format must be one of {POSE_FORMATS}, got {format!r}")
        self.path = Path(path)
        self.format: PoseFormat = format
        self.count = 0
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._handle = self.path.open("a" if append else "w", encoding="utf-8")

    def append(self, pose: ArrayLike, timestamp: float | None = None) -> None:
        """Write one 4×4 pose; TUM lines use ``timestamp`` (default: the running frame index)."""
        matrix = _as_transform(pose, "pose")
        if self.format == "kitti":
            line = _format_kitti(matrix)
        else:
            line = _format_tum(float(self.count if timestamp is None else timestamp), matrix)
        # One write of a whole line, then flush: an interruption never leaves half a line behind in
        # Python's buffer, and the OS holds every completed line.
        self._handle.write(line)
        self._handle.flush()
        self.count += 1

    def close(self) -> None:
        if not self._handle.closed:
            self._handle.flush()
            os.fsync(self._handle.fileno())
            self._handle.close()

    def __enter__(self) -> PoseWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()
