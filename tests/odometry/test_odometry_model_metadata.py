"""What the odometry reads from a model file, checked when the model opens: corrupt `dmlo.*` metadata is a
`ModelError` naming the key, before any scan (issue 25, item 10); and `threads` is bounded to the
machine's cores (issue 25, item 2)."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

import dmlo_rs

onnx = pytest.importorskip("onnx")

from dmlo.cli import main as dmlo_main  # noqa: E402
from dmlo.odometry import Odometry, OdometryConfig  # noqa: E402
from dmlo.odometry import matcher as matcher_module  # noqa: E402
from dmlo.odometry.matcher import ModelError, OnnxMatcher, default_model_path, usable_threads  # noqa: E402


@pytest.fixture(scope="module")
def bundled(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The bundled model's graphs (not its training state nor its range-only model)."""
    folder = tmp_path_factory.mktemp("bundled")
    for graph in default_model_path().glob("*.onnx"):
        shutil.copy(graph, folder)
    return folder


def corrupt(bundled: Path, into: Path, change: dict[str, str | None], graph: str = "frame.onnx") -> Path:
    """A copy of the bundled model with `graph`'s metadata changed: a key set to a value, or removed (None)."""
    into.mkdir()
    for path in bundled.glob("*.onnx"):
        shutil.copy(path, into)
    proto = onnx.load(str(into / graph))
    kept = {p.key: p.value for p in proto.metadata_props}
    for key, value in change.items():
        if value is None:
            kept.pop(key, None)
        else:
            kept[key] = value
    del proto.metadata_props[:]
    for key, value in kept.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.save(proto, str(into / graph))
    return into


def _model_config(drop: str | None = None, **changes: object) -> str:
    proto = onnx.load(str(default_model_path() / "frame.onnx"))
    config = json.loads(next(p.value for p in proto.metadata_props if p.key == "dmlo.model_config"))
    if drop:
        del config[drop]
    config.update(changes)
    return json.dumps(config)


CORRUPT = [
    ({"dmlo.model_config": None}, r"frame\.onnx: no dmlo\.model_config in the graph's metadata: not a dmlo export"),
    ({"dmlo.model_config": "{\"coarse_window\": 15"}, r"frame\.onnx: dmlo\.model_config is not JSON"),
    ({"dmlo.model_config": "[15, 7]"}, r"frame\.onnx: dmlo\.model_config must be a JSON object"),
    ({"dmlo.model_config": "drop coarse_window"}, r"frame\.onnx: dmlo\.model_config\.coarse_window must be an odd integer >= 3; it lacks it"),
    ({"dmlo.model_config": "drop refine_window"}, r"frame\.onnx: dmlo\.model_config\.refine_window must be an odd integer >= 3; it lacks it"),
    ({"dmlo.model_config": "drop refine_offset"}, r"dmlo\.model_config\.refine_offset must be one of window, peak_centroid; it lacks it"),
    ({"dmlo.model_config": "refine_window=6"}, r"dmlo\.model_config\.refine_window must be an odd integer >= 3; got 6"),
    ({"dmlo.model_config": "coarse_window=\"15\""}, r"dmlo\.model_config\.coarse_window must be an odd integer >= 3; got \"15\""),
    ({"dmlo.model_config": "use_reflectance=\"no\""}, r"dmlo\.model_config\.use_reflectance must be true or false; got \"no\""),
    ({"dmlo.similarity_scales": "{\"coarse\": 13.2}"}, r"dmlo\.similarity_scales\.refine must be a finite number > 0; it lacks it"),
    ({"dmlo.similarity_scales": "{\"coarse\": -1, \"refine\": 11}"}, r"dmlo\.similarity_scales\.coarse must be a finite number > 0; got -1"),
    ({"dmlo.similarity_scales": "{\"coarse\": \"13\", \"refine\": 11}"}, r"dmlo\.similarity_scales\.coarse must be a finite number > 0; got \"13\""),
    ({"dmlo.similarity_scales": "[13.2, 11.1]"}, r"dmlo\.similarity_scales must be a JSON object"),
    ({"dmlo.similarity_scales": "13.2, 11.1"}, r"dmlo\.similarity_scales is not JSON"),
    ({"dmlo.cylinder_config": "{}"}, r"frame\.onnx: dmlo\.cylinder_config\.fov_up_deg must be a number"),
    ({"dmlo.height": None}, r"frame\.onnx: no dmlo\.height in the graph's metadata"),
    ({"dmlo.width": "1792.5"}, r"frame\.onnx: dmlo\.width = \"1792\.5\" is not a positive integer"),
    ({"dmlo.interface_version": "2"}, r"frame\.onnx: dmlo\.interface_version \"2\": this crate reads version \"1\""),
]


def _resolved(change: dict[str, str | None]) -> dict[str, str | None]:
    """Shorthands of `CORRUPT` for the model config: "drop KEY" and "KEY=JSON" edit the bundled one."""
    value = change.get("dmlo.model_config")
    if value is not None and value.startswith("drop "):
        return {"dmlo.model_config": _model_config(drop=value.split()[1])}
    if value is not None and "=" in value and not value.startswith(("{", "[")):
        key, literal = value.split("=", 1)
        return {"dmlo.model_config": _model_config(**{key: json.loads(literal)})}
    return change


@pytest.mark.parametrize(("change", "message"), CORRUPT, ids=[str(c) for c, _ in CORRUPT])
def test_corrupt_metadata_is_a_model_error_naming_the_key(
    change: dict[str, str | None], message: str, bundled: Path, tmp_path: Path
) -> None:
    model = corrupt(bundled, tmp_path / "model", _resolved(change))
    with pytest.raises(ModelError, match=message):
        Odometry(model, OdometryConfig())


@pytest.mark.parametrize("stage", ["crate", "graph"])
def test_corrupt_metadata_fails_when_the_model_opens_whichever_stage_matches(stage: str, bundled: Path, tmp_path: Path) -> None:
    # Before, the crate's stage read the model config's windows only at the first pair (a KeyError after frame 0).
    model = corrupt(bundled, tmp_path / "model", {"dmlo.model_config": _model_config(drop="coarse_window")})
    with pytest.raises(ModelError, match="coarse_window must be an odd integer >= 3; it lacks it"):
        OnnxMatcher(model, matching_stage=stage)


def test_a_corrupt_encoder_graph_is_named(bundled: Path, tmp_path: Path) -> None:
    model = corrupt(bundled, tmp_path / "model", {"dmlo.model_config": "{"}, graph="encoder.onnx")
    with pytest.raises(ModelError, match=r"encoder\.onnx: dmlo\.model_config is not JSON"):
        OnnxMatcher(model, matching_stage="crate")
    model = corrupt(bundled, tmp_path / "sized", {"dmlo.height": "sixty-four"}, graph="encoder.onnx")
    with pytest.raises(ModelError, match=r"encoder\.onnx: dmlo\.height = \"sixty-four\" is not a positive integer"):
        OnnxMatcher(model, matching_stage="crate")


def test_the_bundled_models_metadata_passes(bundled: Path) -> None:
    matcher = OnnxMatcher(bundled)
    assert matcher.metadata.coarse_window % 2 == 1 and matcher.metadata.graph == "frame"
    assert matcher.metadata.similarity_scales is not None and min(matcher.metadata.similarity_scales) > 0


def test_a_graph_exported_before_its_cylinder_was_written_takes_kittis_image(bundled: Path, tmp_path: Path) -> None:
    # The crate's rule for every runtime: the only cylinder there was then.
    model = corrupt(bundled, tmp_path / "model", {"dmlo.cylinder_config": None})
    assert OnnxMatcher(model).cylinder == dmlo_rs.CylinderConfig.kitti()


def test_an_encoder_of_other_weights_is_refused(bundled: Path, tmp_path: Path) -> None:
    model = corrupt(bundled, tmp_path / "model", {"dmlo.model_config": _model_config(refine_channels=16)}, graph="encoder.onnx")
    with pytest.raises(ModelError, match=r"encoder\.onnx: not the encoder graph of frame\.onnx's model \(dmlo\.model_config\.refine_channels differ\)"):
        OnnxMatcher(model, matching_stage="crate")


@pytest.mark.parametrize("command", ["run", "register"])
def test_the_cli_reports_corrupt_metadata_in_one_line_before_the_first_scan(
    command: str, bundled: Path, plain_scans: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    model = corrupt(bundled, tmp_path / "model", {"dmlo.similarity_scales": "{\"coarse\": 13.2}"})
    out = tmp_path / "out"
    if command == "run":
        argv = ["run", str(plain_scans), "--format", "folder", "--model", str(model), "--out", str(out)]
    else:
        argv = ["register", str(plain_scans / "000000.bin"), str(plain_scans / "000001.bin"), "--model", str(model)]
    assert dmlo_main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"dmlo {command}: error: {model / 'frame.onnx'}: dmlo.similarity_scales.refine must be")
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not (out / "poses_kitti.txt").exists()


# -- threads (issue 25, item 2) ------------------------------------------------------------------------------


def test_threads_within_the_cores_are_kept(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(matcher_module, "available_cores", lambda: 4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert [usable_threads(n) for n in (0, 1, 4)] == [0, 1, 4]


def test_more_threads_than_cores_are_bounded_with_a_warning(monkeypatch: pytest.MonkeyPatch, bundled: Path) -> None:
    # 100000 threads blocked in onnxruntime's session creation, memory growing: none is created here, since
    # the machine is said to have 2 cores and the sessions get 2.
    monkeypatch.setattr(matcher_module, "available_cores", lambda: 2)
    config = OdometryConfig.from_dict({"threads": 100000})
    with pytest.warns(UserWarning, match=r"^threads: 100000 is more than the 2 cores of this machine; using 2$"):
        odometry = Odometry(bundled, config)
    matcher = odometry.matcher
    assert isinstance(matcher, OnnxMatcher)
    assert matcher._options.intra_op_num_threads == 2 and matcher._threads == 2
    assert odometry.config.threads == 100000  # the config says what was asked for


def test_the_cores_are_counted_as_this_process_may_use_them() -> None:
    assert 1 <= matcher_module.available_cores()


def test_a_corrupt_range_only_model_fails_before_the_first_scan(bundled: Path, tmp_path: Path, scans: list[np.ndarray]) -> None:
    """Before, the range-only model opened at the first scan without reflectance: a ModelError mid-drive."""
    model = tmp_path / "model"
    shutil.copytree(bundled, model)
    corrupt(default_model_path() / "range_only", model / "range_only", {"dmlo.model_config": "{"})
    with pytest.raises(ModelError, match=r"range_only/frame\.onnx: dmlo\.model_config is not JSON"):
        Odometry(model, OdometryConfig())
    shutil.rmtree(model / "range_only")
    shutil.copytree(default_model_path() / "range_only", model / "range_only")
    odometry = Odometry(model, OdometryConfig())
    with pytest.warns(UserWarning, match="the range-only model runs"):
        odometry.register(np.ascontiguousarray(scans[0][:, :3]))  # no reflectance
    assert odometry.matcher.uses_reflectance is False
