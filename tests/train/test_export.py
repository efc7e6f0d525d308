"""ONNX export: onnxruntime reproduces the PyTorch matcher (float64 reference) on a calibrated network."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
ort = pytest.importorskip("onnxruntime")
onnx = pytest.importorskip("onnx")

from dmlo.export import export_onnx, read_metadata  # noqa: E402
from dmlo.model import Matcher, MatcherConfig  # noqa: E402
from dmlo.model.window import decode_window  # noqa: E402

from test_model import synthetic_pair  # noqa: E402

HEIGHT, WIDTH = 64, 448


def calibrated_matcher(config: MatcherConfig) -> Matcher:
    """Random weights with non-zero deformable offsets and BatchNorm statistics measured on scenes, so
    features vary and windows are not flat (ONNX-NOTES item 8)."""
    torch.manual_seed(0)
    model = Matcher(config)
    for module in model.modules():
        if isinstance(module, torch.nn.BatchNorm2d):
            module.momentum = None  # cumulative average over the calibration batches
            module.reset_running_stats()
        if hasattr(module, "offset") and isinstance(module.offset, torch.nn.Conv2d):
            torch.nn.init.normal_(module.offset.weight, std=0.05)
    model.train()
    with torch.no_grad():
        for seed in range(3):
            ref, tgt, _, _ = synthetic_pair(HEIGHT, WIDTH, (2, 9), seed=seed)
            model(ref, tgt)
    return model.eval()


def near_tie(sums: torch.Tensor, tolerance: float = 1e-4) -> torch.Tensor:
    """Cells whose best two 2×2 windows differ by less than ``tolerance`` (relative): argmax may flip."""
    top = sums.topk(2, dim=1).values
    return (top[:, 0] - top[:, 1]) <= tolerance * top[:, 0]


def tied_cells(want, config: MatcherConfig) -> torch.Tensor:
    """(B, H, W): cells of a float64 reference match whose decision float32 may take differently — a near
    tie between the best two windows (coarse or refine; for the peak centroid, the best two cells) or an
    upsampled coarse offset that rounds at half a pixel."""
    from dmlo.model.matcher import upsample_coarse_flow

    coarse_sums = decode_window(want.coarse_logits, config.coarse_window).window_sums
    refine_sums = decode_window(want.refine_logits, config.refine_window).window_sums
    origin = upsample_coarse_flow(want.coarse_flow, config.coarse_stride)
    rounding_tie = ((origin - origin.floor() - 0.5).abs() < 1e-3).any(dim=1)
    stride = config.coarse_stride
    coarse_tie = torch.nn.functional.interpolate(near_tie(coarse_sums).unsqueeze(1).double(), scale_factor=stride)
    ties = (coarse_tie[:, 0] > 0) | near_tie(refine_sums) | rounding_tie
    if config.refine_offset == "peak_centroid":
        top = want.refine_logits.topk(2, dim=1).values
        ties |= (top[:, 0] - top[:, 1]) <= 1e-4 * top[:, 0].abs().clamp(min=1.0)
    return ties


def session(path) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.intra_op_num_threads = 2
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    model = calibrated_matcher(MatcherConfig(refine_channels=8))
    out_dir = tmp_path_factory.mktemp("onnx")
    cylinder = {"height": HEIGHT, "width": WIDTH, "azimuth_resolution_deg": 0.2}
    paths = export_onnx(model, out_dir, HEIGHT, WIDTH, cylinder_config=cylinder)
    return model, paths


def test_frame_graph_matches_pytorch(exported) -> None:
    model, paths = exported
    ref, tgt, _, _ = synthetic_pair(HEIGHT, WIDTH, (3, -11), seed=10)
    reference = Matcher(model.config)
    reference.load_state_dict(model.state_dict())
    reference = reference.double().eval()
    with torch.no_grad():
        ref_features = model.encode(ref)
        want = reference.match(reference.encode(ref.double()), reference.encode(tgt.double()))
    got_flow, got_confidence, got_coarse, got_refine = session(paths["frame"]).run(
        None,
        {
            "scan": tgt.numpy(),
            "prev_coarse_features": ref_features.coarse.numpy(),
            "prev_refine_features": ref_features.refine.numpy(),
        },
    )
    ties = tied_cells(want, model.config)
    assert float(ties.double().mean()) < 0.05
    keep = (~ties[0]).numpy()
    flow_error = np.abs(got_flow - want.flow.numpy()).max(axis=1)[0]
    confidence_error = np.abs(got_confidence - want.confidence.numpy())[0]
    assert flow_error[keep].max() < 1e-3
    # float32 itself (PyTorch's too) leaves a few cells of ~1e-4 against float64.
    assert np.quantile(confidence_error[keep], 0.999) < 1e-4
    assert confidence_error[keep].max() < 3e-4
    # The untied cells are a real test: the network gives varied, non-trivial matches.
    assert np.unique(np.round(got_flow[0, :, keep], 1), axis=0).shape[0] > 20
    with torch.no_grad():
        want_tgt = reference.encode(tgt.double())
    np.testing.assert_allclose(got_coarse, want_tgt.coarse.numpy(), atol=1e-4)
    np.testing.assert_allclose(got_refine, want_tgt.refine.numpy(), atol=1e-4)


def test_encoder_and_match_graphs_agree_with_frame_graph(exported) -> None:
    _, paths = exported
    ref, tgt, _, _ = synthetic_pair(HEIGHT, WIDTH, (-1, 6), seed=11)
    encoder = session(paths["encoder"])
    ref_coarse, ref_refine = encoder.run(None, {"scan": ref.numpy()})
    tgt_coarse, tgt_refine = encoder.run(None, {"scan": tgt.numpy()})
    flow, confidence = session(paths["match"]).run(
        None,
        {
            "ref_coarse_features": ref_coarse,
            "ref_refine_features": ref_refine,
            "tgt_coarse_features": tgt_coarse,
            "tgt_refine_features": tgt_refine,
        },
    )
    frame = session(paths["frame"]).run(
        None, {"scan": tgt.numpy(), "prev_coarse_features": ref_coarse, "prev_refine_features": ref_refine}
    )
    np.testing.assert_allclose(frame[0], flow, atol=1e-5)
    np.testing.assert_allclose(frame[1], confidence, atol=1e-6)
    np.testing.assert_allclose(frame[2], tgt_coarse, atol=1e-6)
    np.testing.assert_allclose(frame[3], tgt_refine, atol=1e-6)


def test_graph_interface_and_metadata(exported) -> None:
    model, paths = exported
    proto = onnx.load(str(paths["frame"]))
    assert any(node.op_type == "DeformConv" for node in proto.graph.node)
    assert not any(node.op_type in ("GridSample", "BatchNormalization") and "coarse" in node.name for node in proto.graph.node)
    frame = session(paths["frame"])
    inputs = {i.name: (i.shape, i.type) for i in frame.get_inputs()}
    outputs = {o.name: (o.shape, o.type) for o in frame.get_outputs()}
    c, cr = model.config.coarse_channels, model.config.refine_channels
    assert inputs == {
        "scan": ([1, 2, HEIGHT, WIDTH], "tensor(float)"),
        "prev_coarse_features": ([1, c, HEIGHT // 4, WIDTH // 8], "tensor(float)"),
        "prev_refine_features": ([1, cr, HEIGHT, WIDTH], "tensor(float)"),
    }
    assert outputs == {
        "flow": ([1, 2, HEIGHT, WIDTH], "tensor(float)"),
        "confidence": ([1, HEIGHT, WIDTH], "tensor(float)"),
        "coarse_features": ([1, c, HEIGHT // 4, WIDTH // 8], "tensor(float)"),
        "refine_features": ([1, cr, HEIGHT, WIDTH], "tensor(float)"),
    }
    metadata = read_metadata(paths["frame"])
    assert metadata["dmlo.graph"] == "frame"
    assert metadata["dmlo.height"] == HEIGHT and metadata["dmlo.width"] == WIDTH
    assert MatcherConfig.from_dict(metadata["dmlo.model_config"]) == model.config
    assert metadata["dmlo.cylinder_config"]["azimuth_resolution_deg"] == 0.2
    assert json.loads(json.dumps(metadata["dmlo.model_config"]))["refine_channels"] == 8
    scales = metadata["dmlo.similarity_scales"]
    assert scales == pytest.approx(
        {"coarse": float(model.coarse_log_scale.detach().exp()), "refine": float(model.refine_log_scale.detach().exp())},
        rel=1e-6,
    )
    for graph in ("encoder", "match"):
        assert read_metadata(paths[graph])["dmlo.similarity_scales"] == scales


def test_plain_refine_exports_without_deformconv(tmp_path) -> None:
    model = Matcher(MatcherConfig.preset("fast"))
    paths = export_onnx(model, tmp_path, 32, 64, graphs=("match",))
    assert model.training  # the caller's mode is restored
    proto = onnx.load(str(paths["match"]))
    assert not any(node.op_type == "DeformConv" for node in proto.graph.node)


def test_export_rejects_bad_arguments(tmp_path) -> None:
    model = Matcher(MatcherConfig.preset("fast"))
    with pytest.raises(ValueError, match="unknown graphs"):
        export_onnx(model, tmp_path, 32, 64, graphs=("decoder",))
    with pytest.raises(ValueError, match="divisible"):
        export_onnx(model, tmp_path, 30, 64)
    (tmp_path / "other.onnx").write_bytes(b"")
    with pytest.raises(Exception):
        read_metadata(tmp_path / "other.onnx")


def test_wide_window_graph_keeps_the_weights_and_widens_the_coarse_window(tmp_path) -> None:
    from dmlo.commands.export import export_wide_frame

    model = Matcher(MatcherConfig.preset("fast")).eval()
    export_onnx(model, tmp_path, 32, 64, graphs=("frame",))
    wide = export_wide_frame(model, tmp_path, 21, (32, 64), None)
    assert wide == tmp_path / "frame_wide.onnx"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frame.onnx", "frame_wide.onnx"]  # no scratch left
    config = read_metadata(wide)["dmlo.model_config"]
    assert config["coarse_window"] == 21
    assert MatcherConfig.from_dict({**config, "coarse_window": model.config.coarse_window}) == model.config
    # Same weights: the initialisers of the two graphs hold the same tensors (the window adds constants only).
    def weights(path):
        return {tuple(np.asarray(onnx.numpy_helper.to_array(t)).ravel()[:8]) for t in onnx.load(str(path)).graph.initializer
                if onnx.numpy_helper.to_array(t).size > 16}
    assert weights(tmp_path / "frame.onnx") <= weights(wide)


def test_peak_centroid_decoding_exports_and_the_command_can_choose_it(tmp_path) -> None:
    import dataclasses

    from dmlo.cli import main as dmlo_main
    from dmlo.train import checkpoint

    model = calibrated_matcher(MatcherConfig(refine_channels=8, refine_offset="peak_centroid"))
    paths = export_onnx(model, tmp_path / "graphs", HEIGHT, WIDTH, graphs=("frame",))
    ref, tgt, _, _ = synthetic_pair(HEIGHT, WIDTH, (3, -11), seed=10)
    with torch.no_grad():
        ref_features = model.encode(ref)
        want = model.match(ref_features, model.encode(tgt))
    got_flow, got_confidence, _, _ = session(paths["frame"]).run(
        None, {"scan": tgt.numpy(), "prev_coarse_features": ref_features.coarse.numpy(),
               "prev_refine_features": ref_features.refine.numpy()},
    )
    agree = np.abs(got_flow - want.flow.numpy()).max(axis=1) < 1e-3
    assert agree.mean() > 0.99  # the rest: float32 near-ties of an argmax, decided differently
    np.testing.assert_allclose(got_confidence, want.confidence.numpy(), atol=3e-4)
    paper = want.refine_origin + decode_window(want.refine_logits, model.config.refine_window).offset
    assert (np.abs(got_flow - paper.numpy()).max(axis=1) > 1e-2).mean() > 0.5  # it is not Eq. 11
    # `dmlo export --refine-offset` re-decodes a checkpoint trained with the paper's decoding.
    paper_model = Matcher(dataclasses.replace(model.config, refine_offset="window"))
    paper_model.load_state_dict(model.state_dict())
    checkpoint.save_atomic({"model": paper_model.state_dict(), "model_config": paper_model.config.to_dict()}, tmp_path / "c.pt")
    out = tmp_path / "chosen"
    assert dmlo_main(["export", str(tmp_path / "c.pt"), "--out", str(out), "--height", str(HEIGHT), "--width", str(WIDTH),
                      "--graphs", "frame", "--refine-offset", "peak_centroid"]) == 0
    assert read_metadata(out / "frame.onnx")["dmlo.model_config"]["refine_offset"] == "peak_centroid"


def test_refine_window_can_be_widened_at_export(tmp_path) -> None:
    from dmlo.cli import main as dmlo_main
    from dmlo.train import checkpoint

    model = Matcher(MatcherConfig.preset("fast"))
    checkpoint.save_atomic({"model": model.state_dict(), "model_config": model.config.to_dict()}, tmp_path / "c.pt")
    common = ["export", str(tmp_path / "c.pt"), "--height", "32", "--width", "64", "--graphs", "frame", "match"]
    assert dmlo_main([*common, "--out", str(tmp_path / "wide"), "--refine-window", "7", "--wide-window", "21"]) == 0
    for graph in ("frame", "match", "frame_wide"):
        config = read_metadata(tmp_path / "wide" / f"{graph}.onnx")["dmlo.model_config"]
        assert config["refine_window"] == 7  # every graph, the large-motion one too
        assert MatcherConfig.from_dict({**config, "refine_window": 5, "coarse_window": model.config.coarse_window}) == model.config
    assert dmlo_main([*common, "--out", str(tmp_path / "even"), "--refine-window", "6"]) == 2  # must be odd


def test_an_export_removes_the_graphs_an_earlier_export_left_beside_its_own(tmp_path, capsys) -> None:
    from dmlo.cli import main as dmlo_main
    from dmlo.train import checkpoint

    model = Matcher(MatcherConfig.preset("fast"))
    checkpoint.save_atomic({"model": model.state_dict(), "model_config": model.config.to_dict()}, tmp_path / "c.pt")
    out = tmp_path / "model"
    size = ["--height", "32", "--width", "64"]
    assert dmlo_main(["export", str(tmp_path / "c.pt"), "--out", str(out), *size, "--wide-window", "21"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["encoder.onnx", "frame.onnx", "frame_wide.onnx", "match.onnx"]
    (out / "range_only").mkdir()
    (out / "notes.txt").write_text("mine")
    capsys.readouterr()
    assert dmlo_main(["export", str(tmp_path / "c.pt"), "--out", str(out), *size, "--graphs", "frame"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["frame.onnx", "notes.txt", "range_only"]
    printed = capsys.readouterr().out
    assert all(f"removed {out / name}" in printed for name in ("frame_wide.onnx", "encoder.onnx", "match.onnx"))
