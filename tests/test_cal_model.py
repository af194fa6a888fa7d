"""The shared calibration model: application, ArduPilot view round trip, serialisation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bridge.calibration.model import AffineCalibration, Calibration
from bridge.core.geometry import euler_to_dcm


def test_apply_batch_and_scalar_agree() -> None:
    cal = AffineCalibration.from_arrays(
        [0.1, -0.2, 0.05], [[1.1, 0.02, 0], [0.01, 0.9, 0.03], [0, 0, 1.05]]
    )
    raw = np.array([[0.3, 0.1, 0.4], [-0.2, 0.5, 0.0]])
    batch = cal.apply(raw)
    expected = (raw - np.array([0.1, -0.2, 0.05])) @ np.asarray(cal.matrix).T
    assert np.allclose(batch, expected)
    assert np.allclose(cal.apply_tuple(*raw[1]), batch[1])


angles = st.floats(-0.05, 0.05)


@settings(max_examples=60, deadline=None)
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
