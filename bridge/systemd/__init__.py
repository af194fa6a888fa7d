"""The systemd adapter: what the service manager hears from the daemon.

* :mod:`~bridge.systemd.notify` -- sd_notify(3): ``READY=1``, ``STATUS=``, ``RELOADING=1``,
  ``STOPPING=1``, and the watchdog that pings only while the pipeline lives (no dependency
  on the bridge: the protocol is a few lines);
* :mod:`~bridge.systemd.status` -- the one-line ``STATUS=`` text ``systemctl status`` shows.

The run loop that drives them (SIGHUP reload, thread deaths) is
:class:`bridge.daemon.runner.Service`.
"""
