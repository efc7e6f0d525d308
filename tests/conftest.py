"""Shared fixtures: where the real data lies (skipping when it is absent), and a plain folder of scans."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """`../shared/data/` beside the repository; tests that need it skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real test data not found at {SHARED_DATA}")
    return SHARED_DATA


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
