"""Pure maths without I/O: geometry, sensor transfer functions, the calibration type, WMM,
attitude."""
