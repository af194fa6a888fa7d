"""``compass-bridge status``: one-shot health of running bridges, for people and scripts.

How it reaches the daemon: over Zenoh, which every bridge already speaks. It
asks the ``<prefix>/status`` queryable (link state, frame rate, counters,
calibration state and age, the drift monitor's verdict) and
``<prefix>/calibration`` (the report of the calibration in use: fitness,
field spread), and listens to
``<prefix>/heading`` for a moment for the latest quality flags (disturbance).
By default it connects to ``tcp/127.0.0.1:7447``, the listener a bridge on
this host opens (the same default as ``compass-bridge monitor``). No unix
socket or MAVLink link is needed, and a bridge on another host answers the
same way (``--connect tcp/HOST:7447``).

:func:`summarise` (pure) turns the answers into one record per bridge;
:func:`format_human` prints it; ``--json`` prints the records.
"""

from __future__ import annotations

import json
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any, TextIO

from bridge.core.quality import heading_usable
from bridge.zenoh import schema
from bridge.zenoh.monitor import DEFAULT_CONNECT, MonitorOptions, monitor_config

#: What ``status`` asks when no key expression is given: every bridge's status.
DEFAULT_STATUS_KEYEXPR = "fleet/**/status"


@dataclass(slots=True)
class BridgeAnswers:
    """The raw documents one bridge gave (any may be missing)."""

    prefix: str
    status: dict[str, Any] | None = None
    calibration: dict[str, Any] | None = None
    heading: dict[str, Any] | None = None
    errors: list[str] = field(default_factory=list)


def _age_text(seconds: float | None) -> str:
    if seconds is None or not math.isfinite(seconds):
        return "unknown age"
    if seconds < 120:
        return f"{seconds:.0f} s old"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min old"
    if seconds < 172800:
        return f"{seconds / 3600:.1f} h old"
    return f"{seconds / 86400:.1f} days old"


def summarise(a: BridgeAnswers) -> dict[str, Any]:
    """One bridge's health as a flat, JSON-ready record. PURE.

    ``healthy`` is True when the link streams at a non-zero rate and the last
    heading was not flagged disturbed or saturated.
    """
    st = a.status or {}
    link = st.get("link") or {}
    counters = link.get("counters") or {}
    cal_state = st.get("calibration") or {}
    cal = a.calibration or {}
    report = cal.get("report") or {}
    flags = (a.heading or {}).get("flags") or {}
    rate = link.get("frame_rate_hz")
    state = link.get("state")
    disturbed = flags.get("disturbed") if flags else None
    rec: dict[str, Any] = {
        "bridge": a.prefix,
        "link": {
            "port": link.get("port"),
            "state": state,
            "frame_rate_hz": rate,
        },
        "counters": {
            k: counters.get(k)
            for k in (
                "frames",
                "attitude_frames",
                "lost_frames",
                "bad_lines_total",
                "reconnects",
                "stale_events",
                "resets",
            )
            if k in counters
        },
        "samples": st.get("samples"),
        "pipeline_errors": st.get("pipeline_errors"),
        "uptime_s": st.get("uptime_s"),
        "calibration": {
            "source": cal_state.get("source", cal.get("source")),
            "state": cal_state.get("state"),
            "age_s": cal_state.get("age_s"),
            "method": report.get("method"),
            "status": report.get("cal_status", report.get("status")),
            "fitness_mG": cal_state.get("fitness_mG", report.get("fitness_mG")),
            # False: no hard- or soft-iron correction in use; None: not said (a heading-only
            # compass calibrates itself, or the bridge is older)
            "calibrated": cal_state.get("calibrated"),
            # why storage refused the calibration in use (lost at a restart until it is saved)
            "save_error": cal_state.get("save_error"),
            "saving": cal_state.get("saving"),
            "field_spread_before_nT": report.get("field_spread_before_nT"),
            "field_spread_after_nT": report.get("field_spread_after_nT"),
        },
        "quality": {
            "disturbed": disturbed,
            "saturated": flags.get("saturated") if flags else None,
            "degraded": flags.get("degraded") if flags else None,
            "accelerating": flags.get("accelerating") if flags else None,
            "heading_deg": (a.heading or {}).get("heading_deg"),
        },
        # where roll and pitch come from (the last heading's), and the tilt source's state
        "tilt": _tilt_record((a.heading or {}).get("tilt"), st.get("tilt")),
        "errors": list(a.errors),
    }
    # The drift monitor's verdict (bridge.app.calibration.drift) as the status document has
    # it; a drifted calibration leaves the bridge "healthy" (it streams a usable heading)
    # but is said on its own line, as `monitor` flags it DRIFT.
    drift = cal_state.get("drift")
    rec["drift"] = dict(drift) if isinstance(drift, dict) else None
    rec["calibrated"] = cal_state.get("calibrated")
    # parameters set over MAVLink or Zenoh that params.json refused (lost at a restart)
    rec["parameters_save_error"] = (st.get("parameters") or {}).get("save_error")
    rec["storage_refused"] = schema.storage_refused(st)  # as `monitor` flags NOSAVE
    shared = (st.get("zenoh") or {}).get("duplicate_prefix")
    if shared:  # bridge.zenoh.instances: the key prefix is not this bridge's alone
        rec["errors"].append(f"key prefix shared with {len(shared)} other bridge(s): {shared}")
    rec["healthy"] = bool(
        state == "streaming"
        and isinstance(rate, int | float)
        and rate > 0
        and heading_usable(bool(flags.get("saturated")), bool(disturbed))
        and not shared  # two bridges' headings under one key: nobody can tell whose
    )
    rec["verdict"] = verdict(rec)
    return rec


#: Exit codes of ``status`` (and ``monitor --once``), for scripts (docs/tools.md).
EXIT_OK = 0  #: every bridge answering streams a usable, calibrated heading
EXIT_NOT_OK = 1  #: a bridge does not stream a usable heading, or none answered
EXIT_UNCALIBRATED = 3  #: every bridge streams, but one runs without a calibration


def verdict(rec: dict[str, Any]) -> str:
    """``OK``, ``NOT OK`` or ``UNCALIBRATED`` (streams, but carries the iron errors). PURE."""
    if not rec.get("healthy"):
        return "NOT OK"
    return "UNCALIBRATED" if rec.get("calibrated") is False else "OK"


def exit_code(records: list[dict[str, Any]]) -> int:
    """The worst verdict among ``records`` as an exit code (none answering: 1). PURE."""
    verdicts = {r.get("verdict") or verdict(r) for r in records}
    if not records or "NOT OK" in verdicts:
        return EXIT_NOT_OK
    return EXIT_UNCALIBRATED if "UNCALIBRATED" in verdicts else EXIT_OK


def _tilt_record(heading: Any, state: Any) -> dict[str, Any] | None:
    """The tilt source as ``status`` shows it: the last heading's source and heading error,
    and (from the status document) the autopilot's attitude heard or not, its clock."""
    if not isinstance(heading, dict) and not isinstance(state, dict):
        return None
    h = heading if isinstance(heading, dict) else {}
    s = state if isinstance(state, dict) else {}
    ap_doc = s.get("autopilot")
    ap: dict[str, Any] = ap_doc if isinstance(ap_doc, dict) else {}
    return {
        "source": h.get("source", s.get("source")),
        "heading_error_deg": h.get("heading_error_deg", s.get("heading_sigma_deg")),
        "frames": s.get("frames"),
        "autopilot_heard": ap.get("heard"),
        "autopilot_rate_hz": ap.get("rate_hz"),
        "autopilot_clock": ap.get("clock"),
        "autopilot_residual_deg": ap.get("residual_deg"),
    }


def _tilt_text(t: dict[str, Any]) -> str:
    """The tilt line: "autopilot, heading error 0.4 deg; autopilot heard at 20 Hz ..."."""
    parts = [str(t.get("source") or "unknown")]
    err = t.get("heading_error_deg")
    if isinstance(err, int | float):
        parts[0] += f", heading error {err:.1f} deg"
    if t.get("autopilot_heard"):
        rate = t.get("autopilot_rate_hz")
        clock = t.get("autopilot_clock")
        res = t.get("autopilot_residual_deg")
        ap = "autopilot attitude heard" + (
            f" at {rate:.0f} Hz" if isinstance(rate, int | float) else ""
        )
        if clock:
            ap += f", clock by {clock}"
        if isinstance(res, int | float):
            ap += f", boards {res:.1f} deg apart"
        parts.append(ap)
    elif t.get("autopilot_heard") is False:
        parts.append("no autopilot attitude")
    return "; ".join(parts)


def _drift_text(d: dict[str, Any]) -> str:
    """The drift monitor's verdict in a few words ("DRIFT 42 mG, up to 11.0 deg, ...")."""
    state, mode = str(d.get("state") or "unknown"), d.get("mode")
    parts = [state.upper() if d.get("detected") else state]
    change, err = d.get("change_mG"), d.get("heading_error_deg")
    if d.get("detected") and isinstance(change, int | float):
        parts.append(f"{change:.0f} mG change")
        if isinstance(err, int | float):
            parts.append(f"heading error up to {err:.1f} deg")
    learned = d.get("learned_mG")
    if isinstance(learned, int | float) and learned > 0:
        parts.append(f"{learned:.0f} mG learned in {d.get('steps', 0)} steps")
    if mode:
        parts.append(f"mode {mode}")
    return ", ".join(parts)


def format_human(records: list[dict[str, Any]]) -> str:
    """A few lines per bridge for a person."""
    if not records:
        return "no compass bridge answered"
    out: list[str] = []
    for r in records:
        link, c, cal, q = r["link"], r["counters"], r["calibration"], r["quality"]
        v = r.get("verdict") or verdict(r)
        why = ": no calibration in use, the heading carries the compass's iron errors"
        # (What storage refused is said on the first line too: the verdict and the exit code
        # stay as documented for scripts, which read it from the JSON.)
        unsaved = r.get("storage_refused") or []
        refused_s = f"; {' and '.join(unsaved)} NOT SAVED" if unsaved else ""
        out.append(f"{r['bridge']}: {v}{why if v == 'UNCALIBRATED' else ''}{refused_s}")
        rate = link.get("frame_rate_hz")
        rate_s = f"{rate:.1f} frames/s" if isinstance(rate, int | float) else "rate unknown"
        out.append(f"  link         {link.get('state')} on {link.get('port')}, {rate_s}")
        out.append(
            "  counters     "
            + ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in c.items() if v is not None)
        )
        up = r.get("uptime_s")
        out.append(
            f"  pipeline     {r.get('samples')} samples, {r.get('pipeline_errors')} errors"
            + (f", up {up:.0f} s" if isinstance(up, int | float) else "")
        )
        parts = [str(cal.get("source") or "unknown"), _age_text(cal.get("age_s"))]
        if cal.get("method"):
            parts.append(f"method {cal['method']}")
        if isinstance(cal.get("fitness_mG"), int | float):
            parts.append(f"fitness {cal['fitness_mG']:.2f} mG")
        b, a = cal.get("field_spread_before_nT"), cal.get("field_spread_after_nT")
        if isinstance(b, int | float) and isinstance(a, int | float):
            parts.append(f"field spread ±{b / 100:.1f} -> ±{a / 100:.1f} mG")
        if cal.get("state") and cal["state"] != "idle":
            parts.append(f"calibration {cal['state']}")
        if cal.get("calibrated") is False:
            parts.append("UNCALIBRATED (calibrate it: docs/calibration.md)")
        if cal.get("save_error"):
            parts.append(
                f"NOT SAVED, lost at a restart until storage takes it: {cal['save_error']}"
            )
        elif cal.get("saving"):
            parts.append("saving")
        out.append("  calibration  " + ", ".join(parts))
        if r.get("parameters_save_error"):
            out.append(
                "  parameters   NOT SAVED, lost at a restart until storage takes them: "
                + str(r["parameters_save_error"])
            )
        drift = r.get("drift")
        if drift:
            out.append("  drift        " + _drift_text(drift))
        if q.get("disturbed") is None:
            out.append("  disturbance  unknown (no heading heard)")
        else:
            flags = [n for n in ("disturbed", "saturated", "degraded", "accelerating") if q.get(n)]
            hdg = q.get("heading_deg")
            h = f"heading {hdg:.1f}, " if isinstance(hdg, int | float) else ""
            out.append(f"  quality      {h}{', '.join(flags).upper() if flags else 'clean'}")
        if r.get("tilt"):
            out.append("  tilt         " + _tilt_text(r["tilt"]))
        for e in r.get("errors") or []:
            out.append(f"  error        {e}")
    return "\n".join(out)


def _prefix_of(key: str, leaf: str) -> str:
    return key[: -len(leaf) - 1] if key.endswith("/" + leaf) else key


def query(opts: MonitorOptions, keyexpr: str, *, timeout: float = 2.0) -> list[BridgeAnswers]:
    """Ask every bridge matching ``keyexpr`` (a ``.../status`` expression) for its health."""
    import zenoh

    session = zenoh.open(monitor_config(opts))
    try:
        answers: dict[str, BridgeAnswers] = {}
        deadline = time.monotonic() + timeout
        # A fresh session needs a moment to meet the bridge's; retry the query until then.
        while not answers and time.monotonic() < deadline:
            for reply in session.get(keyexpr, timeout=max(0.1, deadline - time.monotonic())):
                if reply.ok is None:
                    continue
                key = str(reply.ok.key_expr)
                prefix = _prefix_of(key, "status")
                try:
                    answers.setdefault(prefix, BridgeAnswers(prefix)).status = json.loads(
                        reply.ok.payload.to_bytes()
                    )
                except ValueError as e:
                    answers.setdefault(prefix, BridgeAnswers(prefix)).errors.append(
                        f"{key}: not JSON ({e})"
                    )
            if not answers:
                time.sleep(0.1)
        headings: dict[str, dict[str, Any]] = {}
        lock = threading.Lock()

        def on_heading(sample: zenoh.Sample) -> None:
            try:
                doc = json.loads(sample.payload.to_bytes())
            except ValueError:
                return
            with lock:
                headings[_prefix_of(str(sample.key_expr), "heading")] = doc

        subs = [session.declare_subscriber(f"{p}/heading", on_heading) for p in answers]
        for prefix, a in answers.items():
            for reply in session.get(f"{prefix}/calibration", timeout=timeout):
                if reply.ok is not None:
                    try:
                        a.calibration = json.loads(reply.ok.payload.to_bytes())
                    except ValueError as e:
                        a.errors.append(f"calibration: not JSON ({e})")
        end = time.monotonic() + 1.0  # a bridge at 1 Hz or faster publishes a heading by then
        while time.monotonic() < end:
            with lock:
                if all(p in headings for p in answers):
                    break
            time.sleep(0.05)
        for s in subs:
            s.undeclare()
        with lock:
            for prefix, a in answers.items():
                a.heading = headings.get(prefix)
        return [answers[p] for p in sorted(answers)]
    finally:
        session.close()


def where_text(opts: MonitorOptions, keyexpr: str) -> str:
    """Where ``status`` looks: the key expression and the zenoh endpoints."""
    connect = opts.connect or (() if opts.config_file or opts.listen else DEFAULT_CONNECT)
    via = ", ".join(connect) if connect else "the zenoh configuration's endpoints"
    return f"{keyexpr} via {via}"


def run_status(
    opts: MonitorOptions, out: TextIO, *, as_json: bool = False, timeout: float = 2.0
) -> int:
    """Print the health of every answering bridge; the exit code is :func:`exit_code`'s."""
    keyexpr = opts.keyexpr
    if not keyexpr.endswith("/status"):
        keyexpr = keyexpr.rstrip("/") + "/status"
    records = [summarise(a) for a in query(opts, keyexpr, timeout=timeout)]
    where = where_text(opts, keyexpr)
    if as_json:
        out.write(json.dumps({"asked": where, "bridges": records}, indent=2) + "\n")
    elif not records:
        out.write(
            f"no compass bridge answered {where} within {timeout:g} s: is one running, with "
            "[zenoh] enabled and reachable there? (--connect tcp/HOST:7447 asks another host)\n"
        )
    else:
        n = len(records)
        out.write(f"asked {where}: {n} bridge{'' if n == 1 else 's'} answered\n")
        out.write(format_human(records) + "\n")
    return exit_code(records)


__all__ = [
    "DEFAULT_STATUS_KEYEXPR",
    "EXIT_NOT_OK",
    "EXIT_OK",
    "EXIT_UNCALIBRATED",
    "BridgeAnswers",
    "exit_code",
    "format_human",
    "query",
    "run_status",
    "summarise",
    "verdict",
    "where_text",
]
