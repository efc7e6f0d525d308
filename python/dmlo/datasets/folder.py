"""A plain folder of ``.bin``, ``.ply`` or ``.pcd`` scans, in recording order: by number when every file
name is a number (``1.bin, 2.bin, 10.bin``), otherwise by name.

Optional side files as in a KITTI sequence folder: ``poses.txt`` (+ ``calib.txt``), ``times.txt`` or
KITTI raw ``timestamps.txt``; SemanticKITTI labels ``<stem>.label`` beside a scan or in ``labels/``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from dmlo.datasets.base import DatasetError, SequenceBase
from dmlo.datasets.kitti import load_side_files
from dmlo.datasets.scan_files import SCAN_SUFFIXES, in_scan_order, read_labels, read_scan

__all__ = ["FolderSequence", "scan_files_in"]


def scan_files_in(directory: Path) -> list[Path]:
    """The scan files directly in ``directory`` (suffix ``.bin``, ``.ply`` or ``.pcd``), in the order of
    :func:`~dmlo.datasets.scan_files.in_scan_order`: numerically when every stem is a number, otherwise
    by name."""
    return in_scan_order(
        p for p in directory.iterdir() if p.is_file() and p.suffix.lower() in SCAN_SUFFIXES
    )


class FolderSequence(SequenceBase):
    """Scans in a folder in recording order (numerically when the file names are numbers, otherwise by
    name), with optional poses, timestamps and labels."""

    def __init__(
        self,
        directory: str | os.PathLike[str],
        poses_path: str | os.PathLike[str] | None = None,
        calib_path: str | os.PathLike[str] | None = None,
        tr_cam_lidar: ArrayLike | None = None,
        name: str | None = None,
    ) -> None:
        self.directory = Path(directory)
        if not self.directory.is_dir():
            raise DatasetError(f"{self.directory}: not a folder")
        self._paths = scan_files_in(self.directory)
        if not self._paths:
            raise DatasetError(f"{self.directory}: no {', '.join(SCAN_SUFFIXES)} scans")
        self.name = name or self.directory.name
        self._label_paths: list[Path | None] = []
        for path in self._paths:
            beside = path.with_suffix(".label")
            in_labels = self.directory / "labels" / f"{path.stem}.label"
            self._label_paths.append(
                beside if beside.is_file() else in_labels if in_labels.is_file() else None
            )
        self._poses, self._timestamps = load_side_files(
            self.directory,
            len(self._paths),
            Path(poses_path) if poses_path is not None else None,
            Path(calib_path) if calib_path is not None else None,
            tr_cam_lidar,
        )

    def _read_points(self, index: int) -> NDArray[np.float32]:
        return read_scan(self._paths[index])

    def _read_labels(self, index: int) -> NDArray[np.uint32] | None:
        label_path = self._label_paths[index]
        return None if label_path is None else read_labels(label_path)
