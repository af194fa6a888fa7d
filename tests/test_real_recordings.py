"""Calibration verdicts on recordings of real magnetometers (tests/data, SOURCES.md there).

The simulator is where the truth is known; these are where the verdicts must
hold. Each recording is converted to a ``compass-bridge record`` file of
``$PGMRA`` frames at the nominal transfer (``tests/realdata.py``) and goes
through the same path an operator's does: ``read_recording``, the engine's
methods, ``compass-bridge calibrate --recording``. The product's fit is
compared with reference fits written here, independent of the product's code
(a general ellipsoid by plain linear least squares, then refined on the
geometric residual by Gauss-Newton with a numerical Jacobian), and with the
calibration a source publishes.
"""

from __future__ import annotations

import contextlib
import functools
import io
import math
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from helpers import load_calibration
from realdata import (
    DATA,
    PX4_PUBLISHED_DIAG,
    PX4_PUBLISHED_OFFSETS_G,
    RealData,
    ck_tumble,
    ck_tumble_100hz,
    px4_mag_data1,
    sap6_hc,
    sap6_published,
    write_recording,
)

from bridge.calibration.fits.acceptance import DEFAULT_HEADING_MAX_DEG, Acceptance
from bridge.calibration.fits.methods import CalibrationData, calibrate, judge
from bridge.calibration.fits.methods import fit as fit_method
from bridge.calibration.fits.series import runs
from bridge.cli import main
from bridge.core.attitude import tilt_compensated_heading
from bridge.core.calibration import Calibration, CalibrationResult
from bridge.tools.calibrate import RecordedVectors, read_recording
from bridge.types import BoolArray, FloatArray

SOURCES = {
    "ck_tumble": ck_tumble,
    "ck_tumble_100hz": ck_tumble_100hz,
    "px4_mag_data1": px4_mag_data1,
    "sap6_HC": sap6_hc,
}


# ---------------------------------------------------------------------------
# The reference fits (independent of bridge.calibration)
# ---------------------------------------------------------------------------


def _sym(p: FloatArray) -> FloatArray:
    W = np.zeros((3, 3))
    W[np.triu_indices(3)] = p
    return W + W.T - np.diag(np.diag(W))


def algebraic_ellipsoid(x: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``x' A x + b' x = 1`` by plain linear least squares: centre and ``W`` with ``|W (x - c)| ~ 1``."""
    X, Y, Z = x.T
    D = np.column_stack([X * X, Y * Y, Z * Z, 2 * X * Y, 2 * X * Z, 2 * Y * Z, 2 * X, 2 * Y, 2 * Z])
    v, *_ = np.linalg.lstsq(D, np.ones(len(x)), rcond=None)
    A = np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])
    c = -np.linalg.solve(A, v[6:9])
    w, V = np.linalg.eigh(A / (1.0 + c @ A @ c))
    return c, V @ np.diag(np.sqrt(w)) @ V.T


def geometric_ellipsoid(x: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Least squares of ``|W (x - c)| - 1`` (Gauss-Newton, numerical Jacobian), from the algebraic fit."""
    c0, W0 = algebraic_ellipsoid(x)
    p = np.concatenate([c0, W0[np.triu_indices(3)]])

    def res(q: FloatArray) -> FloatArray:
        return np.asarray(np.linalg.norm((x - q[:3]) @ _sym(q[3:]).T, axis=1) - 1.0)

    for _ in range(40):
        r = res(p)
        J = np.empty((len(x), 9))
        for k in range(9):
            h = 1e-7 * max(1.0, abs(p[k]))
            dp = np.zeros(9)
            dp[k] = h
            J[:, k] = (res(p + dp) - r) / h
        step, *_ = np.linalg.lstsq(J, -r, rcond=None)
        p = p + step
        # The numerical Jacobian (h = 1e-7) leaves steps of ~1e-11 wandering for ever once
        # converged (5-6 steps here); 1e-9 (a millionth of a mG) is converged to the
        # tolerances below by far.
        if np.abs(step).max() < 1e-9:
            break
    return p[:3], _sym(p[3:])


def spread_rel(m: FloatArray) -> float:
    """RMS scatter of |B| about its mean, as a fraction of it (scale-free)."""
    n = np.linalg.norm(m, axis=1)
    return float(np.std(n) / np.mean(n))


# ---------------------------------------------------------------------------
# Fixtures: the recordings as an operator would have them
# ---------------------------------------------------------------------------


pytestmark = pytest.mark.usefixtures("restore_logging")  # main() runs in-process


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, RecordedVectors]]:
    out: dict[str, tuple[Path, RecordedVectors]] = {}
    d = tmp_path_factory.mktemp("real")
    for name, load in SOURCES.items():
        path = write_recording(load(), d / f"{name}.rec")
        out[name] = (path, read_recording(str(path)))
    return out


def _data(v: RecordedVectors) -> CalibrationData:
    return CalibrationData(v.mag_G, v.acc_g, v.saturated, t_s=v.t_s)


def _fit(v: RecordedVectors, method: str) -> CalibrationResult:
    return calibrate(method, _data(v))


Fit = Callable[..., CalibrationResult]


@pytest.fixture(scope="module")
def fit(recorded: dict[str, tuple[Path, RecordedVectors]]) -> Fit:
    """``fit(name, method, acceptance=None)``: that method's fit of the recording, judged
    against ``acceptance`` (``calibrate``'s result). The fit is made once per module:
    several tests check different facts of the same fit (the 100 Hz tumble's is the
    reference of every decimated rate), or hold it to a tighter target; a fit is
    deterministic and no test changes one (``methods.fit``, then ``methods.judge``)."""
    fitted: dict[tuple[str, str], CalibrationResult] = {}
    judged: dict[tuple[str, str, Acceptance | None], CalibrationResult] = {}

    def get(name: str, method: str, acceptance: Acceptance | None = None) -> CalibrationResult:
        v = recorded[name][1]
        if (name, method) not in fitted:
            fitted[name, method] = fit_method(method, _data(v))
        if (name, method, acceptance) not in judged:
            judged[name, method, acceptance] = judge(fitted[name, method], _data(v), acceptance)
        return judged[name, method, acceptance]

    return get


Reference = tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]


@pytest.fixture(scope="module")
def reference(recorded: dict[str, tuple[Path, RecordedVectors]]) -> Callable[[str], Reference]:
    """``reference(name)``: the recording's unsaturated samples and the independent
    geometric and algebraic ellipsoid fits of them (``x, c_geo, W_geo, c_alg, W_alg``),
    made once per module: two tests hold the bridge's fits against the same ones."""
    made: dict[str, Reference] = {}

    def get(name: str) -> Reference:
        if name not in made:
            x = recorded[name][1].mag_G[~recorded[name][1].saturated]
            made[name] = (x, *geometric_ellipsoid(x), *algebraic_ellipsoid(x))
        return made[name]

    return get


# ---------------------------------------------------------------------------
# 1. The recordings
# ---------------------------------------------------------------------------


def test_the_shipped_excerpts_are_small_and_every_one_has_its_source_and_licence() -> None:
    sources = (DATA / "SOURCES.md").read_text()
    shipped = ("ck_tumble.csv", "ck_tumble_100hz.csv", "px4_mag_data1.csv", "sap6_HC.json")
    for f in (*shipped, "sap6_HC.cfg"):
        assert (DATA / f).stat().st_size < 150_000, f
        assert f"`{f}`" in sources
    assert sum((DATA / f).stat().st_size for f in shipped) < 300_000
    for words in (
        "Apache-2.0",
        "Copyright 2023 CK-Explorer",
        "BSD-3-Clause",
        "Copyright (C) 2021 PX4 Development Team",
        "The Unlicense",
        "Phil Underwood",
        "6f2f3d216398c0ef4155fe1dd2238c02d42629d7",
        "25ed6b67fb1174d88b4834076ec812c3fabd139d",
        "6bf53ffd8978df46e958f55e97e9691c4f84da06",
    ):
        assert words in sources, words
    assert (DATA / "licenses" / "Apache-2.0.txt").read_text().count("Apache License") >= 1
    assert "Neither the name PX4" in (DATA / "licenses" / "PX4-BSD-3-Clause.txt").read_text()


@pytest.mark.parametrize("name", sorted(SOURCES))
def test_the_recording_carries_the_source_samples_at_the_nominal_transfer_and_their_times(
    name: str, recorded: dict[str, tuple[Path, RecordedVectors]]
) -> None:
    src: RealData = SOURCES[name]()
    _, v = recorded[name]
    assert len(v.mag_G) == len(src) and not v.saturated.any() and v.dropped_lines == 0
    # rounded to the ADC's count: half a count, 0.2 mG and 1 mg
    assert np.abs(v.mag_G - src.mag_G).max() <= 0.5 / 2560.0 + 1e-12
    assert np.abs(v.acc_g - src.acc_g).max() <= 0.5 / 491.5 + 1e-12
    # the frame times the product derives from the $PGMRA counter are the source's
    assert v.t_s is not None
    assert np.allclose(v.t_s, src.t_s - src.t_s[0], atol=1e-6)


def test_the_recordings_are_what_the_suite_needs() -> None:
    ck, px4, sap = ck_tumble(), px4_mag_data1(), sap6_hc()
    # a full 3-D hand tumble with an accelerometer: gravity seen from every side
    g = ck.acc_g / np.linalg.norm(ck.acc_g, axis=1, keepdims=True)
    assert g.min(axis=0).max() < -0.75 and g.max(axis=0).min() > 0.75
    # slow and sparse: a few hundred samples
    assert 200 <= len(px4) <= 400
    # hard iron larger than the Earth's field, on two sensors
    for d in (ck, px4):
        c, W = geometric_ellipsoid(d.mag_G)
        radius = float(np.linalg.det(W)) ** (-1.0 / 3.0)
        assert np.linalg.norm(c) > radius, d.name
    # three sources, three sensors; two with an accelerometer
    assert ck.has_accelerometer and sap.has_accelerometer and not px4.has_accelerometer


# ---------------------------------------------------------------------------
# 2. The fit itself, against independent fits and what the sources publish
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(SOURCES))
def test_the_fit_agrees_with_independent_least_squares_and_leaves_the_same_spread(
    name: str, fit: Fit, reference: Callable[[str], Reference]
) -> None:
    x, c_geo, W_geo, c_alg, W_alg = reference(name)
    field_mG = 1000.0 * float(np.linalg.det(W_geo)) ** (-1.0 / 3.0)
    tol_mG = max(1.0, 0.005 * field_mG)
    best_reference = min(spread_rel((x - c_geo) @ W_geo.T), spread_rel((x - c_alg) @ W_alg.T))
    for method in ("ellipsoid", "best"):
        res = fit(name, method)
        c = np.asarray(res.calibration.mag.offset)
        assert 1000.0 * np.linalg.norm(c - c_geo) <= tol_mG, (method, c, c_geo)
        assert spread_rel(res.calibration.mag.apply(x)) <= 1.05 * best_reference, method
    # the default method succeeds where the independent fit calibrates
    best = fit(name, "best")
    assert best.report.ok, best.report.reason
    assert best.report.predicted_heading_deg <= best.report.heading_limit_deg


@pytest.mark.parametrize("name", ["ck_tumble", "ck_tumble_100hz"])
def test_the_default_method_calibrates_the_real_hand_tumble_and_saves_it(
    name: str,
    recorded: dict[str, tuple[Path, RecordedVectors]],
    tmp_path: Path,
    reference: Callable[[str], Reference],
) -> None:
    # `compass-bridge calibrate --recording` as an operator runs it: no --method (the
    # default, best), --yes: it succeeds and saves what the independent fit finds
    path, _ = recorded[name]
    state = tmp_path / "state"
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(["calibrate", "--recording", str(path), "--yes", "--state-dir", str(state)])
    text = out.getvalue()
    assert code == 0, text
    assert "MAG_CAL_SUCCESS  (method ellipsoid_aligned)" in text and "saved to" in text
    assert f"limit {DEFAULT_HEADING_MAX_DEG:.2f} deg" in text
    saved, _ = load_calibration(state)
    x, c_geo, W_geo, c_alg, W_alg = reference(name)
    field_mG = 1000.0 * float(np.linalg.det(W_geo)) ** (-1.0 / 3.0)
    centre_mG = 1000.0 * np.linalg.norm(np.asarray(saved.mag.offset) - c_geo)
    assert centre_mG <= max(1.0, 0.005 * field_mG)
    best_reference = min(spread_rel((x - c_geo) @ W_geo.T), spread_rel((x - c_alg) @ W_alg.T))
    assert spread_rel(saved.mag.apply(x)) <= 1.05 * best_reference


def test_a_real_hand_tumble_is_judged_on_its_accelerometer_and_alignment_too(
    fit: Fit,
) -> None:
    # 394 frames of a hand tumble with 0.05 g of shake: the magnetometer's part leaves
    # ~0.1 deg, the accelerometer and alignment a jackknife ~0.6 deg -- within the 1 deg
    # target, so it succeeds; asked for 0.25 deg, it fails naming that part, not the
    # magnetometer
    rep = fit("ck_tumble", "best").report
    mag_only = fit("ck_tumble", "ellipsoid").report
    assert mag_only.ok and mag_only.predicted_heading_deg < 0.2
    assert rep.ok and rep.heading_limit_deg == DEFAULT_HEADING_MAX_DEG
    assert 0.4 < rep.heading_error_deg <= rep.predicted_heading_deg <= rep.heading_limit_deg
    assert rep.predicted_heading_deg == pytest.approx(
        math.hypot(rep.heading_error_deg, mag_only.predicted_heading_deg), rel=0.1
    )
    assert 0.03 < rep.motion_g < 0.08
    assert any("alignment from 394 frames" in n for n in rep.notes)
    strict = fit("ck_tumble", "best", Acceptance(heading_max_deg=0.25)).report
    assert not strict.ok and strict.status == "MAG_CAL_FAILED_RESIDUALS_HIGH"
    assert strict.reason.startswith("heading error ~") and "> 0.25" in strict.reason
    assert strict.reason.endswith("turn slower / steadier")


def test_px4s_published_calibration_is_matched(
    fit: Fit,
) -> None:
    res = fit("px4_mag_data1", "ellipsoid")
    assert res.report.ok
    c = np.asarray(res.calibration.mag.offset)
    # PX4's own test: offsets within 0.01 G, the diagonal within 0.01 (relative to x here)
    assert np.abs(c - PX4_PUBLISHED_OFFSETS_G).max() <= 0.01
    diag = np.asarray(res.calibration.mag.ardupilot_view().diag)
    assert np.abs(diag / diag[0] - PX4_PUBLISHED_DIAG).max() <= 0.02


def test_the_survey_instruments_own_calibration_is_matched(
    recorded: dict[str, tuple[Path, RecordedVectors]],
    fit: Fit,
) -> None:
    _, v = recorded["sap6_HC"]
    pub = sap6_published()
    res = fit("sap6_HC", "best")
    assert res.report.ok, res.report.reason
    c = np.asarray(res.calibration.mag.offset)
    assert 1000.0 * np.abs(c - np.asarray(pub["centre_G"])).max() <= 1.0
    after = np.linalg.norm(res.calibration.mag.apply(v.mag_G), axis=1)
    assert float(np.mean(after)) == pytest.approx(float(pub["field_G"]), rel=0.01)
    g = v.acc_g / np.linalg.norm(v.acc_g, axis=1, keepdims=True)
    m = res.calibration.mag.apply(v.mag_G)
    dip = np.degrees(np.arcsin(np.median(np.sum(g * m, axis=1) / after)))
    assert dip == pytest.approx(float(pub["dip_deg"]), abs=0.5)


# ---------------------------------------------------------------------------
# 3. One acceptance rule: no method says SUCCESS when its own figures condemn it
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(SOURCES))
def test_min_max_keeps_every_sample_and_fails_when_its_scatter_condemns_it(
    name: str, recorded: dict[str, tuple[Path, RecordedVectors]], tmp_path: Path, fit: Fit
) -> None:
    path, v = recorded[name]
    rep = fit(name, "minmax").report
    assert rep.n_samples == rep.n_frames == len(v.mag_G)  # a min/max of the tumble: all of it
    assert not rep.ok and rep.status == "MAG_CAL_FAILED_RESIDUALS_HIGH"
    # what it leaves condemns it: min/max on real tumbles leaves 1.4-5 deg against a 1 deg
    # target (CK 1.39, PX4 3.37 against its floor-scaled 1.22, SAP6 5.06); on the 20 s
    # run its fitness is over COMPASS_CAL_FIT too, and that bound speaks first
    assert rep.predicted_heading_deg > max(DEFAULT_HEADING_MAX_DEG, rep.heading_limit_deg)
    if name == "ck_tumble_100hz":
        assert rep.reason.startswith("fitness ") and "above COMPASS_CAL_FIT 16.0" in rep.reason
    else:
        assert rep.reason.startswith("heading error ~")
        assert "minmax leaves |B| scattered" in rep.reason
    # and it is never saved, whatever the operator answers
    state = tmp_path / "state"
    args = ["calibrate", "--recording", str(path), "--method", "minmax", "--yes"]
    code = main([*args, "--state-dir", str(state)])
    assert code == 1 and not (state / "calibration.json").exists()


def test_a_min_max_leaving_a_fifth_of_the_field_is_condemned_by_the_heading_rule(
    recorded: dict[str, tuple[Path, RecordedVectors]],
) -> None:
    # The min/max a collector that kept too few samples gave (the bug this suite was
    # written for: +-32 % of |B|, ~21 deg, said SUCCESS): a min/max of the first 40 of
    # PX4's samples, a cap of the sphere, judged on all of them. Even with
    # COMPASS_CAL_FIT at QGroundControl's 100 mG, the heading rule condemns it.
    from bridge.calibration.fits.acceptance import accept
    from bridge.calibration.fits.minmax import fit_minmax

    _, v = recorded["px4_mag_data1"]
    res = fit_minmax(v.mag_G[:40])
    n = np.linalg.norm(res.calibration.mag.apply(v.mag_G), axis=1)
    assert 0.2 < (n.max() - n.min()) / 2.0 / n.mean() < 0.4
    rep = accept(res, _data(v), Acceptance(fitness_max_mG=100.0)).report
    assert not rep.ok and rep.status == "MAG_CAL_FAILED_RESIDUALS_HIGH"
    assert rep.predicted_heading_deg > 10.0 > 5.0 * rep.heading_limit_deg
    assert rep.reason.startswith("heading error ~") and "minmax leaves |B| scattered" in rep.reason


def test_a_noisy_sparse_sensor_is_held_to_what_its_noise_and_count_allow(
    fit: Fit,
) -> None:
    # PX4's 231 samples carry ~11 mG of noise: their offsets are known to a few mG only
    # (a fixed 1 mG bound failed them); the limit is 3x what a perfect fit of these
    # samples would leave, and the ellipsoid, the best method and scalar all pass it alike
    reps = {m: fit("px4_mag_data1", m).report for m in ("ellipsoid", "best", "scalar")}
    ell = reps["ellipsoid"]
    assert ell.noise_mG > 8.0
    floor = math.degrees(
        math.atan2(ell.noise_mG * math.sqrt(3.0 / ell.n_samples), ell.horizontal_mG)
    )
    assert ell.heading_floor_deg == pytest.approx(floor, rel=1e-6)
    assert ell.heading_limit_deg == pytest.approx(3.0 * floor)
    assert ell.heading_limit_deg > DEFAULT_HEADING_MAX_DEG
    for m, rep in reps.items():
        assert rep.ok, (m, rep.reason)
        assert rep.predicted_heading_deg <= rep.heading_limit_deg
        assert rep.field_spread_after_all_nT == pytest.approx(
            ell.field_spread_after_all_nT, rel=0.02
        )


def test_a_quiet_sensor_is_held_to_the_operators_target(
    fit: Fit,
) -> None:
    rep = fit("sap6_HC", "ellipsoid").report
    assert rep.noise_mG < 1.0 and rep.heading_limit_deg == DEFAULT_HEADING_MAX_DEG
    assert rep.ok and rep.predicted_heading_deg < rep.heading_limit_deg
    # the same samples judged against a target they cannot reach fail, saying why
    tight = fit("sap6_HC", "ellipsoid", Acceptance(heading_max_deg=0.01))
    assert not tight.report.ok and "turn the unit through more directions" in tight.report.reason


# ---------------------------------------------------------------------------
# 4. A failure says its cause; figures say which samples they cover
# ---------------------------------------------------------------------------


@functools.cache
def _cli(path: Path, *extra: str) -> tuple[int, str]:
    """``calibrate --recording path --no *extra`` run in-process: its exit code and output.

    Cached: the command is deterministic and shows, saves nothing (``--no``), so a test
    asking for the same one gets the same run's output (the 394-frame excerpt's minmax
    run is read by two tests)."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(["calibrate", "--recording", str(path), "--no", *extra])
    return code, buf.getvalue()


def test_offline_a_failure_prints_its_cause_and_no_parameters(
    recorded: dict[str, tuple[Path, RecordedVectors]],
) -> None:
    path, _ = recorded["ck_tumble"]
    code, out = _cli(path, "--method", "minmax")
    assert code == 1
    cause = next(ln for ln in out.splitlines() if ln.startswith("cause"))
    assert cause.startswith("cause         heading error ~") and "> 1.00: minmax leaves" in cause
    assert cause.endswith("use the best method, or keep iron away while turning")
    assert "no reference field" not in out and "COMPASS_OFS" not in out
    assert "parameters    none: the fit failed" in out
    assert "over the 394 samples the fit kept (of 394 frames)" in out


def test_offline_figures_say_which_samples_they_cover(
    recorded: dict[str, tuple[Path, RecordedVectors]],
) -> None:
    path, _ = recorded["px4_mag_data1"]
    code, out = _cli(path, "--method", "ellipsoid")
    assert code == 0 and "COMPASS_OFS_X/Y/Z" in out
    spread = next(ln for ln in out.splitlines() if ln.startswith("field spread"))
    assert "after over the 231 samples the fit kept (of 231 frames)" in spread
    assert "after over all 231 frames" in spread
    assert "predicted, limit" in out and "sensor noise" in out


def test_the_coverage_map_is_drawn_from_the_raw_samples_whatever_the_method(
    recorded: dict[str, tuple[Path, RecordedVectors]],
) -> None:
    path, _ = recorded["ck_tumble"]
    maps = set()
    for method in ("best", "ellipsoid", "minmax", "scalar"):
        _, out = _cli(path, "--method", method)
        lines = out.splitlines()
        i = next(k for k, ln in enumerate(lines) if ln.startswith("sphere coverage"))
        maps.add("\n".join(lines[i : i + 10]))
    assert len(maps) == 1
    assert "sphere coverage: 60/80 sections" in maps.pop()


def _live_session(src: RealData) -> tuple[str, dict[str, object], str]:
    """A live host calibration fed ``src``'s frames on a fake clock at their own times.

    Returns the session's end (its phase), the report of the final event and its text:
    ``calibration.done`` or ``calibration.failed``, the event Zenoh publishes and the
    MAVLink adapter sends as STATUSTEXT. No [location]: the fit's first note is then
    the informational "no reference field".
    """
    import threading

    from bridge.app.calibration import CalibrationController
    from bridge.calibration.sessions.state import CalibratorSettings
    from bridge.core.attitude import AttitudeEngine
    from bridge.events import Event, EventBus
    from bridge.protocol.gmr import AttitudeFrame, Flags

    counts = np.rint(np.column_stack([src.mag_G * 2560.0, src.acc_g * 491.5]) + 2458.0)
    clock = [1000.0]
    final: list[Event] = []
    ended = threading.Event()

    def on_event(e: Event) -> None:
        if e.kind in ("calibration.done", "calibration.failed"):
            final.append(e)
            ended.set()

    bus = EventBus()
    bus.subscribe(on_event)
    # a small buffer (a few hundred frames fill ArduPilot's two steps of 20) and the
    # recordings' own gaps between stretches (seconds) allowed
    settings = CalibratorSettings(capacity=20, no_data_timeout_s=60.0)
    ctl = CalibrationController(
        AttitudeEngine(), bus, field=None, settings=settings, clock=lambda: clock[0]
    )
    ctl.run_inline()  # its fits run in this thread, on the recording's clock
    try:
        assert ctl.start_mag().ok
        for i, c in enumerate(counts.astype(int)):
            clock[0] = 1000.0 + float(src.t_s[i] - src.t_s[0])
            mx, my, mz, ax, ay, az = (int(v) for v in c)
            ctl.feed(
                AttitudeFrame(
                    int(src.seq[i]) % 65536, 0.0, 0.0, 0.0, mx, my, mz, ax, ay, az, Flags(0)
                )
            )
            snap = ctl.snapshot()
            if not snap.running:
                break
            if snap.step == 1 and snap.completion_pct >= 33.0:
                ctl.step()  # step one's fit, before the frames go on
                assert ctl.snapshot().step != 1 or not ctl.snapshot().running
        ctl.step()  # the final fit
        done = ctl.snapshot()
        assert not done.running and ended.wait(10.0) and len(final) == 1
        ev = final[0]
        return done.phase.value, ev.data, ev.text
    finally:
        ctl.close()


def test_a_live_failure_carries_its_cause_not_a_note() -> None:
    # The 394-frame excerpt live: ArduPilot's second step keeps ~250 frames, from which
    # the accelerometer and alignment are known to ~2 deg only (> 1): the session fails
    # with the fit's cause as calibration.failed, not the fit's first note
    phase, data, text = _live_session(ck_tumble())
    assert phase == "failed"
    reason = data["reason"]
    assert isinstance(reason, str)
    assert reason.startswith("heading error ~") and "no reference field" not in reason
    assert reason.endswith("turn slower / steadier")
    assert text == f"Calibration failed: {reason}"


def test_a_live_session_calibrates_a_real_100_hz_hand_tumble() -> None:
    # The 20 s run at its own 100 Hz, live: every frame of the second step is fitted as a
    # series and the calibration succeeds within the target, seeing the hand's shake
    phase, data, text = _live_session(ck_tumble_100hz())
    assert phase == "succeeded", data
    report = data["report"]
    assert isinstance(report, dict)
    assert report["n_frames"] > 1000 and report["n_samples"] == report["n_frames"]
    assert 0.03 < report["motion_g"] < 0.08
    assert 0.0 < report["heading_error_deg"] <= report["predicted_heading_deg"]
    assert report["predicted_heading_deg"] <= report["heading_limit_deg"] == 1.0
    assert text.startswith("Calibration done")


# ---------------------------------------------------------------------------
# 5. Methods a recording cannot feed are refused when the command is read
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("method", ["twelve_position", "accel_six_face"])
def test_methods_that_need_a_live_unit_are_refused_on_a_recording(
    method: str,
    recorded: dict[str, tuple[Path, RecordedVectors]],
    capsys: pytest.CaptureFixture[str],
) -> None:
    path, _ = recorded["sap6_HC"]
    assert main(["calibrate", "--recording", str(path), "--method", method]) == 2
    err = capsys.readouterr().err
    assert f"method {method!r} needs a live unit" in err and "ellipsoid" in err
    tools = (Path(__file__).parent.parent / "docs" / "tools.md").read_text()
    assert "needs a live unit" in tools and method in tools


# ---------------------------------------------------------------------------
# 6. The hand-held model at real rates: 3 Hz to 100 Hz
# ---------------------------------------------------------------------------


def _held_headings(cal: Calibration, v: RecordedVectors) -> tuple[FloatArray, BoolArray]:
    """Tilt-compensated headings of every frame under ``cal``, and which are under 60 deg tilt."""
    roll, pitch, heading = tilt_compensated_heading(
        cal.mag.apply(v.mag_G), cal.accel.apply(v.acc_g)
    )
    tilt = np.degrees(np.arccos(np.clip(np.cos(roll) * np.cos(pitch), -1.0, 1.0)))
    return heading, tilt < 60.0


def test_a_100_hz_hand_tumble_is_read_at_its_own_frame_times(
    recorded: dict[str, tuple[Path, RecordedVectors]],
    fit: Fit,
) -> None:
    # 2000 consecutive rows of the log: one run of frames 10 ms apart, 20 s, fitted as
    # a series over 2 s windows (seconds, not frames), with the hand's shake measured
    _, v = recorded["ck_tumble_100hz"]
    assert v.t_s is not None and len(v.t_s) == 2000
    assert np.allclose(np.diff(v.t_s), 0.01, atol=1e-6) and v.t_s[-1] == pytest.approx(19.99)
    assert runs(v.t_s, ~v.saturated) == [(0, 2000)]
    rep = fit("ck_tumble_100hz", "best").report
    assert rep.ok and rep.n_frames == rep.n_samples == 2000
    assert 0.03 < rep.motion_g < 0.08
    assert any(n.startswith("alignment from ") and " 2 s window means" in n for n in rep.notes)


@pytest.mark.parametrize("every", [2, 5, 10, 20, 30])
def test_the_hand_held_model_copes_with_real_rates(
    every: int, recorded: dict[str, tuple[Path, RecordedVectors]], tmp_path: Path, fit: Fit
) -> None:
    # The 20 s run as slower loggers see the same motion: every 2nd frame 50 Hz, 5th
    # 20 Hz, 10th 10 Hz, 20th 5 Hz, 30th 3.3 Hz (decimated: no public recording of a few
    # Hz was found, tests/data/SOURCES.md), against its own 100 Hz fit. At 100 Hz itself
    # (every frame) this would be that fit against itself: the 100 Hz run is
    # test_a_100_hz_hand_tumble_is_read_at_its_own_frame_times.
    src = ck_tumble_100hz().every(every)
    v = read_recording(str(write_recording(src, tmp_path / "ck.rec")))
    assert v.t_s is not None and np.allclose(v.t_s, src.t_s - src.t_s[0], atol=1e-6)
    assert src.rate_hz == pytest.approx(100.0 / every, rel=1e-6)
    _, v_full = recorded["ck_tumble_100hz"]
    full = fit("ck_tumble_100hz", "best")
    res = _fit(v, "best")
    rep = res.report
    # the motion it sees is the same hand whatever the rate (not a rate artefact), and
    # it averages windows of seconds, not of a number of frames
    assert rep.motion_g == pytest.approx(full.report.motion_g, rel=0.35)
    assert any(re.match(r"alignment from \d+ [1-6] s window means", n) for n in rep.notes)
    # the magnetometer part is the same fit at every rate
    c, c_full = np.asarray(res.calibration.mag.offset), np.asarray(full.calibration.mag.offset)
    assert 1000.0 * np.linalg.norm(c - c_full) < 2.0
    # the jackknife prediction grows as frames get fewer, and covers what fewer frames
    # change: the headings differ from the 100 Hz fit's by no more than it predicts
    assert rep.heading_error_deg >= 0.95 * full.report.heading_error_deg
    h, level = _held_headings(res.calibration, v_full)
    h_full, _ = _held_headings(full.calibration, v_full)
    d = (h - h_full + 180.0) % 360.0 - 180.0
    assert float(np.sqrt(np.mean(d[level] ** 2))) <= rep.predicted_heading_deg
    # and the verdict is the rule's: within the target it succeeds, beyond it it says why
    assert rep.ok == (rep.predicted_heading_deg <= rep.heading_limit_deg)
    if not rep.ok:
        assert rep.reason.endswith("turn slower / steadier"), rep.reason
    assert rep.ok == (every <= 5)  # 400 frames or more of these 20 s; 200 or fewer fail


@pytest.mark.parametrize("every", [2, 5])
def test_the_hand_held_model_copes_with_frames_in_separate_runs(
    every: int, tmp_path: Path, fit: Fit
) -> None:
    # The 394-frame excerpt: eight runs a few seconds each, gaps between, decimated (~8
    # and 3 Hz) against its own fit at ~17 Hz (every frame: that fit against itself;
    # test_a_real_hand_tumble_is_judged_on_its_accelerometer_and_alignment_too has it)
    src = ck_tumble().every(every)
    v = read_recording(str(write_recording(src, tmp_path / "ck.rec")))
    assert v.t_s is not None and np.allclose(v.t_s, src.t_s - src.t_s[0], atol=1e-6)
    assert len(runs(v.t_s, ~v.saturated)) == 8
    full = fit("ck_tumble", "best")  # the same excerpt, written and read back alike
    res = _fit(v, "best")
    rep = res.report
    assert rep.motion_g == pytest.approx(full.report.motion_g, rel=0.35)
    c, c_full = np.asarray(res.calibration.mag.offset), np.asarray(full.calibration.mag.offset)
    assert 1000.0 * np.linalg.norm(c - c_full) < 2.0
    assert math.isfinite(rep.heading_error_deg)
    assert rep.heading_error_deg >= 0.95 * full.report.heading_error_deg
    assert rep.ok == (rep.predicted_heading_deg <= rep.heading_limit_deg)
    if not rep.ok:
        assert rep.reason.endswith("turn slower / steadier"), rep.reason
