"""The application layer: the running bridge's state and its owners.

* :mod:`~bridge.app.bridge`    -- :class:`Bridge`, which holds the parts below and reacts
  to their changes; :func:`build_bridge`, which builds them
* :mod:`~bridge.app.sample`    -- what outputs receive: :class:`CompassSample`,
  :class:`DaemonStatus`, the :class:`Output` contract
* :mod:`~bridge.app.settings`  -- :class:`EngineSettings`, the one writer of the engine's settings
* :mod:`~bridge.app.params`    -- :class:`ParamStore`, the parameter table, saved and applied
* :mod:`~bridge.app.paramspec` -- the parameters' names, types, ranges (pure)
* :mod:`~bridge.app.pipeline`  -- :class:`Pipeline`, frames to samples to outputs
* :mod:`~bridge.app.services`  -- :class:`BridgeServices`, what every adapter receives

Adapters (serial link, MAVLink, Zenoh, systemd, console) depend on this layer,
never on each other nor on :mod:`bridge.daemon`, which wires them.
"""

from bridge.app.bridge import Bridge, BridgeOptions, build_bridge
from bridge.app.params import ParamStore
from bridge.app.pipeline import Pipeline
from bridge.app.sample import CompassSample, DaemonStatus, LatestSampleWorker, Output
from bridge.app.services import BridgeServices, MessageTap, SentMessage
from bridge.app.settings import EngineSettings

__all__ = [
    "Bridge",
    "BridgeOptions",
    "BridgeServices",
    "CompassSample",
    "DaemonStatus",
    "EngineSettings",
    "LatestSampleWorker",
    "MessageTap",
    "Output",
    "ParamStore",
    "Pipeline",
    "SentMessage",
    "build_bridge",
]
