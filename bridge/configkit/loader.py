"""The generic loader: TOML text + ``SECTION.KEY=VALUE`` overrides -> validated dataclasses.

It walks any configuration class whose fields are sections (see
:mod:`bridge.configkit.schema`); it knows none of them by name. Every failure is
a :class:`~bridge.configkit.schema.ConfigError` naming the file or the key --
never another exception, never a hang: the file is read with
:func:`bridge.files.read_regular_file` (a regular file, bounded), must be
UTF-8, and nesting too deep for the parser is an error like any other.
"""

from __future__ import annotations

import difflib
import math
import os
import tomllib
import typing
from collections.abc import Mapping, Sequence
from typing import Any

from bridge.configkit.rules import ItemError, Rule, short_repr
from bridge.configkit.schema import (
    ConfigError,
    LoadContext,
    Section,
    annotation_type_name,
    field_hints,
    optional_sections,
    section_types,
    settings_of,
)
from bridge.files import FileRefused, read_regular_file

#: A configuration file is a few kB; anything over this is a mistake (or /dev/zero).
MAX_CONFIG_BYTES = 1 << 20


def show_path(path: str | os.PathLike[str]) -> str:
    """A path as an error message shows it: as is when printable, else escaped (NUL...)."""
    text = os.fspath(path)
    return text if text.isprintable() else repr(text)


def toml_kind(v: Any) -> str:
    """The TOML kind of a parsed value ("integer", "list", "table", ...)."""
    if isinstance(v, bool):
        return "boolean"
    if isinstance(v, int):
        return "integer"
    if isinstance(v, float):
        return "number"
    if isinstance(v, str):
        return "string"
    if isinstance(v, list):
        return "list"
    if isinstance(v, dict):
        return "table"
    return type(v).__name__


def coerce(t: Any, v: Any) -> Any:
    """Check ``v``'s TOML type against annotation ``t``; ValueError(reason) if wrong."""
    want = annotation_type_name(t)
    if typing.get_origin(t) is tuple:
        (item,) = typing.get_args(t)[:1]
        if not isinstance(v, list):
            raise ValueError(f"must be a {want}, got {toml_kind(v)}")
        out = []
        for i, x in enumerate(v):
            try:
                out.append(coerce(item, x))
            except ValueError as e:
                raise ItemError(i, str(e)) from None
        return tuple(out)
    ok = {
        str: isinstance(v, str),
        bool: isinstance(v, bool),
        int: isinstance(v, int) and not isinstance(v, bool),
        # TOML distinguishes 2 from 2.0; a float key accepts both.
        float: isinstance(v, int | float) and not isinstance(v, bool),
    }.get(t)
    if ok is None:  # pragma: no cover - a programming error in a section declaration
        raise TypeError(f"unsupported setting type {t!r}")
    if not ok:
        raise ValueError(f"must be a {want}, got {toml_kind(v)} {short_repr(v)}")
    if t is float:
        v = float(v)
        if not math.isfinite(v):
            raise ValueError(f"must be a finite number, got {v}")
    if t is str and "\x00" in v:
        # No OS call takes a NUL in a path, no protocol in an address or key: it can
        # only fail later, in a worker thread. Refused here for every string key.
        raise ValueError(f"contains a NUL byte: {short_repr(v)}")
    return v


def _unknown(key: str, name: str, known: Sequence[str], what: str = "key") -> ConfigError:
    close = difflib.get_close_matches(name, known, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return ConfigError(show_path(key), f"unknown {what}{hint}; known: {', '.join(known)}")


def build_section(cls: type[Section], raw: Mapping[str, Any], name: str, ctx: LoadContext) -> Any:
    """One section from its TOML table: unknown keys, types, rules, then ``finish``."""
    fields = settings_of(cls)
    known = [f.name for f in fields]
    for k in raw:
        if k not in known:
            raise _unknown(f"{name}.{k}", k, known)
    hints = field_hints(cls)
    values: dict[str, Any] = {}
    for f in fields:
        key = f"{name}.{f.name}"
        if f.name not in raw:
            if f.metadata.get("required"):
                others = ", ".join(g.name for g in fields if g.metadata.get("required"))
                raise ConfigError(key, f"required when [{name}] is present ({others} go together)")
            continue
        rule: Rule | None = f.metadata.get("rule")
        try:
            v = coerce(hints[f.name], raw[f.name])
            values[f.name] = rule(v) if rule is not None else v
        except ItemError as e:
            raise ConfigError(f"{key}[{e.index}]", str(e)) from None
        except ValueError as e:
            raise ConfigError(key, str(e)) from None
    return cls(**values).finish(ctx)


def build(config_cls: type, raw: Mapping[str, Any], ctx: LoadContext) -> Any:
    """The whole configuration from a parsed document (absent sections: defaults / None)."""
    sections = section_types(config_cls)
    optional = optional_sections(config_cls)
    for k in raw:
        if k not in sections:
            raise _unknown(k, k, list(sections), "section")
    built: dict[str, Any] = {}
    for name, cls in sections.items():
        sub = raw.get(name)
        if sub is None:
            if name in optional:  # absent means "unknown", e.g. [location]
                continue
            sub = {}
        if not isinstance(sub, dict):
            raise ConfigError(name, f"must be a table [{name}], got {toml_kind(sub)}")
        built[name] = build_section(cls, sub, name, ctx)
    return config_cls(**built)


def _parse_override(config_cls: type, item: str) -> tuple[str, str, Any]:
    key, eq, text = item.partition("=")
    key = key.strip()
    parts = key.split(".")
    if not eq or len(parts) != 2 or not all(parts):
        raise ConfigError(show_path(key or item), "an override must look like SECTION.KEY=VALUE")
    section, name = parts
    value: Any
    try:
        value = tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        value = text  # bare words are strings: --set device.port=sim
    except RecursionError:
        raise ConfigError(show_path(key), "value nested too deeply") from None
    cls = section_types(config_cls).get(section)
    if cls is not None and name in field_hints(cls) and field_hints(cls)[name] is str:
        value = text if not isinstance(value, str) else value  # "--set x.y=007" stays a string
    return section, name, value


def merge_overrides(
    config_cls: type, raw: Mapping[str, Any], overrides: Sequence[str]
) -> dict[str, Any]:
    """Apply ``SECTION.KEY=VALUE`` overrides (values parsed as TOML, else strings) to ``raw``."""
    out: dict[str, Any] = {k: dict(v) if isinstance(v, dict) else v for k, v in raw.items()}
    for item in overrides:
        section, name, value = _parse_override(config_cls, item)
        table = out.setdefault(section, {})
        if not isinstance(table, dict):
            raise ConfigError(section, f"must be a table [{section}], got {toml_kind(table)}")
        table[name] = value
    return out


def read_toml(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a TOML file; any failure is a :class:`ConfigError` naming the file.

    The file must be a regular file of at most :data:`MAX_CONFIG_BYTES` (never a
    device or a FIFO: ``--config /dev/zero`` is refused, not read forever) and
    UTF-8 text, as TOML requires.
    """
    where = show_path(path)
    try:
        data = read_regular_file(path, MAX_CONFIG_BYTES)
    except FileRefused as e:
        raise ConfigError(where, f"cannot read: {e}") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        bom = " (UTF-16? save it as UTF-8)" if data[:2] in (b"\xff\xfe", b"\xfe\xff") else ""
        raise ConfigError(
            where, f"not UTF-8 text: byte 0x{data[e.start]:02x} at offset {e.start}{bom}"
        ) from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(where, f"not valid TOML: {e}") from None
    except RecursionError:
        raise ConfigError(where, "not valid TOML: arrays or tables nested too deeply") from None


def load(
    config_cls: type,
    path: str | os.PathLike[str] | None,
    overrides: Sequence[str],
    ctx: LoadContext,
) -> Any:
    """Defaults < the file at ``path`` (if any) < ``overrides``, validated."""
    raw = read_toml(path) if path is not None else {}
    return build(config_cls, merge_overrides(config_cls, raw, overrides), ctx)


def to_toml(cfg: Any) -> str:
    """The effective configuration as TOML (derived values omitted), e.g. for ``config``."""
    lines: list[str] = []
    for name in section_types(type(cfg)):
        sec = getattr(cfg, name)
        if sec is None:
            continue
        lines.append(f"[{name}]")
        for f in settings_of(type(sec)):
            lines.append(f"{f.name} = {toml_value(getattr(sec, f.name))}")
        lines.append("")
    return "\n".join(lines)


def _toml_char(c: str) -> str:
    if c in '"\\':
        return "\\" + c
    # TOML basic strings may not hold control characters (DEL included) unescaped.
    return f"\\u{ord(c):04X}" if ord(c) < 0x20 or c == "\x7f" else c


def toml_value(v: Any) -> str:
    """One value in TOML syntax (strings as basic strings, escaped where TOML needs it)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + "".join(_toml_char(c) for c in v) + '"'
    if isinstance(v, tuple):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    return repr(v)
