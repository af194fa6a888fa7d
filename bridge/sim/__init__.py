"""The simulated GMR compass: develop and test everything without the hardware.

* :mod:`bridge.sim.physics`  -- Earth field (WMM) + per-unit errors + noise, ADC, saturation
  (``UnitErrors``, ``SensorModel``; ``UnitErrors.true_calibration()`` is the exact answer).
* :mod:`bridge.sim.motion`   -- attitude scripts with ground truth (``Still``, ``YawTurns``,
  ``Tumble``, ``AttitudeList``, ``OnboardCalRotation``, ``SixFaces``, ``Shaken``, ``Sequence``).
* :mod:`bridge.sim.flash`    -- the unit's flash page, kept in a file written atomically.
* :mod:`bridge.sim.firmware` -- sans-I/O firmware 2.x emulation, to the datasheet
  (``Firmware``; ``make_firmware(seed)`` for a ready unit).
* :mod:`bridge.sim.pty`      -- the firmware served on a pseudo-terminal at a symlinked path
  (``PtyCompass``; ``run_simulator`` behind ``compass-bridge simulate``).

Submodules are imported on demand (nothing here pulls in the WMM or threads).
"""
