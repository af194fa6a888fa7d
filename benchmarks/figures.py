"""A benchmark's figures: :class:`Figure` (a value against its target), the table they are
printed as and the JSON they are written as (:func:`report`), and the CPU clock and
progress callback the in-process measurements share."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bridge.tools.progress import progress_option

#: A measurement's progress: (fraction done, what it is doing).
Step = Callable[[float, str], None]


def no_step(frac: float, note: str) -> None:
    """A :data:`Step` that shows nothing."""
    return None


def process_cpu() -> float:
    """User+system CPU seconds of this process so far, every thread (native ones included),
    to the nanosecond (CLOCK_PROCESS_CPUTIME_ID; ``os.times`` counts 10 ms ticks)."""
    return time.process_time()


@dataclass(slots=True)
class Figure:
    """One measured figure against its target (``target`` None: reported only)."""

    name: str
    value: float
    unit: str
    target: float | None = None
    lower_is_better: bool = True
    detail: dict[str, Any] = field(default_factory=dict)

    @property
    def passed(self) -> bool | None:
        """PASS/FAIL against the target; None when there is none or nothing was measured."""
        if self.target is None or not math.isfinite(self.value):
            return None if self.target is None else False
        return self.value <= self.target if self.lower_is_better else self.value >= self.target

    def verdict(self) -> str:
        """``PASS``, ``FAIL`` or ``-``."""
        p = self.passed
        return "-" if p is None else ("PASS" if p else "FAIL")

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (NaN becomes None)."""
        v = self.value if math.isfinite(self.value) else None
        return {
            "name": self.name,
            "value": v,
            "unit": self.unit,
            "target": self.target,
            "target_is": None
            if self.target is None
            else ("max" if self.lower_is_better else "min"),
            "passed": self.passed,
            "detail": self.detail,
        }


def format_figures(figures: list[Figure]) -> str:
    """The human table: name, value, target, verdict."""
    lines = []
    for f in figures:
        target = "" if f.target is None else f"{'<=' if f.lower_is_better else '>='} {f.target:g}"
        value = f"{f.value:,.3f}" if abs(f.value) < 100 else f"{f.value:,.0f}"
        lines.append(f"{f.name:<16} {value:>12} {f.unit:<24} {target:<10} {f.verdict()}")
        extra = ", ".join(f"{k} {v}" for k, v in f.detail.items())
        if extra:
            lines.append(f"{'':<16} {extra}")
    return "\n".join(lines)


def json_option(ap: argparse.ArgumentParser) -> None:
    """``--json FILE``, the same on every benchmark: the figures also written as JSON to
    FILE, or with ``-`` printed as JSON on standard output instead of the text."""
    ap.add_argument(
        "--json", metavar="FILE", help="also write the figures as JSON ('-': JSON on stdout)"
    )


def write_json(
    text: str, doc: Any, json_to: str | None, default: Callable[[Any], Any] | None = None
) -> bool:
    """What :func:`json_option` asks: ``text`` printed and ``doc`` written as JSON to
    ``json_to`` (when given), or ``doc`` printed as JSON instead of ``text`` (``-``).
    ``default`` is for what json cannot write itself. False (said on stderr) when the file
    could not be written."""
    if json_to == "-":
        print(json.dumps(doc, indent=2, default=default))
        return True
    print(text)
    if json_to:
        try:
            Path(json_to).write_text(json.dumps(doc, indent=2, default=default) + "\n")
        except OSError as exc:
            print(f"cannot write {json_to}: {exc}", file=sys.stderr)
            return False
    return True


def report_options(ap: argparse.ArgumentParser, *, progress: bool = True) -> None:
    """``--json FILE`` (:func:`json_option`) and, with ``progress``, ``--progress``."""
    json_option(ap)
    if progress:
        progress_option(ap, "live bar")


def report(figures: list[Figure], json_to: str | None, **extra: Any) -> int:
    """Print the figures (a table, or JSON with ``json_to="-"``), maybe write them as JSON.

    Returns the exit code of a benchmark: 0 when every figure meets its target (2 when
    the JSON could not be written).
    """
    ok = all(f.passed is not False for f in figures)
    doc = {"figures": [f.to_dict() for f in figures], "passed": ok, **extra}
    text = f"{format_figures(figures)}\noverall: {'PASS' if ok else 'FAIL'}"
    if not write_json(text, doc, json_to):
        return 2
    return 0 if ok else 1


def result_options(p: argparse.ArgumentParser, progress: str) -> None:
    """``--json FILE`` (:func:`json_option`) and ``--progress`` of a benchmark that prints a
    result dict with its ``targets`` (``progress``: what the bar shows, for the help); see
    :func:`finish`."""
    json_option(p)
    progress_option(p, progress)


def finish(
    text: str,
    result: dict[str, Any],
    json_to: str | None,
    default: Callable[[Any], Any] | None = None,
) -> int:
    """Print ``text`` (the result's report) and write ``result`` as JSON as ``json_to`` asks
    (:func:`write_json`). Returns the exit code: 2 when the JSON could not be written, else
    0 when every target passed."""
    if not write_json(text, result, json_to, default):
        return 2
    return 0 if all(t["pass"] for t in result["targets"]) else 1
