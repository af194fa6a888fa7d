"""EventBus: fan-out, history bound, a failing subscriber does not stop the others."""

from __future__ import annotations

from bridge.events import Event, EventBus, Severity


def test_fan_out_history_and_unsubscribe() -> None:
    bus = EventBus(history=3)
    got_a: list[str] = []
    got_b: list[str] = []
    unsub_a = bus.subscribe(lambda e: got_a.append(e.kind))
    bus.subscribe(lambda e: got_b.append(e.kind))
    for i in range(5):
        bus.emit(Event(f"k{i}", "text"))
    unsub_a()
    bus.emit(Event("k5", "text", Severity.WARNING))
    assert got_a == ["k0", "k1", "k2", "k3", "k4"]
    assert got_b == ["k0", "k1", "k2", "k3", "k4", "k5"]
    assert [e.kind for e in bus.recent()] == ["k3", "k4", "k5"]


def test_failing_subscriber_is_counted_and_isolated() -> None:
    bus = EventBus()
    got: list[str] = []

    def broken(_: Event) -> None:
        raise RuntimeError("boom")

    bus.subscribe(broken)
    bus.subscribe(lambda e: got.append(e.text))
    bus.emit(Event("a", "one"))
    bus.emit(Event("b", "two"))
    assert got == ["one", "two"]
    assert bus.subscriber_errors == 2
