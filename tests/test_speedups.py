"""bridge._speedups (the compiled hot path) gives exactly what its pure-Python twins give.

The C module is optional at install time, so the daemon's results must not depend on
whether it was built: every test here runs the same input through the C function and
its Python twin and compares the results bit for bit (``repr`` tells -0.0 from 0.0
and shows every float's shortest round-trip digits; field types are compared too).

* ``decode_attitude_lines`` vs ``bridge.protocol.gmr._decode_attitude_lines``: valid
  lines, lines damaged the ways tests/test_protocol_fastpath.py damages them, random
  bytes, several lines per chunk. (That file also checks the decoder's fast path, which
  is the C one when built, against the general path.)
* ``solve`` vs ``AttitudeEngine._solve_python``: random calibrations, mountings,
  declinations and counts, including the degenerate ones (no field, no gravity), over
  several frames so the quality monitor's debouncing runs through both.

Without the module (no compiler at install time) the comparisons cannot run:
``test_the_compiled_hot_path_is_built`` then fails unless COMPASS_BRIDGE_PURE_PYTHON
says the pure-Python install is intended.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from dataclasses import fields

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_protocol_fastpath import attitude_frames, encoded, mutated_lines

from bridge import speedups
from bridge.calibration.model import AffineCalibration, Calibration
from bridge.core import attitude
from bridge.core.attitude import AttitudeEngine, AttitudeSolution, FieldReference
from bridge.core.mounting import Mounting, Rotation
from bridge.core.quality import QualityLimits
from bridge.protocol import gmr
from bridge.protocol.gmr import AttitudeFrame

EXAMPLES = settings(max_examples=400, deadline=None)

needs_c = pytest.mark.skipif(
    speedups.decode_attitude_lines is None,
    reason="bridge._speedups is not built (see test_the_compiled_hot_path_is_built)",
)


def test_the_compiled_hot_path_is_built() -> None:
    # A fresh machine of the kind this runs on has gcc and the Python headers, so
    # `pip install` builds the module; only an explicit pure-Python run may lack it.
    if os.environ.get(speedups.PURE_PYTHON_ENV):
        assert speedups.IMPLEMENTATION == "python"
        assert gmr._decode_fast is gmr._decode_attitude_lines
        assert attitude._c_solve is None
    else:
        assert speedups.IMPLEMENTATION == "c", "bridge._speedups did not build (C compiler?)"
        assert gmr._decode_fast is speedups.decode_attitude_lines
        assert attitude._c_solve is speedups.solve


def test_pure_python_switch_runs_the_python_twins_with_the_same_results() -> None:
    # A child process, since the choice is made once at import.
    code = (
        "from bridge import speedups\n"
        "from bridge.protocol.gmr import GmrDecoder, _decode_fast, _decode_attitude_lines\n"
        "from bridge.core.attitude import AttitudeEngine\n"
        "assert (_decode_fast is _decode_attitude_lines) == (speedups.IMPLEMENTATION == 'python')\n"
        "f = GmrDecoder().feed(b'$PGMRA,1024,87.3,-1.2,0.4,3101,2470,3311,2470,2452,2950,06*50\\r\\n')\n"
        "a = f[0]\n"
        "s = AttitudeEngine().solve_counts(a.mx, a.my, a.mz, a.ax, a.ay, a.az)\n"
        "print(speedups.IMPLEMENTATION, repr(f), repr(s))\n"
    )
    runs = {}
    for pure in ("1", ""):
        env = {**os.environ, speedups.PURE_PYTHON_ENV: pure}
        out = subprocess.run(
            [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60
        )
        assert out.returncode == 0, out.stderr
        impl, _, rest = out.stdout.partition(" ")
        runs[impl] = rest
    assert "python" in runs
    if speedups.IMPLEMENTATION == "c":
        assert runs["c"] == runs["python"]
        assert "AttitudeFrame(seq=1024, heading=87.3, pitch=-1.2, roll=0.4" in runs["c"]


# --------------------------------------------------------------------------- decode


def frames_key(out: list[gmr.GmrFrame] | None) -> object:
    """Everything observable about a decode result (repr tells -0.0 from 0.0)."""
    if out is None:
        return None
    return [
        (type(f), repr(f), [type(getattr(f, x.name)) for x in fields(f)], f.flags is f.flags)
        for f in out
    ]


def assert_same_decode(chunk: bytes) -> list[gmr.GmrFrame] | None:
    assert speedups.decode_attitude_lines is not None
    c_out = speedups.decode_attitude_lines(chunk)
    py_out = gmr._decode_attitude_lines(chunk)
    assert frames_key(c_out) == frames_key(py_out), chunk
    if c_out is not None:
        assert py_out is not None
        for a, b in zip(c_out, py_out, strict=True):
            assert type(a) is AttitudeFrame
            assert a.flags is b.flags  # the same Flags member, not just an equal int
    return c_out


@needs_c
def test_decode_the_datasheet_example() -> None:
    out = assert_same_decode(b"$PGMRA,1024,87.3,-1.2,0.4,3101,2470,3311,2470,2452,2950,06*50\r\n")
    assert out is not None and len(out) == 1
    f = out[0]
    assert (f.seq, f.heading, f.pitch, f.roll) == (1024, 87.3, -1.2, 0.4)
    assert (f.mx, f.my, f.mz, f.ax, f.ay, f.az) == (3101, 2470, 3311, 2470, 2452, 2950)
    assert f.flags == gmr.Flags(6)
    with pytest.raises(AttributeError):
        f.seq = 1  # type: ignore[misc]  # still the frozen AttitudeFrame


@needs_c
@EXAMPLES
@given(st.lists(st.tuples(attitude_frames, st.booleans()), max_size=7))
def test_decode_valid_lines_alike(items: list[tuple[AttitudeFrame, bool]]) -> None:
    chunk = b"".join(encoded(frame, cr) for frame, cr in items)
    out = assert_same_decode(chunk)
    assert out is not None and len(out) == len(items)


@needs_c
@EXAMPLES
@given(
    st.lists(
        st.tuples(attitude_frames, st.booleans()).map(lambda t: encoded(*t)) | mutated_lines(),
        min_size=1,
        max_size=4,
    )
)
def test_decode_damaged_lines_alike(lines: list[bytes]) -> None:
    assert_same_decode(b"".join(lines))


@needs_c
@EXAMPLES
@given(st.binary(max_size=90), attitude_frames)
def test_decode_random_bytes_and_cut_lines_alike(noise: bytes, frame: AttitudeFrame) -> None:
    whole = encoded(frame, True)
    for chunk in (noise, whole + noise, noise + whole, whole[: len(noise) % len(whole)]):
        assert_same_decode(chunk)


@needs_c
def test_decode_edge_values_alike() -> None:
    body_fmt = "PGMRA,{},{},{},{},{},{},{},{},{},{},{}"
    cases = [
        ("65535", "359.9", "90.0", "180.0", "4095", "0", "0000", "4095", "1", "1", "1F"),
        ("65536", "0.0", "0.0", "0.0", "1", "1", "1", "1", "1", "1", "00"),
        ("0", "360.0", "-0.0", "-0.0", "1", "1", "1", "1", "1", "1", "00"),
        ("0", "360.1", "0.0", "0.0", "1", "1", "1", "1", "1", "1", "00"),
        ("0", "999.9", "-90.0", "-180.0", "1", "1", "1", "1", "1", "1", "00"),
        ("0", "0.0", "-90.1", "0.0", "1", "1", "1", "1", "1", "1", "00"),
        ("0", "0.0", "99.9", "-999.9", "1", "1", "1", "1", "1", "1", "00"),
        ("99999", "0.0", "0.0", "0.0", "9999", "1", "1", "1", "1", "1", "00"),
        ("0", "0.0", "0.0", "0.0", "4096", "1", "1", "1", "1", "1", "20"),
    ]
    for fields_ in cases:
        body = body_fmt.format(*fields_)
        cs = 0
        for b in body.encode():
            cs ^= b
        for end in (b"\r\n", b"\n", b"\r", b""):
            line = b"$" + body.encode() + b"*" + f"{cs:02X}".encode() + end
            assert_same_decode(line)
            assert_same_decode(line + line)
    # the tolerated rounding artefact: 360.0 reads as 0.0, in both
    body = body_fmt.format(*cases[2])
    cs = 0
    for b in body.encode():
        cs ^= b
    out = assert_same_decode(b"$" + body.encode() + b"*" + f"{cs:02X}".encode() + b"\n")
    assert out is not None
    assert repr((out[0].heading, out[0].pitch, out[0].roll)) == "(0.0, 0.0, 0.0)"


@needs_c
def test_decode_takes_any_bytes_like_and_refuses_others() -> None:
    assert speedups.decode_attitude_lines is not None
    line = b"$PGMRA,1024,87.3,-1.2,0.4,3101,2470,3311,2470,2452,2950,06*50\r\n"
    assert frames_key(speedups.decode_attitude_lines(memoryview(line))) == frames_key(
        gmr._decode_attitude_lines(line)
    )
    assert speedups.decode_attitude_lines(b"") == []
    with pytest.raises(TypeError):
        speedups.decode_attitude_lines("$PGMRA")  # type: ignore[arg-type]


# --------------------------------------------------------------------------- attitude

finite = st.floats(allow_nan=False, allow_infinity=False)


@st.composite
def affine(draw: st.DrawFn, scale: float) -> AffineCalibration:
    off = tuple(draw(st.floats(-0.5, 0.5)) * scale for _ in range(3))
    m = [
        [(1.0 if i == j else 0.0) + draw(st.floats(-0.2, 0.2)) for j in range(3)] for i in range(3)
    ]
    return AffineCalibration(off, tuple(tuple(r) for r in m))  # type: ignore[arg-type]


@st.composite
def engine_settings(draw: st.DrawFn) -> dict[str, object]:
    decl = draw(st.none() | st.floats(-180.0, 180.0) | st.sampled_from([-180.0, 180.0, 0.0]))
    ref = FieldReference(
        declination_deg=decl,
        total_G=draw(st.none() | st.floats(0.2, 0.7)),
        dip_deg=draw(st.none() | st.floats(-90.0, 90.0)),
    )
    return {
        "calibration": Calibration(draw(affine(1.0)), draw(affine(1.0))),
        "mounting": Mounting(
            draw(st.sampled_from(list(Rotation)[:8])),
            trim_yaw_deg=draw(st.floats(-10.0, 10.0)),
        ),
        "reference": draw(st.none()) if draw(st.booleans()) else ref,
        "heading_reference": draw(st.sampled_from(["magnetic", "true"])),
        "limits": QualityLimits(raise_after=draw(st.integers(1, 3))),
    }


counts = st.integers(0, 4095) | st.sampled_from([2048, 0, 4095])
frame_counts = st.tuples(counts, counts, counts, counts, counts, counts)
# As the physics gives them: each sensor a whole vector at the zero point, or not at all.
zero_vectors = st.sampled_from(
    [(2048, 2048, 2048, 2300, 2100, 2900), (1500, 2600, 2400, 2048, 2048, 2048), (2048,) * 6]
)


def solution_key(a: AttitudeSolution) -> str:
    return repr(a)  # every field, floats to their last bit, -0.0 as "-0.0"


def assert_same_solve(cfg: dict[str, object], frames: list[tuple[float, ...]]) -> None:
    c_eng = AttitudeEngine(**cfg)  # type: ignore[arg-type]
    py_eng = AttitudeEngine(**cfg)  # type: ignore[arg-type]
    assert c_eng._state.consts is not None  # the compiled path is the one solve_counts takes
    for fr in frames:
        try:
            c_sol = solution_key(c_eng.solve_counts(*fr))
        except ValueError as e:
            c_sol = f"ValueError: {e}"
        try:
            py_sol = solution_key(py_eng._solve_python(py_eng._state, *fr))
        except ValueError as e:
            py_sol = f"ValueError: {e}"
        assert c_sol == py_sol, fr


@needs_c
@EXAMPLES
@given(engine_settings(), st.lists(frame_counts | zero_vectors, min_size=1, max_size=6))
def test_solve_alike_on_counts(cfg: dict[str, object], frames: list[tuple[int, ...]]) -> None:
    assert_same_solve(cfg, frames)  # type: ignore[arg-type]


@needs_c
@EXAMPLES
@given(
    engine_settings(),
    st.lists(st.tuples(*[st.floats(-1e6, 1e6) | st.sampled_from([2048.0])] * 6), max_size=4),
)
def test_solve_alike_on_any_floats(cfg: dict[str, object], frames: list[tuple[float, ...]]) -> None:
    assert_same_solve(cfg, frames)  # type: ignore[arg-type]


@needs_c
def test_solve_refuses_what_python_refuses() -> None:
    cfg: dict[str, object] = {}
    assert_same_solve(cfg, [(math.nan, 2048, 2048, 2048, 2048, 3000), (1e308, 1e308, 0, 0, 0, 0)])
    eng = AttitudeEngine()
    with pytest.raises(ValueError, match="non-finite frame"):
        eng.solve_counts(math.inf, 2048, 2048, 2048, 2048, 3000)
    with pytest.raises(TypeError):
        eng.solve_counts("1", 2048, 2048, 2048, 2048, 3000)  # type: ignore[arg-type]
    with pytest.raises(OverflowError):
        eng.solve_counts(10**400, 2048, 2048, 2048, 2048, 3000)
    assert speedups.solve is not None
    with pytest.raises(TypeError):
        speedups.solve((1.0,) * 5, 1, 2, 3, 4, 5, 6)
    with pytest.raises(TypeError):
        speedups.solve(eng._state.consts, 1, 2, 3)


@needs_c
def test_the_field_database_source_stays_in_python() -> None:
    # Attitude from a field database (no accelerometer) is not in C: no consts, so
    # solve_counts takes the Python path for it.
    eng = AttitudeEngine()
    assert eng._state.consts is not None
    eng.set_field_database(object())  # type: ignore[arg-type]
    assert eng._state.consts is None
    eng.set_field_database(None)
    assert eng._state.consts is not None
