"""``compass-bridge calibrate``: a magnetometer calibration a person runs and judges.

Two ways:

* **offline** (``--recording FILE``): a ``compass-bridge record`` recording is
  replayed through the GMR decoder, every ``$PGMRA`` frame's raw vectors are
  collected (saturated frames flagged, never fitted), and any engine method
  (``--method``, a name of :mod:`bridge.calibration.fits.methods`) is run on them.
  No daemon needed. Accepting writes the result where the daemon loads it
  (``--state-dir``: ``calibration.json`` there, with the report).
* **live over MAVLink** (``--mavlink URL``): the ArduPilot flow against a
  running bridge -- ``MAV_CMD_DO_START_MAG_CAL``, ``MAG_CAL_PROGRESS`` (the
  percentage drives the bar, ``completion_mask`` the map of the 80 sphere
  sections still missing), ``MAG_CAL_REPORT``, then ``DO_ACCEPT_MAG_CAL`` or
  ``DO_CANCEL_MAG_CAL``. MAG_CAL_REPORT carries fitness and parameters but
  no field spread, so the tool raises RAW_IMU to 10 Hz for the run
  (SET_MESSAGE_INTERVAL, put back to the configured rate at the end) and
  computes the spread before/after itself from those raw counts and the
  reported parameters (:func:`add_live_figures`); the same samples feed
  ``--plot``. The estimated heading error comes from the fitness and the
  horizontal field (WMM at ``--location``, else the field the calibrated
  samples show; see :func:`heading_error_estimate_deg`). Ctrl-C, a timeout or
  a failed fit cancel the calibration on the bridge.

The report pieces (:mod:`bridge.tools.calreport`: ``report_lines``,
``coverage_map``, ``heading_error_estimate_deg``, ``progress_note``; and
here :func:`report_mag_calibration`, :class:`RawImuCollector`) are pure.
While the unit is moved too hard the bridge says "slower / steadier"
(``calibration.motion``, a STATUSTEXT): the progress line shows it.
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TextIO

import numpy as np
import numpy.typing as npt

from bridge.calibration.fits.acceptance import raw_sections
from bridge.calibration.fits.coverage import N_SECTIONS, mask_sections
from bridge.calibration.fits.methods import CalibrationData, calibrate
from bridge.core.calibration import (
    AffineCalibration,
    ArduPilotView,
    Calibration,
    CalibrationResult,
)
from bridge.core.sensor import acc_counts_to_g, mag_counts_to_gauss
from bridge.tools import calhelp
from bridge.tools.calreport import (
    MOTION_NOTE_S,
    StatusTextChunks,
    coverage_map,
    coverage_text,
    frame_times,
    heading_error_estimate_deg,
    horizontal_field_G,
    is_motion_warning,
    offline_lines,
    progress_note,
    report_lines,
)
from bridge.types import FloatArray

# ---------------------------------------------------------------------------
# Offline: a recording
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class RecordedVectors:
    """Raw vectors of every ``$PGMRA`` frame of a recording (counts -> nominal units).

    ``t_s``: frame times (seconds) when the frames are consecutive (a recording),
    so the best method can fit them as a hand-held tumble; None for a sample bag.
    """

    mag_G: FloatArray
    acc_g: FloatArray
    saturated: npt.NDArray[np.bool_]
    dropped_lines: int
    t_s: FloatArray | None = None


def read_recording(path: str, progress: Callable[[float], None] | None = None) -> RecordedVectors:
    """Replay ``path`` through the host decoder; raises ``RecordingFormatError``/``OSError``."""
    import os

    from bridge.link.record import RecordingReader
    from bridge.protocol.gmr import AttitudeFrame, GmrDecoder

    size = max(1, os.path.getsize(path))
    dec = GmrDecoder(direction="host")
    mag: list[tuple[int, int, int]] = []
    acc: list[tuple[int, int, int]] = []
    sat: list[bool] = []
    seq: list[int] = []
    arrival: list[float] = []
    done = 0
    with RecordingReader(path) as rec:
        for chunk in rec.chunks():
            done += len(chunk.data) + 16
            for f in dec.feed(chunk.data):
                if isinstance(f, AttitudeFrame):
                    mag.append((f.mx, f.my, f.mz))
                    acc.append((f.ax, f.ay, f.az))
                    sat.append(f.sat_flag)
                    seq.append(f.seq)
                    arrival.append(chunk.t)
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
        frame_times(seq, arrival),
    )


def recording_data(
    vectors: RecordedVectors, location: tuple[float, float, float] | None
) -> CalibrationData:
    """The recorded frames as the engine's input (the WMM field at ``location``, if given)."""
    from bridge.core.wmm import earth_field

    field = earth_field(*location) if location is not None else None
    return CalibrationData(
        mag_G=vectors.mag_G,
        acc_g=vectors.acc_g,
        saturated=vectors.saturated,
        reference=field,
        t_s=vectors.t_s,
    )


def fit_recording(
    vectors: RecordedVectors, method: str, location: tuple[float, float, float] | None
) -> tuple[CalibrationResult, float]:
    """Run ``method`` on the recorded vectors; returns the result and its predicted heading error.

    The result is judged by the engine's acceptance rule (the heading error it
    is predicted to leave, :mod:`bridge.calibration.fits.acceptance`), the same for
    every method and the same as a live calibration's.
    """
    res = calibrate(method, recording_data(vectors, location))
    return res, res.report.predicted_heading_deg


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


def raw_missing(data: CalibrationData) -> frozenset[int]:
    """Sections of the 80 the raw samples never reached, seen from the reference fit's centre.

    Drawn from the samples as recorded (nominal transfer), not from one
    method's calibrated output, so the map is the same whatever ``--method``.
    """
    covered = raw_sections(data)
    return frozenset(range(N_SECTIONS)) - (covered or frozenset())


def offline_report(res: CalibrationResult) -> dict[str, Any]:
    """The fit as the bridge reports a calibration (the calibrator's report, JSON form) with
    ``cal_status``, the MAG_CAL_STATUS name a live calibration's MAG_CAL_REPORT gives."""
    from bridge.calibration.sessions.report import fit_report
    from bridge.calibration.sessions.state import Mode
    from bridge.mavlink.calmap import report_status

    report = fit_report(Mode.MAG, res.calibration.mag, res.report)
    return {**report.to_dict(), "cal_status": report_status(report).name}


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
    """Write the calibration where the daemon loads it (the calibration store, with its report)."""
    from bridge.app.calibration.store import CalibrationStore
    from bridge.storage import StateStore

    CalibrationStore(StateStore(state_dir)).save(
        res.calibration, source="calibrate", accepted_unix=time.time(), report=report
    )


# ---------------------------------------------------------------------------
# Live over MAVLink: the pure pieces
# ---------------------------------------------------------------------------

#: The ADC's range; a channel at either end is saturated (datasheet, "Frame content").
ADC_MIN, ADC_MAX = 0, 4095

#: RAW_IMU rate asked for (MAV_CMD_SET_MESSAGE_INTERVAL) while a live calibration
#: runs. The bridge's default (BRG_SR_RIMU) is 2 Hz: a minute of tumbling would
#: give ~100 samples, too few for a field spread and a plot worth looking at.
RAW_IMU_RATE_HZ = 10.0


class RawImuCollector:
    """RAW_IMU counts seen during a live calibration: the before/after samples.

    Frames with a channel at 0 or 4095 (saturated) are counted and dropped, as
    the engine never fits them; values outside the 12-bit range cannot come
    from the compass and are counted as invalid. PURE.
    """

    def __init__(self) -> None:
        self._rows: list[tuple[int, int, int, int, int, int]] = []
        self.saturated = 0
        self.invalid = 0

    def add(self, mx: int, my: int, mz: int, ax: int, ay: int, az: int) -> None:
        """One RAW_IMU's xmag..zmag, xacc..zacc (ADC counts)."""
        row = (mx, my, mz, ax, ay, az)
        if any(not ADC_MIN <= v <= ADC_MAX for v in row):
            self.invalid += 1
        elif any(v in (ADC_MIN, ADC_MAX) for v in row):
            self.saturated += 1
        else:
            self._rows.append(row)

    def __len__(self) -> int:
        return len(self._rows)

    def vectors(self) -> RecordedVectors:
        """The samples in nominal units (the same shape the offline path fits)."""
        a = np.asarray(self._rows, dtype=np.float64).reshape(-1, 6)
        return RecordedVectors(
            mag_counts_to_gauss(a[:, :3]),
            acc_counts_to_g(a[:, 3:]),
            np.zeros(a.shape[0], dtype=bool),
            self.invalid,
        )


def report_mag_calibration(report: dict[str, Any]) -> AffineCalibration:
    """The magnetometer calibration a MAG_CAL_REPORT describes (COMPASS_OFS/DIA/ODI/SCALE).

    The bridge's alignment rotation is not on the wire (MAG_CAL_REPORT has no
    field for it), so it is left out: a rotation changes no field magnitude
    (the spread after is exact) and only turns the calibrated cloud in the
    plot. Raises ``ValueError`` on missing, non-finite or singular parameters.
    """

    def v3(prefix: str) -> tuple[float, float, float]:
        return (
            float(report[prefix + "x"]),
            float(report[prefix + "y"]),
            float(report[prefix + "z"]),
        )

    try:
        view = ArduPilotView(
            ofs_mG=v3("ofs_"),
            diag=v3("diag_"),
            offdiag=v3("offdiag_"),
            scale=float(report.get("scale_factor") or 1.0),
            rotation_rotvec=(0.0, 0.0, 0.0),
        )
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"MAG_CAL_REPORT without its parameters: {e}") from None
    return AffineCalibration.from_ardupilot(view)


def add_live_figures(
    report: dict[str, Any], samples: RecordedVectors, location: tuple[float, float, float] | None
) -> float:
    """Field spread before/after (into ``report``) from RAW_IMU samples; returns the heading error.

    Before: ``|B|`` of the raw samples at the nominal transfer; after: with the
    reported parameters applied; both as the engine reports them (+- half peak
    to peak, nT). The heading error is estimated from the fitness across the
    horizontal field: the WMM's at ``location``, else the one the calibrated
    samples show (their mean ``|B|`` and the dip between field and gravity).
    """
    from bridge.calibration.fits.scalar import field_spread_nT

    fitness = float(report.get("fitness") or math.nan)
    try:
        cal = report_mag_calibration(report)
    except ValueError:
        cal = None
    if cal is not None and samples.mag_G.shape[0] >= 2:
        report["field_spread_before_nT"] = field_spread_nT(samples.mag_G)[0]
        report["field_spread_after_nT"] = field_spread_nT(cal.apply(samples.mag_G))[0]
        report["spread_samples"] = int(samples.mag_G.shape[0])
    if location is not None:
        from bridge.core.wmm import earth_field

        f = earth_field(*location)
        return heading_error_estimate_deg(fitness, horizontal_field_G(f.total_G, f.inclination_deg))
    if cal is None or samples.mag_G.shape[0] == 0:
        return math.nan
    return heading_error_estimate_deg(
        fitness, _measured_horizontal_G(Calibration(mag=cal), samples)
    )


# ---------------------------------------------------------------------------
# Live over MAVLink: the conversation
# ---------------------------------------------------------------------------


@dataclass(slots=True)
class LiveOutcome:
    """What the MAVLink flow ended with (``samples``: the RAW_IMU seen while it ran)."""

    report: dict[str, Any] | None
    accepted: bool
    message: str
    samples: RawImuCollector


def run_mavlink(
    url: str,
    *,
    target_system: int,
    target_component: int,
    timeout_s: float,
    accept: Callable[[dict[str, Any], RawImuCollector], bool],
    on_progress: Callable[[float, frozenset[int]], None],
    on_text: Callable[[str], None] | None = None,
    on_linked: Callable[[Any], None] | None = None,
    source_system: int = 255,
    raw_imu_hz: float = RAW_IMU_RATE_HZ,
) -> LiveOutcome:
    """The ArduPilot magcal flow against a bridge at ``url`` (a pymavlink connection string).

    HEARTBEAT from the target first (so a udpin link knows where to send; then
    ``on_linked(heartbeat)``, before anything is asked of anyone), and
    ours every second while the calibration runs (so it does not forget us);
    RAW_IMU raised to ``raw_imu_hz``; ``DO_START_MAG_CAL`` (all compasses, no
    retry, no autosave: the person decides); ``MAG_CAL_PROGRESS`` ->
    ``on_progress(completion_pct, missing sections)``, STATUSTEXT ->
    ``on_text``, RAW_IMU collected; on ``MAG_CAL_REPORT`` with
    ``MAG_CAL_SUCCESS`` ``accept(report, samples)`` decides between
    ``DO_ACCEPT_MAG_CAL`` and ``DO_CANCEL_MAG_CAL``. A timeout, a failed fit
    or Ctrl-C cancels the calibration on the bridge; RAW_IMU goes back to its
    configured rate (SET_MESSAGE_INTERVAL 0) whatever happens.
    """
    os.environ.setdefault("MAVLINK20", "1")  # the bridge speaks MAVLink 2 only
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(
        url, source_system=source_system, source_component=190, dialect="ardupilotmega"
    )
    M: Any = mavutil.mavlink
    samples = RawImuCollector()
    texts: list[str] = []
    chunks = StatusTextChunks()

    def ours(m: Any) -> bool:
        return bool(m.get_srcSystem() == target_system and m.get_srcComponent() == target_component)

    def command(cmd: int, *params: float, final_wait_s: float = 30.0) -> int | None:
        """COMMAND_LONG, resent up to 3 times; the final result (after IN_PROGRESS acks)."""
        p = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][:7]
        for confirmation in range(3):
            conn.mav.command_long_send(target_system, target_component, cmd, confirmation, *p)
            end = time.monotonic() + 1.5
            while time.monotonic() < end:
                ack = conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.2)
                if ack is None or ack.command != cmd or not ours(ack):
                    continue
                if ack.result != M.MAV_RESULT_IN_PROGRESS:
                    return int(ack.result)
                # long work on the bridge (the compass's own MAGCAL,END): wait, do not resend
                end = time.monotonic() + final_wait_s
        return None

    started = False
    linked = False  # the bridge answered: there is something to put back at the end
    try:
        deadline = time.monotonic() + min(10.0, timeout_s)
        hb = None
        while hb is None and time.monotonic() < deadline:
            conn.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            end = min(deadline, time.monotonic() + 1.0)
            while hb is None and time.monotonic() < end:
                m = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=0.2)
                hb = m if m is not None and ours(m) else None
        if hb is None:
            return LiveOutcome(
                None,
                False,
                f"no HEARTBEAT from system {target_system} component {target_component} on {url}",
                samples,
            )
        linked = True
        if on_linked is not None:
            on_linked(hb)
        command(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_RAW_IMU, round(1e6 / raw_imu_hz))
        result = command(M.MAV_CMD_DO_START_MAG_CAL, 0, 0, 0, 0)
        if result != M.MAV_RESULT_ACCEPTED:
            why = (
                "a calibration is already running (DO_CANCEL_MAG_CAL it first)"
                if result == M.MAV_RESULT_TEMPORARILY_REJECTED
                else f"result {result}"
            )
            return LiveOutcome(None, False, f"DO_START_MAG_CAL refused: {why}", samples)
        started = True
        end = time.monotonic() + timeout_s
        report: dict[str, Any] | None = None
        kinds = ["MAG_CAL_PROGRESS", "MAG_CAL_REPORT", "RAW_IMU", "STATUSTEXT"]
        next_beat = time.monotonic() + 1.0
        while report is None and time.monotonic() < end:
            if time.monotonic() >= next_beat:
                # A ground station says it is there once a second: a bridge's udpin
                # endpoint forgets a peer that stays silent (the tumble can take minutes).
                conn.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                next_beat = time.monotonic() + 1.0
            m = conn.recv_match(type=kinds, blocking=True, timeout=0.2)
            if m is None or not ours(m):
                continue
            kind = m.get_type()
            if kind == "RAW_IMU":
                samples.add(m.xmag, m.ymag, m.zmag, m.xacc, m.yacc, m.zacc)
            elif kind == "STATUSTEXT":
                text = chunks.add(m)
                if text is not None:
                    texts.append(text)
                    if on_text is not None:
                        on_text(text)
            elif kind == "MAG_CAL_PROGRESS":
                missing = frozenset(range(N_SECTIONS)) - mask_sections(bytes(m.completion_mask))
                on_progress(float(m.completion_pct), missing)
            else:
                report = m.to_dict()
        if report is None:
            return LiveOutcome(None, False, f"no MAG_CAL_REPORT within {timeout_s:g} s", samples)
        report["cal_status"] = _mag_cal_status_name(M, int(report.get("cal_status", -1)))
        if report["cal_status"] != "MAG_CAL_SUCCESS":
            # The bridge sends the reason as a STATUSTEXT right after the report.
            end = time.monotonic() + 1.0
            while time.monotonic() < end and not any("fail" in t.lower() for t in texts):
                m = conn.recv_match(type="STATUSTEXT", blocking=True, timeout=0.2)
                text = chunks.add(m) if m is not None and ours(m) else None
                if text is not None:
                    texts.append(text)
            why = next((t for t in reversed(texts) if "fail" in t.lower()), "")
            return LiveOutcome(
                report,
                False,
                f"calibration failed: {report['cal_status']}" + (f" ({why})" if why else ""),
                samples,
            )
        if accept(report, samples):
            r = command(M.MAV_CMD_DO_ACCEPT_MAG_CAL, 0)
            ok = r == M.MAV_RESULT_ACCEPTED
            started = not ok  # refused: cancel below, so the bridge is not left waiting
            return LiveOutcome(report, ok, "accepted" if ok else f"accept refused ({r})", samples)
        return LiveOutcome(
            report, False, "cancelled: the bridge keeps its previous calibration", samples
        )
    finally:
        # Also on Ctrl-C: never leave the bridge calibrating (or waiting for an accept).
        if started:
            command(M.MAV_CMD_DO_CANCEL_MAG_CAL, 0)
        if linked:
            command(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_RAW_IMU, 0)
        conn.close()


def _mag_cal_status_name(M: Any, code: int) -> str:
    entry = M.enums["MAG_CAL_STATUS"].get(code)
    return str(entry.name) if entry is not None else f"MAG_CAL_STATUS({code})"


# ---------------------------------------------------------------------------
# The command
# ---------------------------------------------------------------------------


def write_coverage(out: TextIO, missing: frozenset[int]) -> None:
    """The coverage map with its legend."""
    out.write(coverage_text(missing) + "\n")


def _plot(out: TextIO, path: str, raw_G: FloatArray, cal_G: FloatArray, title: str) -> None:
    from bridge.tools.plot import PlotUnavailableError, plot_calibration

    try:
        plot_calibration(path, raw_G, cal_G, title=title)
    except (PlotUnavailableError, OSError, ValueError) as e:
        out.write(f"no plot: {e}\n")
        return
    out.write(f"plot written to {path}\n")


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
        data = recording_data(vectors, location)
        with Progress(f"fitting ({args.method})", None, enabled=args.progress, tick=True) as bar:
            bar.update(note=f"{len(vectors.mag_G)} frames")
            res = calibrate(args.method, data)
        report = offline_report(res)
        out.write(
            f"{args.recording}: {len(vectors.mag_G)} frames "
            f"({int(vectors.saturated.sum())} saturated, {vectors.dropped_lines} bad lines)\n"
        )
        write_coverage(out, raw_missing(data))
        out.write("\n".join(offline_lines(report)) + "\n")
        if not res.report.ok:
            # A failed fit has no parameters to show, plot or save: only its cause.
            out.write("calibration failed: nothing to accept\n")
            return 1
        if args.plot:
            ok = ~vectors.saturated
            _plot(
                out,
                args.plot,
                vectors.mag_G[ok],
                res.calibration.mag.apply(vectors.mag_G[ok]),
                f"{args.recording}: {res.report.method}",
            )
        if args.state_dir is None:
            out.write("(no --state-dir: the result is shown, not saved)\n")
            return 0
        if decide(report):
            save_offline(args.state_dir, res, report)
            out.write(f"saved to {args.state_dir}/calibration.json\n")
            return 0
        out.write("not saved\n")
        return 1
    return _cmd_calibrate_live(args, out, decide)


def _cmd_calibrate_live(args: Any, out: TextIO, decide: Callable[[dict[str, Any]], bool]) -> int:
    from bridge.tools.progress import Progress

    if args.method not in (None, "best"):
        out.write("note: --method applies offline; the bridge fits with its configured method\n")
    bar = Progress("calibrating", 100.0, enabled=args.progress)
    plain = None if bar.enabled else calhelp.PlainProgress(out)  # piped: whole lines instead
    last_missing: list[frozenset[int]] = []
    shown: list[bool] = []
    found: list[bool] = []
    calhelp.say(out, calhelp.looking_line(args.mavlink, args.target_system, args.target_component))

    def on_linked(heartbeat: Any) -> None:
        found.append(True)  # only now, with a bridge there, is anyone asked to turn anything
        calhelp.say(out, calhelp.found_line(heartbeat, args.mavlink), calhelp.TURN)

    warning: list[tuple[float, str]] = []  # the last motion warning and when it came

    def recent_warning() -> str | None:
        if warning and time.monotonic() - warning[0][0] < MOTION_NOTE_S:
            return warning[0][1]
        return None

    def on_progress(pct: float, missing: frozenset[int]) -> None:
        last_missing[:] = [missing]
        if plain is not None:
            plain.progress(pct, len(missing))
        note = progress_note(len(missing), recent_warning())
        bar.update(pct, note=note, detail=coverage_text(missing))

    def on_text(text: str) -> None:
        if calhelp.is_progress_text(text):  # the bar (or the lines) already say how far
            if plain is not None:
                plain.again()  # the bridge's reminder: it has not moved on for a while
            return
        if plain is not None:
            plain.text(text)
        if is_motion_warning(text):
            warning[:] = [(time.monotonic(), text)]
            n = len(last_missing[0]) if last_missing else N_SECTIONS
            bar.update(note=progress_note(n, text))
        else:
            bar.update(note=text[:60])

    def show(report: dict[str, Any], samples: RawImuCollector) -> None:
        bar.close()
        shown.append(True)
        if last_missing:
            write_coverage(out, last_missing[0])
        vec = samples.vectors()
        herr = add_live_figures(report, vec, args.location)
        out.write("\n".join(report_lines(report, herr)) + "\n")
        out.write(
            f"RAW_IMU during the run: {len(samples)} samples "
            f"({samples.saturated} saturated, {samples.invalid} invalid dropped)\n"
        )
        if args.plot:
            try:
                cal = report_mag_calibration(report)
            except ValueError as e:
                out.write(f"no plot: {e}\n")
                return
            if len(samples) == 0:
                out.write("no plot: no RAW_IMU samples came during the run\n")
                return
            _plot(out, args.plot, vec.mag_G, cal.apply(vec.mag_G), f"{args.mavlink}: live")

    def accept(report: dict[str, Any], samples: RawImuCollector) -> bool:
        show(report, samples)
        return decide(report)

    try:
        outcome = run_mavlink(
            args.mavlink,
            target_system=args.target_system,
            target_component=args.target_component,
            timeout_s=args.timeout,
            accept=accept,
            on_progress=on_progress,
            on_text=on_text,
            on_linked=on_linked,
        )
    finally:
        bar.close()
    if outcome.report is not None and not shown:
        show(outcome.report, outcome.samples)  # a failed fit: its figures say why
    out.write(outcome.message + "\n")
    if not found:
        calhelp.say(out, calhelp.no_bridge_hint(args.mavlink))
    return 0 if outcome.accepted else 1


__all__ = [
    "MOTION_NOTE_S",
    "LiveOutcome",
    "RawImuCollector",
    "RecordedVectors",
    "StatusTextChunks",
    "add_live_figures",
    "cmd_calibrate",
    "coverage_map",
    "coverage_text",
    "fit_recording",
    "frame_times",
    "heading_error_estimate_deg",
    "horizontal_field_G",
    "is_motion_warning",
    "offline_lines",
    "progress_note",
    "raw_missing",
    "read_recording",
    "recording_data",
    "report_lines",
    "report_mag_calibration",
    "run_mavlink",
]
