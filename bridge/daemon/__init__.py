"""The ONE place that wires the parts into the running daemon.

* :mod:`~bridge.daemon.wiring` -- :func:`build_daemon`: the application
  (:class:`bridge.app.Bridge`), the compass link and its port, built from the
  configuration in one function, each part after what it needs, into a
  :class:`Daemon`; :func:`build_outputs` for the configured adapters;
* :mod:`~bridge.daemon.runner` -- :class:`Service`: the run loop under a
  service manager (sd_notify, watchdog, SIGHUP reload), and :func:`run_daemon`.
"""

from bridge.daemon.runner import Service, plan_reload, run_daemon
from bridge.daemon.wiring import (
    Daemon,
    build_daemon,
    build_outputs,
    make_simulator,
    make_transport,
)

__all__ = [
    "Daemon",
    "Service",
    "build_daemon",
    "build_outputs",
    "make_simulator",
    "make_transport",
    "plan_reload",
    "run_daemon",
]
