"""The command line's value types: each turns one option's text into a value, or an
:class:`argparse.ArgumentTypeError` that argparse prints as a usage error."""

from __future__ import annotations

import argparse
import math


def zenoh_endpoint(text: str) -> str:
    """``--connect``/``--listen`` value: a zenoh endpoint (same rule as the config)."""
    from bridge.config import zenoh_endpoint as check

    try:
        return str(check(text))
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def positive_seconds(text: str) -> float:
    """A positive, finite number of seconds."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not v > 0 or v == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number of seconds, got {text!r}")
    return v


#: Options whose value may start with a minus sign (a southern latitude, a western longitude).
SIGNED_VALUE_OPTIONS = frozenset({"--location"})


def glue_negative_values(argv: list[str]) -> list[str]:
    """``--location -35.36,149.16`` as ``--location=-35.36,149.16``: argparse takes a word
    starting with ``-`` for an option unless it is a plain negative number, and
    ``-35.36,149.16`` (a southern latitude) is not one."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        a = argv[i]
        nxt = argv[i + 1] if i + 1 < len(argv) else ""
        if a in SIGNED_VALUE_OPTIONS and len(nxt) > 1 and nxt[0] == "-" and nxt[1] in "0123456789.":
            out.append(f"{a}={nxt}")
            i += 2
            continue
        if a == "--":
            out.extend(argv[i:])
            break
        out.append(a)
        i += 1
    return out


def location(text: str) -> tuple[float, float, float]:
    """``LAT,LON[,ALT]`` for ``simulate --location``."""
    try:
        parts = [float(p) for p in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not numbers: {text!r}") from None
    if len(parts) not in (2, 3) or not (-90 <= parts[0] <= 90 and -180 <= parts[1] <= 180):
        raise argparse.ArgumentTypeError(
            f"want LAT,LON[,ALT] in degrees (and metres), got {text!r}"
        )
    return (parts[0], parts[1], parts[2] if len(parts) == 3 else 0.0)


def hard_iron_change(text: str) -> tuple[tuple[float, float, float], float]:
    """``X,Y,Z@S`` (mG, seconds) for ``simulate --hard-iron-change``: (gauss vector, time)."""
    vec, at, when = text.partition("@")
    try:
        parts = [float(p) / 1000.0 for p in vec.split(",")]
        t = float(when) if at else 0.0
    except ValueError:
        raise argparse.ArgumentTypeError(f"want X,Y,Z@S (mG, seconds), got {text!r}") from None
    if len(parts) != 3 or not all(math.isfinite(v) for v in (*parts, t)) or t < 0.0:
        raise argparse.ArgumentTypeError(f"want X,Y,Z@S (mG, seconds), got {text!r}")
    return (parts[0], parts[1], parts[2]), t
