"""The parameter reference in Markdown, generated from the parameters' own declarations.

Every parameter a ground station shows (PARAM_VALUE) comes from
:data:`bridge.app.paramspec.SPECS`; this renders one row per spec -- type,
default, range, unit, the configuration key that gives its default, meaning --
so none can be left out of the docs. ``compass-bridge config --docs`` prints it
after the configuration reference (:func:`reference_markdown`);
``docs/configuration.md`` is that output, and tests/test_config_docs.py fails when
the committed file is stale or a parameter has no row.
"""

from __future__ import annotations

from bridge.app.paramspec import INT8, INT16, INT32, REAL32, SPECS, ParamSpec, decimal7
from bridge.config import reference_markdown as configuration_reference

_TYPES = {INT8: "INT8", INT16: "INT16", INT32: "INT32", REAL32: "REAL32"}

PARAMETERS_INTRO = """
Every parameter a ground station shows (MAVProxy `param show`, QGroundControl's
parameter editor, Mission Planner), by ArduPilot's names where ArduPilot has one,
the bridge's own under `BRG_`. A value set over MAVLink (PARAM_SET) is checked
against its type and range, applied at once and kept in `<storage.dir>/params.json`,
where it wins over the configuration key that gives the parameter's default
(`compass-bridge config` shows the values in effect and where each comes from;
`PREFLIGHT_STORAGE` 2 resets them). The calibration group (`COMPASS_OFS/DIA/ODI/SCALE/ORIENT`,
`BRG_ALIGN_*`) is a view of the calibration in use, kept in `<storage.dir>/calibration.json`.
How values travel for each ground station: [mavlink.md](mavlink.md#parameters).
This table is generated from the declarations in `bridge/app/paramspec.py` (`SPECS`).
"""


def _cell(text: str) -> str:
    """Table-cell safe: no pipes breaking the row ("|accel|"), no newlines."""
    return " ".join(text.replace("|", "\\|").split())


def _num(spec: ParamSpec, v: float) -> str:
    v = decimal7(v) if spec.ptype == REAL32 else v
    return f"{int(v)}" if float(v).is_integer() else f"{v:g}"


def _range(spec: ParamSpec) -> str:
    if spec.read_only:
        return "read-only"
    if spec.choices is not None and len(spec.choices) > 8:
        return f"{_num(spec, spec.minimum)}..{_num(spec, spec.maximum)} (ArduPilot Rotation)"
    if spec.config_choices is not None:
        return ", ".join(f"{i} {name}" for i, name in enumerate(spec.config_choices))
    return f"[{_num(spec, spec.minimum)}, {_num(spec, spec.maximum)}]"


def parameter_rows() -> list[str]:
    """The table's rows, one per parameter in index order (PARAM_VALUE.param_index)."""
    rows = []
    for spec in SPECS:
        key = f"`{spec.config_key}`" if spec.config_key else "-"
        rows.append(
            f"| `{spec.name}` | {_TYPES[spec.ptype]} | `{_num(spec, spec.default)}` "
            f"| {_cell(_range(spec))} | {spec.unit or '-'} | {key} | {_cell(spec.doc)} |"
        )
    return rows


def parameters_markdown() -> str:
    """The ``## Parameters`` section."""
    out = ["## Parameters", "", " ".join(PARAMETERS_INTRO.split()), ""]
    out += [
        "| parameter | type | default | range | unit | configuration key | meaning |",
        "| --- | --- | --- | --- | --- | --- | --- |",
        *parameter_rows(),
        "",
    ]
    return "\n".join(out)


def reference_markdown() -> str:
    """``docs/configuration.md``: the configuration keys, then the parameters."""
    return configuration_reference() + "\n" + parameters_markdown()


__all__ = ["parameter_rows", "parameters_markdown", "reference_markdown"]
