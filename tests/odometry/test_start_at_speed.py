"""A drive that starts at speed (`motion_model.start_check_m`): the first pair has no velocity to match from,
so it is matched from the identity, and along a highway's evenly spaced posts that can find an alias — the car
reported driving backwards — as readily as the truth. The first pair is matched again from starts ahead and
behind; another motion that holds there flags the frame, and `dmlo run` says so. A flagged pair reversing
faster than `motion_model.start_max_reverse_m` takes a start's forward motion."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dmlo.commands.run import format_summary
from dmlo.datasets import open_sequence
from dmlo.odometry import Odometry, OdometryConfig
from dmlo.run import run_sequence
from dmlo.simulator import simulate_sequence


def first_pair(folder: Path, **settings: object) -> Odometry:
    config = OdometryConfig()
    for name, value in settings.items():
        setattr(config.motion_model, name, value)
    odometry = Odometry.from_default(config)
    sequence = open_sequence(folder)
    for index in range(min(3, len(sequence))):
        odometry.register(sequence[index].points)
    return odometry


@pytest.fixture(scope="module")
def highway_at_speed(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two scans of the simulated highway along KITTI 01 from frame 150 (2.4 m a frame), lasers with gains of
    their own as a real sensor's: the posts of the guard rails stand about 4 m apart."""
    out = tmp_path_factory.mktemp("highway") / "from_150"
    simulate_sequence(out, frames=2, seed=32, scene="highway", start=150, laser_gain_spread=0.6, progress=False,
                      trajectory=shared_data / "kitti_gt_poses" / "01.txt")
    return out


def test_a_first_pair_at_highway_speed_that_another_start_explains_is_flagged(highway_at_speed: Path) -> None:
    sequence = open_sequence(highway_at_speed)
    truth = np.linalg.inv(sequence[1].pose) @ sequence[0].pose  # T_tgt_ref: forward moves the scene to −x
    assert truth[0, 3] < -2.0

    # With no preference for driving forward the pair keeps its own motion: the alias, reversing.
    kept = first_pair(highway_at_speed, start_max_reverse_m=None)
    reported = np.linalg.inv(kept.poses[1])
    assert reported[0, 3] > 1.0  # the alias: what the flag is for
    first = kept.diagnostics[1]
    assert first.ambiguous_start is True and first.fallback is None
    assert first.timings_ms["start_check"] > 0
    assert first.to_dict()["ambiguous_start"] is True

    unchecked = first_pair(highway_at_speed, start_check_m=None)
    assert unchecked.diagnostics[1].ambiguous_start is None
    np.testing.assert_allclose(unchecked.poses[1], kept.poses[1], atol=1e-9)  # the flag alone changes no pose

    # By default the start that drives forward is taken, and the frame says so.
    odometry = first_pair(highway_at_speed)
    first = odometry.diagnostics[1]
    assert first.ambiguous_start is True and first.fallback == "forward_start"
    reported = np.linalg.inv(odometry.poses[1])
    assert np.linalg.norm(reported[:3, 3] - truth[:3, 3]) < 0.2


def test_dmlo_run_warns_of_an_ambiguous_first_motion(highway_at_speed: Path, tmp_path: Path) -> None:
    sequence = open_sequence(highway_at_speed)
    summary = run_sequence(sequence, Odometry.from_default(OdometryConfig()), tmp_path / "run", progress=False)
    assert summary.ambiguous_starts == 1 and summary.fallbacks == {"forward_start": 1}
    assert "warning: the first motion is ambiguous" in format_summary(summary)
    assert "the start driving forward was taken" in format_summary(summary)
    lines = (tmp_path / "run" / "diagnostics.jsonl").read_text().splitlines()
    assert '"ambiguous_start": true' in lines[1]


@pytest.mark.parametrize("name", ["odometry_01", "odometry_03"])
def test_real_first_pairs_and_a_street_are_not_flagged(shared_data: Path, drive: Path, name: str) -> None:
    folder = shared_data / "kitti_real" / name
    if not folder.is_dir():
        pytest.skip(f"{folder} not found")
    for scans in (folder, drive):
        diagnostics = first_pair(scans).diagnostics
        assert [d.ambiguous_start for d in diagnostics] == [None, False, None], scans
