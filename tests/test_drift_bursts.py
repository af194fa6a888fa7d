"""The drift monitor watches a drive as well when the link reads its frames in bursts as when
it reads each frame as it comes.

At 100 Hz with the outputs' streams at 10 Hz the link holds the port and reads nine frames
at once, then the due one as it comes (docs/architecture.md, "How a frame travels"). The
monitor keeps about one sample per 0.1 s and judges the heading's steadiness from the time
steps between its samples. Handed each frame's arrival, it took the oldest frame of every
burst (10 Hz) stamped 85 ms after it was sampled, where the frames read as they come gave
mostly every ninth frame (11 Hz) at its instant: other samples, other fits, the learning
seconds apart. The pipeline hands it the instant each frame was sampled (its frame clock,
from ``seq``), as it hands the attitude engine and the calibration controller, and it keeps
every ninth frame of that clock at 100 Hz: the same frames at the same instants, however
they were read.

In memory: the application's pipeline, a 10 Hz output paced as the MAVLink output is, the
link's stamping worked out by its own rules, and the monitor, on one simulated drive whose
hard iron changes and is learned back, read two ways (``benchmarks.reads``, whose figures,
``python -m benchmarks reads``, add a busy host and the arrivals the monitor once took).
"""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.reads import LATENCY_S, T0, Watched, drive, watch

#: The monitor is switched on this far into the drive: the frame clock has learnt the
#: compass's rate (4 s of arrivals), as it has long before anyone watches a running bridge.
LEAD_S = 6.0
BEFORE_S, AFTER_S = 60.0, 110.0  # the drive before and after its hard iron changes


@pytest.fixture(scope="module")
def read_two_ways() -> tuple[Watched, Watched]:
    """The drive read as it comes, and in the link's bursts."""
    unit, frames, sampled = drive(2, BEFORE_S, AFTER_S)
    even = watch(unit, frames, sampled, bursts=False, lead_s=LEAD_S)
    held = watch(unit, frames, sampled, bursts=True, lead_s=LEAD_S)
    # nine frames a burst, ten bursts a second
    assert even.bursts == 0 and held.bursts >= 9.9 * (BEFORE_S + AFTER_S)
    return even, held


def test_a_drive_read_in_bursts_is_watched_as_one_read_as_it_comes(
    read_two_ways: tuple[Watched, Watched],
) -> None:
    even, held = read_two_ways
    # the same frames (the calibrated field and gravity of each) at the same instants:
    # one sample per 0.09 s of the compass's clock, and that instant the frame's own
    a, b = even.samples, held.samples
    seconds = BEFORE_S + AFTER_S - LEAD_S
    assert a.shape == b.shape, f"{len(a) / seconds:.2f} vs {len(b) / seconds:.2f} samples/s"
    np.testing.assert_array_equal(b[:, 1:], a[:, 1:])
    np.testing.assert_allclose(b[:, 0], a[:, 0], rtol=0.0, atol=1e-6)
    assert np.diff(a[:, 0]) == pytest.approx(0.09, abs=1e-6)  # every ninth frame, always
    # ... sampled when the frames were (their clock: the least-delayed arrival)
    assert a[0, 0] - LATENCY_S == pytest.approx(T0 + LEAD_S, abs=1e-6)

    # the same fits: the same steadiness verdicts (the dip rows are the samples judged
    # steady), the same offsets
    assert [f.n_dip for f in held.fits] == [f.n_dip for f in even.fits]
    assert [f.n_field for f in held.fits] == [f.n_field for f in even.fits]
    np.testing.assert_allclose(
        [f.offset_G for f in held.fits], [f.offset_G for f in even.fits], rtol=0.0, atol=1e-9
    )

    # the same alarms, the same learning, the same state at the end
    kinds = [k for k, _ in even.kinds("calibration.")]
    assert "calibration.drift" in kinds and "calibration.learned" in kinds, kinds
    assert held.kinds("calibration.") == even.kinds("calibration.")
    assert held.applied == even.applied and len(even.applied) >= 2
    assert held.status == even.status


def test_a_drive_read_in_bursts_gets_the_same_disturbance_events(
    read_two_ways: tuple[Watched, Watched],
) -> None:
    # The pipeline's disturbance events: at most one per 5 s, a change within the hold-off
    # told when it ends -- on the first frame after it, read either way.
    even, held = read_two_ways

    assert len(even.kinds("disturbance.")) >= 4  # the drive's magnets, held-off ends among them
    assert held.kinds("disturbance.") == even.kinds("disturbance.")
