"""Declaring a configuration: sections are frozen dataclasses whose fields are :func:`setting`\\ s.

Adding a key is ONE line in a section dataclass::

    rate_hz: int = setting(10, one_of(1, 2, 5, 10, 20, 50, 100), "output rate asked of the device", "Hz")

The annotation gives the TOML type, :func:`setting` the default, the rule (a
:class:`~bridge.configkit.rules.Rule`: range, choices, shape), the text the
docs use and the unit. Checks that span keys live in the section's
:meth:`Section.finish` hook; values computed at load (not keys) are
:func:`derived`.
"""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Self

from bridge.configkit.rules import Rule


class ConfigError(ValueError):
    """An invalid configuration: ``key`` is the dotted key (or file), ``reason`` why."""

    def __init__(self, key: str, reason: str) -> None:
        super().__init__(f"{key}: {reason}")
        self.key = key
        self.reason = reason


def setting(
    default: Any,
    rule: Rule | None = None,
    doc: str = "",
    unit: str = "",
    *,
    required: bool = False,
) -> Any:
    """Declare one TOML key: default, validation rule, docs text and unit."""
    meta = {"rule": rule, "doc": doc, "unit": unit, "required": required}
    return field(default=default, metadata=meta)


def derived(default: Any, doc: str = "") -> Any:
    """A value computed at load (not a TOML key), e.g. the signing key read from its file."""
    return field(default=default, metadata={"derived": True, "doc": doc}, compare=False)


@dataclass(frozen=True, slots=True)
class LoadContext:
    """What a section's ``finish()`` may consult: the environment and the host name."""

    env: Mapping[str, str]
    hostname: str


class Section:
    """Mixin for section dataclasses: ``finish`` does cross-key checks and derived values."""

    __slots__ = ()

    def finish(self, ctx: LoadContext) -> Self:
        """Return the section, possibly with derived values set; raise ConfigError if bad."""
        return self


def section_types(config_cls: type) -> dict[str, type[Section]]:
    """Section name -> its dataclass, in the order ``config_cls`` declares them."""
    hints = typing.get_type_hints(config_cls)
    out: dict[str, type[Section]] = {}
    for f in dataclasses.fields(config_cls):
        t = hints[f.name]
        args = [a for a in typing.get_args(t) if a is not type(None)]
        out[f.name] = args[0] if args else t
    return out


def optional_sections(config_cls: type) -> frozenset[str]:
    """Sections typed ``X | None`` (absent from the file means None)."""
    hints = typing.get_type_hints(config_cls)
    return frozenset(
        f.name
        for f in dataclasses.fields(config_cls)
        if type(None) in typing.get_args(hints[f.name])
    )


_HINTS: dict[type, dict[str, Any]] = {}


def field_hints(cls: type) -> dict[str, Any]:
    """Resolved annotations of a section (cached: overrides ask per key)."""
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


def settings_of(cls: type[Section]) -> list[dataclasses.Field[Any]]:
    """The TOML keys of a section (its fields that are not derived)."""
    return [f for f in dataclasses.fields(cls) if not f.metadata.get("derived")]  # type: ignore[arg-type]


def _type_name(t: Any) -> str:
    if typing.get_origin(t) is tuple:
        return f"list of {_type_name(typing.get_args(t)[0])}s"
    return {str: "string", int: "integer", float: "number", bool: "boolean"}.get(t, str(t))


def type_name(cls: type[Section], name: str) -> str:
    """Human name of a key's TOML type ("string", "integer", "list of strings")."""
    return _type_name(field_hints(cls)[name])


def annotation_type_name(t: Any) -> str:
    """Human name of a TOML type given by an annotation."""
    return _type_name(t)
