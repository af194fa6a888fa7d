"""docs/configuration.md is generated from the configuration's and the parameters' own
declarations, and fresh (the parameters' rows: tests/test_param_docs.py)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from bridge.app.paramdocs import reference_markdown
from bridge.config import section_types, settings_of, type_name
from bridge.configkit.loader import toml_value

REFERENCE = Path(__file__).resolve().parents[1] / "docs" / "configuration.md"


def test_committed_reference_is_the_generated_one() -> None:
    """Fails when a setting() changed and docs/configuration.md was not regenerated."""
    assert REFERENCE.read_text() == reference_markdown(), (
        "docs/configuration.md is stale: run `compass-bridge config --docs > docs/configuration.md`"
    )


def test_every_key_has_a_row_with_its_type_default_and_meaning() -> None:
    text = reference_markdown()
    for section, cls in section_types().items():
        assert f"## `[{section}]`" in text
        for f in settings_of(cls):
            row = next(
                (
                    line
                    for line in text.splitlines()
                    if line.startswith(f"| `{section}.{f.name}` |")
                ),
                None,
            )
            assert row is not None, f"{section}.{f.name} has no row"
            cells = [c.strip() for c in row.strip("|").split(" | ")]
            assert cells[1] == type_name(cls, f.name)
            want_default = "required" if f.metadata["required"] else f"`{toml_value(f.default)}`"
            assert cells[2] == want_default.replace("|", "\\|")
            assert f.metadata["doc"], f"{section}.{f.name} has no doc text"
            assert cells[4] == " ".join(f.metadata["doc"].split())


def test_rows_hold_no_unescaped_pipe() -> None:
    for line in reference_markdown().splitlines():
        if line.startswith("| `"):
            # a configuration key's row has 5 cells, a parameter's 7
            want = 8 if re.match(r"\| `[A-Z]", line) else 6
            assert len(re.findall(r"(?<!\\)\|", line)) == want, line


@pytest.mark.integration
def test_cli_prints_the_reference() -> None:
    res = subprocess.run(
        [sys.executable, "-m", "bridge", "config", "--docs"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 0, res.stderr
    assert res.stdout == reference_markdown()
