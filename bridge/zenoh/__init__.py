"""The compass on the fleet's data bus: Eclipse Zenoh publications, queries, and the fleet view.

Inside this package ``import zenoh`` is the Eclipse Zenoh library, as everywhere: imports
are absolute, so :mod:`bridge.zenoh` never shadows it (``tests/test_zenoh_schema.py`` checks).

* ``schema``   -- PURE. The JSON documents: names, versions, builders, validation.
* ``pacing``   -- PURE. Per-stream rate caps and the frame-rate meter.
* ``mirror``   -- PURE. MAVLink messages in bluerobotics/mavlink-server's JSON layout.
* ``session``  -- zenoh configuration from ``[zenoh]`` (loopback listener, no multicast,
  fast re-join) and opening the session.
* ``output``   -- ADAPTER. :class:`~bridge.zenoh.output.ZenohOutput`, the daemon's Zenoh output.
* ``monitor``  -- ``compass-bridge monitor``: the live table of every bridge seen.

Key layout under ``<prefix>`` (``[zenoh] key_prefix``, default ``fleet/<hostname>/compass``)::

    <prefix>                       liveliness token (present while the bridge runs)
    <prefix>/heading               publication  compass-bridge/heading@1
    <prefix>/attitude              publication  compass-bridge/attitude@1
    <prefix>/imu                   publication  compass-bridge/imu@1
    <prefix>/status                publication + queryable  compass-bridge/status@1
    <prefix>/events                publication  compass-bridge/event@1
    <prefix>/calibration           queryable    compass-bridge/calibration@1
    <prefix>/params                queryable    compass-bridge/params@1
    <prefix>/cmd/calibration/{start,accept,cancel}
                                   queryables (remote_calibration = true only)
                                   -> compass-bridge/command-result@1
    mavlink/<sys>/<comp>/<MSG>     MAVLink mirror (mavlink_mirror = true only)
"""
