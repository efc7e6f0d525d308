"""The real-scan benchmark's reference: the pose graph behind the multi-scan GICP consensus, and the consensus
against a simulated drive's truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dmlo.peers import consensus
from dmlo.peers.pose_graph import solve_pose_graph


def _random_drive(rng: np.random.Generator, count: int) -> np.ndarray:
    """Poses of a car driving about a metre a scan and turning a little."""
    poses = [np.eye(4)]
    for _ in range(count - 1):
        step = np.eye(4)
        step[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.02, 3)).as_matrix()
        step[:3, 3] = [1.0, 0.0, 0.0] + rng.normal(0, 0.1, 3)
        poses.append(poses[-1] @ step)
    return np.stack(poses)


def _edges(count: int, span: int) -> np.ndarray:
    return np.array([(i, j) for i in range(count) for j in range(i + 1, min(count, i + span + 1))])


def _perturbed(motion: np.ndarray, rng: np.random.Generator, metres: float, radians: float) -> np.ndarray:
    noise = np.eye(4)
    noise[:3, :3] = Rotation.from_rotvec(rng.normal(0, radians, 3)).as_matrix()
    noise[:3, 3] = rng.normal(0, metres, 3)
    return motion @ noise


def _delta_errors_m(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    deltas = np.linalg.inv(poses[:-1]) @ poses[1:]
    true_deltas = np.linalg.inv(truth[:-1]) @ truth[1:]
    return np.linalg.norm((np.linalg.inv(true_deltas) @ deltas)[:, :3, 3], axis=1)


def _relative(poses: np.ndarray, edges: np.ndarray) -> np.ndarray:
    return np.linalg.inv(poses[edges[:, 0]]) @ poses[edges[:, 1]]


def _chain(edges: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """The poses the consecutive pairs' measured motions alone give: where the solve starts."""
    chain = [np.eye(4)]
    for motion in measured[edges[:, 1] - edges[:, 0] == 1]:
        chain.append(chain[-1] @ motion)
    return np.stack(chain)


def test_consistent_motions_give_back_the_poses_from_a_wrong_start() -> None:
    rng = np.random.default_rng(1)
    truth = _random_drive(rng, 7)
    edges = _edges(7, 3)
    start = np.stack([truth[0]] + [_perturbed(pose, rng, 0.05, 0.01) for pose in truth[1:]])
    solved = solve_pose_graph(start, edges, _relative(truth, edges))
    np.testing.assert_allclose(solved, truth, atol=1e-7)


def test_noisy_alignments_of_scans_further_apart_average_out() -> None:
    """The reason for the multi-scan reference: each pair's error is averaged with its neighbours'."""
    rng = np.random.default_rng(2)
    chained, solved = [], []
    for _ in range(20):
        truth = _random_drive(rng, 10)
        edges = _edges(10, 3)
        measured = np.stack([_perturbed(m, rng, 0.01, 0.0005) for m in _relative(truth, edges)])
        chain = _chain(edges, measured)
        chained.append(_delta_errors_m(chain, truth).mean())
        solved.append(_delta_errors_m(solve_pose_graph(chain, edges, measured), truth).mean())
    assert np.mean(solved) < 0.75 * np.mean(chained), (np.mean(solved), np.mean(chained))


def test_an_alignment_that_failed_outright_does_not_drag_the_others() -> None:
    rng = np.random.default_rng(3)
    truth = _random_drive(rng, 8)
    edges = _edges(8, 3)
    measured = _relative(truth, edges)
    failed = np.flatnonzero((edges[:, 0] == 2) & (edges[:, 1] == 5))[0]
    measured[failed, :3, 3] += [2.0, -1.0, 0.0]  # a GICP that converged on the wrong wall
    solved = solve_pose_graph(truth, edges, measured)
    assert _delta_errors_m(solved, truth).max() < 0.01


def test_a_long_drive_is_solved_to_the_end() -> None:
    """A drive of hundreds of scans (a user's own, in `benchmarks/real.py`): the solve ends where solving
    again from its answer moves nothing, every pair nearer the truth than the chain it started from."""
    rng = np.random.default_rng(4)
    count = 300
    truth = _random_drive(rng, count)
    edges = _edges(count, 3)
    measured = np.stack([_perturbed(m, rng, 0.01, 0.0005) for m in _relative(truth, edges)])
    failed = np.flatnonzero((edges[:, 0] == 150) & (edges[:, 1] == 152))[0]
    measured[failed, :3, 3] += [2.0, -1.0, 0.0]
    chain = _chain(edges, measured)
    solved = solve_pose_graph(chain, edges, measured)
    again = solve_pose_graph(solved, edges, measured)
    assert np.abs(again - solved).max() < 1e-6
    assert _delta_errors_m(solved, truth).mean() < 0.75 * _delta_errors_m(chain, truth).mean()


def test_edges_that_cannot_place_every_scan_are_refused() -> None:
    poses = np.tile(np.eye(4), (4, 1, 1))
    with pytest.raises(ValueError, match=r"scan\(s\) \[3\] not joined to the first"):
        solve_pose_graph(poses, [(0, 1), (1, 2)], poses[:2])
    with pytest.raises(ValueError, match=r"scan\(s\) \[2, 3\] not joined to the first"):
        solve_pose_graph(poses, [(0, 1), (2, 3)], poses[:2])  # every scan on an edge, two islands
    with pytest.raises(ValueError, match="two different scans"):
        solve_pose_graph(poses, [(0, 1), (1, 4), (2, 3)], poses[:3])
    with pytest.raises(ValueError, match="two different scans"):
        solve_pose_graph(poses, [(0, 1), (2, 2), (2, 3)], poses[:3])
    with pytest.raises(ValueError, match="3 edges but 2 motions"):
        solve_pose_graph(poses, [(0, 1), (1, 2), (2, 3)], poses[:2])


def test_the_multi_scan_consensus_lies_nearer_a_simulated_drives_truth(
    drive: Path, scans: list[np.ndarray], monkeypatch: pytest.MonkeyPatch
) -> None:
    pytest.importorskip("small_gicp")
    from dmlo.datasets import open_sequence

    monkeypatch.setattr(consensus, "GICPS", tuple(g for g in consensus.GICPS if g[0] == "small_gicp"))
    truth = open_sequence(drive).poses
    true_motions = np.linalg.inv(truth[:-1]) @ truth[1:]
    pairwise = consensus.gicp_consensus(scans, truth)
    multi = consensus.gicp_consensus(scans, truth, span=3)

    def error_cm(reference: consensus.ConsensusReference) -> float:
        return float(np.linalg.norm((np.linalg.inv(true_motions) @ reference.motions)[:, :3, 3], axis=1).mean() * 100)

    assert (pairwise.span, multi.span) == (1, 3)
    assert multi.consecutive_motions is not None  # small_gicp's threads may add in another order: not bit for bit
    np.testing.assert_allclose(multi.consecutive_motions, pairwise.motions, atol=1e-4)
    count = len(scans)
    assert len(multi.residual_m) == sum(min(count - 1, i + 3) - i for i in range(count - 1))
    assert error_cm(multi) < 0.5 * error_cm(pairwise), (error_cm(multi), error_cm(pairwise))
    with pytest.raises(ValueError, match="span must be an integer ≥ 1"):
        consensus.gicp_consensus(scans, truth, span=0)
