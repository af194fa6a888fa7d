"""``calibrate --plot FILE.png``: raw vs calibrated samples, the picture people judge a fit by.

Four panels: the XY, XZ and YZ projections of the raw samples (an offset,
squashed ellipse) and of the calibrated ones (a circle about the origin), and
a 3-D view of the calibrated samples on the unit sphere they should lie on.
Both sets are normalised by the calibrated mean field so raw and calibrated
share an axis scale. matplotlib is an optional extra (``pip install
'compass-bridge[plot]'``); without it :class:`PlotUnavailableError` says so.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

#: Figure size in inches and resolution: 1200 x 1000 pixels.
FIG_SIZE_IN = (12.0, 10.0)
DPI = 100
MAX_POINTS = 5000  #: more points only slow the drawing down


class PlotUnavailableError(RuntimeError):
    """matplotlib is not installed."""


def plot_calibration(
    path: str, raw_G: npt.ArrayLike, calibrated_G: npt.ArrayLike, *, title: str = ""
) -> tuple[int, int]:
    """Write the PNG; returns its (width, height) in pixels."""
    try:
        # A Figure on the Agg canvas, without pyplot: pyplot's figure manager, backend
        # selection and colormap registry are for interactive use, and importing it costs
        # more than drawing this figure (the PNG is the same, byte for byte).
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as e:
        raise PlotUnavailableError(
            "--plot needs matplotlib: pip install 'compass-bridge[plot]' (or pip install matplotlib)"
        ) from e
    raw = np.asarray(raw_G, dtype=np.float64).reshape(-1, 3)
    cal = np.asarray(calibrated_G, dtype=np.float64).reshape(-1, 3)
    if raw.shape != cal.shape or raw.shape[0] == 0:
        raise ValueError("raw and calibrated samples must be the same non-empty (N, 3) shape")
    if raw.shape[0] > MAX_POINTS:
        idx = np.linspace(0, raw.shape[0] - 1, MAX_POINTS).astype(int)
        raw, cal = raw[idx], cal[idx]
    radius = float(np.mean(np.linalg.norm(cal, axis=1))) or 1.0
    raw_n, cal_n = raw / radius, cal / radius
    fig = Figure(figsize=FIG_SIZE_IN, dpi=DPI)
    FigureCanvasAgg(fig)
    t = np.linspace(0.0, 2.0 * np.pi, 200)
    for k, (i, j, name) in enumerate(((0, 1, "X-Y"), (0, 2, "X-Z"), (1, 2, "Y-Z"))):
        ax = fig.add_subplot(2, 2, k + 1)
        ax.scatter(raw_n[:, i], raw_n[:, j], s=2, c="tab:red", alpha=0.4, label="raw")
        ax.scatter(cal_n[:, i], cal_n[:, j], s=2, c="tab:blue", alpha=0.4, label="calibrated")
        ax.plot(np.cos(t), np.sin(t), "k--", lw=0.8, label="unit circle")
        ax.set_aspect("equal")
        ax.set_title(f"{name} projection (field / calibrated mean)")
        ax.set_xlabel("xyz"[i])
        ax.set_ylabel("xyz"[j])
        ax.grid(True, lw=0.3)
        if k == 0:
            ax.legend(loc="upper right", fontsize=8)
    ax3 = fig.add_subplot(2, 2, 4, projection="3d")
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 24), np.linspace(0, np.pi, 12))
    ax3.plot_wireframe(np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v), color="0.7", lw=0.4)
    ax3.scatter(cal_n[:, 0], cal_n[:, 1], cal_n[:, 2], s=2, c="tab:blue")
    ax3.set_title("calibrated samples on the unit sphere")
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=DPI)
    return int(FIG_SIZE_IN[0] * DPI), int(FIG_SIZE_IN[1] * DPI)
