"""Pose loss: the ground-truth flow's pose Jacobian against an analytic numpy derivative, the motion error it
recovers from a flow, and fine-tuning with it."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

torch = pytest.importorskip("torch")
import dmlo_rs  # noqa: E402

from dmlo.cli import main as dmlo_main  # noqa: E402
from dmlo.model.pose_loss import pose_error, pose_loss  # noqa: E402
from dmlo.train import ArrayPairDataset, Augmentation, TrainConfig, Trainer  # noqa: E402
from dmlo.train.checkpoint import load  # noqa: E402
from dmlo.train.dataset import RustGeometry, crop, flow_pose_jacobian, mirror_columns, roll_columns  # noqa: E402

from test_core_projection import reference_locate, reference_unproject, static_scans, yaw_pitch_roll  # noqa: E402, F401
from test_train import TINY, sample, tiny_run  # noqa: E402

MOTION = yaw_pitch_roll(np.radians(2.0), np.radians(0.4), np.radians(-0.3), (1.1, -0.2, 0.04))


def perturbation(xi: np.ndarray) -> np.ndarray:
    """exp(ξ) for ξ = (ω mrad, t mm), the convention of `flow_pose_jacobian`."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.asarray(xi[:3]) * 1e-3).as_matrix()
    T[:3, 3] = np.asarray(xi[3:]) * 1e-3
    return T


@pytest.fixture(scope="module")
def moved_pair(static_scans):  # noqa: F811
    """A real scan, its copy moved by MOTION, their ground truth and its pose Jacobian."""
    geometry = RustGeometry()
    scan = static_scans[0]
    moved = scan.copy()
    moved[:, :3] = (scan[:, :3].astype(np.float64) @ MOTION[:3, :3].T + MOTION[:3, 3]).astype(np.float32)
    ref_range, _ = geometry.project(scan)
    tgt_range, _ = geometry.project(moved)
    flow, valid = geometry.ground_truth(ref_range, tgt_range, MOTION)
    jacobian = flow_pose_jacobian(geometry, ref_range, tgt_range, MOTION)
    return {"geometry": geometry, "ref_range": ref_range, "tgt_range": tgt_range, "flow": flow, "valid": valid,
            "jacobian": jacobian}


def analytic_jacobian(ref_range: np.ndarray, rows: np.ndarray, cols: np.ndarray, config) -> np.ndarray:
    """d(row, col)/dξ of the moved virtual points by the chain rule: (N, 6, 2) pixels per (mrad, mm)."""
    p = reference_unproject(rows.astype(float), cols.astype(float), ref_range[rows, cols].astype(float), config)
    q = p @ MOTION[:3, :3].T + MOTION[:3, 3]
    x, y, z = q.T
    horizontal2 = x * x + y * y
    horizontal, range2 = np.sqrt(horizontal2), horizontal2 + z * z
    d_elevation = np.stack([-x * z / (range2 * horizontal), -y * z / (range2 * horizontal), horizontal / range2], 1)
    d_azimuth = np.stack([-y / horizontal2, x / horizontal2, np.zeros_like(x)], 1)
    rows_per_radian = 1.0 / np.radians(config.vertical_resolution_deg)
    cols_per_radian = 1.0 / np.radians(config.horizontal_resolution_deg)
    d_pixel = np.stack([-d_elevation * rows_per_radian, -d_azimuth * cols_per_radian], 1)  # (N, 2, 3) per metre
    skew = np.zeros((len(q), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -z, y, -x
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = z, -y, x
    d_point = np.concatenate([-skew, np.broadcast_to(np.eye(3), skew.shape)], 2) * 1e-3  # (N, 3, 6) per unit
    return np.einsum("nij,njk->nki", d_pixel, d_point)


def test_pose_jacobian_equals_the_analytic_derivative(moved_pair) -> None:
    config = dmlo_rs.CylinderConfig.kitti()
    jacobian = moved_pair["jacobian"]
    assert jacobian.shape == (6, 2, 64, 1792) and jacobian.dtype == np.float32
    defined = np.isfinite(jacobian).all(axis=(0, 1))
    assert not (defined & ~moved_pair["valid"]).any()
    assert defined.sum() > 0.95 * moved_pair["valid"].sum()
    rows, cols = np.nonzero(defined)
    reference = analytic_jacobian(moved_pair["ref_range"], rows, cols, config)
    ours = np.moveaxis(jacobian[:, :, rows, cols], 2, 0)
    # Forward differences over 1 mrad / 1 mm: the flow's curvature leaves ~1e-3 of the derivative.
    np.testing.assert_allclose(ours, reference, rtol=2e-2, atol=2e-3)
    # A yaw turns every column alike: −(1 mrad in °)/resolution columns per mrad, whatever the range.
    np.testing.assert_allclose(ours[:, 2, 1], -np.degrees(1e-3) / config.horizontal_resolution_deg, rtol=1e-3)


def as_batch(flow: np.ndarray, gt_flow: np.ndarray, valid: np.ndarray, jacobian: np.ndarray, confidence=None):
    tensors = [torch.from_numpy(np.ascontiguousarray(a))[None] for a in (flow, gt_flow, valid, jacobian)]
    flow_t, gt_t, valid_t, jacobian_t = tensors
    confidence_t = torch.ones_like(valid_t, dtype=torch.float32) if confidence is None else torch.from_numpy(confidence)[None]
    return flow_t, confidence_t, gt_t, valid_t, jacobian_t


def test_pose_error_recovers_a_motion_error_through_every_augmentation(moved_pair) -> None:
    """A flow that is the ground truth of a slightly wrong motion exp(ξ)·T gives back ξ."""
    xi = np.array([0.8, -0.5, 1.2, 6.0, -4.0, 3.0])
    wrong, wrong_valid = moved_pair["geometry"].ground_truth(
        moved_pair["ref_range"], moved_pair["tgt_range"], perturbation(xi) @ MOTION
    )
    full = {"ref": moved_pair["ref_range"][None], "tgt": moved_pair["tgt_range"][None], "flow": moved_pair["flow"],
            "valid": moved_pair["valid"] & wrong_valid, "pose_jacobian": moved_pair["jacobian"], "predicted": wrong}
    mirrored = mirror_columns(roll_columns(dict(full), 700))
    mirrored["predicted"][1] *= -1  # the prediction is a flow too
    samples = {"full": full, "rolled, mirrored": mirrored, "rolled, mirrored, cropped": crop(dict(mirrored), 0, 200, 64, 448)}
    for name, s in samples.items():
        error, defined = pose_error(*as_batch(s["predicted"], s["flow"], s["valid"], s["pose_jacobian"]), damping=0.0)
        assert bool(defined[0]), name
        np.testing.assert_allclose(error[0].numpy(), xi, rtol=0.02, atol=0.02, err_msg=name)


def test_pose_loss_drops_outliers_and_undefined_samples(moved_pair) -> None:
    rng = np.random.default_rng(0)
    gt, valid, jacobian = moved_pair["flow"], moved_pair["valid"], moved_pair["jacobian"]
    noisy = gt + rng.normal(0, 0.3, gt.shape).astype(np.float32)
    base, _ = pose_error(*as_batch(noisy, gt, valid, jacobian))
    # Cells 10 px off are no matches (RANSAC drops them at run time): they leave the error unchanged.
    outliers = noisy.copy()
    outliers[:, :, ::7] += 10.0
    kept = valid.copy()
    kept[:, ::7] = False
    with_outliers, _ = pose_error(*as_batch(outliers, gt, valid, jacobian))
    without, _ = pose_error(*as_batch(noisy, gt, kept, jacobian))
    torch.testing.assert_close(with_outliers, without)
    assert float(base.norm()) < 0.5  # independent noise mostly averages out

    # A batch whose second sample has no usable cell: loss and gradients come from the first alone.
    flow = torch.from_numpy(np.stack([noisy, noisy])).requires_grad_()
    confidence = torch.full((2, *valid.shape), 0.7, requires_grad=True)
    no_cells = torch.from_numpy(np.stack([valid, np.zeros_like(valid)]))
    loss, errors = pose_loss(flow, confidence, torch.from_numpy(np.stack([gt, gt])), no_cells,
                             torch.from_numpy(np.stack([jacobian, jacobian])))
    loss.backward()
    assert torch.isfinite(flow.grad).all()
    assert confidence.grad is None  # the weights are held fixed: the pose loss trains the flow alone
    assert flow.grad[0].abs().sum() > 0 and flow.grad[1].abs().sum() == 0
    assert torch.isfinite(errors[0]).all() and torch.isnan(errors[1]).all()
    single, _ = pose_loss(*as_batch(noisy, gt, valid, jacobian, np.full(valid.shape, 0.7, np.float32)))
    torch.testing.assert_close(loss, single)


def with_jacobian(s: dict[str, np.ndarray], seed: int) -> dict[str, np.ndarray]:
    height, width = s["valid"].shape
    s["pose_jacobian"] = np.random.default_rng(seed).normal(0, 1, (6, 2, height, width)).astype(np.float32)
    return s


def pose_data() -> ArrayPairDataset:
    shifts = [(1, 3), (-2, 5), (0, -6), (3, 1)]
    samples = [with_jacobian(sample(s, seed=k, width=96), k) for k, s in enumerate(shifts)]
    return ArrayPairDataset(samples, Augmentation(None, 64, mirror=True))


def test_fine_tuning_starts_from_init_and_keeps_the_best_pose(tmp_path) -> None:
    Trainer(TINY, tiny_run(tmp_path / "base", max_steps=1), pose_data(), progress=False).run()
    start = load(tmp_path / "base" / "last.pt")["model"]
    other = dict(TINY.to_dict(), coarse_channels=4)  # --init brings its own model config
    config = tiny_run(tmp_path / "tuned", epochs=2, init=str(tmp_path / "base" / "last.pt"), pose_loss_weight=0.5)
    tuned = Trainer(type(TINY).from_dict(other), config, pose_data(), val_set=pose_data(), progress=False)
    assert tuned.model_config == TINY
    for name, value in tuned.model.state_dict().items():
        torch.testing.assert_close(value, start[name], rtol=0, atol=0, msg=name)
    tuned.run()
    rows = [json.loads(line) for line in (tmp_path / "tuned" / "log.jsonl").read_text().splitlines()]
    assert all(np.isfinite(r["val_rotation_mrad"]) and np.isfinite(r["val_translation_mm"]) for r in rows)
    best = load(tmp_path / "tuned" / "best.pt")
    assert best["best_metric"] == min(r["val_rotation_mrad"] for r in rows)


def test_command_line_rejects_a_missing_init(tmp_path, capsys) -> None:
    data = tmp_path / "data"
    data.mkdir()
    code = dmlo_main(["train", "--data", str(data), "--out", str(tmp_path / "run"), "--init", str(tmp_path / "no.pt")])
    assert code == 2
    assert "--init checkpoint not found" in capsys.readouterr().err


def test_config_rejects_a_negative_pose_weight() -> None:
    with pytest.raises(ValueError, match="pose_loss_weight"):
        TrainConfig(pose_loss_weight=-1.0)
