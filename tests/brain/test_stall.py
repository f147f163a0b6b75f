"""The stall watch: a blocked corridor reported within seconds, a stall recovered, neither for an
operator's pause or the finish."""

from __future__ import annotations

from brain.stall import StallWatch, Standing, leads_on
from protocol.messages import Path, PathPoint, Severity

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


def test_a_blockage_that_lasts_backs_up_where_there_is_a_way_back_and_is_still_reported() -> None:
    watch = StallWatch(finish_m=1000.0, blocked_after_s=3.0, stall_after_s=5.0)
    run(watch, 1.0, speed=5.0)
    start = run.now_ns / S
    events = []
    for _ in range(60):
        run.now_ns += S // 10
        events += [(run.now_ns / S - start, e) for e in watch.update(run.now_ns, 0.0, 300.0, False, False, True)]
    assert [e.code for _t, e in events] == ["corridor_blocked", "backing_up"]
    assert 3.0 <= events[0][0] <= 3.2 and 5.0 <= events[1][0] <= 5.2
    assert events[1][1].back_up and events[1][1].recover
    assert watch.state is Standing.BACKING
    assert run(watch, 10.0, speed=0.0, way=False) == []  # silent while it backs up
    watch.backed_up()
    assert watch.state is Standing.MOVING


def test_a_stall_a_re_plan_did_not_end_backs_up_next() -> None:
    watch = StallWatch(finish_m=1000.0, stall_after_s=5.0)
    run(watch, 1.0, speed=5.0)
    events = []
    for _ in range(120):
        run.now_ns += S // 10
        events += [e.code for e in watch.update(run.now_ns, 0.0, 300.0, True, False, True)]
    assert events == ["stalled", "backing_up"]


def test_back_ups_are_bounded_around_one_standing_place() -> None:
    """Backing up 4 m and driving back to the same dead end: three times, then it stays reported."""
    watch = StallWatch(finish_m=1000.0, blocked_after_s=3.0, stall_after_s=5.0)
    codes = []
    for _ in range(5):
        run(watch, 2.0, speed=1.0, station=296.0)  # back to the dead end
        for _ in range(100):
            run.now_ns += S // 10
            codes += [e.code for e in watch.update(run.now_ns, 0.0, 300.0, False, False, True)]
        if watch.state is Standing.BACKING:
            watch.backed_up()
    assert codes.count("backing_up") == 3
    assert codes.count("corridor_blocked") == 5
    # A new place, far on, may back up again.
    run(watch, 2.0, speed=5.0, station=400.0)
    codes = []
    for _ in range(60):
        run.now_ns += S // 10
        codes += [e.code for e in watch.update(run.now_ns, 0.0, 400.0, False, False, True)]
    assert codes == ["corridor_blocked", "backing_up"]


def test_a_path_leads_on_only_if_it_asks_to_drive_a_metre_or_more_from_the_vehicle() -> None:
    def path(*points: tuple[float, float]) -> Path:
        return Path(1, tuple(PathPoint(east, 0.0, speed) for east, speed in points), slow_mode=True)

    at_the_nose = path((0.0, 0.3), (0.5, 0.2), (0.9, 0.0))  # a partial path run out against a wall
    assert not leads_on(at_the_nose, 0.0, 0.0)
    assert not leads_on(path((0.0, 0.0), (3.0, 0.0)), 0.0, 0.0)  # a path that says stand
    assert leads_on(path((0.0, 0.5), (1.5, 1.0), (4.0, 0.0)), 0.0, 0.0)
    assert not leads_on(path((0.0, 0.5), (1.5, 1.0), (4.0, 0.0)), 3.5, 0.0)  # driven to its end
