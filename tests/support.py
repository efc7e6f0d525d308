"""Helpers shared by several test files (`tests/` and its area folders are on the import path: pyproject's
pytest `pythonpath`)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from dmlo.metrics import registration_errors

if TYPE_CHECKING:
    from dmlo.odometry import Odometry, OdometryConfig

FloatArray = npt.NDArray[np.float64]
REPO = Path(__file__).resolve().parent.parent  # the repository; `../shared/data` lies beside it


def assert_simulation_reproducible(tmp_path: Path, same: list[str], differing: list[str], **options: str) -> None:
    """Seed 5 gives the same bytes in `same` in-process and from `dmlo simulate` on one thread (the options
    passed as `--name value`), and seed 6 different bytes in `differing`."""
    from dmlo.simulator import simulate_sequence

    first, second, other = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    simulate_sequence(first, 2, seed=5, progress=False, **options)  # type: ignore[arg-type]
    flags = [part for name, value in options.items() for part in (f"--{name}", value)]
    command = [sys.executable, "-m", "dmlo", "simulate", "--frames", "2", "--seed", "5", *flags]
    env = dict(os.environ, RAYON_NUM_THREADS="1")
    subprocess.run([*command, "--out", str(second), "--quiet"], check=True, env=env)
    simulate_sequence(other, 2, seed=6, progress=False, **options)  # type: ignore[arg-type]
    for name in same:
        assert (first / name).read_bytes() == (second / name).read_bytes(), name
    for name in differing:
        assert (first / name).read_bytes() != (other / name).read_bytes(), name


def rigid(translation: list[float], rotvec_deg: list[float]) -> FloatArray:
    """A 4×4 transform from a translation and a rotation vector in degrees."""
    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_rotvec(rotvec_deg, degrees=True).as_matrix()
    transform[:3, 3] = translation
    return transform


def transform_points(transform: FloatArray, points: FloatArray) -> FloatArray:
    return points @ transform[:3, :3].T + transform[:3, 3]


def gicp_departure_from_truth(target: FloatArray, source: FloatArray, truth: FloatArray) -> tuple[float, float]:
    """How far (m, °) small_gicp's GICP moves away from the true `T_target_source` it starts at: ~0 when
    two scans agree with the ground truth written beside them."""
    import small_gicp

    result = small_gicp.align(
        target,
        source,
        init_T_target_source=truth,
        registration_type="GICP",
        downsampling_resolution=0.25,
        max_correspondence_distance=1.0,
        num_threads=2,
        max_iterations=30,
        translation_epsilon=1e-5,
        rotation_epsilon=1e-5,
    )
    errors = registration_errors(result.T_target_source[None], truth[None])
    return errors.translation_max, errors.angular_max


def frame_to_frame(**settings: object) -> OdometryConfig:
    """The paper's frame-to-frame DMLO (`mapping.enabled = False`, the default before DMLO + mapping became
    it), with top-level `settings`: for the tests of what DMLO's matches and motion model do on their own."""
    from dmlo.odometry import OdometryConfig

    config = OdometryConfig()
    config.mapping.enabled = False
    for name, value in settings.items():
        setattr(config, name, value)
    return config


def rust_example(name: str) -> Path:
    """`target/release/examples/<name>`, as `cargo test --release --features inference,onnxruntime` builds it (CI
    builds it before pytest); the test skips when it is missing or older than the crate's sources."""
    import pytest

    example = Path(os.environ.get("CARGO_TARGET_DIR", REPO / "target")) / "release" / "examples" / name
    if not example.is_file():
        pytest.skip(f"{example} not built: cargo test --release --features inference,onnxruntime builds it")
    sources = [*REPO.joinpath("src").rglob("*.rs"), REPO / "examples" / f"{name}.rs", REPO / "Cargo.toml"]
    if example.stat().st_mtime < max(path.stat().st_mtime for path in sources):
        pytest.skip(f"{example} is older than the crate's sources: rebuild it with cargo test --release "
                    "--features inference,onnxruntime")
    return example


def projected(odometry: Odometry, cloud: npt.NDArray[np.float32]) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The network input `[2, H, W]`, the range image `[H, W]` and the point image `[H, W, 3]` (each cell's kept
    point, NaN where empty) of a scan of finite points, as the odometry projects it."""
    import dmlo_rs

    image, ranges = odometry.project(cloud)
    index = dmlo_rs.project(np.ascontiguousarray(cloud, dtype=np.float32), odometry.cylinder).index
    points = np.take(cloud[:, :3], np.maximum(index, 0), axis=0)
    points[index < 0] = np.nan
    return image, ranges, points
