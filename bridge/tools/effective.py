"""``compass-bridge config``: the configuration in effect, each value with where it comes from.

What a ``run`` with the same options would use is not only the file: layers, in
order, are the built-in defaults, the ``--config`` file, ``run --simulate``'s own
settings (with ``--simulate``), the ``--set`` overrides -- and then, for every
key that gives a parameter its default (``BRG_HDG_REF`` for
``heading.reference`` ...: :data:`bridge.app.paramspec.CONFIG_PARAMS`), a value
set over MAVLink and stored in ``<storage.dir>/params.json``, which the daemon
applies at start and which wins. :func:`effective` resolves all of them;
:func:`render` prints TOML whose every line ends in a comment naming its origin
(still valid TOML), followed by what else the state directory holds.
:func:`warnings` lists what is valid but will not work now (a port that is not
there, a signing key anyone can read).
"""

from __future__ import annotations

import dataclasses
import os
import stat
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bridge.app.params import PARAMS_DOCUMENT
from bridge.app.paramspec import CONFIG_PARAMS, ParamTable, config_from_param
from bridge.app.state import calibration_summary, stored_parameters, value_text
from bridge.config import Config, load_config, read_toml, section_types, settings_of
from bridge.configkit.loader import toml_value
from bridge.storage import StateStore

#: Where a value comes from when nothing sets it.
DEFAULT = "default"
#: The column the origin comments start at.
COMMENT_COLUMN = 44


@dataclass(slots=True)
class Effective:
    """The configuration in effect and the origin of each ``section.key``."""

    cfg: Config
    origins: dict[str, str]
    layers: list[str]
    state_dir: str
    stored_elsewhere: dict[str, Any] = field(default_factory=dict)  #: params with no key
    calibration: str = ""  #: the stored calibration in words ("" = none)
    problems: list[str] = field(default_factory=list)  #: what could not be read


def _override_key(item: str) -> str:
    return item.partition("=")[0].strip()


def _file_keys(path: str) -> list[str]:
    raw = read_toml(path)
    return [
        f"{section}.{key}"
        for section, table in raw.items()
        if isinstance(table, dict)
        for key in table
    ]


def effective(
    path: str | None,
    overrides: Sequence[str],
    *,
    simulate: Sequence[str] = (),
    env: Mapping[str, str] | None = None,
) -> Effective:
    """Resolve the configuration in effect (see the module docstring).

    ``simulate`` are ``run --simulate``'s own overrides (applied before ``overrides``).
    Raises :class:`~bridge.config.ConfigError` as ``run`` would.
    """
    env = os.environ if env is None else env
    cfg = load_config(path, [*simulate, *overrides], env=env)
    origins: dict[str, str] = {}
    layers = ["built-in defaults"]
    if path is not None:
        for key in _file_keys(path):
            origins[key] = path
        layers.append(path)
    if simulate:
        for item in simulate:
            origins[_override_key(item)] = "run --simulate"
        layers.append("run --simulate")
    if overrides:
        for item in overrides:
            origins[_override_key(item)] = "--set"
        layers.append("--set")
    if "storage.dir" not in origins and env.get("STATE_DIRECTORY"):
        origins["storage.dir"] = "$STATE_DIRECTORY (systemd StateDirectory=)"
    out = Effective(cfg, origins, layers, cfg.storage.dir)
    _apply_stored(out)
    return out


def _apply_stored(out: Effective) -> None:
    """The parameters stored in the state directory, over the configuration."""
    store = StateStore(out.state_dir)
    params_file = Path(out.state_dir) / "params.json"
    try:
        loaded = store.load(PARAMS_DOCUMENT)
        stored = stored_parameters(store)
        out.calibration = calibration_summary(store)
    except Exception as e:
        out.problems.append(f"cannot read the state directory {out.state_dir}: {e}")
        return
    for problem in loaded.problems:  # e.g. not readable by this user: say what is left out
        out.problems.append(
            f"{out.state_dir}: {problem}; the values shown leave its stored parameters out "
            "(run config as the service's user or root)"
        )
    if not stored:
        return
    out.layers.append(f"parameters stored in {params_file}")
    table = ParamTable()
    by_name = {s.name: s for s in CONFIG_PARAMS}
    cfg = out.cfg
    for name, value in sorted(stored.items()):
        spec = table.spec(str(name))
        reason = table.check(spec, value) if spec is not None else "unknown parameter"
        if reason:
            out.problems.append(f"{params_file}: {name} = {value!r} is ignored ({reason})")
            continue
        keyed = by_name.get(str(name))
        if keyed is None:
            out.stored_elsewhere[str(name)] = value
            continue
        section, _, key = keyed.config_key.partition(".")
        before = getattr(getattr(cfg, section), key)
        after = config_from_param(keyed, float(value), before)
        was = out.origins.get(keyed.config_key, DEFAULT)
        out.origins[keyed.config_key] = (
            f"parameter {name} stored in {params_file} (over the {was}'s {toml_value(before)})"
            if after != before
            else f"parameter {name} stored in {params_file} (the same as the {was}'s)"
        )
        new_section = dataclasses.replace(getattr(cfg, section), **{key: after})
        cfg = dataclasses.replace(cfg, **{section: new_section})
    out.cfg = cfg


def render(e: Effective) -> str:
    """TOML with an origin comment on every line, then what else the state holds."""
    lines = [
        "# The configuration in effect. Each value says where it comes from; later layers win:",
        "# " + " < ".join(e.layers) + ".",
        "",
    ]
    for name in section_types():
        sec = getattr(e.cfg, name)
        if sec is None:
            lines += [f"# [{name}] is absent", ""]
            continue
        lines.append(f"[{name}]")
        for f in settings_of(type(sec)):
            text = f"{f.name} = {toml_value(getattr(sec, f.name))}"
            origin = e.origins.get(f"{name}.{f.name}", DEFAULT)
            lines.append(f"{text.ljust(COMMENT_COLUMN - 2)}  # {origin}")
        lines.append("")
    lines.append(f"# State directory {e.state_dir}:")
    lines.append(f"#   calibration: {e.calibration or 'none stored'}")
    if e.stored_elsewhere:
        held = ", ".join(f"{k} = {value_text(v)}" for k, v in sorted(e.stored_elsewhere.items()))
        lines.append(f"#   parameters with no configuration key, set over MAVLink: {held}")
    return "\n".join(lines) + "\n"


def warnings(e: Effective) -> list[str]:
    """What is valid but will not work now (or is unsafe), one sentence each."""
    out = list(e.problems)
    port = e.cfg.device.port
    if port.startswith("replay:"):
        if not os.path.exists(port[len("replay:") :]):
            out.append(f'device.port = "{port}": the recording does not exist')
    elif port != "sim" and not os.path.exists(port):
        out.append(
            f'device.port = "{port}": no such device now; the bridge will start and wait '
            f'for it ("waiting for the compass on {port}")'
        )
    if e.cfg.heading.reference == "true" and e.cfg.location is None:
        out.append(
            'heading.reference = "true" but [location] is absent: the magnetic heading is '
            "published (labelled magnetic) until a declination is known (the autopilot's "
            "position in the companion role, or COMPASS_DEC with COMPASS_AUTODEC = 0)"
        )
    key = e.cfg.mavlink.signing_key_file
    if key:
        try:
            mode = os.stat(key).st_mode
        except OSError:
            mode = 0
        if mode & stat.S_IROTH:
            out.append(
                f"mavlink.signing_key_file = {key!r} is readable by everyone (mode "
                f"{stat.S_IMODE(mode):04o}): chmod 0640 (docs/service.md)"
            )
    return out


__all__ = ["Effective", "effective", "render", "warnings"]
