"""The shared calibration model: application, ArduPilot view round trip, serialisation."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import examples
from hypothesis import given
from hypothesis import strategies as st

from bridge.core.calibration import AffineCalibration, ArduPilotView, Calibration
from bridge.core.geometry import euler_to_dcm
from bridge.protocol.gmr import ParamsFrame


def test_apply_one_vector_and_a_batch_agree() -> None:
    cal = AffineCalibration.from_arrays(
        [0.1, -0.2, 0.05], [[1.1, 0.02, 0], [0.01, 0.9, 0.03], [0, 0, 1.05]]
    )
    raw = np.array([[0.3, 0.1, 0.4], [-0.2, 0.5, 0.0]])
    batch = cal.apply(raw)
    expected = (raw - np.array([0.1, -0.2, 0.05])) @ np.asarray(cal.matrix).T
    assert np.allclose(batch, expected)
    assert np.allclose(cal.apply(raw[1]), batch[1])  # one vector (3,), as a row of the batch


angles = st.floats(-0.05, 0.05)


@examples(60)
@given(
    st.tuples(st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), st.floats(-0.3, 0.3)),
    st.tuples(st.floats(0.8, 1.2), st.floats(0.8, 1.2), st.floats(0.8, 1.2)),
    st.tuples(st.floats(-0.05, 0.05), st.floats(-0.05, 0.05), st.floats(-0.05, 0.05)),
    st.tuples(angles, angles, angles),
)
def test_ardupilot_view_round_trip(
    offset: tuple[float, float, float],
    diag: tuple[float, float, float],
    offdiag: tuple[float, float, float],
    rpy: tuple[float, float, float],
) -> None:
    S = np.array(
        [
            [diag[0], offdiag[0], offdiag[1]],
            [offdiag[0], diag[1], offdiag[2]],
            [offdiag[1], offdiag[2], diag[2]],
        ]
    )
    M = euler_to_dcm(*rpy) @ S
    cal = AffineCalibration.from_arrays(offset, M)
    view = cal.ardupilot_view()
    assert np.allclose(view.ofs_mG, -1000.0 * np.asarray(offset))
    assert np.mean(view.diag) == pytest.approx(1.0)
    back = AffineCalibration.from_ardupilot(view)
    assert np.allclose(back.matrix_array, M, atol=1e-9)
    assert np.allclose(back.offset_array, offset, atol=1e-12)


def test_refuses_nonfinite_and_singular() -> None:
    with pytest.raises(ValueError, match="finite"):
        AffineCalibration.from_arrays([np.nan, 0, 0], np.eye(3))
    with pytest.raises(ValueError, match="singular"):
        AffineCalibration.from_arrays([0, 0, 0], np.zeros((3, 3)))


def test_calibration_dict_round_trip() -> None:
    cal = Calibration(
        AffineCalibration.from_arrays([0.1, 0.2, 0.3], euler_to_dcm(0.01, 0.02, 0.03)),
        AffineCalibration.from_arrays([0.01, 0, 0], np.diag([1.01, 0.99, 1.0])),
    )
    assert Calibration.from_dict(cal.to_dict()) == cal
    with pytest.raises((KeyError, ValueError, TypeError)):
        Calibration.from_dict({"mag": {"offset": [1, 2]}, "accel": {}})


# -- the views: one calibration seen as ArduPilot's parameters and as the device's flash page


def test_the_parameter_view_is_the_ardupilot_view_by_name() -> None:
    mag = AffineCalibration.from_arrays(
        [0.12, -0.08, 0.21], euler_to_dcm(0.02, -0.01, 0.03) @ np.diag([1.1, 0.95, 1.0])
    )
    cal = Calibration(mag=mag)
    view, params = cal.ardupilot_view(), cal.ardupilot_parameters()
    assert [params[f"COMPASS_OFS_{a}"] for a in "XYZ"] == list(view.ofs_mG)
    assert [params[f"COMPASS_DIA_{a}"] for a in "XYZ"] == list(view.diag)
    assert params["COMPASS_SCALE"] == view.scale and params["COMPASS_ORIENT"] == 0.0
    assert np.allclose([params[f"BRG_ALIGN_{a}"] for a in "XYZ"], view.rotation_rotvec)
    assert view.rotation_deg == pytest.approx(np.degrees(np.linalg.norm(view.rotation_rotvec)))
    back = Calibration.from_ardupilot_parameters(params)
    assert np.allclose(back.mag.matrix_array, mag.matrix_array, atol=1e-12)
    assert back.accel == AffineCalibration()  # the identity unless one is given


def test_the_device_view_keeps_the_devices_level_reference() -> None:
    cal = Calibration(mag=AffineCalibration.from_arrays([0.1, 0.0, -0.1], np.diag([1.0, 1.1, 0.9])))
    mine = ParamsFrame(2400.0, 2400.0, 2400.0, 1.0, 1.0, 1.0, 2401.5, 2502.5, 2903.5)
    page = cal.device_page(mine)
    assert (page.xoff, page.yoff, page.zoff) == (2714.0, 2458.0, 2202.0)  # 2458 + 2560 * offset
    assert (page.gxoff, page.gyoff, page.gzoff) == (2401.5, 2502.5, 2903.5)
    factory = ParamsFrame.factory()
    assert cal.device_page().values()[6:] == (factory.gxoff, factory.gyoff, factory.gzoff)
    # a flash page seen the ArduPilot way: offsets as COMPASS_OFS (mG), gains as the diagonal
    seen = ArduPilotView.of_device(page)
    assert seen.ofs_mG == pytest.approx((-100.0, 0.0, 100.0))
    assert seen.diag == (page.kx, page.ky, page.kz) and seen.rotation_deg == 0.0


def _numpy_corrects_iron(mag: AffineCalibration, tol: float = 1e-6) -> bool:
    """The rule as numpy says it (what corrects_iron computed before it went plain float)."""
    m = mag.matrix_array
    off = mag.offset_array
    return bool(np.any(np.abs(off) > tol) or not np.allclose(m @ m.T, np.eye(3), atol=tol))


@examples(300)
@given(
    roll=st.floats(-3.2, 3.2),
    pitch=st.floats(-1.6, 1.6),
    yaw=st.floats(-3.2, 3.2),
    scale=st.sampled_from([1.0, 1.0 + 2e-7, 1.0 + 2e-6, 1.0 + 2e-5, 0.95]),
    skew=st.sampled_from([0.0, 3e-7, 3e-6]),
    offset=st.sampled_from([0.0, 5e-7, 2e-6, -0.03]),
)
def test_corrects_iron_is_numpys_allclose_rule(
    roll: float, pitch: float, yaw: float, scale: float, skew: float, offset: float
) -> None:
    """Rotations (a level trim, a mounting) alone are no calibration; any offset or gain
    beyond the tolerance is -- the same answer as numpy's allclose, at the borders too."""
    from bridge.core.calibration import corrects_iron

    r = euler_to_dcm(roll, pitch, yaw) @ np.diag([scale, 1.0, 1.0])
    r[0, 1] += skew
    mag = AffineCalibration.from_arrays((offset, 0.0, 0.0), r)
    assert corrects_iron(mag) is _numpy_corrects_iron(mag)
