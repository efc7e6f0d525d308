"""Dataset readers behind one interface, :class:`ScanSequence` of :class:`Frame`.

``open_sequence(path)`` picks the reader from the folder's layout, checked in this order:

1. ``path/sequences/`` exists → ``kitti`` odometry tree (``sequence`` picks ``XX``; optional when there is
   only one);
2. ``path/velodyne/`` exists → ``kitti`` sequence folder;
3. ``path/sensors/lidar/`` exists → ``argoverse2`` log;
4. ``path/lidar/`` holds ``PC_<ts>.ply`` sweeps → ``argoverse`` (Argoverse 1 tracking) log;
5. ``path`` itself holds ``.bin`` / ``.ply`` / ``.pcd`` files → ``folder``;
6. sub-folders up to two levels down are Argoverse 2 or Argoverse 1 logs → that format, ``sequence``
   naming the log (optional when there is only one).

Anything else raises :class:`DatasetError` saying what was looked for. ``format=`` skips the detection.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

from numpy.typing import ArrayLike

from dmlo.datasets.argoverse import Argoverse1Sequence, Argoverse2Sequence
from dmlo.datasets.base import (
    MAX_SENSOR_RANGE_M,
    MOVING_CLASSES,
    DatasetError,
    Frame,
    ScanSequence,
    check_plausible_scan,
    moving_mask,
)
from dmlo.datasets.folder import FolderSequence, scan_files_in
from dmlo.datasets.kitti import KittiSequence, read_timestamps
from dmlo.datasets.scan_files import (
    SCAN_SUFFIXES,
    in_scan_order,
    lzf_decompress,
    read_bin,
    read_labels,
    read_pcd,
    read_ply,
    read_scan,
    write_bin,
    write_labels,
)

__all__ = [
    "FORMATS",
    "MAX_SENSOR_RANGE_M",
    "MOVING_CLASSES",
    "SCAN_SUFFIXES",
    "Argoverse1Sequence",
    "Argoverse2Sequence",
    "DatasetError",
    "FolderSequence",
    "Frame",
    "KittiSequence",
    "ScanSequence",
    "check_plausible_scan",
    "detect_format",
    "in_scan_order",
    "lzf_decompress",
    "moving_mask",
    "open_sequence",
    "read_bin",
    "read_labels",
    "read_pcd",
    "read_ply",
    "read_scan",
    "read_timestamps",
    "write_bin",
    "write_labels",
]

PathLike = str | os.PathLike[str]


def _is_argoverse2_log(directory: Path) -> bool:
    return (directory / "sensors" / "lidar").is_dir()


def _is_argoverse1_log(directory: Path) -> bool:
    lidar = directory / "lidar"
    return lidar.is_dir() and any(lidar.glob("PC_*.ply"))


def _find_logs(root: Path, is_log: Callable[[Path], bool]) -> dict[str, Path]:
    """Logs one or two levels below ``root``, keyed by their path relative to ``root``."""
    found: dict[str, Path] = {}
    for child in sorted(p for p in root.iterdir() if p.is_dir()):
        if is_log(child):
            found[child.name] = child
            continue
        for grandchild in sorted(p for p in child.iterdir() if p.is_dir()):
            if is_log(grandchild):
                found[f"{child.name}/{grandchild.name}"] = grandchild
    return found


def _pick_log(
    root: Path, logs: dict[str, Path], sequence: str | None, kind: str, marker: str
) -> tuple[Path, str]:
    if not logs:
        raise DatasetError(f"{root}: no {kind} log ({marker}) in this folder or two levels below")
    if sequence is not None:
        for key, directory in logs.items():
            if sequence in (key, directory.name):
                return directory, directory.name
        raise DatasetError(
            f"{root}: no {kind} log {sequence!r} (found: {', '.join(logs) or 'none'})"
        )
    if len(logs) == 1:
        directory = next(iter(logs.values()))
        return directory, directory.name
    raise DatasetError(f"{root}: {len(logs)} {kind} logs, pick one with sequence= ({', '.join(logs)})")


def _open_kitti(path: Path, sequence: str | None, tr_cam_lidar: ArrayLike | None) -> KittiSequence:
    if (path / "sequences").is_dir():
        if sequence is None:
            available = sorted(p.name for p in (path / "sequences").iterdir() if p.is_dir())
            if len(available) != 1:
                raise DatasetError(
                    f"{path}: a KITTI tree with sequences {', '.join(available) or 'none'}; "
                    "pick one with sequence="
                )
            sequence = available[0]
        return KittiSequence.from_root(path, sequence, tr_cam_lidar=tr_cam_lidar)
    return KittiSequence(path, tr_cam_lidar=tr_cam_lidar)


def _open_argoverse(path: Path, sequence: str | None) -> Argoverse1Sequence:
    if _is_argoverse1_log(path) and sequence is None:
        return Argoverse1Sequence(path)
    directory, name = _pick_log(
        path, _find_logs(path, _is_argoverse1_log), sequence, "Argoverse 1", "lidar/PC_*.ply"
    )
    return Argoverse1Sequence(directory, name=name)


def _open_argoverse2(path: Path, sequence: str | None) -> Argoverse2Sequence:
    if _is_argoverse2_log(path) and sequence is None:
        return Argoverse2Sequence(path)
    directory, name = _pick_log(
        path, _find_logs(path, _is_argoverse2_log), sequence, "Argoverse 2", "sensors/lidar/"
    )
    return Argoverse2Sequence(directory, name=name)


def _open_folder(path: Path, sequence: str | None, tr_cam_lidar: ArrayLike | None) -> FolderSequence:
    directory = path / sequence if sequence is not None else path
    return FolderSequence(directory, tr_cam_lidar=tr_cam_lidar)


# The registry: format name → opener(path, sequence, tr_cam_lidar). Readers are plain classes; these
# wrappers only resolve a root folder to the one sequence/log asked for.
FORMATS: dict[str, Callable[[Path, str | None, ArrayLike | None], ScanSequence]] = {
    "kitti": _open_kitti,
    "argoverse": lambda path, sequence, _tr: _open_argoverse(path, sequence),
    "argoverse2": lambda path, sequence, _tr: _open_argoverse2(path, sequence),
    "folder": _open_folder,
}


def detect_format(path: PathLike) -> str:
    """The format ``open_sequence`` would pick for ``path`` (rules in the module docstring)."""
    directory = Path(path)
    if not directory.is_dir():
        raise DatasetError(f"{directory}: no such folder")
    if (directory / "sequences").is_dir() or (directory / "velodyne").is_dir():
        return "kitti"
    if _is_argoverse2_log(directory):
        return "argoverse2"
    if _is_argoverse1_log(directory):
        return "argoverse"
    if scan_files_in(directory):
        return "folder"
    if _find_logs(directory, _is_argoverse2_log):
        return "argoverse2"
    if _find_logs(directory, _is_argoverse1_log):
        return "argoverse"
    raise DatasetError(
        f"{directory}: cannot tell the dataset format: no sequences/ or velodyne/ (KITTI), "
        "sensors/lidar/ (Argoverse 2), lidar/PC_*.ply (Argoverse 1), nor .bin/.ply/.pcd scans; "
        f"pass format= one of {', '.join(FORMATS)}"
    )


def open_sequence(
    path: PathLike,
    format: str | None = None,
    sequence: str | int | None = None,
    tr_cam_lidar: ArrayLike | None = None,
) -> ScanSequence:
    """Open a scan sequence, detecting the format from the folder layout when ``format`` is None.

    ``sequence`` picks a KITTI sequence (``"00"`` or ``0``) or an Argoverse log inside a root folder;
    ``tr_cam_lidar`` (4×4) supplies the KITTI calibration when there is no ``calib.txt``.
    """
    directory = Path(path)
    if not directory.is_dir():
        raise DatasetError(f"{directory}: no such folder")
    name = detect_format(directory) if format is None else format
    if name not in FORMATS:
        raise DatasetError(f"unknown dataset format {format!r}: choose one of {', '.join(FORMATS)}")
    return FORMATS[name](directory, None if sequence is None else str(sequence), tr_cam_lidar)
