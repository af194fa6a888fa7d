"""Operator tools: calibrate, status, plots, progress bars (``compass-bridge calibrate|status``)."""
