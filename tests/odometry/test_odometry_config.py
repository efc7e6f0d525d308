"""The odometry config: defaults are the paper's, files round-trip, and the crate's one schema refuses every
bad value by name when the config is loaded — before the first scan, in the API and on the command line. The
rules and their messages are the crate's (`cargo test`, `odometry::config`); these tests show them reaching
Python intact, and that Python declares no setting of its own."""

from __future__ import annotations

import ast
import dataclasses
import json
import re
import typing
from pathlib import Path

import pytest

import dmlo
import dmlo_rs
from dmlo.cli import main as dmlo_main
from dmlo.odometry.config import SCHEMA, ConfigError, OdometryConfig, stub_text


def test_defaults_are_the_papers() -> None:
    config = OdometryConfig()
    assert config.matching.nms_radius == 1.0  # r = 1 (§IV-B)
    assert config.ransac.threshold == 0.1  # 0.1 m inlier threshold
    assert config.motion_model.min_inliers == 10  # fewer than 10 inliers → motion model
    assert config.matching_stage == "auto"  # beyond the paper: where the matching runs, not what it computes
    # Beyond the paper: RANSAC's refits weigh each match by its ray (ransac.refit = "point_to_point" is Eq. 12–14).
    assert config.ransac.refit == "ray_noise"


def test_the_defaults_fit_the_schema() -> None:
    OdometryConfig().validate()
    assert OdometryConfig.from_dict({}) == OdometryConfig()


def test_round_trip_through_a_file(tmp_path: Path) -> None:
    config = OdometryConfig()
    config.ransac.seed = 7
    config.mapping.enabled = False
    config.large_motion.search_yaw_deg = (0.0, 90.0)  # tuples come back from JSON's lists
    config.save(tmp_path / "config.json")
    assert OdometryConfig.load(tmp_path / "config.json") == config


def test_an_integer_is_a_number() -> None:
    config = OdometryConfig.from_dict({"ransac": {"threshold": 1}, "large_motion": {"search_ahead_m": [0, 5]}})
    assert config.ransac.threshold == 1.0 and config.large_motion.search_ahead_m == (0.0, 5.0)


def test_a_limit_may_be_infinite_but_not_nan() -> None:
    config = OdometryConfig.from_dict({"motion_model": {"max_deviation": float("inf")}})  # never gated
    assert config.motion_model.max_deviation == float("inf")
    with pytest.raises(ConfigError, match=r"^motion_model\.max_deviation: must be a number >= 0 or Infinity \(no limit\), got NaN$"):
        OdometryConfig.from_dict({"motion_model": {"max_deviation": float("nan")}})


def test_unknown_setting_is_named() -> None:
    with pytest.raises(ConfigError, match=r"^ransac\.treshold: no such setting \(did you mean ransac\.threshold\?\)$"):
        OdometryConfig.from_dict({"ransac": {"treshold": 0.2}})
    with pytest.raises(ConfigError, match=r"^mapping\.colour: no such setting; mapping has enabled, voxel_size"):
        OdometryConfig.from_dict({"mapping": {"colour": "red"}})


@pytest.mark.parametrize("data", [{"mapping": True}, {"mapping": None}, {"mapping": [1]}])
def test_section_must_be_a_mapping(data: dict[str, object]) -> None:
    with pytest.raises(ConfigError, match=r"^mapping: must be a mapping of settings, got "):
        OdometryConfig.from_dict(data)


@pytest.mark.parametrize("data", [[], "ransac", None, 3])
def test_the_whole_config_must_be_a_mapping(data: object) -> None:
    with pytest.raises(ConfigError, match=r"^config: must be a mapping of settings"):
        OdometryConfig.from_dict(data)


# Python values as they reach the crate, with the message that names them.
BAD = [
    ({"ransac": {"threshold": "abc"}}, "ransac.threshold: must be a number > 0, got \"abc\""),
    ({"ransac": {"threshold": 0}}, "ransac.threshold: must be a number > 0, got 0"),
    ({"ransac": {"threshold": None}}, "ransac.threshold: must be a number > 0, got null"),
    ({"ransac": {"threshold": float("inf")}}, "ransac.threshold: must be a finite number > 0, got Infinity"),
    ({"ransac": {"confidence": 1.0}}, "ransac.confidence: must be a number > 0 and < 1, got 1.0"),
    ({"ransac": {"confidence": "0.99"}}, "ransac.confidence: must be a number > 0 and < 1, got \"0.99\""),
    ({"ransac": {"max_iterations": 0}}, "ransac.max_iterations: must be an integer from 1 to 1000000, got 0"),
    ({"ransac": {"max_iterations": 10.5}}, "ransac.max_iterations: must be an integer from 1 to 1000000, got 10.5"),
    # A scene without a consensus runs every hypothesis, in the crate, where Ctrl-C cannot stop them.
    ({"ransac": {"max_iterations": 2**63}}, "ransac.max_iterations: must be an integer from 1 to 1000000, got 9223372036854775808"),
    ({"ransac": {"seed": -1}}, "ransac.seed: must be an integer >= 0, got -1"),
    ({"ransac": {"seed": 2**64}}, "ransac.seed: must be an integer from 0 to 2^64 - 1, got 18446744073709551616"),
    ({"ransac": {"seed": "7"}}, "ransac.seed: must be an integer >= 0, got \"7\""),
    ({"matching": {"max_matches": 0}}, "matching.max_matches: must be an integer >= 3, got 0"),
    ({"matching": {"max_matches": None}}, "matching.max_matches: must be an integer >= 3, got null"),
    ({"matching": {"nms_radius": -1}}, "matching.nms_radius: must be an integer >= 0, got -1"),
    ({"matching": {"nms_radius": 1.5}}, "matching.nms_radius: must be an integer >= 0, got 1.5"),
    ({"matching": {"min_confidence": float("nan")}}, "matching.min_confidence: must be a finite number >= 0 and <= 1, got NaN"),
    ({"matching": {"min_confidence": 2}}, "matching.min_confidence: must be a number >= 0 and <= 1, got 2"),
    ({"matching": {"coherence_radius": 99}}, "matching.coherence_radius: must be an integer from 0 to 15, got 99"),
    ({"matching": {"consistency_px": "1"}}, "matching.consistency_px: must be a number >= 0 or Infinity (no limit) or null, got \"1\""),
    ({"motion_model": {"min_inliers": -1}}, "motion_model.min_inliers: must be an integer >= 3, got -1"),
    ({"min_points": -5}, "min_points: must be an integer >= 0, got -5"),
    ({"threads": -1}, "threads: must be an integer >= 0, got -1"),
    ({"threads": "4"}, "threads: must be an integer >= 0, got \"4\""),
    ({"mapping": {"enabled": "false"}}, "mapping.enabled: must be true or false, got \"false\""),
    ({"mapping": {"enabled": 0}}, "mapping.enabled: must be true or false, got 0"),
    ({"matching": {"symmetric": "true"}}, "matching.symmetric: must be true or false, got \"true\""),
    ({"deskew": {"enabled": None}}, "deskew.enabled: must be true or false, got null"),
    ({"matching_stage": "gpu"}, "matching_stage: must be one of auto, crate, graph, got \"gpu\""),
    ({"large_motion": {"search_ahead_m": []}}, "large_motion.search_ahead_m: must be a non-empty list of finite numbers, got []"),
    ({"large_motion": {"search_yaw_deg": [0, "90"]}}, "large_motion.search_yaw_deg: must be a non-empty list of finite numbers, got [0, \"90\"]"),
]


@pytest.mark.parametrize(("data", "message"), BAD, ids=[message.split(":")[0] + "=" + message.split("got ")[-1] for _, message in BAD])
def test_a_bad_value_is_refused_when_loaded_naming_the_key(data: dict[str, object], message: str, tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as refused:
        OdometryConfig.from_dict(data)
    assert str(refused.value) == message
    assert isinstance(refused.value, ValueError)
    path = tmp_path / "config.json"
    path.write_text(json.dumps(data))  # JSON writes NaN and Infinity, and Python reads them back
    with pytest.raises(ConfigError, match="^" + re.escape(message.split(", got")[0])):
        OdometryConfig.load(path)


def test_every_bad_key_is_named_in_one_line() -> None:
    with pytest.raises(ConfigError) as refused:
        OdometryConfig.from_dict({"ransac": {"threshold": -1, "confidence": 2}, "threads": "4"})
    assert str(refused.value) == (
        "ransac.threshold: must be a number > 0, got -1; ransac.confidence: must be a number > 0 and < 1, got 2; "
        'threads: must be an integer >= 0, got "4"'
    )


def _settings() -> list[tuple[str, str, object]]:
    """Every (section, name, type) of the schema; section "" for the top-level settings."""
    found = []
    for name, hint in typing.get_type_hints(OdometryConfig, include_extras=True).items():
        if dataclasses.is_dataclass(hint):
            found += [(name, inner, kind) for inner, kind in typing.get_type_hints(hint, include_extras=True).items()]
        else:
            found.append(("", name, hint))
    return found


def _with(section: str, name: str, value: object) -> dict[str, object]:
    return {section: {name: value}} if section else {name: value}


def _key(section: str, name: str) -> str:
    return f"{section}.{name}" if section else name


def _optional(kind: object) -> bool:
    return type(None) in typing.get_args(kind)


SETTINGS = _settings()
FLAGS = [(s, n, _optional(kind)) for s, n, kind in SETTINGS if "bool" in str(kind)]


@pytest.mark.parametrize(("section", "name", "optional"), FLAGS)
@pytest.mark.parametrize("value", ["false", "true", 0, 1, None])
def test_no_boolean_setting_reads_a_string_or_a_number_as_a_boolean(
    section: str, name: str, optional: bool, value: object
) -> None:
    if optional and value is None:  # null: the setting's own default rule (e.g. motion_model.guided_windows)
        config = OdometryConfig.from_dict(_with(section, name, value))
        assert getattr(getattr(config, section) if section else config, name) is None
        return
    allowed = "true or false or null" if optional else "true or false"
    with pytest.raises(ConfigError, match=rf"^{_key(section, name)}: must be {allowed}, got "):
        OdometryConfig.from_dict(_with(section, name, value))


@pytest.mark.parametrize(("section", "name"), [(s, n) for s, n, kind in SETTINGS if not _optional(kind)])
def test_null_is_refused_where_a_setting_is_not_optional(section: str, name: str) -> None:
    with pytest.raises(ConfigError, match=rf"^{_key(section, name)}: must be .*, got null$"):
        OdometryConfig.from_dict(_with(section, name, None))


NUMBERS = [(s, n) for s, n, kind in SETTINGS if ("float" in str(kind) or "int" in str(kind)) and "bool" not in str(kind)]


@pytest.mark.parametrize(("section", "name"), NUMBERS)
def test_a_string_is_refused_where_a_number_belongs(section: str, name: str) -> None:
    default = OdometryConfig.from_dict({}).to_dict()
    value = default[section][name] if section else default[name]
    text = json.dumps(list(value) if isinstance(value, tuple) else value)  # the default, written as a string
    with pytest.raises(ConfigError, match=rf'^{_key(section, name)}: must be .*, got "'):
        OdometryConfig.from_dict(_with(section, name, text))


def test_the_schema_lists_the_reflectance_scales() -> None:
    (setting,) = [s for s in SCHEMA["settings"] if s["key"] == "reflectance"]
    assert tuple(setting["choices"]) == ("auto", "unit", "0-255", "0-65535", "none")


def test_the_classes_are_the_crates_schema() -> None:
    crate = json.loads(dmlo_rs.odometry_config_json())  # every key with the crate's default
    assert OdometryConfig().to_dict() == {
        key: {k: tuple(v) if isinstance(v, list) else v for k, v in value.items()} if isinstance(value, dict) else value
        for key, value in crate.items()
    }
    assert [s[:2] for s in SETTINGS] == [
        (section["key"], setting["key"]) for section in SCHEMA["sections"] for setting in section["settings"]
    ] + [("", setting["key"]) for setting in SCHEMA["settings"]]


def test_the_type_stub_is_written_from_the_schema() -> None:
    stub = Path(dmlo.__file__).parent / "odometry" / "config.pyi"
    assert stub.read_text() == stub_text(), "run `python -m dmlo.odometry.config` to write it again"


def test_no_class_of_the_package_declares_a_second_copy_of_a_section() -> None:
    # A class with several of a section's settings as its own fields would be a second declaration of
    # them: every setting is declared in the crate, and Python's classes are made from that.
    sections = [{s["key"] for s in section["settings"]} for section in SCHEMA["sections"]]
    sections.append({s["key"] for s in SCHEMA["settings"]})
    package = Path(dmlo.__file__).parent
    for path in package.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.ClassDef):
                continue
            fields = {item.target.id for item in node.body if isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name)}
            for settings in sections:
                shared = fields & settings
                assert len(shared) < 3, f"{path}: class {node.name} declares {sorted(shared)} again"


# -- the Python API: the config as it is when the odometry is built ------------------------------------------


@pytest.mark.parametrize(
    ("section", "name", "value", "message"),
    [
        ("ransac", "threshold", "abc", 'ransac.threshold: must be a number > 0, got "abc"'),
        ("mapping", "enabled", "false", 'mapping.enabled: must be true or false, got "false"'),
        ("motion_model", "min_inliers", -1, "motion_model.min_inliers: must be an integer >= 3, got -1"),
        ("", "threads", -2, "threads: must be an integer >= 0, got -2"),
        ("", "min_points", None, "min_points: must be an integer >= 0, got null"),
        ("matching", "max_matches", 2.0, "matching.max_matches: must be an integer >= 3, got 2.0"),
    ],
)
def test_the_odometry_refuses_a_setting_changed_after_loading(section: str, name: str, value: object, message: str) -> None:
    from dmlo.odometry import Odometry

    config = OdometryConfig()
    setattr(getattr(config, section) if section else config, name, value)
    with pytest.raises(ConfigError) as refused:
        Odometry.from_default(config)
    assert str(refused.value) == message


def test_a_section_replaced_by_a_mapping_is_refused() -> None:
    from dmlo.odometry import Odometry

    config = OdometryConfig()
    config.ransac = {"threshold": 0.2}  # type: ignore[assignment]
    with pytest.raises(ConfigError, match=r"^ransac: must be a RansacConfig, got \{'threshold': 0.2\}$"):
        Odometry.from_default(config)


# -- the command line: one line, exit code 2, before frame 0 -------------------------------------------------


@pytest.mark.parametrize(
    ("data", "message"),
    [case for case in BAD if case[1].endswith(('threshold: must be a number > 0, got "abc"', 'got "false"', "min_inliers: must be an integer >= 3, got -1"))],
)
@pytest.mark.parametrize("command", ["run", "register"])
def test_the_cli_refuses_a_bad_config_in_one_line_before_the_first_scan(
    command: str, data: dict[str, object], message: str, plain_scans: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "bad.json"
    config.write_text(json.dumps(data))
    out = tmp_path / "out"
    if command == "run":
        argv = ["run", str(plain_scans), "--format", "folder", "--config", str(config), "--out", str(out)]
    else:
        argv = ["register", str(plain_scans / "000000.bin"), str(plain_scans / "000001.bin"), "--config", str(config)]
    assert dmlo_main(argv) == 2
    captured = capsys.readouterr()
    assert captured.err == f"dmlo {command}: error: cannot read config {config}: {message}\n"
    assert "Traceback" not in captured.out + captured.err
    assert not (out / "poses_kitti.txt").exists()  # no frame was written


def test_the_cli_names_a_config_that_is_not_json(plain_scans: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "bad.json"
    config.write_text('{"ransac": {"threshold": 0.1,}}')
    assert dmlo_main(["run", str(plain_scans), "--format", "folder", "--config", str(config), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"dmlo run: error: cannot read config {config}: ") and err.count("\n") == 1
