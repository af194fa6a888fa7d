"""``run --simulate``'s own settings and state, and what ``simulate`` says when it serves.

The simulated compass keeps its calibration and parameters apart from any real
unit's: ``$XDG_STATE_HOME/compass-bridge/sim`` (``~/.local/state/...`` by
default), the one directory the bridge writes outside a configured
``storage.dir``; ``run --simulate --reset`` empties it (:func:`reset_state`).
``config --simulate`` resolves the same settings (:func:`simulate_overrides`).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

from bridge.config import ConfigError, read_toml
from bridge.storage import StateStore


def simulator_state_dir() -> str:
    """State directory of ``run --simulate``: ``$XDG_STATE_HOME/compass-bridge/sim``.

    Falls back to ``~/.local/state`` (the XDG default) when XDG_STATE_HOME is unset.
    """
    base = os.environ.get("XDG_STATE_HOME") or os.path.join(
        os.path.expanduser("~"), ".local", "state"
    )
    return os.path.join(base, "compass-bridge", "sim")


def simulate_overrides(overrides: Sequence[str], config_path: str | None = None) -> list[str]:
    """``run --simulate``'s own settings, before the user's ``--set`` (which win).

    ``config_path`` is the ``--config`` file, if any: a ``storage.dir`` it sets is kept.
    """
    # The simulated compass speaks the GMR protocol, whatever a --config file says.
    # A first run shows a heading that turns with the unit: it starts calibrated with
    # its true errors unless a calibration is stored (or --set sim.calibrated=false).
    own = ["device.port=sim", "device.protocol=gmr", "sim.calibrated=true"]
    named = any(o.partition("=")[0].strip() == "storage.dir" for o in overrides)
    if not named and not _file_sets(config_path, "storage", "dir"):
        # The simulated unit must never read or overwrite a real unit's calibration
        # in the service's state directory: give it a per-user directory of its own --
        # unless the user named one (--set storage.dir=, or the --config file's).
        own.append(f"storage.dir={simulator_state_dir()}")
    return own


def _file_sets(path: str | None, section: str, key: str) -> bool:
    """Whether the configuration file at ``path`` sets ``[section] key`` (False without a
    file; a file that cannot be read is reported by the load that follows)."""
    if path is None:
        return False
    try:
        raw = read_toml(path)
    except ConfigError:
        return False
    table = raw.get(section)
    return isinstance(table, dict) and key in table


def reset_state(state_dir: str) -> str:
    """``run --simulate --reset``: delete the stored documents; returns what it did, in words.

    Raises :class:`~bridge.documents.StorageError` when a file cannot go.
    """
    removed = StateStore(state_dir).clear()
    what = ", ".join(p.name for p in removed) if removed else "nothing was stored"
    return f"reset {state_dir}: {what}"


def serving_line(args: Any, device: str | None) -> str:
    """What ``simulate`` says once it serves: the pty, the link, how a bridge reads it."""
    what = "a perfect unit" if args.ideal else f"seed {args.seed}"
    return (
        f"simulated compass ({what}, motion {args.motion}) serving on {device}, "
        f"linked at {args.link}\n"
        f"  a bridge reads it with: compass-bridge run --config FILE "
        f"--set device.port={args.link}\n"
        f"  SIGUSR1 unplugs it for {args.unplug_s:g} s, SIGUSR2 sends "
        f"{args.garbage_bytes} bytes of line noise; Ctrl-C stops it"
    )


__all__ = ["reset_state", "serving_line", "simulate_overrides", "simulator_state_dir"]
