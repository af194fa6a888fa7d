"""The configuration reference in Markdown, generated from the declarations themselves.

Every key's type, default, allowed values and meaning come from its
:func:`~bridge.configkit.schema.setting` (and each section's docstring), so the
reference cannot drift from what the loader accepts. ``compass-bridge config
--docs`` prints it; ``docs/configuration.md`` is that output, and a test fails
when the committed file is stale.
"""

from __future__ import annotations

import inspect
from typing import Any

from bridge.configkit.loader import toml_value
from bridge.configkit.rules import Rule
from bridge.configkit.schema import section_types, settings_of, type_name

GENERATED_NOTE = (
    "<!-- Generated from the setting() declarations in bridge/config.py by "
    "`compass-bridge config --docs > docs/configuration.md`. Do not edit by hand: "
    "tests/test_config_docs.py fails when this file is stale. -->"
)


def _cell(text: str) -> str:
    """Table-cell safe: no pipes breaking the row, no newlines."""
    return " ".join(text.replace("|", "\\|").split())


def _docstring_parts(cls: type) -> tuple[str, str]:
    """(first line, the rest) of a section's docstring."""
    doc = inspect.getdoc(cls) or ""
    first, _, rest = doc.partition("\n")
    return first.strip(), rest.strip()


def _allowed(rule: Rule | None, kind: str, unit: str) -> str:
    if rule is not None:
        text = rule.text
    else:
        text = "true or false" if kind == "boolean" else f"any {kind}"
    return f"{text} ({unit})" if unit else text


def _default(f: Any) -> str:
    if f.metadata.get("required"):
        return "required"
    return f"`{toml_value(f.default)}`"


def render_reference(config_cls: type, *, title: str, intro: str) -> str:
    """Markdown: ``title``, ``intro``, then one table per section of ``config_cls``."""
    out = [f"# {title}", "", GENERATED_NOTE, "", intro.strip(), ""]
    for name, cls in section_types(config_cls).items():
        summary, details = _docstring_parts(cls)
        # The docstrings open with "``[name]``: what it is"; the heading names the section.
        summary = summary.split(":", 1)[1].strip() if summary.startswith("``[") else summary
        out += [f"## `[{name}]`", "", summary[:1].upper() + summary[1:]]
        if details:
            out += ["", " ".join(details.replace("``", "`").split())]
        out += [
            "",
            "| key | type | default | allowed | meaning |",
            "| --- | --- | --- | --- | --- |",
        ]
        for f in settings_of(cls):
            rule: Rule | None = f.metadata.get("rule")
            kind = type_name(cls, f.name)
            out.append(
                f"| `{name}.{f.name}` | {kind} | {_cell(_default(f))} "
                f"| {_cell(_allowed(rule, kind, f.metadata.get('unit', '')))} "
                f"| {_cell(f.metadata.get('doc', ''))} |"
            )
        out.append("")
    return "\n".join(out)
