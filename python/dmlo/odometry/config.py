"""The odometry's settings: small typed sections with the paper's defaults, saved beside every result.

Every setting is declared once, in the crate (`dmlo_rs::odometry::config`): its type, default, range and
doc. The classes here are made from that declaration (`dmlo_rs.odometry_config_schema()`) when this module
is imported, and every check is the crate's: a config is checked when it is loaded
(`OdometryConfig.from_dict`, `load`) and when an odometry is built from it (`OdometryConfig.validate`,
since fields may be changed after loading), so a bad value fails before the first scan, as one
`ConfigError` naming each bad key: ``ransac.threshold: must be a number > 0, got "abc"``.
`config.pyi` beside this file gives type checkers the same classes (`python -m dmlo.odometry.config`
writes it from the schema; a test keeps it current).
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import dmlo_rs

ConfigError = dmlo_rs.ConfigError

SCHEMA: dict[str, Any] = json.loads(dmlo_rs.odometry_config_schema())


def class_name(section_key: str) -> str:
    """The Python class of a section: `motion_model` → `MotionModelConfig`."""
    return "".join(part.capitalize() for part in section_key.split("_")) + "Config"


def _default(setting: dict[str, Any]) -> Any:
    value = setting["default"]
    return tuple(value) if isinstance(value, list) else value


_TYPES = {"bool": bool, "int": int, "float": float, "str": str, "list[float]": tuple}


def _field(setting: dict[str, Any]) -> tuple[str, Any, Any]:
    kind: Any = _TYPES[setting["type"]]
    if setting["optional"]:
        kind = kind | None
    return setting["key"], kind, dataclasses.field(default=_default(setting))


def _doc(doc: str, settings: list[dict[str, Any]]) -> str:
    lines = [doc, "", "Settings:"]
    for setting in settings:
        lines.append(f"    {setting['key']} ({setting['rule']}; default {setting['default']!r}): {setting['doc']}")
    return "\n".join(lines)


def _section_class(section: dict[str, Any]) -> type:
    cls = dataclasses.make_dataclass(class_name(section["key"]), [_field(s) for s in section["settings"]])
    cls.__doc__ = _doc(section["doc"], section["settings"])
    cls.__module__ = __name__
    return cls


SECTIONS: dict[str, type] = {section["key"]: _section_class(section) for section in SCHEMA["sections"]}
globals().update({cls.__name__: cls for cls in SECTIONS.values()})


class _Config:
    """Loading, saving and checking, for the class made below: every rule is the crate's."""

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)  # type: ignore[call-overload]

    @classmethod
    def from_dict(cls, data: Any) -> Any:
        """The config a mapping of settings describes (JSON's lists for tuples), checked by the crate;
        `ConfigError` names every bad key."""
        checked = json.loads(dmlo_rs.odometry_config_json(_as_json(data)))
        sections = {key: section(**_tuples(checked.pop(key))) for key, section in SECTIONS.items()}
        return cls(**sections, **_tuples(checked))

    def validate(self) -> None:
        """Checks every setting as it is now (fields may have been changed since loading): `ConfigError`."""
        for key, section in SECTIONS.items():
            value = getattr(self, key)
            if not isinstance(value, section):
                raise ConfigError(f"{key}: must be a {section.__name__}, got {value!r}")
        dmlo_rs.odometry_config_json(_as_json(self.to_dict()))

    def save(self, path: Path) -> None:
        """The config as the crate writes it (every key; `Infinity` for no limit)."""
        path.write_text(dmlo_rs.odometry_config_json(_as_json(self.to_dict())) + "\n")

    @classmethod
    def load(cls, path: Path) -> Any:
        """A config file (JSON); `ConfigError` for settings out of the schema, ValueError for bad JSON,
        OSError when it cannot be read."""
        return cls.from_dict(json.loads(path.read_text()))


def _as_json(data: Any) -> str:
    """`data` as JSON for the crate; a value JSON cannot hold is written as its repr, which the crate then
    names as the wrong type."""
    return json.dumps(data, default=repr)


def _tuples(values: dict[str, Any]) -> dict[str, Any]:
    """The settings with JSON's lists as the tuples the classes hold."""
    return {key: tuple(value) if isinstance(value, list) else value for key, value in values.items()}


OdometryConfig = dataclasses.make_dataclass(
    "OdometryConfig",
    [(key, section, dataclasses.field(default_factory=section)) for key, section in SECTIONS.items()]
    + [_field(s) for s in SCHEMA["settings"]],
    bases=(_Config,),
)
OdometryConfig.__module__ = __name__
OdometryConfig.__doc__ = _doc("Every setting of the odometry; the defaults are `dmlo run`'s.", SCHEMA["settings"])


def stub_text() -> str:
    """`config.pyi`: the classes above as a type checker reads them, written from the schema."""
    def annotation(setting: dict[str, Any]) -> str:
        if setting["type"] == "str":
            kind = "Literal[" + ", ".join(json.dumps(c) for c in setting["choices"]) + "]"
        else:
            kind = {"list[float]": "tuple[float, ...]"}.get(setting["type"], setting["type"])
        return f"{kind} | None" if setting["optional"] else kind

    lines = [
        '"""Generated from the crate\'s schema by `python -m dmlo.odometry.config`; do not edit."""',
        "",
        "from pathlib import Path",
        "from typing import Any, Literal",
        "",
        "import dmlo_rs",
        "",
        "ConfigError = dmlo_rs.ConfigError",
        "SCHEMA: dict[str, Any]",
        "SECTIONS: dict[str, type]",
        "",
        "def class_name(section_key: str) -> str: ...",
        "def stub_text() -> str: ...",
    ]
    for section in SCHEMA["sections"]:
        lines += ["", f"class {class_name(section['key'])}:"]
        lines += [f"    {s['key']}: {annotation(s)}" for s in section["settings"]]
        lines.append(f"    def __init__(self, {', '.join(s['key'] + ': ' + annotation(s) + ' = ...' for s in section['settings'])}) -> None: ...")
    top = [f"{s['key']}: {annotation(s)}" for s in SCHEMA["settings"]]
    sections = [f"{s['key']}: {class_name(s['key'])}" for s in SCHEMA["sections"]]
    lines += ["", "class OdometryConfig:"]
    lines += [f"    {line}" for line in sections + top]
    lines += [
        f"    def __init__(self, {', '.join(line + ' = ...' for line in sections + top)}) -> None: ...",
        "    def to_dict(self) -> dict[str, Any]: ...",
        "    @classmethod",
        "    def from_dict(cls, data: Any) -> OdometryConfig: ...",
        "    def validate(self) -> None: ...",
        "    def save(self, path: Path) -> None: ...",
        "    @classmethod",
        "    def load(cls, path: Path) -> OdometryConfig: ...",
    ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    target = Path(__file__).with_suffix(".pyi")
    target.write_text(stub_text())
    print(f"wrote {target}", file=sys.stderr)
