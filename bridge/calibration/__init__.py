"""Pure calibration fits (no I/O): each method returns parameters and a quality report."""
