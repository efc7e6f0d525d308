"""Shared fixtures: where the real data lies (skipping when it is absent), a plain folder of scans, and the
5-scan simulated street drive many odometry tests run on (simulated once a session)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from support import REPO

SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """`../shared/data/` beside the repository; tests that need it skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real test data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="session")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 5-scan simulated street drive (seed 5) in KITTI layout; read-only for the tests that share it."""
    from dmlo.simulator import simulate_sequence

    out = tmp_path_factory.mktemp("drive")
    simulate_sequence(out, frames=5, seed=5, progress=False)
    return out


@pytest.fixture(scope="session")
def scans(drive: Path) -> list[np.ndarray]:
    """The points of `drive`'s scans (treat as read-only: every test sharing them sees the same arrays)."""
    from dmlo.datasets import open_sequence

    sequence = open_sequence(drive)
    return [sequence[i].points for i in range(len(sequence))]


@pytest.fixture()
def plain_scans(tmp_path: Path) -> Path:
    """A plain folder of two plausible `.bin` scans, for command lines refused before they read a scan."""
    folder = tmp_path / "scans"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for index in range(2):
        points = np.concatenate([rng.uniform(-20, 20, (3000, 3)), rng.uniform(0, 1, (3000, 1))], axis=1)
        points.astype(np.float32).tofile(folder / f"{index:06d}.bin")
    return folder
