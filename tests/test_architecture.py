"""The layer rule of docs/architecture.md holds: `lint-imports` keeps every contract in
pyproject.toml (layers, adapters independent, no import cycle in a package, TYPE_CHECKING
imports included), and the package has no compiled twin of its Python."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.integration
def test_the_import_contracts_are_kept() -> None:
    lint = Path(sys.executable).with_name("lint-imports")
    r = subprocess.run([str(lint)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    assert ", 0 broken." in r.stdout


def test_no_compiled_twin() -> None:
    assert not list((ROOT / "bridge").rglob("*.c"))


def test_no_module_over_700_lines() -> None:
    """A module a next engineer can read in one sitting: the package, the benchmarks and
    the tests (their helper modules too)."""
    big = {
        str(p.relative_to(ROOT)): n
        for top in ("bridge", "benchmarks", "tests")
        for p in (ROOT / top).rglob("*.py")
        if (n := len(p.read_text().splitlines())) > 700
    }
    assert not big, big
