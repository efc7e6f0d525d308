"""Confidence loss: binary cross entropy of Q* against "the match is within 1 px", checked against a numpy
reference, its gradients, and its place in a training step."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from dmlo.model.confidence_loss import _EPSILON, confidence_loss, confidence_target  # noqa: E402
from dmlo.train import TrainConfig, Trainer  # noqa: E402
from dmlo.train.dataset import collate  # noqa: E402

from test_train import TINY, tiny_data, tiny_run  # noqa: E402


def reference_loss(confidence, flow, gt, valid, inlier_px=1.0) -> float:
    """The loss written out cell by cell in numpy."""
    total, cells = 0.0, 0
    for b, row, col in np.ndindex(*valid.shape):
        if not valid[b, row, col] or not np.isfinite(gt[b, :, row, col]).all():
            continue
        right = np.hypot(*(flow[b, :, row, col] - gt[b, :, row, col])) < inlier_px
        p = _EPSILON + (1 - 2 * _EPSILON) * float(confidence[b, row, col])
        total += -np.log(p) if right else -np.log(1 - p)
        cells += 1
    return total / max(cells, 1)


def random_case(seed: int = 0):
    rng = np.random.default_rng(seed)
    shape = (2, 5, 7)
    gt = rng.normal(0, 3, (2, 2, 5, 7)).astype(np.float32)
    flow = (gt + rng.normal(0, 1.2, gt.shape)).astype(np.float32)
    gt[0, :, 1, 2] = np.nan  # no ground truth there: must not count even where marked valid
    confidence = rng.uniform(0, 1, shape).astype(np.float32)
    confidence[1, 0, :3] = (0.0, 1.0, 1.0)  # the extremes a float32 softmax ratio reaches
    valid = rng.uniform(size=shape) < 0.8
    return confidence, flow, gt, valid


def test_loss_matches_the_numpy_reference() -> None:
    confidence, flow, gt, valid = random_case()
    target, counted = confidence_target(torch.from_numpy(flow), torch.from_numpy(gt), torch.from_numpy(valid))
    assert 0 < target.sum() < counted.sum()  # both classes present
    assert not counted[0, 1, 2]
    loss = confidence_loss(*(torch.from_numpy(a) for a in (confidence, flow, gt, valid)))
    assert float(loss) == pytest.approx(reference_loss(confidence, flow, gt, valid), rel=1e-5)
    wider = confidence_loss(*(torch.from_numpy(a) for a in (confidence, flow, gt, valid)), inlier_px=2.5)
    assert float(wider) == pytest.approx(reference_loss(confidence, flow, gt, valid, 2.5), rel=1e-5)


def test_gradient_lowers_confidently_wrong_and_raises_right_cells_but_leaves_the_flow() -> None:
    gt = torch.zeros(1, 2, 1, 3)
    flow = torch.tensor([[[[0.2, 5.0, 0.1]], [[0.1, 0.0, 0.3]]]], requires_grad=True)
    confidence = torch.tensor([[[0.6, 1.0, 1.0]]], requires_grad=True)  # right, wrong at Q* = 1, right at Q* = 1
    confidence_loss(confidence, flow, gt, torch.ones(1, 1, 3, dtype=torch.bool)).backward()
    grad = confidence.grad[0, 0]
    assert grad[0] < 0 and grad[2] < 0  # descent raises the right cells' confidence
    assert grad[1] > 0  # and lowers the wrong one's, even at Q* = 1 where a clamp would have no gradient
    assert abs(grad[1]) > 100 * abs(grad[2])  # confidently wrong costs far more than confidently right gains
    assert flow.grad is None  # the target is a fixed label: the loss does not move the matches


def test_no_counted_cell_gives_a_zero_loss_in_the_graph() -> None:
    confidence = torch.full((1, 2, 2), 0.5, requires_grad=True)
    loss = confidence_loss(confidence, torch.zeros(1, 2, 2, 2), torch.zeros(1, 2, 2, 2), torch.zeros(1, 2, 2, dtype=torch.bool))
    loss.backward()
    assert float(loss.detach()) == 0 and torch.equal(confidence.grad, torch.zeros_like(confidence))


def test_mismatched_shapes_are_named() -> None:
    with pytest.raises(ValueError, match="same"):
        confidence_loss(torch.ones(1, 2, 3), torch.zeros(1, 2, 2, 3), torch.zeros(1, 2, 2, 3), torch.ones(1, 3, 2, dtype=torch.bool))


def test_training_step_adds_the_weighted_confidence_loss(tmp_path) -> None:
    data = tiny_data()
    batch = collate([data[0], data[1]])
    plain = Trainer(TINY, tiny_run(tmp_path / "plain"), tiny_data(), progress=False)
    weighted = Trainer(TINY, tiny_run(tmp_path / "weighted", confidence_loss_weight=0.7), tiny_data(), progress=False)
    without, _ = plain.train_step(batch)
    with_, _ = weighted.train_step(batch)
    assert "confidence_loss" not in without and with_["confidence_loss"] > 0
    # Same seed, same weights before the step: the losses differ by exactly the weighted term.
    assert with_["loss"] == pytest.approx(without["loss"] + 0.7 * with_["confidence_loss"], rel=1e-5)


def test_config_rejects_a_negative_weight() -> None:
    with pytest.raises(ValueError, match="confidence_loss_weight"):
        TrainConfig(confidence_loss_weight=-0.1)
