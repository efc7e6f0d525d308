"""The matching network against independent references: loops over windows, conv2d, known shifts."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

torch = pytest.importorskip("torch")
import torch.nn.functional as F  # noqa: E402

from dmlo.model import Matcher, MatcherConfig, coarse_ground_truth, matching_loss  # noqa: E402
from dmlo.model.correlation import block_window_correlation, clamp_origin, local_correlation, window_correlation  # noqa: E402
from dmlo.model.deform_conv import DeformConv2d, deform_conv2d_reference  # noqa: E402
from dmlo.model.loss import window_cross_entropy, window_target  # noqa: E402
from dmlo.model.matcher import upsample_coarse_flow  # noqa: E402
from dmlo.model.window import decode_window, peak_centroid  # noqa: E402

TINY = MatcherConfig(coarse_channels=8, refine_channels=4, refine_plain_layers=1, refine_deformable_layers=1)


def numpy_window_correlation(ref: np.ndarray, tgt: np.ndarray, origin: np.ndarray, window: int) -> np.ndarray:
    """Eq. 2 by loops: similarity of ref[:, i, j] with tgt at clamp((i, j) + origin) + (h, w), zero outside."""
    batch, _, height, width = ref.shape
    radius = window // 2
    out = np.zeros((batch, window * window, height, width))
    for b, i, j in itertools.product(range(batch), range(height), range(width)):
        ci = min(max(i + int(origin[b, 0, i, j]), 0), height - 1)
        cj = min(max(j + int(origin[b, 1, i, j]), 0), width - 1)
        for h, w in itertools.product(range(-radius, radius + 1), repeat=2):
            ti, tj = ci + h, cj + w
            if 0 <= ti < height and 0 <= tj < width:
                out[b, (h + radius) * window + w + radius, i, j] = ref[b, :, i, j] @ tgt[b, :, ti, tj]
    return out


def numpy_deform_conv(x: np.ndarray, offset: np.ndarray, weight: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """Deformable 3×3 convolution by loops with torchvision's bilinear rule (outside corners read zero)."""
    batch, channels, height, width = x.shape

    def sample(b: int, c: int, y: float, xx: float) -> float:
        y0, x0 = int(np.floor(y)), int(np.floor(xx))
        value = 0.0
        for yi, xi in ((y0, x0), (y0, x0 + 1), (y0 + 1, x0), (y0 + 1, x0 + 1)):
            if 0 <= yi < height and 0 <= xi < width:
                value += (1 - abs(y - yi)) * (1 - abs(xx - xi)) * x[b, c, yi, xi]
        return value

    out = np.zeros((batch, weight.shape[0], height, width))
    for b, i, j in itertools.product(range(batch), range(height), range(width)):
        columns = np.zeros((channels, 9))
        for k in range(9):
            y = i + k // 3 - 1 + offset[b, 2 * k, i, j]
            xx = j + k % 3 - 1 + offset[b, 2 * k + 1, i, j]
            for c in range(channels):
                columns[c, k] = sample(b, c, y, xx)
        out[b, :, i, j] = weight.reshape(weight.shape[0], -1) @ columns.reshape(-1) + bias
    return out


def synthetic_pair(height: int, width: int, shift: tuple[int, int], seed: int = 0) -> tuple:
    """A smooth random scene and the same scene moved by ``shift`` (rows, cols): flow = shift everywhere
    the moved cell stays in the image."""
    generator = torch.Generator().manual_seed(seed)
    margin = max(abs(shift[0]), abs(shift[1]), 1)
    noise = torch.rand(1, 2, (height + 2 * margin) // 3 + 2, (width + 2 * margin) // 3 + 2, generator=generator)
    scene = F.interpolate(noise, size=(height + 2 * margin, width + 2 * margin), mode="bilinear", align_corners=False)
    scene = scene * torch.tensor([60.0, 1.0]).view(1, 2, 1, 1) + torch.tensor([5.0, 0.0]).view(1, 2, 1, 1)
    ref = scene[:, :, margin : margin + height, margin : margin + width]
    top, left = margin - shift[0], margin - shift[1]
    tgt = scene[:, :, top : top + height, left : left + width]
    flow = torch.tensor(shift, dtype=torch.float32).view(1, 2, 1, 1).expand(1, 2, height, width).clone()
    rows = torch.arange(height).view(height, 1) + shift[0]
    cols = torch.arange(width).view(1, width) + shift[1]
    valid = ((rows >= 0) & (rows < height) & (cols >= 0) & (cols < width)).unsqueeze(0)
    return ref.contiguous(), tgt.contiguous(), flow, valid


def test_window_correlation_matches_loops_with_random_origins() -> None:
    generator = torch.Generator().manual_seed(1)
    ref = torch.randn(2, 3, 6, 7, generator=generator)
    tgt = torch.randn(2, 3, 6, 7, generator=generator)
    origin = torch.randint(-9, 10, (2, 2, 6, 7), generator=generator).float()
    clamped = clamp_origin(origin, 6, 7)
    got = window_correlation(ref, tgt, clamped, 5)
    want = numpy_window_correlation(ref.double().numpy(), tgt.double().numpy(), origin.numpy(), 5)
    np.testing.assert_allclose(got.numpy(), want, atol=1e-5)


def matcher_like_origin(batch: int, height: int, width: int, spread: float, generator: torch.Generator) -> torch.Tensor:
    """The matcher's unclamped refine origin: a random coarse flow of up to ``spread`` coarse cells,
    pointing out of the image along all four borders (by half a coarse cell at the corners, which clamps
    part of a block), upsampled by 4×8 and rounded."""
    size = (batch, 2, height // 4, width // 8)
    coarse = (torch.rand(size, generator=generator) * 2 - 1) * spread
    outward = torch.rand(size, generator=generator) * spread
    coarse[:, 0, 0], coarse[:, 0, -1] = -outward[:, 0, 0], outward[:, 0, -1]
    coarse[:, 1, :, 0], coarse[:, 1, :, -1] = -outward[:, 1, :, 0], outward[:, 1, :, -1]
    coarse[:, :, 0, 0], coarse[:, :, -1, -1] = -0.5, 0.5
    return torch.round(upsample_coarse_flow(coarse, (4, 8)))


@pytest.mark.parametrize(("height", "width", "window", "spread"), [(8, 32, 3, 3.0), (8, 32, 5, 6.0), (12, 48, 7, 4.0), (16, 40, 9, 9.0)])
def test_block_window_correlation_is_window_correlation_on_matcher_origins(height: int, width: int, window: int, spread: float) -> None:
    generator = torch.Generator().manual_seed(height * window)
    ref = torch.randn(2, 3, height, width, generator=generator)
    tgt = torch.randn(2, 3, height, width, generator=generator)
    origin = matcher_like_origin(2, height, width, spread, generator)
    clamped = clamp_origin(origin, height, width)
    for border in (0, -1):  # windows are clamped at all four borders
        assert (clamped[:, 0, border] != origin[:, 0, border]).any() and (clamped[:, 1, :, border] != origin[:, 1, :, border]).any()
    moved = (clamped != origin).any(dim=1).view(2, height // 4, 4, width // 8, 8)
    assert (moved.any(dim=(2, 4)) & ~moved.all(dim=(2, 4))).any(), "some block must be clamped only in part"
    got = block_window_correlation(ref, tgt, origin[:, :, ::4, ::8], (4, 8), window)
    torch.testing.assert_close(got, window_correlation(ref, tgt, clamped, window), atol=1e-5, rtol=1e-5)
    want = numpy_window_correlation(ref.double().numpy(), tgt.double().numpy(), origin.numpy(), window)
    np.testing.assert_allclose(got.numpy(), want, atol=1e-5)


def test_block_window_correlation_at_full_size() -> None:
    generator = torch.Generator().manual_seed(3)
    ref = F.normalize(torch.randn(1, 8, 64, 1792, generator=generator), dim=1)
    tgt = F.normalize(torch.randn(1, 8, 64, 1792, generator=generator), dim=1)
    origin = matcher_like_origin(1, 64, 1792, 7.0, generator)
    got = block_window_correlation(ref, tgt, origin[:, :, ::4, ::8], (4, 8), 7)
    torch.testing.assert_close(got, window_correlation(ref, tgt, clamp_origin(origin, 64, 1792), 7), atol=1e-5, rtol=1e-5)


def test_block_window_correlation_gradients_equal_window_correlation() -> None:
    generator = torch.Generator().manual_seed(4)
    origin = matcher_like_origin(2, 8, 32, 5.0, generator)
    weights = torch.randn(2, 25, 8, 32, generator=generator)  # a loss that weighs every window cell
    grads = []
    for correlate in (
        lambda ref, tgt: block_window_correlation(ref, tgt, origin[:, :, ::4, ::8], (4, 8), 5),
        lambda ref, tgt: window_correlation(ref, tgt, clamp_origin(origin, 8, 32), 5),
    ):
        ref = torch.randn(2, 3, 8, 32, generator=torch.Generator().manual_seed(5)).requires_grad_()
        tgt = torch.randn(2, 3, 8, 32, generator=torch.Generator().manual_seed(6)).requires_grad_()
        (correlate(ref, tgt) * weights).sum().backward()
        grads.append((ref.grad, tgt.grad))
    for got, want in zip(*grads):
        torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize(("shape", "message"), [((1, 2, 3, 8), "split into"), ((1, 2, 2, 3), "block_origin must have shape")])
def test_block_window_correlation_rejects_bad_shapes(shape: tuple[int, ...], message: str) -> None:
    features = torch.zeros(1, 3, 8, 16)
    if message == "split into":
        features = torch.zeros(1, 3, 6, 16)
    with pytest.raises(ValueError, match=message):
        block_window_correlation(features, features, torch.zeros(shape), (4, 8), 5)


@pytest.mark.parametrize(("height", "width", "window"), [(6, 7, 5), (4, 28, 11), (3, 2, 11), (5, 9, 3)])
def test_local_correlation_equals_window_correlation_at_origin_zero(height: int, width: int, window: int) -> None:
    generator = torch.Generator().manual_seed(height * width)
    ref = torch.randn(2, 4, height, width, generator=generator)
    tgt = torch.randn(2, 4, height, width, generator=generator)
    want = window_correlation(ref, tgt, torch.zeros(2, 2, height, width), window)
    torch.testing.assert_close(local_correlation(ref, tgt, window), want, atol=1e-5, rtol=1e-5)


def test_window_correlation_peaks_at_known_shift() -> None:
    features = F.normalize(torch.randn(1, 16, 12, 20, generator=torch.Generator().manual_seed(2)), dim=1)
    shift = (2, -3)  # target = reference moved by shift
    tgt = torch.roll(features, shifts=shift, dims=(2, 3))
    similarity = window_correlation(features, tgt, torch.zeros(1, 2, 12, 20), 7)
    best = similarity.argmax(dim=1)[0, 4:8, 5:15]
    assert (best == (shift[0] + 3) * 7 + shift[1] + 3).all()


def test_decode_window_recovers_subpixel_location_and_mass() -> None:
    window = 5
    for location in [(0.3, -1.7), (-2.0, 2.0), (1.5, 0.25), (-1.9, -1.9)]:
        target = window_target(torch.tensor(location).view(1, 2, 1, 1), window)
        assert bool(target.inside.all())
        probability = target.probability
        assert abs(float(probability.sum()) - 1) < 1e-6
        # A little mass elsewhere: the decoded offset uses only the winning window.
        logits = torch.log(0.9 * probability + 0.1 / window**2)
        decoded = decode_window(logits, window)
        np.testing.assert_allclose(decoded.offset.view(2).numpy(), location, atol=0.02)
        assert 0.9 < float(decoded.confidence) <= 1.0
    flat = decode_window(torch.zeros(1, 25, 1, 1), 5)
    np.testing.assert_allclose(float(flat.confidence), 4 / 25, rtol=1e-6)


def reference_decode_window(logits: torch.Tensor, window: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The straightforward decoding (four strided corner slices, channel-axis reductions): offset, Q*, sums."""
    batch, _, height, width = logits.shape
    radius = window // 2
    weights = torch.exp(logits - logits.amax(dim=1, keepdim=True)).view(batch, window, window, height, width)
    total = weights.sum(dim=(1, 2))
    top_left = weights[:, :-1, :-1].reshape(batch, -1, height, width)
    top_right = weights[:, :-1, 1:].reshape(batch, -1, height, width)
    bottom_left = weights[:, 1:, :-1].reshape(batch, -1, height, width)
    bottom_right = weights[:, 1:, 1:].reshape(batch, -1, height, width)
    sums = top_left + top_right + bottom_left + bottom_right
    best = sums.argmax(dim=1, keepdim=True)

    def pick(values: torch.Tensor) -> torch.Tensor:
        return values.gather(1, best).squeeze(1)

    best_sum = pick(sums)
    best_row = torch.div(best.squeeze(1), window - 1, rounding_mode="floor")
    best_col = best.squeeze(1) - best_row * (window - 1)
    row = best_row + (pick(bottom_left) + pick(bottom_right)) / best_sum - radius
    col = best_col + (pick(top_right) + pick(bottom_right)) / best_sum - radius
    return torch.stack((row, col), dim=1), best_sum / total, sums


@pytest.mark.parametrize("window", [2, 3, 5, 7, 9, 11, 13])  # both ways to the sums (MatMul up to 9, adds above)
def test_decode_window_equals_the_straightforward_decoding_ties_and_gradients_included(window: int) -> None:
    generator = torch.Generator().manual_seed(window)
    shape = (2, window * window, 5, 7)
    random = torch.randn(shape, generator=generator) * 3
    # Exact ties: every cell 1 or 0 after exp, so window sums are small integers and many windows tie; the
    # first maximum (lowest channel) must win, as in the reference. The all-equal cell ties every window.
    ties = torch.where(torch.rand(shape, generator=generator) < 0.5, 0.0, -1e4)
    ties[0, :, 0, 0] = 0.0
    for logits in (random, ties, random.double(), random.to(memory_format=torch.channels_last)):
        got = decode_window(logits, window)
        want = reference_decode_window(logits, window)
        torch.testing.assert_close(got.offset, want[0])
        torch.testing.assert_close(got.confidence, want[1])
        torch.testing.assert_close(got.window_sums, want[2])
        assert got.offset.shape == (2, 2, 5, 7) and got.confidence.shape == (2, 5, 7)
    # Cell by cell: the winner among tied windows is the first maximal one (row-major), and ties are common.
    offset = decode_window(ties, window).offset.numpy()
    cells = (ties - ties.amax(dim=1, keepdim=True)).exp().numpy().reshape(2, window, window, 5, 7)
    tied = 0
    for b, i, j in itertools.product(range(2), range(5), range(7)):
        weights = cells[b, :, :, i, j]
        sums = [weights[r : r + 2, c : c + 2].sum() for r in range(window - 1) for c in range(window - 1)]
        tied += sums.count(max(sums)) > 1
        row, col = divmod(sums.index(max(sums)), window - 1)
        best = weights[row : row + 2, col : col + 2]
        expected = [row + best[1].sum() / best.sum() - window // 2, col + best[:, 1].sum() / best.sum() - window // 2]
        np.testing.assert_allclose(offset[:, :, i, j][b], expected, atol=1e-6)
    assert tied > 20 or window == 2  # one window only at D = 2
    # Same gradients through all three outputs (float64: no rounding noise to tolerate).
    logits = random.double().requires_grad_()
    grads = [torch.randn(t.shape, generator=generator, dtype=torch.float64) for t in reference_decode_window(logits, window)]
    got = torch.autograd.grad(tuple(decode_window(logits, window)), logits, grads)[0]
    want = torch.autograd.grad(reference_decode_window(logits, window), logits, grads)[0]
    torch.testing.assert_close(got, want)


def numpy_peak_centroid(logits: np.ndarray, window: int) -> np.ndarray:
    """The 3×3 centroid around the most likely cell, cell by cell (the peak moved inside at the edge)."""
    batch, _, height, width = logits.shape
    out = np.zeros((batch, 2, height, width))
    for b, i, j in itertools.product(range(batch), range(height), range(width)):
        weights = np.exp(logits[b, :, i, j] - logits[b, :, i, j].max()).reshape(window, window)
        row, col = divmod(int(np.argmax(logits[b, :, i, j])), window)
        row, col = min(max(row, 1), window - 2), min(max(col, 1), window - 2)
        patch = weights[row - 1 : row + 2, col - 1 : col + 2]
        grid_rows, grid_cols = np.mgrid[row - 1 : row + 2, col - 1 : col + 2]
        out[b, :, i, j] = [(patch * grid_rows).sum() / patch.sum() - window // 2, (patch * grid_cols).sum() / patch.sum() - window // 2]
    return out


def test_peak_centroid_matches_loops_and_removes_the_pull_towards_cell_borders() -> None:
    rng = np.random.default_rng(4)
    logits = rng.normal(0, 2, (2, 25, 3, 4)).astype(np.float32)
    logits[0, 0, 0, 0] = 9.0  # the peak in a corner: the 3×3 moves inside
    got = peak_centroid(torch.from_numpy(logits), 5).numpy()
    np.testing.assert_allclose(got, numpy_peak_centroid(logits, 5), atol=1e-5)
    # A match 0.1 px from a cell centre, its mass spread symmetrically over the neighbours (as the network
    # does): the paper's best 2×2 window decodes it at 0.375, towards the border; the 3×3 centroid at 0.1.
    centre, spread = 0.1, np.array([0.2, 0.6, 0.2])
    row_mass = np.zeros(5)
    row_mass[1:4] = spread
    row_mass[2] -= centre
    row_mass[3] += centre
    mass = np.outer(row_mass, np.eye(5)[2])  # all in the centre column
    logits = torch.log(torch.from_numpy(mass + 1e-9).float()).view(1, 25, 1, 1)
    paper = decode_window(logits, 5).offset.view(2).numpy()
    ours = peak_centroid(logits, 5).view(2).numpy()
    assert abs(paper[0] - centre) > 0.1
    np.testing.assert_allclose(ours, [centre, 0.0], atol=1e-3)


def test_matcher_config_chooses_the_refine_offset() -> None:
    with pytest.raises(ValueError, match="refine_offset"):
        MatcherConfig(refine_offset="parabola")
    torch.manual_seed(0)
    assert TINY.refine_offset == "window"  # the paper's Eq. 11 by default
    ours = Matcher(MatcherConfig(**dict(TINY.to_dict(), refine_offset="peak_centroid"))).eval()
    paper = Matcher(TINY).eval()
    paper.load_state_dict(ours.state_dict())
    scans = torch.rand(2, 2, 2, 16, 64)
    with torch.no_grad():
        a, b = ours(scans[0], scans[1]), paper(scans[0], scans[1])
    torch.testing.assert_close(a.confidence, b.confidence)  # Q* is the 2×2 mass either way
    expected = a.refine_origin + peak_centroid(a.refine_logits, TINY.refine_window)
    torch.testing.assert_close(a.flow, expected)
    torch.testing.assert_close(b.flow, b.refine_origin + decode_window(b.refine_logits, TINY.refine_window).offset)


def test_window_target_expectation_outside_and_one_hot() -> None:
    window = 5
    offsets = torch.tensor([[0.3, 2.6], [-1.25, 0.75]]).T.reshape(1, 2, 1, 2)
    target = window_target(offsets, window)
    assert target.inside.tolist() == [[[False, True]]]
    cells = torch.arange(window * window)
    rows, cols = (cells // window - 2).float(), (cells % window - 2).float()
    p = target.probability[0, :, 0, 1]
    assert abs(float((p * rows).sum()) + 1.25) < 1e-6 and abs(float((p * cols).sum()) - 0.75) < 1e-6
    assert float(target.probability[0, :, 0, 0].sum()) == 0
    one_hot = window_target(offsets, window, subpixel=False).probability[0, :, 0, 1]
    assert float(one_hot.max()) == 1 and int(one_hot.argmax()) == (-1 + 2) * window + 1 + 2


def test_cross_entropy_is_lowest_at_the_truth_and_ignores_invalid() -> None:
    gt = torch.tensor([0.4, -0.6]).view(1, 2, 1, 1)
    target = window_target(gt, 5).probability
    right = torch.log(target + 1e-9)
    wrong = torch.roll(right, 7, dims=1)
    valid = torch.ones(1, 1, 1, dtype=torch.bool)
    loss_right, cells = window_cross_entropy(right, gt, valid, 5)
    loss_wrong, _ = window_cross_entropy(wrong, gt, valid, 5)
    assert int(cells) == 1 and float(loss_right) < float(loss_wrong)
    loss_none, cells_none = window_cross_entropy(wrong, gt, ~valid, 5)
    assert int(cells_none) == 0 and float(loss_none) == 0


def test_deform_conv_zero_offset_is_conv2d_and_matches_loops() -> None:
    generator = torch.Generator().manual_seed(3)
    x = torch.randn(2, 3, 5, 6, generator=generator)
    weight = torch.randn(4, 3, 3, 3, generator=generator)
    bias = torch.randn(4, generator=generator)
    zero = deform_conv2d_reference(x, torch.zeros(2, 18, 5, 6), weight, bias)
    torch.testing.assert_close(zero, F.conv2d(x, weight, bias, padding=1), atol=1e-5, rtol=1e-5)
    offset = 2.5 * torch.randn(2, 18, 5, 6, generator=generator)
    got = deform_conv2d_reference(x, offset, weight, bias)
    want = numpy_deform_conv(*(t.double().numpy() for t in (x, offset, weight, bias)))
    np.testing.assert_allclose(got.numpy(), want, atol=1e-4)
    layer = DeformConv2d(3, 4)
    torch.testing.assert_close(layer(x), F.conv2d(x, layer.weight, layer.bias, padding=1), atol=1e-5, rtol=1e-5)


def test_upsample_and_coarse_ground_truth_are_inverse_on_constant_flow() -> None:
    coarse = torch.tensor([1.25, -0.5]).view(1, 2, 1, 1).expand(1, 2, 2, 3)
    full = upsample_coarse_flow(coarse, (4, 8))
    assert full.shape == (1, 2, 8, 24)
    assert float(full[0, 0].unique()) == 5.0 and float(full[0, 1].unique()) == -4.0
    valid = torch.ones(1, 8, 24, dtype=torch.bool)
    valid[:, :4, :8] = False  # one whole coarse cell without ground truth
    back, back_valid = coarse_ground_truth(full, valid, (4, 8))
    torch.testing.assert_close(back[:, :, back_valid[0]], coarse[:, :, back_valid[0]])
    assert back_valid.sum() == 5 and not bool(back_valid[0, 0, 0])


def test_matcher_shapes_and_gradients() -> None:
    torch.manual_seed(0)
    model = Matcher(TINY)
    ref, tgt, flow, valid = synthetic_pair(16, 64, (1, 5))
    out = model(ref, tgt)
    assert out.flow.shape == (1, 2, 16, 64) and out.confidence.shape == (1, 16, 64)
    assert out.coarse_logits.shape == (1, 121, 4, 8) and out.refine_logits.shape == (1, 25, 16, 64)
    assert bool(((out.confidence > 0) & (out.confidence <= 1)).all()) and bool(torch.isfinite(out.flow).all())
    loss, metrics = matching_loss(out, flow, valid, TINY)
    loss.backward()
    gradients = [p.grad for p in model.parameters() if p.requires_grad]
    assert all(g is not None and bool(torch.isfinite(g).all()) for g in gradients)
    # The loss reaches every layer, and its gradient descends: a few steps on this pair lower its loss and
    # bring the predicted flow closer to the shift.
    assert all(bool(g.abs().sum() > 0) for g in gradients if g is not None)
    assert metrics["loss"] > 0

    def epe(prediction: torch.Tensor) -> float:
        return float(torch.linalg.vector_norm(prediction - flow, dim=1)[valid].mean())

    first_epe = epe(out.flow.detach())
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-2)
    for _ in range(20):
        optimizer.zero_grad()
        trained = model(ref, tgt)
        trained_loss, _ = matching_loss(trained, flow, valid, TINY)
        trained_loss.backward()
        optimizer.step()
    assert float(trained_loss.detach()) < 0.8 * float(loss.detach())
    assert epe(trained.flow.detach()) < first_epe


@pytest.mark.parametrize(
    ("shape", "message"),
    [((1, 3, 16, 64), r"\(B, 2, H, W\)"), ((1, 2, 15, 64), "divisible"), ((1, 2, 16, 60), "divisible")],
)
def test_matcher_rejects_bad_scans(shape: tuple[int, ...], message: str) -> None:
    model = Matcher(TINY)
    with pytest.raises(ValueError, match=message):
        model(torch.zeros(shape), torch.zeros(shape))


def test_config_round_trip_and_validation(tmp_path) -> None:
    path = tmp_path / "model.json"
    TINY.save(path)
    assert MatcherConfig.load(path) == TINY
    with pytest.raises(ValueError, match="coarse_window"):
        MatcherConfig(coarse_window=10)
    with pytest.raises(ValueError, match="unknown MatcherConfig fields"):
        MatcherConfig.from_dict({"nope": 1})
    with pytest.raises(ValueError, match="preset"):
        MatcherConfig.preset("huge")
    assert MatcherConfig.preset("fast").refine_deformable_layers == 0


@pytest.mark.slow
def test_training_learns_synthetic_shifts() -> None:
    """A few dozen SGD steps on random scenes with known shifts bring the flow error well down."""
    torch.manual_seed(0)
    config = MatcherConfig(coarse_channels=16, refine_channels=8, refine_plain_layers=2, refine_deformable_layers=1)
    model = Matcher(config)
    optimiser = torch.optim.Adam(model.parameters(), lr=3e-3)
    rng = np.random.default_rng(0)

    def batch(seed: int) -> tuple:
        pairs = [synthetic_pair(16, 64, (int(rng.integers(-6, 7)), int(rng.integers(-16, 17))), seed * 4 + k) for k in range(4)]
        return tuple(torch.cat(items) for items in zip(*pairs, strict=True))

    def epe(seed: int) -> float:
        model.eval()
        with torch.no_grad():
            ref, tgt, flow, valid = batch(seed)
            error = (model(ref, tgt).flow - flow).norm(dim=1)
        model.train()
        return float(error[valid].mean())

    before = epe(1000)
    for step in range(60):
        ref, tgt, flow, valid = batch(step)
        loss, _ = matching_loss(model(ref, tgt), flow, valid, config)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    after = epe(1000)
    assert after < 0.3 * before, (before, after)
