"""``compass-bridge calibrate``: a magnetometer calibration a person runs and judges.

Two ways:

* **offline** (``--recording FILE``): a ``compass-bridge record`` recording is
  replayed through the GMR decoder, every ``$PGMRA`` frame's raw vectors are
  collected (saturated frames flagged, never fitted), and any engine method
  (``--method``, a name of :mod:`bridge.calibration.methods`) is run on them.
  No daemon needed. Accepting writes the result where the daemon loads it
  (``--state-dir``: ``calibration.json`` there, with the report).
* **live over MAVLink** (``--mavlink URL``): the ArduPilot flow against a
  running bridge -- ``MAV_CMD_DO_START_MAG_CAL``, ``MAG_CAL_PROGRESS`` (the
  percentage drives the bar, ``completion_mask`` the map of the 80 sphere
  sections still missing), ``MAG_CAL_REPORT``, then ``DO_ACCEPT_MAG_CAL`` or
  ``DO_CANCEL_MAG_CAL``. MAG_CAL_REPORT carries fitness and parameters but
  no field spread: the estimated heading error is computed from the fitness
  and the horizontal field (WMM at ``--location``; see
  :func:`heading_error_estimate_deg`).

The report pieces (:func:`report_lines`, :func:`coverage_map`,
:func:`heading_error_estimate_deg`) are pure.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any, TextIO

import numpy as np
import numpy.typing as npt

from bridge.calibration.coverage import N_SECTIONS, mask_sections, sections
from bridge.calibration.methods import CalibrationData, calibrate
from bridge.calibration.model import Calibration, CalibrationResult
from bridge.core.sensor import acc_counts_to_g, mag_counts_to_gauss

FloatArray = npt.NDArray[np.float64]

#: Rows x columns of the terminal coverage map (latitude bands x longitude sectors).
MAP_ROWS, MAP_COLS = 9, 36


# ---------------------------------------------------------------------------
# Pure helpers
# ---------------------------------------------------------------------------


def _grid_sections(rows: int = MAP_ROWS, cols: int = MAP_COLS) -> npt.NDArray[np.int64]:
    lat = np.radians(90.0 - (np.arange(rows) + 0.5) * 180.0 / rows)
    lon = np.radians((np.arange(cols) + 0.5) * 360.0 / cols)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    v = np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), -np.sin(la)], axis=-1)
    return sections(v.reshape(-1, 3)).reshape(rows, cols)


_GRID = _grid_sections()


def coverage_map(missing: Iterable[int]) -> str:
    """The sphere as a latitude/longitude map: ``#`` sections covered, ``.`` still missing.

    Rows go from straight up (field pointing to -z in the sensor frame, top)
    to straight down; columns go round the horizon. PURE.
    """
    miss = set(missing)
    lines = ["".join("." if int(s) in miss else "#" for s in row) for row in _GRID]
    return "\n".join(f"  |{line}|" for line in lines)


def horizontal_field_G(total_G: float, dip_deg: float) -> float:
    """Horizontal intensity of a field of ``total_G`` and inclination ``dip_deg``."""
    return total_G * math.cos(math.radians(dip_deg))


def heading_error_estimate_deg(fitness_mG: float, horizontal_G: float) -> float:
    """Expected RMS heading error of a fit: the RMS residual seen as a sideways error.

    A residual of ``fitness`` milligauss across the horizontal field ``H``
    turns the heading by ``atan(fitness / H)``. The fit's residual is radial
    (|B| error), the heading error is tangential; for a fit without a
    systematic shape error the two are of the same size, which is what makes
    this a fair *estimate*, not a measurement. NaN when either is unknown.
    """
    if not (math.isfinite(fitness_mG) and math.isfinite(horizontal_G) and horizontal_G > 0):
        return math.nan
    return math.degrees(math.atan2(fitness_mG / 1000.0, horizontal_G))


def _fmt(v: Any, spec: str = ".2f") -> str:
    if isinstance(v, int | float) and math.isfinite(v):
        return format(v, spec)
    return "n/a"


def report_lines(report: dict[str, Any], heading_error_deg: float) -> list[str]:
    """The calibration report for a person (``report`` is a MAG_CAL_REPORT-shaped dict)."""
    out = [
        f"status        {report.get('cal_status', '?')}"
        + (f"  (method {report['method']})" if report.get("method") else ""),
        f"fitness       {_fmt(report.get('fitness'))} mG RMS"
        + (f", {report['n_samples']} samples" if report.get("n_samples") else ""),
        "offsets       COMPASS_OFS_X/Y/Z  "
        + "  ".join(_fmt(report.get(f"ofs_{a}"), "+.1f") for a in "xyz")
        + " mG",
        "diagonal      COMPASS_DIA_X/Y/Z  "
        + "  ".join(_fmt(report.get(f"diag_{a}"), ".4f") for a in "xyz"),
        "off-diagonal  COMPASS_ODI_X/Y/Z  "
        + "  ".join(_fmt(report.get(f"offdiag_{a}"), "+.4f") for a in "xyz"),
        f"scale         COMPASS_SCALE  {_fmt(report.get('scale_factor'), '.4f')}",
    ]
    b, a = report.get("field_spread_before_nT"), report.get("field_spread_after_nT")
    if isinstance(b, int | float) or isinstance(a, int | float):
        out.append(f"field spread  ±{_fmt(b, '.0f')} nT before  ->  ±{_fmt(a, '.0f')} nT after")
    else:
        out.append("field spread  not reported over this path (see the fitness)")
    out.append(f"heading error ~{_fmt(heading_error_deg)} deg RMS (estimated from the fitness)")
    return out


# ---------------------------------------------------------------------------
# Offline: a recording
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class RecordedVectors:
    """Raw vectors of every ``$PGMRA`` frame of a recording (counts -> nominal units)."""

    mag_G: FloatArray
    acc_g: FloatArray
    saturated: npt.NDArray[np.bool_]
    dropped_lines: int


def read_recording(path: str, progress: Callable[[float], None] | None = None) -> RecordedVectors:
    """Replay ``path`` through the host decoder; raises ``RecordingFormatError``/``OSError``."""
    import os

    from bridge.link.record import RecordingReader
    from bridge.protocol.gmr import AttitudeFrame, Flags, GmrDecoder

    size = max(1, os.path.getsize(path))
    dec = GmrDecoder(direction="host")
    mag: list[tuple[int, int, int]] = []
    acc: list[tuple[int, int, int]] = []
    sat: list[bool] = []
    done = 0
    with RecordingReader(path) as rec:
        for chunk in rec.chunks():
            done += len(chunk.data) + 16
            for f in dec.feed(chunk.data):
                if isinstance(f, AttitudeFrame):
                    mag.append((f.mx, f.my, f.mz))
                    acc.append((f.ax, f.ay, f.az))
                    sat.append(bool(f.flags & Flags.SAT))
            if progress is not None:
                progress(min(1.0, done / size))
    dropped = sum(dec.counters.dropped.values())
    if not mag:
        raise ValueError(f"{path}: no $PGMRA frames in the recording")
    return RecordedVectors(
        mag_counts_to_gauss(np.asarray(mag, dtype=np.float64)),
        acc_counts_to_g(np.asarray(acc, dtype=np.float64)),
        np.asarray(sat, dtype=bool),
        dropped,
    )


def fit_recording(
    vectors: RecordedVectors, method: str, location: tuple[float, float, float] | None
) -> tuple[CalibrationResult, float]:
    """Run ``method`` on the recorded vectors; returns the result and the heading error estimate."""
    from bridge.core.wmm import earth_field

    field = earth_field(*location) if location is not None else None
    data = CalibrationData(
        mag_G=vectors.mag_G, acc_g=vectors.acc_g, saturated=vectors.saturated, reference=field
    )
    res = calibrate(method, data)
    if field is not None:
        h = horizontal_field_G(field.total_G, field.inclination_deg)
    else:
        # No location: the dip the calibrated samples themselves show, and their mean |B|.
        h = _measured_horizontal_G(res.calibration, vectors)
    return res, heading_error_estimate_deg(res.report.fitness_mG, h)


def _measured_horizontal_G(cal: Calibration, v: RecordedVectors) -> float:
    ok = ~v.saturated
    m = cal.mag.apply(v.mag_G[ok])
    g = cal.accel.apply(v.acc_g[ok])
    mn, gn = np.linalg.norm(m, axis=1), np.linalg.norm(g, axis=1)
    good = (mn > 0) & (gn > 0)
    if not np.any(good):
        return math.nan
    sin_dip = np.sum(m[good] * g[good], axis=1) / (mn[good] * gn[good])
    dip = float(np.degrees(np.arcsin(np.clip(np.median(sin_dip), -1.0, 1.0))))
    return horizontal_field_G(float(np.mean(mn[good])), dip)


def calibrated_missing(cal: Calibration, v: RecordedVectors) -> frozenset[int]:
    """Sections of the 80 the calibrated samples never reached."""
    hit = set(int(s) for s in sections(cal.mag.apply(v.mag_G[~v.saturated])) if s >= 0)
    return frozenset(range(N_SECTIONS)) - hit


def offline_report(res: CalibrationResult) -> dict[str, Any]:
    """The fit as a MAG_CAL_REPORT-shaped dict with the engine's figures."""
    from bridge.calibrator.results import mag_report

    rep = mag_report(res.calibration, res.report)
    d = res.report.to_dict()
    rep.update(
        {
            "field_spread_before_nT": d["field_spread_before_nT"],
            "field_spread_after_nT": d["field_spread_after_nT"],
            "method": res.report.method,
            "n_samples": res.report.n_samples,
        }
    )
    return rep


# ---------------------------------------------------------------------------
# Accepting
# ---------------------------------------------------------------------------


def ask_accept(question: str, stdin: TextIO, out: TextIO) -> bool:
    """``[y/N]`` on the terminal; anything but y/yes (or end of input) is a no."""
    out.write(f"{question} [y/N] ")
    out.flush()
    line = stdin.readline()
    return line.strip().lower() in ("y", "yes")


def save_offline(state_dir: str, res: CalibrationResult, report: dict[str, Any]) -> None:
    """Write the calibration where the daemon loads it (``calibration.json``, with its report)."""
    from bridge.daemon import CALIBRATION_DOCUMENT
    from bridge.storage import StateStore

    StateStore(state_dir).save(
        CALIBRATION_DOCUMENT,
        {"calibration": res.calibration.to_dict(), "report": report, "source": "calibrate"},
    )


# ---------------------------------------------------------------------------
# Live over MAVLink
# ---------------------------------------------------------------------------


@dataclass(slots=True)
class LiveOutcome:
    """What the MAVLink flow ended with."""

    report: dict[str, Any] | None
    accepted: bool
    message: str


def run_mavlink(
    url: str,
    *,
    target_system: int,
    target_component: int,
    timeout_s: float,
    accept: Callable[[dict[str, Any]], bool],
    on_progress: Callable[[float, frozenset[int]], None],
    source_system: int = 255,
) -> LiveOutcome:
    """The ArduPilot magcal flow against a bridge at ``url`` (pymavlink connection string)."""
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(
        url, source_system=source_system, source_component=190, dialect="ardupilotmega"
    )
    M = mavutil.mavlink
    try:
        deadline = time.monotonic() + min(10.0, timeout_s)
        # udpin learns the bridge's address from its first packet; tcp/udpout can send at once.
        hb = None
        while hb is None and time.monotonic() < deadline:
            conn.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            hb = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
        if hb is None:
            return LiveOutcome(None, False, f"no HEARTBEAT from the bridge on {url}")

        def command(cmd: int, *params: float) -> int | None:
            p = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][:7]
            for _ in range(3):
                conn.mav.command_long_send(target_system, target_component, cmd, 0, *p)
                end = time.monotonic() + 1.5
                while time.monotonic() < end:
                    ack = conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.2)
                    if ack is not None and ack.command == cmd:
                        return int(ack.result)
            return None

        # mag mask 0 (all), retry 0, autosave 0 (we ask the person), delay 0.
        result = command(M.MAV_CMD_DO_START_MAG_CAL, 0, 0, 0, 0)
        if result != M.MAV_RESULT_ACCEPTED:
            return LiveOutcome(None, False, f"DO_START_MAG_CAL refused (result {result})")
        end = time.monotonic() + timeout_s
        report = None
        while time.monotonic() < end:
            m = conn.recv_match(
                type=["MAG_CAL_PROGRESS", "MAG_CAL_REPORT"], blocking=True, timeout=0.2
            )
            if m is None:
                continue
            if m.get_type() == "MAG_CAL_PROGRESS":
                missing = frozenset(range(N_SECTIONS)) - mask_sections(bytes(m.completion_mask))
                on_progress(float(m.completion_pct), missing)
            else:
                report = m.to_dict()
                break
        if report is None:
            command(M.MAV_CMD_DO_CANCEL_MAG_CAL, 0)
            return LiveOutcome(None, False, f"no MAG_CAL_REPORT within {timeout_s:g} s")
        report["cal_status"] = _mag_cal_status_name(M, int(report.get("cal_status", -1)))
        if report["cal_status"] != "MAG_CAL_SUCCESS":
            return LiveOutcome(report, False, f"calibration failed: {report['cal_status']}")
        if accept(report):
            r = command(M.MAV_CMD_DO_ACCEPT_MAG_CAL, 0)
            ok = r == M.MAV_RESULT_ACCEPTED
            return LiveOutcome(report, ok, "accepted" if ok else f"accept refused ({r})")
        command(M.MAV_CMD_DO_CANCEL_MAG_CAL, 0)
        return LiveOutcome(report, False, "cancelled: the bridge keeps its previous calibration")
    finally:
        conn.close()


def _mag_cal_status_name(M: Any, code: int) -> str:
    for name, entry in M.enums["MAG_CAL_STATUS"].items():
        if name == code:
            return str(entry.name)
    return f"MAG_CAL_STATUS({code})"


# ---------------------------------------------------------------------------
# The command
# ---------------------------------------------------------------------------


def write_coverage(out: TextIO, missing: frozenset[int]) -> None:
    """The coverage map with its legend."""
    out.write(
        f"sphere coverage: {N_SECTIONS - len(missing)}/{N_SECTIONS} sections "
        "(# covered, . still missing)\n"
    )
    out.write(coverage_map(missing) + "\n")


def cmd_calibrate(args: Any, out: TextIO | None = None, stdin: TextIO | None = None) -> int:
    """``compass-bridge calibrate``: returns the exit code (0 accepted/saved, 1 otherwise)."""
    out = out if out is not None else sys.stdout
    stdin = stdin if stdin is not None else sys.stdin
    from bridge.tools.progress import Progress

    def decide(report: dict[str, Any]) -> bool:
        if args.yes:
            return True
        if args.no:
            return False
        return ask_accept("accept this calibration?", stdin, out)

    location = args.location
    if args.recording:
        with Progress("reading", 1.0, enabled=args.progress) as bar:
            vectors = read_recording(args.recording, lambda f: bar.update(f))
        with Progress(f"fitting ({args.method})", None, enabled=args.progress) as bar:
            bar.update(note=f"{len(vectors.mag_G)} frames")
            res, herr = fit_recording(vectors, args.method, location)
        report = offline_report(res)
        out.write(
            f"{args.recording}: {len(vectors.mag_G)} frames "
            f"({int(vectors.saturated.sum())} saturated, {vectors.dropped_lines} bad lines)\n"
        )
        write_coverage(out, calibrated_missing(res.calibration, vectors))
        out.write("\n".join(report_lines(report, herr)) + "\n")
        if args.plot:
            from bridge.tools.plot import plot_calibration

            ok = ~vectors.saturated
            plot_calibration(
                args.plot, vectors.mag_G[ok], res.calibration.mag.apply(vectors.mag_G[ok])
            )
            out.write(f"plot written to {args.plot}\n")
        if not res.report.ok:
            out.write("calibration failed: nothing to accept\n")
            return 1
        if args.state_dir is None:
            out.write("(no --state-dir: the result is shown, not saved)\n")
            return 0
        if decide(report):
            save_offline(args.state_dir, res, report)
            out.write(f"saved to {args.state_dir}/calibration.json\n")
            return 0
        out.write("not saved\n")
        return 1

    from bridge.tools.progress import Progress as Bar

    h = math.nan
    if location is not None:
        from bridge.core.wmm import earth_field

        f = earth_field(*location)
        h = horizontal_field_G(f.total_G, f.inclination_deg)
    bar = Bar("calibrating", 100.0, enabled=args.progress)
    last_missing: list[frozenset[int]] = []

    def on_progress(pct: float, missing: frozenset[int]) -> None:
        last_missing[:] = [missing]
        bar.update(pct, note=f"{len(missing)} sections missing")

    def accept(report: dict[str, Any]) -> bool:
        bar.close()
        if last_missing:
            write_coverage(out, last_missing[0])
        out.write("\n".join(report_lines(report, heading_error_estimate_deg(
            float(report.get("fitness", math.nan)), h))) + "\n")  # fmt: skip
        return decide(report)

    outcome = run_mavlink(
        args.mavlink,
        target_system=args.target_system,
        target_component=args.target_component,
        timeout_s=args.timeout,
        accept=accept,
        on_progress=on_progress,
    )
    bar.close()
    out.write(outcome.message + "\n")
    return 0 if outcome.accepted else 1
