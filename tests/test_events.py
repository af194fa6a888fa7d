"""EventBus: fan-out, history bound, a failing subscriber does not stop the others;
Subscribers, the copy-on-write list every fan-out of the bridge keeps."""

from __future__ import annotations

from bridge.events import Event, EventBus, Severity, Subscribers


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


def test_subscribers_remove_one_registration_and_deliveries_see_a_snapshot() -> None:
    subs: Subscribers[int] = Subscribers()
    assert not subs and len(subs) == 0
    got: list[str] = []

    def a(v: int) -> None:
        got.append(f"a{v}")

    remove_first = subs.add(a)
    subs.add(a)  # the same function twice: two registrations
    removers: list[object] = []

    def b(v: int) -> None:
        got.append(f"b{v}")
        remove_b()  # removing itself (and adding) during a delivery
        removers.append(subs.add(lambda v: got.append(f"c{v}")))

    remove_b = subs.add(b)
    assert subs and len(subs) == 3
    for fn in subs:
        fn(1)
    assert got == ["a1", "a1", "b1"]  # the delivery in flight is undisturbed
    remove_first()
    remove_first()  # removing twice removes one registration only
    got.clear()
    for fn in subs:
        fn(2)
    assert got == ["a2", "c2"] and len(removers) == 1
