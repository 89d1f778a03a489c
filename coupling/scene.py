"""Scenes: TOML files describing a coupled run, validated on load.

A scene is one table per concern (``[scene]`` and the tables of its application: see
:mod:`coupling.apps.punch.scene` and :mod:`coupling.apps.penetration.scene`), each a frozen
dataclass of typed defaults; ``scene.kind`` picks the application's schema from
:mod:`coupling.applications`. Layering (pyro2 / FFCx style): dataclass defaults, then the TOML file,
then ``--set section.key=value`` overrides. An unknown section or key, a value of the wrong
type, or a value out of range raises :class:`SceneError` naming ``section.key``.

A key that sets a run parameter is declared with :func:`parameter`: its default, range and
message are the parameter dataclass's (stated once), and :func:`parameter_keys` maps the
dataclass's messages back to ``section.key``.
"""

from __future__ import annotations

import dataclasses
import math
import re
import tomllib
from dataclasses import dataclass, fields
from pathlib import Path

from coupling.applications import APPLICATIONS, application

__all__ = ["SceneError", "SceneInfo", "load_scene", "parse_overrides", "KINDS", "parameter",
           "parameter_keys", "parameter_values"]

KINDS = tuple(APPLICATIONS)


class SceneError(ValueError):
    """A scene file problem; the message names the key (``section.key``) and the rule."""


def _positive(section, name, value):
    if not (math.isfinite(value) and value > 0):
        raise SceneError(f"{section}.{name} must be > 0, got {value!r}")


def _in_range(key, value, lo, hi, text, upper_open=False):
    ok = math.isfinite(value) and lo <= value and (value < hi if upper_open else value <= hi)
    if not ok:
        raise SceneError(f"{key} must lie in {text}, got {value!r}")


@dataclass(frozen=True)
class SceneInfo:
    """The ``[scene]`` table: a name (the output directory), the application (``kind``) and
    the dimension it runs in."""

    name: str = "scene"
    kind: str = "bonded_punch"
    dimension: int = 2

    def __post_init__(self):
        if not self.name or self.name in (".", "..") or any(c in self.name for c in "/\0"):
            raise SceneError(f"scene.name must be a plain name (it names the output directory), "
                             f"got {self.name!r}")
        if self.kind not in KINDS:
            raise SceneError(f"scene.kind must be one of {list(KINDS)}, got {self.kind!r}")
        allowed = APPLICATIONS[self.kind].dimensions
        if self.dimension not in allowed:
            raise SceneError(f"scene.dimension must be one of {list(allowed)} for kind {self.kind!r}, "
                             f"got {self.dimension!r}")


class _Tables:
    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def to_toml(self) -> str:
        lines = []
        for section, values in self.to_dict().items():
            lines.append(f"[{section}]")
            for k, v in values.items():
                lines.append(f"{k} = {_toml_value(v)}")
            lines.append("")
        return "\n".join(lines)


def _named(message: str, keys: dict) -> str:
    """``message`` with the parameter names it mentions (leading, or as ``name = value``)
    replaced by the scene's ``section.key``."""
    for name, key in sorted(keys.items(), key=lambda kv: -len(kv[0])):
        if message.startswith(name + " "):
            message = key + message[len(name):]
        message = re.sub(rf"(?<![\w.]){re.escape(name)}(?= = )", key, message)
    return message


def parameter(owner, name: str, default=dataclasses.MISSING):
    """A scene key that sets the field ``name`` of the parameter dataclass ``owner``; its
    default is that field's (stated once, there) unless the scene spells it differently."""
    f = owner.__dataclass_fields__[name]
    return dataclasses.field(default=f.default if default is dataclasses.MISSING else default,
                             metadata={"parameter": (owner, name)})


def _parameter_fields(tables, owner):
    """``(section, key, field of owner)`` of every scene key declared with :func:`parameter`
    for ``owner`` (``tables``: the scene dataclass or its type)."""
    for section in fields(tables):
        for f in fields(section.default_factory()):
            target = f.metadata.get("parameter")
            if target is not None and target[0] is owner:
                yield section.name, f.name, target[1]


def parameter_keys(tables, owner) -> dict[str, str]:
    """``{field of owner: "section.key"}`` over the scene's tables (a dataclass or its type)."""
    return {name: f"{section}.{key}" for section, key, name in _parameter_fields(tables, owner)}


def parameter_values(scene, owner) -> dict:
    """``{field of owner: value}`` read from the scene's tables."""
    return {name: getattr(getattr(scene, section), key) for section, key, name in _parameter_fields(scene, owner)}


def _toml_value(v):
    """``v`` as a TOML value that :mod:`tomllib` reads back equal."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return _toml_string(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
    return repr(v)


_ESCAPES = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f",
            "\r": "\\r"}


def _toml_string(s: str) -> str:
    """A TOML basic string: quotes, backslashes and control characters escaped."""
    out = []
    for ch in s:
        if ch in _ESCAPES:
            out.append(_ESCAPES[ch])
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04X}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _coerce(section: str, key: str, value, expected_type):
    if expected_type is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if expected_type is bool and not isinstance(value, bool):
        raise SceneError(f"{section}.{key} must be true or false, got {value!r}")
    if expected_type is int and (isinstance(value, bool) or not isinstance(value, int)):
        raise SceneError(f"{section}.{key} must be an integer, got {value!r}")
    if not isinstance(value, expected_type):
        raise SceneError(f"{section}.{key} must be a {expected_type.__name__}, got {value!r}")
    return value


def _build(data: dict):
    info = data.get("scene")
    kind = info.get("kind", "bonded_punch") if isinstance(info, dict) else "bonded_punch"
    try:
        app = application(kind)
    except ValueError as err:
        raise SceneError(str(err)) from None
    schema = app.load("scene")
    _SECTIONS = {f.name: type(f.default_factory()) for f in fields(schema)}
    sections = {}
    for name, values in data.items():
        if name not in _SECTIONS:
            raise SceneError(f"unknown section [{name}]; known sections: {sorted(_SECTIONS)}")
        if not isinstance(values, dict):
            raise SceneError(f"[{name}] must be a table")
        cls = _SECTIONS[name]
        types = {f.name: eval(f.type, {}, {}) if isinstance(f.type, str) else f.type  # noqa: S307
                 for f in fields(cls)}
        for key in values:
            if key not in types:
                raise SceneError(f"unknown key {name}.{key}; known keys of [{name}]: {sorted(types)}")
        kwargs = {k: _coerce(name, k, v, types[k]) for k, v in values.items()}
        if name == "scene":
            kwargs.setdefault("name", app.default_name)
        sections[name] = cls(**kwargs)
    return schema(**sections)


def parse_overrides(items: list[str]) -> dict:
    """``["window.half_width=0.08", ...]`` -> nested dict (values parsed as TOML)."""
    out: dict = {}
    for item in items or []:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise SceneError(f"--set expects section.key=value, got {item!r}")
        path, value = item.split("=", 1)
        section, key = path.strip().split(".", 1)
        try:
            parsed = tomllib.loads(f"v = {value.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            parsed = value.strip()  # bare strings
        out.setdefault(section, {})[key] = parsed
    return out


def load_scene(path: str | Path | None = None, overrides: dict | None = None):
    """Scene from a TOML file (or defaults) with overrides; raises :class:`SceneError`."""
    data: dict = {}
    if path is not None:
        path = Path(path)
        if not path.exists():
            raise SceneError(f"scene file {path} does not exist")
        if path.is_dir():
            raise SceneError(f"{path} is a directory, not a scene file (to continue a run in it: "
                             f"granfe restart {path})")
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except tomllib.TOMLDecodeError as err:
            raise SceneError(f"{path} is not valid TOML: {err}") from None
        except UnicodeDecodeError:
            raise SceneError(f"{path} is not a text (UTF-8 TOML) scene file") from None
        except OSError as err:
            raise SceneError(f"cannot read {path}: {err.strerror or err}") from None
    for section, values in (overrides or {}).items():
        data.setdefault(section, {}).update(values)
    return _build(data)
