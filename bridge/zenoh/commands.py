"""Remote command arguments, bounded: as guarded as a MAVLink command's seven floats.

A ``cmd/calibration/<name>`` query carries its arguments as a JSON object in
its payload and/or as selector parameters (``...start?what=level``). Anything
a sender puts there is parsed here, in zenoh's callback thread, before the
command is queued -- so the checks are cheap and everything they refuse is
answered at once with ``bad arguments: <why>``:

* the payload and the selector parameters at most :data:`MAX_ARGUMENT_BYTES`
  each; at most :data:`MAX_ARGUMENTS` arguments, names at most
  :data:`MAX_NAME_CHARS` characters;
* every value a scalar: a number (finite, integers of at most
  :data:`MAX_INT_DIGITS` digits), ``true``/``false``, ``null`` or a string of at
  most :data:`MAX_TEXT_CHARS` characters -- no nested objects or arrays (a
  deeply nested document is refused, not a stack overflow);
* a refusal quotes at most a few characters of what it refuses: a 4 MB
  argument is not echoed in the reply nor in the log.

Zenoh bounds the rest before any of this runs: the session's
``transport/link/rx/max_message_size`` (:mod:`bridge.zenoh.session`) keeps a
flood of huge queries from costing memory. :func:`query_args` reads a query's
arguments through these checks; :func:`reply_command` answers it with the
command's outcome.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any, Final

from bridge.zenoh import schema
from bridge.zenoh.contract import CommandOutcome
from bridge.zenoh.session import describe_error

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger(__name__)

#: Largest payload, and largest selector parameter string, of a command (bytes).
MAX_ARGUMENT_BYTES: Final = 4096
MAX_ARGUMENTS: Final = 16
MAX_NAME_CHARS: Final = 32
MAX_TEXT_CHARS: Final = 64
MAX_INT_DIGITS: Final = 18  #: beyond any real argument, well inside a float's exact range
_QUOTE_CHARS: Final = 24


class ArgumentError(ValueError):
    """An argument refused for what it is (not for malformed JSON)."""


def quote(v: object) -> str:
    """``repr(v)`` cut to a few characters (for messages about arguments)."""
    text = repr(v)
    return text if len(text) <= _QUOTE_CHARS else text[: _QUOTE_CHARS - 3] + "..."


def _int(text: str) -> int:
    if len(text.lstrip("-")) > MAX_INT_DIGITS:
        raise ArgumentError(f"integer of {len(text)} digits is out of range")
    return int(text)


def _float(text: str) -> float:
    v = float(text)
    if not math.isfinite(v):
        raise ArgumentError(f"number {quote(text)} is out of range")
    return v


def _constant(text: str) -> float:
    raise ArgumentError(f"{text} is not a number")


def _loads(text: str | bytes) -> Any:
    """JSON with bounded numbers; ValueError for anything malformed (deep nesting too)."""
    try:
        return json.loads(text, parse_int=_int, parse_float=_float, parse_constant=_constant)
    except RecursionError:
        raise ArgumentError("nested too deeply") from None


def _scalar(name: str, v: Any) -> Any:
    if isinstance(v, dict | list):
        raise ValueError(f"{quote(name)} must be a number, true/false or a text, not a structure")
    if isinstance(v, str) and len(v) > MAX_TEXT_CHARS:
        raise ValueError(f"{quote(name)}: text of {len(v)} characters (at most {MAX_TEXT_CHARS})")
    return v


def _put(args: dict[str, Any], name: str, v: Any) -> None:
    if not isinstance(name, str) or not name or len(name) > MAX_NAME_CHARS:
        raise ValueError(f"argument name {quote(name)} (1 to {MAX_NAME_CHARS} characters)")
    args[name] = _scalar(name, v)
    if len(args) > MAX_ARGUMENTS:
        raise ValueError(f"more than {MAX_ARGUMENTS} arguments")


def check_sizes(payload_bytes: int, parameter_chars: int) -> None:
    """ValueError when a payload or selector parameters are over :data:`MAX_ARGUMENT_BYTES`
    (checked before anything is read or copied)."""
    if parameter_chars > MAX_ARGUMENT_BYTES:
        raise ValueError(
            f"selector parameters of {parameter_chars} characters (at most {MAX_ARGUMENT_BYTES})"
        )
    if payload_bytes > MAX_ARGUMENT_BYTES:
        raise ValueError(f"payload of {payload_bytes} bytes (at most {MAX_ARGUMENT_BYTES})")


def parse_command_args(
    payload: bytes | None, parameters: str, pairs: Iterable[tuple[str, str]]
) -> dict[str, Any]:
    """The arguments of one command query (see the module docstring); ValueError says why not.

    ``payload`` is the query's payload (None: none), ``parameters`` its selector
    parameters as text (for the size check) and ``pairs`` the same, parsed by zenoh.
    A parameter value is taken as JSON where it parses (``true``, ``1``), else as
    text; the payload, a JSON object, wins over a parameter of the same name.
    """
    check_sizes(len(payload) if payload is not None else 0, len(parameters))
    args: dict[str, Any] = {}
    for k, v in pairs:
        try:
            value = _loads(v)
        except ArgumentError:
            raise
        except ValueError:
            value = v  # plain text (?what=level)
        _put(args, k, value)
    if payload:
        try:
            body = _loads(payload)
        except ArgumentError:
            raise
        except (ValueError, UnicodeDecodeError) as e:
            raise ValueError(f"payload is not JSON: {quote(str(e))}") from None
        if not isinstance(body, dict):
            raise ValueError("payload must be a JSON object")
        for k, v in body.items():
            _put(args, k, v)
    return args


def query_args(query: zenoh.Query) -> dict[str, Any]:
    """Arguments from the query's JSON payload (an object) and its selector parameters,
    bounded (:func:`parse_command_args`); ValueError says why not."""
    params = query.parameters
    text = str(params)
    payload = query.payload
    size = len(payload) if payload is not None else 0
    check_sizes(size, len(text))  # refused unread
    data = payload.to_bytes() if payload is not None and size else None
    pairs: list[tuple[str, str]] = list(params)  # type: ignore[call-overload]  # stub: __iter__ -> list
    return parse_command_args(data, text, pairs)


def reply_command(query: zenoh.Query, key: str, cmd: str, outcome: CommandOutcome) -> None:
    """Answer a command's query on ``key`` with its outcome (a command result document),
    and end the query: its final reply goes now, not when the object is collected."""
    import zenoh

    doc = schema.command_result_doc(cmd, outcome.ok, outcome.message, outcome.detail)
    try:
        query.reply(
            key,
            schema.dumps(doc),
            encoding=zenoh.Encoding(schema.encoding_text(schema.COMMAND_RESULT)),
        )
    except Exception as e:
        log.debug("zenoh: replying to %s failed: %s", key, describe_error(e))
    finally:
        with contextlib.suppress(Exception):
            query.drop()
