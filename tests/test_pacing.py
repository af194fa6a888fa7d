"""The one rule rate-capped streams follow (bridge.core.pacing), in MAVLink's schedule and in
Zenoh's rate caps alike: exact average rates, no catch-up burst after a pause, and slots on a
grid of the clock, so streams whose periods divide one another fall due on the same frames
(the compass link then wakes once for all of them), and a slow stream whose period is not a
multiple of the 10 Hz grid's takes that grid's nearest point. Pure: in memory."""

from __future__ import annotations

import itertools
import random

import pytest

from bridge.core.pacing import EARLY_MAX_S, GRID_S, early_s, next_slot, slot_time
from bridge.mavlink import schedule as S  # noqa: N812 - short
from bridge.zenoh.pacing import Decimator, StatusTiming

FRAME_S = 0.01  # 100 Hz frames


def frames(start: float, seconds: float, jitter: float, seed: int = 1) -> list[float]:
    rng = random.Random(seed)
    n = round(seconds / FRAME_S)
    return [start + i * FRAME_S + rng.uniform(-jitter, jitter) for i in range(n)]


def test_streams_started_apart_fall_due_on_the_same_frames() -> None:
    # MAVLink's 10 Hz ATTITUDE and 4 Hz VFR_HUD, Zenoh's 10 Hz heading cap and a 2 Hz one,
    # each starting with a different frame: after their first sends, every 10 Hz send is on
    # the same frames, and the slower streams' on 10 Hz ones too (VFR_HUD at the 10 Hz grid
    # point nearest its quarter-second one).
    sched = S.StreamSchedule({S.ATTITUDE: 10.0, S.VFR_HUD: 4.0})
    sched.set_sample_streams([S.ATTITUDE, S.VFR_HUD])
    zen10, zen2 = Decimator(10.0), Decimator(2.0)
    sent: dict[str, list[int]] = {"att": [], "hud": [], "z10": [], "z2": []}
    for i, t in enumerate(frames(1000.003, 20.0, 0.002)):
        if i >= 3:
            due = sched.due_samples(t)
            if S.ATTITUDE in due:
                sent["att"].append(i)
            if S.VFR_HUD in due:
                sent["hud"].append(i)
        if i >= 7 and zen10.accept(t):
            sent["z10"].append(i)
        if i >= 11 and zen2.accept(t):
            sent["z2"].append(i)

    def settled(name: str) -> list[int]:  # once every stream has started (from 0.2 s on)
        return [i for i in sent[name] if i >= 20]

    att = set(settled("att"))
    assert att == set(settled("z10"))  # the two 10 Hz streams: on one frame
    assert set(settled("z2")) <= att  # 2 Hz: every send with a 10 Hz one
    hud = settled("hud")
    assert set(hud) <= att
    # 0.2 s and 0.3 s in turn: 20 and 30 frames.
    gaps = [b - a for a, b in itertools.pairwise(hud)]
    assert set(gaps) == {20, 30}
    assert all(a + b == 50 for a, b in itertools.pairwise(gaps))
    # ... and at their rates.
    assert len(sent["att"]) == pytest.approx(200, abs=1)
    assert len(sent["hud"]) == pytest.approx(80, abs=1)
    assert len(sent["z2"]) == pytest.approx(40, abs=1)


@pytest.mark.parametrize("hz", [1.0, 2.0, 4.0, 7.0, 10.0, 30.0, 50.0, 100.0])
def test_the_rate_is_exact_and_a_pause_starts_anew(hz: float) -> None:
    period = 1.0 / hz
    slot: float | None = None
    sent: list[float] = []
    jitter = 0.0 if hz >= 100.0 else 0.003  # a stream at the frame rate takes every frame
    times = frames(500.0, 30.0, jitter) + frames(560.0, 30.0, jitter, seed=2)  # a 30 s pause
    for t in times:
        if slot is None or t >= slot - early_s(period):
            slot = next_slot(slot, t, period)
            sent.append(t)
    first, second = [t for t in sent if t < 540.0], [t for t in sent if t >= 540.0]
    for part in (first, second):
        assert len(part) == pytest.approx(30.0 * min(hz, 100.0), abs=1)
    # After the pause: one send with its first frame, no burst for the slots missed.
    assert second[0] == times[len(times) // 2]
    assert all(b - a >= 0.5 * min(period, FRAME_S) for a, b in itertools.pairwise(second))


def test_a_sample_may_come_a_little_early_never_more() -> None:
    assert early_s(1.0) == EARLY_MAX_S  # slow streams open when 10 Hz ones do
    assert early_s(0.1) == pytest.approx(0.025)
    assert early_s(0.02) == pytest.approx(0.005)  # a quarter period: never a period's worth
    # The first slot: a grid point of the period at least half a period on.
    for now in (10.0, 10.04, 10.05, 10.06, 10.099):
        slot = next_slot(None, now, 0.1)
        assert 0.05 - 1e-9 <= slot - now <= 0.15 + 1e-9
        assert slot / 0.1 == pytest.approx(round(slot / 0.1))


@pytest.mark.parametrize("hz", [0.3, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0])
def test_a_slow_stream_takes_the_nearest_grid_point(hz: float) -> None:
    # Every slot of a stream at 5 Hz or slower is a point of the 10 Hz grid, within half a
    # grid step of its exact time (at most a quarter period), however far the clock has run.
    period = 1.0 / hz
    for k0 in (0, 7, 10**6, 4 * 10**7):  # up to about 4e7 / hz seconds of monotonic clock
        slots = [slot_time(k, period) for k in range(k0, k0 + 200)]
        for k, s in zip(range(k0, k0 + 200), slots, strict=True):
            assert s / GRID_S == pytest.approx(round(s / GRID_S), abs=1e-6)
            err = abs(s - k * period)  # float rounding: about 1e-16 of the clock's value
            assert err <= GRID_S / 2 + 1e-14 * s + 1e-9
            assert err <= 0.25 * period + 1e-14 * s + 1e-9
        gaps = [b - a for a, b in itertools.pairwise(slots)]
        assert min(gaps) >= period - GRID_S - 1e-6
        assert max(gaps) <= period + GRID_S + 1e-6
        # The average stays exact: 200 slots span 199 periods, give or take one grid step.
        assert slots[-1] - slots[0] == pytest.approx(199 * period, abs=GRID_S + 1e-6)


@pytest.mark.parametrize("hz", [6.0, 7.0, 10.0, 20.0, 30.0, 50.0])
def test_a_stream_faster_than_5_hz_keeps_its_own_grid(hz: float) -> None:
    period = 1.0 / hz
    assert [slot_time(k, period) for k in range(50)] == [k * period for k in range(50)]
    slot = next_slot(None, 100.0, period)
    for _ in range(100):  # a stream that takes every slot books the next one of its grid
        nxt = next_slot(slot, slot, period)
        assert nxt - slot == pytest.approx(period, abs=1e-9)
        slot = nxt


# ---------------------------------------------------------------------------
# <prefix>/status: on the period, and at once on a change (bridge.zenoh.pacing.StatusTiming)
# ---------------------------------------------------------------------------


def test_the_status_goes_out_on_its_period_and_its_key_is_read_only_on_a_change() -> None:
    timing = StatusTiming(1.0)  # told of link state changes: no polling
    assert timing.due(0.0)  # the first at once
    timing.published(("streaming", "idle", "stored"), 0.0)
    assert timing.next_look == 1.0  # asleep until the period: nothing read meanwhile
    assert not timing.due(0.99) and not timing.must_look(0.99)
    timing.note_change()  # an event, or the link's state moved
    assert timing.next_look == 1.0 and timing.must_look(0.3)
    assert not timing.must_look(0.3)  # the note is taken by the look
    assert not timing.changed(("streaming", "idle", "stored"))  # the same: nothing goes out
    timing.note_change()
    assert timing.must_look(0.4) and timing.changed(("stale", "idle", "stored"))
    timing.published(("stale", "idle", "stored"), 0.4)
    assert timing.next_look == 1.4  # the period starts again from the change's status


def test_a_change_noted_while_the_key_is_read_is_looked_at_again() -> None:
    timing = StatusTiming(1.0)
    timing.published(("opening",), 0.0)
    timing.note_change()
    assert timing.must_look(0.1)
    timing.note_change()  # the link moves on while the key is read
    assert not timing.changed(("opening",))
    assert timing.must_look(0.1)  # the second change is not lost


def test_without_change_notices_the_key_is_polled() -> None:
    timing = StatusTiming(1.0, poll_s=0.5)
    timing.published(("opening",), 0.0)
    assert timing.next_look == 0.5
    assert not timing.must_look(0.49) and timing.must_look(0.5)
    assert timing.next_look == 1.0  # the period's look comes next
    with pytest.raises(ValueError):
        StatusTiming(0.0)
