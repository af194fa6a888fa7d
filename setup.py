"""Build script for the optional C hot path (everything else is in pyproject.toml).

``bridge._speedups`` moves the per-frame ``$PGMRA`` decode and attitude arithmetic into C
(see bridge/_speedups.c for why). It is optional: without a C compiler the build only
warns and the pure-Python twins run, with identical results. Set
``COMPASS_BRIDGE_PURE_PYTHON=1`` to skip building it.
"""

from __future__ import annotations

import os
import sys

from setuptools import Extension, setup

ext_modules = []
if not os.environ.get("COMPASS_BRIDGE_PURE_PYTHON"):
    # -ffp-contract=off: no fused multiply-add, so the C arithmetic rounds exactly as
    # Python's does, operation by operation (gcc contracts by default on aarch64, e.g. a
    # Raspberry Pi). MSVC does not contract across statements without /fp:fast.
    flags = [] if sys.platform == "win32" else ["-O2", "-ffp-contract=off", "-fno-fast-math"]
    ext_modules.append(
        Extension(
            "bridge._speedups",
            ["bridge/_speedups.c"],
            extra_compile_args=flags,
            optional=True,
        )
    )

setup(ext_modules=ext_modules)
