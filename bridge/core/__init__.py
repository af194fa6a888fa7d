"""Pure maths without I/O: geometry, sensor transfer functions, WMM, attitude."""
