"""The crate's matching stage (`dmlo_rs.match_features`) against the PyTorch matcher (float64), the
exported match graph on real KITTI scans, and bad input; and the run-time matcher's choice of stage."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
ort = pytest.importorskip("onnxruntime")
onnx = pytest.importorskip("onnx")

import dmlo_rs  # noqa: E402
from dmlo.export import export_onnx, similarity_scales  # noqa: E402
from dmlo.model import Matcher, MatcherConfig  # noqa: E402
from dmlo.odometry.matcher import FrameMatcherAdapter, ModelError, OnnxMatcher, default_model_path  # noqa: E402

from test_export import HEIGHT, WIDTH, calibrated_matcher, tied_cells  # noqa: E402
from test_model import synthetic_pair  # noqa: E402


def crate_match(model: Matcher, ref, tgt, **overrides):  # type: ignore[no-untyped-def]
    scales = similarity_scales(model)
    config = model.config
    settings = dict(
        coarse_window=config.coarse_window,
        refine_window=config.refine_window,
        coarse_scale=scales["coarse"],
        refine_scale=scales["refine"],
        refine_offset=config.refine_offset,
    )
    settings.update(overrides)
    return dmlo_rs.match_features(ref.coarse.numpy(), ref.refine.numpy(), tgt.coarse.numpy(), tgt.refine.numpy(), **settings)


@pytest.fixture(scope="module")
def weights() -> dict:
    return calibrated_matcher(MatcherConfig(refine_channels=8)).state_dict()


@pytest.mark.parametrize(
    ("coarse_window", "refine_window", "refine_offset", "shift"),
    [(11, 5, "window", (3, -11)), (11, 5, "peak_centroid", (-2, 17)), (21, 7, "window", (6, 60))],
)
def test_crate_reproduces_the_pytorch_matcher(weights, coarse_window, refine_window, refine_offset, shift) -> None:
    config = MatcherConfig(
        refine_channels=8, coarse_window=coarse_window, refine_window=refine_window, refine_offset=refine_offset
    )
    model = Matcher(config)
    model.load_state_dict(weights)
    model.eval()
    reference = Matcher(config)
    reference.load_state_dict(weights)
    reference = reference.double().eval()
    ref, tgt, _, _ = synthetic_pair(HEIGHT, WIDTH, shift, seed=12)
    with torch.no_grad():
        ref_features, tgt_features = model.encode(ref), model.encode(tgt)
        want = reference.match(
            type(ref_features)(ref_features.coarse.double(), ref_features.refine.double()),
            type(tgt_features)(tgt_features.coarse.double(), tgt_features.refine.double()),
        )
    flow, confidence = crate_match(model, ref_features, tgt_features)
    assert flow.shape == (2, HEIGHT, WIDTH) and confidence.shape == (HEIGHT, WIDTH)
    assert flow.dtype == np.float32 and confidence.dtype == np.float32
    ties = tied_cells(want, config)[0].numpy()
    assert ties.mean() < 0.05
    keep = ~ties
    flow_error = np.abs(flow - want.flow[0].numpy()).max(axis=0)
    confidence_error = np.abs(confidence - want.confidence[0].numpy())
    assert flow_error[keep].max() < 1e-3
    assert np.quantile(confidence_error[keep], 0.999) < 1e-4
    assert confidence_error[keep].max() < 3e-4
    # Not a flat answer: the kept cells hold many different matches, most of them the scene's shift.
    assert np.unique(np.round(flow[:, keep].T, 1), axis=0).shape[0] > 20


def test_thread_count_does_not_change_the_answer(weights) -> None:
    model = Matcher(MatcherConfig(refine_channels=8))
    model.load_state_dict(weights)
    ref, tgt, _, _ = synthetic_pair(HEIGHT, WIDTH, (1, 5), seed=13)
    with torch.no_grad():
        ref_features, tgt_features = model.eval().encode(ref), model.encode(tgt)
    one = crate_match(model, ref_features, tgt_features, num_threads=1)
    two = crate_match(model, ref_features, tgt_features, num_threads=2)
    for a, b in zip(one, two):
        np.testing.assert_array_equal(a, b)


def kitti_images(shared_data: Path, matcher: OnnxMatcher) -> list[np.ndarray]:
    """Two real KITTI scans five frames apart as the model's input images."""
    folder = shared_data / "kitti_raw_static"
    if not folder.is_dir():
        pytest.skip(f"{folder} is absent")
    images = []
    for index in (0, 5):
        points = np.fromfile(folder / f"{index:010d}.bin", dtype=np.float32).reshape(-1, 4)
        projection = dmlo_rs.project(points, matcher.cylinder)
        images.append(np.stack([projection.range, projection.reflectance]))
    return images


def test_crate_agrees_with_the_bundled_match_graph_on_kitti_scans(shared_data: Path) -> None:
    graph = OnnxMatcher(default_model_path(), threads=2, matching_stage="graph")
    crate = OnnxMatcher(default_model_path(), threads=2, matching_stage="crate")
    assert (graph.matching_stage, crate.matching_stage) == ("graph", "crate")
    first, second = (graph.encode(image) for image in kitti_images(shared_data, graph))
    for ref, tgt in ((first, second), (second, first)):
        want_flow, want_confidence = graph.match(ref, tgt)
        flow, confidence = crate.match(ref, tgt)
        # Both float32: only argmax near-ties may decide differently, on a handful of cells.
        differing = np.abs(flow - want_flow).max(axis=0) > 1e-3
        assert differing.mean() < 1e-3
        np.testing.assert_allclose(confidence[~differing], want_confidence[~differing], atol=1e-5)
        assert np.median(np.abs(flow[:, ~differing] - want_flow[:, ~differing])) < 1e-5
        assert np.abs(want_flow).max() > 1  # a real motion between the frames, not a zero flow


def test_the_occupied_cells_alone_are_matched_as_in_the_dense_stage(shared_data: Path) -> None:
    # What the odometry asks for (`FrameMatcherAdapter.match_cells`): a real scan's cells that hold a point.
    matcher = OnnxMatcher(default_model_path(), threads=2, matching_stage="crate")
    images = kitti_images(shared_data, matcher)
    ref, tgt = (matcher.encode(image) for image in images)
    occupied = images[0][0] > 0
    assert 0.5 < occupied.mean() < 0.95
    dense_flow, dense_confidence = matcher.match(ref, tgt)
    crate = FrameMatcherAdapter(matcher)
    flow, confidence = crate.match_cells(ref, tgt, occupied)
    np.testing.assert_array_equal(flow[:, occupied], dense_flow[:, occupied])
    np.testing.assert_allclose(confidence[occupied], dense_confidence[occupied], rtol=1e-5)
    assert np.isnan(flow[:, ~occupied]).all() and (confidence[~occupied] == 0).all()


def test_a_matcher_in_its_graphs_matches_every_cell() -> None:
    graph = OnnxMatcher(default_model_path(), threads=2, matching_stage="graph")
    assert not hasattr(FrameMatcherAdapter(graph), "match_cells")
    assert not hasattr(FrameMatcherAdapter(graph), "match_guided")
    height, width = graph.cylinder.height, graph.cylinder.width
    features = graph.encode(np.zeros((2, height, width), np.float32))
    with pytest.raises(ModelError, match="guide"):
        graph.match(features, features, guide=np.zeros((height, width, 2), np.float32))


def test_windows_placed_by_the_expected_flow_reach_a_turn_beyond_the_window(shared_data: Path) -> None:
    # A real scan and the same scan turned by 20° (its image rolled by 100 columns): the model's coarse
    # window (±7 coarse cells, ±56 columns) cannot reach the turn from each cell, windows placed where the
    # turn takes each cell can.
    matcher = OnnxMatcher(default_model_path(), threads=2, matching_stage="crate")
    image = kitti_images(shared_data, matcher)[0]
    turned = np.roll(image, 100, axis=2)
    turned[:, :, :100] = 0.0  # the columns the roll brought round: nothing seen there
    ref, tgt = matcher.encode(image), matcher.encode(turned)
    occupied = image[0] > 0
    columns = np.arange(image.shape[2])
    inside = occupied & ((columns >= 40) & (columns < image.shape[2] - 140))[None, :]
    def reached(flow: np.ndarray) -> float:
        # Within 3 pixels: the network's sub-pixel decoding leaves a third of a scan matched against itself
        # more than half a pixel off.
        return float(((np.abs(flow[0]) < 3) & (np.abs(flow[1] - 100) < 3))[inside].mean())
    plain, _ = matcher.match(ref, tgt, occupied)
    expected = np.full(image.shape[1:] + (2,), np.nan, np.float32)
    expected[occupied] = [0.0, 97.0]  # a few columns off, as a prediction is
    guided, confidence = FrameMatcherAdapter(matcher).match_guided(ref, tgt, occupied, expected)
    assert reached(plain) < 0.05 and reached(guided) > 0.95, (reached(plain), reached(guided))
    assert np.isnan(guided[:, ~occupied]).all() and (confidence[~occupied] == 0).all()
    # Expecting nothing anywhere is the plain match.
    nothing = np.full_like(expected, np.nan)
    np.testing.assert_array_equal(matcher.match(ref, tgt, occupied, nothing)[0], plain)


def test_frame_in_the_crate_matches_the_frame_graph(shared_data: Path) -> None:
    graph = OnnxMatcher(default_model_path(), threads=2, matching_stage="graph")
    crate = OnnxMatcher(default_model_path(), threads=2)
    assert crate.matching_stage == "crate"  # the CPU default with the bundled model
    images = kitti_images(shared_data, graph)
    first_graph, first_crate = graph.frame(images[0], None), crate.frame(images[0], None)
    assert first_crate.flow is None and first_crate.confidence is None
    np.testing.assert_allclose(first_crate.features.refine, first_graph.features.refine, atol=1e-5)
    got = crate.frame(images[1], first_crate.features)
    want = graph.frame(images[1], first_graph.features)
    assert got.flow is not None and want.flow is not None and got.confidence is not None
    differing = np.abs(got.flow - want.flow).max(axis=0) > 1e-3
    assert differing.mean() < 1e-3
    np.testing.assert_allclose(got.confidence[~differing], want.confidence[~differing], atol=1e-5)


def test_a_model_without_scales_matches_in_its_graph(tmp_path: Path) -> None:
    folder = tmp_path / "old"
    shutil.copytree(default_model_path(), folder)
    for path in folder.glob("*.onnx"):
        proto = onnx.load(str(path))
        kept = [p for p in proto.metadata_props if p.key != "dmlo.similarity_scales"]
        del proto.metadata_props[:]
        proto.metadata_props.extend(kept)
        onnx.save(proto, str(path))
    assert OnnxMatcher(folder).matching_stage == "graph"
    with pytest.raises(ModelError, match="similarity_scales"):
        OnnxMatcher(folder, matching_stage="crate")
    (default_copy := tmp_path / "no_encoder").mkdir()
    shutil.copy(default_model_path() / "frame.onnx", default_copy)
    assert OnnxMatcher(default_copy).matching_stage == "graph"
    with pytest.raises(ModelError, match="encoder.onnx"):
        OnnxMatcher(default_copy, matching_stage="crate")
    with pytest.raises(ValueError, match="matching_stage"):
        OnnxMatcher(default_model_path(), matching_stage="gpu")


def test_the_wide_graph_matches_in_the_crate_with_its_own_window(shared_data: Path) -> None:
    wide = default_model_path() / "frame_wide.onnx"
    crate = OnnxMatcher(wide, threads=2)
    graph = OnnxMatcher(wide, threads=2, matching_stage="graph")
    assert crate.matching_stage == "crate" and crate.metadata.coarse_window > 11
    first, second = kitti_images(shared_data, crate)
    previous = crate.encode(first)
    got, want = crate.frame(second, previous), graph.frame(second, previous)
    assert got.flow is not None and want.flow is not None
    assert (np.abs(got.flow - want.flow).max(axis=0) > 1e-3).mean() < 1e-3


def test_exported_scales_drive_the_crate_like_the_graph(tmp_path: Path) -> None:
    model = calibrated_matcher(dataclasses.replace(MatcherConfig.preset("fast"), coarse_window=9))
    with torch.no_grad():
        model.coarse_log_scale.fill_(2.9)  # far from the initial 10: a wrong scale would show
    export_onnx(model, tmp_path, HEIGHT, WIDTH, cylinder_config=dmlo_rs.CylinderConfig(height=HEIGHT, width=WIDTH))
    crate, graph = OnnxMatcher(tmp_path), OnnxMatcher(tmp_path, matching_stage="graph")
    assert crate.matching_stage == "crate"
    ref, tgt, _, _ = synthetic_pair(HEIGHT, WIDTH, (2, -7), seed=14)
    first, second = crate.encode(ref[0].numpy()), crate.encode(tgt[0].numpy())
    flow, confidence = crate.match(first, second)
    want_flow, want_confidence = graph.match(first, second)
    differing = np.abs(flow - want_flow).max(axis=0) > 1e-3
    assert differing.mean() < 1e-3
    np.testing.assert_allclose(confidence[~differing], want_confidence[~differing], atol=1e-5)


def features(channels: int, height: int, width: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).standard_normal((1, channels, height, width)).astype(np.float32)


def good_arguments() -> tuple[list[np.ndarray], dict]:
    arrays = [features(32, 4, 8), features(8, 16, 64), features(32, 4, 8, 1), features(8, 16, 64, 1)]
    settings = dict(coarse_window=5, refine_window=3, coarse_scale=10.0, refine_scale=10.0)
    return arrays, settings


def test_good_arguments_run_in_both_layouts_and_dtypes() -> None:
    arrays, settings = good_arguments()
    flow, confidence = dmlo_rs.match_features(*arrays, **settings)
    assert flow.shape == (2, 16, 64) and confidence.shape == (16, 64)
    assert np.isfinite(flow).all() and ((confidence > 0) & (confidence <= 1)).all()
    squeezed = dmlo_rs.match_features(*[a[0].astype(np.float64) for a in arrays], **settings)
    np.testing.assert_allclose(squeezed[0], flow, atol=1e-6)
    strided = dmlo_rs.match_features(*[np.asfortranarray(a[0]) for a in arrays], **settings)
    np.testing.assert_array_equal(strided[0], squeezed[0])
    marked = np.zeros((16, 64), bool)
    marked[3:, ::3] = True
    some_flow, some_confidence = dmlo_rs.match_features(*arrays, **settings, cells=marked)
    np.testing.assert_array_equal(some_flow[:, marked], flow[:, marked])
    assert np.isnan(some_flow[:, ~marked]).all() and (some_confidence[~marked] == 0).all()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda a, s: a.__setitem__(1, features(8, 16, 60)), "ref_refine"),
        (lambda a, s: a.__setitem__(2, features(16, 4, 8)), "tgt_coarse"),
        (lambda a, s: a.__setitem__(0, a[0][0, 0]), r"ref_coarse: expected shape \(1, C, h, w\)"),
        (lambda a, s: a.__setitem__(3, a[3].astype(np.int32)), "tgt_refine"),
        (lambda a, s: a[3].__setitem__((0, 2, 5, 7), np.nan), "tgt_refine"),
        (lambda a, s: a[0].__setitem__((0, 0, 0, 0), np.inf), "ref_coarse"),
        (lambda a, s: s.update(coarse_window=4), "coarse_window"),
        (lambda a, s: s.update(refine_window=1), "refine_window"),
        (lambda a, s: s.update(coarse_window=10**6 + 1), "coarse_window: 1000001 is wider than the 4×8 features"),
        (lambda a, s: s.update(coarse_scale=float("nan")), "coarse_scale"),
        (lambda a, s: s.update(refine_scale=0.0), "refine_scale"),
        (lambda a, s: s.update(refine_offset="centroid"), "refine_offset"),
        (lambda a, s: s.update(stride=(0, 8)), "stride"),
        (lambda a, s: s.update(stride=(2, 8)), "stride"),
        (lambda a, s: s.update(cells=np.ones((16, 63), bool)), r"cells: expected shape \(16, 64\) bool"),
        (lambda a, s: s.update(cells=np.ones((16, 64), np.float32)), "cells"),
        (lambda a, s: s.update(guide=np.zeros((16, 64), np.float32)), "guide"),
        (lambda a, s: s.update(guide=np.zeros((16, 64, 3), np.float32)), r"guide: expected shape \(16, 64, 2\) float32"),
        (lambda a, s: s.update(guide=np.zeros((16, 64, 2), np.float64)), "guide"),
    ],
)
def test_bad_input_is_named(change, message) -> None:
    arrays, settings = good_arguments()
    change(arrays, settings)
    with pytest.raises((ValueError, TypeError), match=message):
        dmlo_rs.match_features(*arrays, **settings)


def test_on_a_gpu_auto_leaves_the_matching_in_the_graphs(monkeypatch: pytest.MonkeyPatch) -> None:
    matcher = OnnxMatcher(default_model_path())

    class OnCuda:
        def get_providers(self) -> list[str]:
            return ["CUDAExecutionProvider", "CPUExecutionProvider"]

    monkeypatch.setattr(matcher, "_session", OnCuda())
    assert matcher._choose_stage("auto") == "graph"
    assert matcher._choose_stage("crate") == "crate"  # asked for explicitly: the CPU-side stage after a GPU encoder
