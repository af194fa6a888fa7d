"""The simulated GMR compass: physics, motion scripts, firmware emulation, pty server."""
