"""The benchmark's peers behave as odometries: on real scans of a car standing still they stay put."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dmlo.peers.peers import PEERS
from support import frame_to_frame


def _static_scans(shared_data: Path, count: int) -> list[np.ndarray]:
    files = sorted((shared_data / "kitti_raw_static").glob("*.bin"))[:count]
    return [np.fromfile(f, dtype=np.float32).reshape(-1, 4) for f in files]


@pytest.mark.parametrize("name", ["KISS-ICP", "KISS-ICP deskewed", "KISS-ICP 0.25 m voxels", "small_gicp GICP"])
def test_peer_stays_still_on_static_scans(shared_data: Path, name: str) -> None:
    peer = next(p for p in PEERS if p.name == name)
    if not peer.available:
        pytest.skip(f"{peer.package} not installed")
    odometry = peer.make()
    poses = [odometry.register(scan) for scan in _static_scans(shared_data, 3)]
    assert np.allclose(poses[0], np.eye(4))
    for pose in poses[1:]:
        assert np.linalg.norm(pose[:3, 3]) < 0.02
        assert np.allclose(pose[:3, :3], np.eye(3), atol=1e-3)


def test_peers_are_optional(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Listing the peers imports none of them, and a benchmark asked for a peer that is not installed says so,
    # with the extra to install, and still runs DMLO.
    assert {p.name for p in PEERS} >= {"KISS-ICP", "small_gicp GICP", "Open3D GICP", "Open3D FPFH+RANSAC"}
    listing = subprocess.run(
        [sys.executable, "-c", "import sys; from dmlo.peers.peers import PEERS; [p.name for p in PEERS]; "
         "print(sorted({'kiss_icp', 'small_gicp', 'open3d'} & set(sys.modules)))"],
        capture_output=True, text=True, check=True,
    )
    assert listing.stdout.strip() == "[]"

    from dmlo.peers import runner
    from dmlo.peers.peers import Peer
    from dmlo.datasets import open_sequence
    from dmlo.odometry import Odometry
    from dmlo.simulator import simulate_sequence

    def never_made() -> None:
        raise AssertionError("an unavailable peer must not run")

    absent = Peer("Absent ICP", "dmlo_test_absent_peer_package", never_made)  # type: ignore[arg-type]
    monkeypatch.setattr(runner, "PEERS", (*PEERS, absent))
    drive = tmp_path / "drive"
    simulate_sequence(drive, frames=3, seed=4, progress=False)
    with pytest.warns(runner.PeerUnavailableWarning) as caught:
        rows = runner.benchmark_sequence(
            open_sequence(drive), {"DMLO": lambda: Odometry.from_default(frame_to_frame())}, tmp_path / "bench",
            peers=["Absent ICP"],
        )
    assert [str(w.message) for w in caught] == [
        "skipping Absent ICP: dmlo_test_absent_peer_package is not installed (pip install 'dmlo[bench]')"
    ]
    assert [row.method for row in rows] == ["DMLO"]
    assert rows[0].hz > 0 and rows[0].metrics["ate_rmse"] < 0.1  # 3 frames, 2 m: DMLO ran and tracked
    assert not (tmp_path / "bench" / "Absent_ICP.txt").exists() and (tmp_path / "bench" / "DMLO.txt").is_file()


def test_a_peer_whose_package_is_missing_or_does_not_load_is_unavailable(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from dmlo.peers.peers import Peer

    # An installed package that fails on import, as Open3D's wheel does without the system's libusb.
    (tmp_path / "broken_peer_package").mkdir()
    (tmp_path / "broken_peer_package" / "__init__.py").write_text(
        "raise ImportError('libusb-1.0.so.0: cannot open shared object file')\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    broken = Peer("broken", "broken_peer_package", lambda: None)  # type: ignore[arg-type, return-value]
    assert not broken.available
    assert "does not load: libusb-1.0.so.0" in str(broken.unavailable_reason)
    missing = Peer("missing", "no_such_peer_package_here", lambda: None)  # type: ignore[arg-type, return-value]
    assert not missing.available and "not installed" in str(missing.unavailable_reason)
    assert next(p for p in PEERS if p.name == "KISS-ICP").unavailable_reason is None


def test_half_motion_is_the_slerp_midpoint() -> None:
    # KISS-ICP deskewed's poses are moved back by half its last motion: the midpoint with the identity.
    from scipy.spatial.transform import Rotation, Slerp

    from dmlo.poses import midpoint_motion

    def _half_motion(motion: np.ndarray) -> np.ndarray:
        return midpoint_motion(np.eye(4), motion)

    rng = np.random.default_rng(3)
    for _ in range(5):
        motion = np.eye(4)
        rotation = Rotation.from_rotvec(rng.normal(0, 0.3, 3))
        motion[:3, :3], motion[:3, 3] = rotation.as_matrix(), rng.normal(0, 1, 3)
        half = _half_motion(motion)
        middle = Slerp([0, 1], Rotation.concatenate([Rotation.identity(), rotation]))(0.5)
        assert np.allclose(half[:3, :3], middle.as_matrix(), atol=1e-12)
        assert np.allclose(half[:3, 3], motion[:3, 3] / 2)
    assert np.array_equal(_half_motion(np.eye(4)), np.eye(4))
