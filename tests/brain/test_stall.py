"""The stall watch: a blocked corridor reported within seconds, a stall recovered, neither for an
operator's pause or the finish."""

from __future__ import annotations

from brain.stall import StallWatch, Standing
from protocol.messages import Severity

S = 1_000_000_000


def run(
    watch: StallWatch, seconds: float, speed: float = 0.0, station: float = 300.0, way: bool = True, held: bool = False
) -> list[tuple[float, str]]:
    """Ten cycles a second for ``seconds`` from the watch's own clock; (time s, code) of events."""
    events = []
    for _ in range(int(seconds * 10)):
        run.now_ns += S // 10
        events += [(run.now_ns / S, e.code) for e in watch.update(run.now_ns, speed, station, way, held)]
    return events


run.now_ns = 0  # type: ignore[attr-defined]


def test_a_blocked_corridor_is_reported_once_within_the_delay_and_clears_when_moving() -> None:
    watch = StallWatch(finish_m=1000.0, blocked_after_s=3.0)
    start = run.now_ns / S
    assert run(watch, 2.0, speed=5.0) == []
    events = run(watch, 10.0, way=False)
    assert [code for _t, code in events] == ["corridor_blocked"]
    assert 3.0 <= events[0][0] - (start + 2.0) <= 3.2
    assert watch.state is Standing.BLOCKED
    assert [code for _t, code in run(watch, 1.0, speed=2.0, station=302.0)] == ["moving_again"]
    assert watch.state is Standing.MOVING


def test_a_stall_with_a_way_ahead_starts_a_recovery_and_repeats_it_while_it_lasts() -> None:
    watch = StallWatch(finish_m=1000.0, stall_after_s=5.0)
    run(watch, 1.0, speed=5.0)
    events = [(t, code) for t, code in run(watch, 16.0)]
    assert [code for _t, code in events] == ["stalled", "stalled", "stalled"]
    assert watch.recoveries == 3
    update = watch.update(run.now_ns + S, 0.0, 300.0, True, False)
    assert update == [] or update[0].severity is Severity.WARNING


def test_an_operator_hold_and_the_finish_are_not_stalls() -> None:
    watch = StallWatch(finish_m=1000.0)
    run(watch, 1.0, speed=5.0)
    assert run(watch, 20.0, held=True) == []
    assert run(watch, 20.0, station=1000.5) == []
    assert watch.state is Standing.MOVING


def test_creeping_forward_restarts_the_clock() -> None:
    """Slow but getting somewhere (1.5 m every 3 s, under the 0.1 m/s of a stall): no recovery."""
    watch = StallWatch(finish_m=1000.0, stall_after_s=5.0)
    run(watch, 1.0, speed=5.0)
    events = []
    for step in range(10):
        events += run(watch, 3.0, speed=0.05, station=300.0 + 1.5 * step)
    assert events == []
