"""Every parameter a ground station shows is documented, from the same declarations.

docs/configuration.md's "Parameters" table is generated from
``bridge.app.paramspec.SPECS`` (tests/test_config_docs.py keeps the file fresh);
here: every row is whole, every configuration key a parameter names exists and
round-trips, and -- the ground station's view -- every PARAM_VALUE a running
bridge sends for a PARAM_REQUEST_LIST has a row with a meaning.
"""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest
from test_mavlink_rig import start_rig

from bridge.app.bridge import BridgeOptions, config_value
from bridge.app.paramdocs import parameter_rows, reference_markdown
from bridge.app.paramspec import CONFIG_PARAMS, SPECS, config_from_param, param_from_config
from bridge.config import load_config, section_types, settings_of

DOC = Path(__file__).resolve().parents[1] / "docs" / "configuration.md"


def _rows(text: str) -> dict[str, list[str]]:
    """Parameter name -> its cells, from the Markdown's parameter rows."""
    out = {}
    for line in text.splitlines():
        m = re.match(r"\| `([A-Z][A-Z0-9_]*)` \|", line)
        if m:
            cells = [c.strip() for c in re.split(r"(?<!\\)\|", line.strip())[1:-1]]
            out[m.group(1)] = cells
    return out


def test_every_declared_parameter_has_a_whole_row() -> None:
    rows = _rows(reference_markdown())
    assert list(rows) == [s.name for s in SPECS]  # all of them, in index order
    assert len(parameter_rows()) == len(SPECS)
    for spec in SPECS:
        cells = rows[spec.name]
        assert len(cells) == 7, cells
        assert cells[1] in ("INT8", "INT16", "INT32", "REAL32")
        assert cells[6].replace("\\|", "|") == " ".join(spec.doc.split()), cells
        assert cells[5] == (f"`{spec.config_key}`" if spec.config_key else "-")


def test_the_heading_reference_parameter_is_documented_with_its_key() -> None:
    row = _rows(DOC.read_text())["BRG_HDG_REF"]
    assert row[5] == "`heading.reference`" and "0 magnetic, 1 true" in row[3]


def test_config_keys_exist_and_round_trip() -> None:
    keys = {f"{s}.{f.name}" for s, cls in section_types().items() for f in settings_of(cls)}
    cfg = load_config(None, ["heading.reference=true", "calibration.learn=learn"])
    defaults = BridgeOptions.from_config(cfg).param_defaults
    for spec in CONFIG_PARAMS:
        assert spec.config_key in keys, spec
        value = config_value(cfg, spec.config_key)
        assert defaults[spec.name] == param_from_config(spec, value)
        assert config_from_param(spec, defaults[spec.name], value) == value
    assert defaults["BRG_HDG_REF"] == 1.0 and defaults["BRG_CAL_LEARN"] == 2.0


@pytest.mark.integration
@pytest.mark.parametrize("role", ["standalone", "companion"])
def test_every_parameter_a_ground_station_receives_is_documented(tmp_path: Path, role: str) -> None:
    """PARAM_REQUEST_LIST to a running bridge: each PARAM_VALUE's name has a documented row."""
    target = (1, 1) if role == "standalone" else (1, 200)
    mav = {"role": role} if role == "standalone" else {"role": role, "component_id": 200}
    rig = start_rig(tmp_path, mavlink=mav)
    try:
        g = rig.gcs()
        g.mav.param_request_list_send(*target)
        first = g.wait("PARAM_VALUE")
        names = {first.param_id}
        end = time.monotonic() + 20.0
        while len(names) < first.param_count and time.monotonic() < end:
            names.add(g.wait("PARAM_VALUE").param_id)
    finally:
        rig.stop()
    assert len(names) == first.param_count, (len(names), first.param_count)
    rows = _rows(DOC.read_text())
    missing = sorted(n for n in names if n not in rows)
    assert not missing, (
        f"parameters a ground station shows but docs/configuration.md lacks: {missing}"
    )
    assert all(rows[n][6] for n in names)
