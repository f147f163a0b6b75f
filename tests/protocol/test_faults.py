"""Link faults (protocol.faults) on the in-process transport, on a manual clock: what each fault
does to a stream, measured over thousands of datagrams, and how rules are read."""

from __future__ import annotations

import itertools
import time
from collections import OrderedDict
from typing import Any

import pytest

from protocol import channels
from protocol.codec import Envelope
from protocol.faults import (
    FaultConfigError,
    FaultRule,
    FaultyTransport,
    format_rules,
    header_route,
    parse_rules,
)
from protocol.framing import fragment
from protocol.messages import Obstacle, ObstacleList, WheelSpeed
from protocol.transport import MemTransport, UrlError, open_transport
from rascal.runtime.bus import Bus
from rascal.runtime.clock import ManualClock
from tests.protocol.wire_samples import keyring

SENDER = 7
RECEIVER = 8
N = 5000


class Link:
    """A publishing Bus and a receiving Bus behind a FaultyTransport, timed by a manual clock."""

    def __init__(self, hub: str, *rules: FaultRule, max_held: int = 4096) -> None:
        self.now = [0]
        clock = ManualClock()
        keys = keyring()
        self.faulty = FaultyTransport(MemTransport(hub), rules, now_ns=lambda: self.now[0], max_held=max_held)
        self.receiver = Bus(self.faulty, RECEIVER, keys, clock)
        self.sender = Bus(MemTransport(hub), SENDER, keys, clock)
        self.seqs: dict[str, list[int]] = {}
        for channel in (channels.WHEEL_SPEED, channels.OBSTACLES_LIDAR):
            self.receiver.subscribe(channel, self._record)

    def _record(self, _msg: Any, envelope: Envelope) -> None:
        self.seqs.setdefault(envelope.channel, []).append(envelope.seq)

    def send(self, count: int, channel: str = channels.WHEEL_SPEED) -> None:
        msg = WheelSpeed(5.0, 5.0) if channel == channels.WHEEL_SPEED else obstacles(2)
        for _ in range(count):
            self.sender.publish(channel, msg)
            self.receiver.poll(0.0)

    def drain(self, after_ms: float = 20_000.0) -> None:
        self.now[0] += int(after_ms * 1e6)
        while self.receiver.poll(0.0):
            pass

    def delivered(self, channel: str = channels.WHEEL_SPEED) -> list[int]:
        return self.seqs.get(channel, [])

    def close(self) -> None:
        self.receiver.close()
        self.sender.close()


def obstacles(count: int) -> ObstacleList:
    return ObstacleList(1, 0, tuple(Obstacle(float(i), 2.0, 1.0, 1.0, 1.0, 0.0, 0.9, 10.0) for i in range(count)))


def test_loss_drops_the_set_fraction_and_the_bus_counts_it_as_lost() -> None:
    link = Link("faults-loss", FaultRule(loss_pct=20, seed=1))
    link.send(N)
    delivered = len(link.delivered())
    assert abs(delivered / N - 0.8) < 0.03, delivered
    assert link.faulty.stats["lost"] == N - delivered
    # Sequence gaps are what every module's loss statistics see (between its first and last).
    seqs = link.delivered()
    assert link.receiver.stats[channels.WHEEL_SPEED].lost == max(seqs) - min(seqs) + 1 - delivered
    link.close()


def test_rules_apply_only_to_their_channels_and_sources() -> None:
    link = Link("faults-select", FaultRule(channels="OBSTACLES_.*", loss_pct=100))
    link.send(200)
    link.send(200, channels.OBSTACLES_LIDAR)
    assert len(link.delivered()) == 200 and not link.delivered(channels.OBSTACLES_LIDAR)
    link.close()
    other_source = Link("faults-source", FaultRule(sources=(SENDER + 1,), loss_pct=100))
    other_source.send(200)
    assert len(other_source.delivered()) == 200
    other_source.close()


def test_delay_and_jitter_hold_each_datagram_within_bounds() -> None:
    link = Link("faults-delay", FaultRule(delay_ms=10, jitter_ms=20, seed=3))
    link.send(60)  # all at once, so within the replay window (64) whatever order jitter gives them
    assert not link.delivered(), "nothing may arrive before its delay"
    arrived_by: list[int] = []
    for ms in range(1, 40):
        link.now[0] = ms * 1_000_000
        link.receiver.poll(0.0)
        arrived_by.append(len(link.delivered()))
    assert arrived_by[8] == 0 and arrived_by[29] == 60  # none before 10 ms, all by 30 ms
    assert 10 < arrived_by[19] < 50  # and spread between
    assert link.faulty.held() == 0 and link.faulty.stats["delayed"] == 60
    link.close()


def test_jitter_reorders_and_the_replay_window_takes_the_late_ones() -> None:
    link = Link("faults-jitter", FaultRule(jitter_ms=5, seed=4))
    for i in range(1000):
        link.now[0] = i * 1_000_000  # 1 kHz against 5 ms of jitter
        link.send(1)
    link.drain()
    seqs = link.delivered()
    assert sorted(seqs) == list(range(seqs and min(seqs), min(seqs) + 1000))
    assert seqs != sorted(seqs)
    assert link.receiver.rejected_total() == 0
    link.close()


def test_reordered_datagrams_are_overtaken() -> None:
    link = Link("faults-reorder", FaultRule(reorder_pct=10, reorder_ms=3, seed=5))
    for i in range(N):
        link.now[0] = i * 1_000_000
        link.send(1)
    link.drain()
    seqs = link.delivered()
    late = sum(1 for before, after in itertools.pairwise(seqs) if after < before)
    assert len(seqs) == N and abs(late / N - 0.1) < 0.03, late
    assert link.faulty.stats["reordered"] == pytest.approx(N * 0.1, rel=0.2)
    link.close()


def test_duplicates_are_delivered_twice_and_the_second_rejected_as_replay() -> None:
    link = Link("faults-dup", FaultRule(duplicate_pct=10, seed=6))
    link.send(N)
    duplicated = link.faulty.stats["duplicated"]
    assert abs(duplicated / N - 0.1) < 0.02
    assert len(link.delivered()) == N
    assert link.receiver.rejects[(SENDER, "replay")] == duplicated
    link.close()


def test_corrupted_datagrams_are_rejected_by_the_codec_and_counted() -> None:
    link = Link("faults-corrupt", FaultRule(corrupt_pct=100, seed=7))
    link.send(2000)
    link.receiver.reassembler.expire(10**19)
    link.receiver.poll(0.0)
    assert not link.delivered()
    assert link.faulty.stats["corrupted"] == 2000
    assert link.receiver.rejected_total() == 2000
    reasons = {reason for _source, reason in link.receiver.rejects}
    assert "bad_mac" in reasons, reasons
    link.close()


def test_a_full_hold_queue_drops_and_counts() -> None:
    link = Link("faults-overflow", FaultRule(delay_ms=100), max_held=10)
    link.send(25)
    link.drain()
    assert len(link.delivered()) == 10 and link.faulty.stats["overflow"] == 15
    link.close()


def test_fragments_follow_the_channel_of_their_first_fragment() -> None:
    big = obstacles(120)  # ~5 kB: four fragments
    dropped = Link("faults-frag-drop", FaultRule(channels="OBSTACLES_LIDAR", loss_pct=100))
    dropped.sender.publish(channels.OBSTACLES_LIDAR, big)
    dropped.drain()
    assert not dropped.delivered(channels.OBSTACLES_LIDAR) and dropped.faulty.stats["lost"] >= 4
    dropped.close()
    kept = Link("faults-frag-keep", FaultRule(channels="GPS", loss_pct=100))
    kept.sender.publish(channels.OBSTACLES_LIDAR, big)
    kept.drain()
    assert len(kept.delivered(channels.OBSTACLES_LIDAR)) == 1
    kept.close()


def test_header_route_reads_channel_and_source_without_trusting_them() -> None:
    bus = Bus(MemTransport("faults-route"), 33, keyring(), ManualClock())
    _seq, data = bus.encode(channels.OBSTACLES_LIDAR, obstacles(120))
    parts = fragment(data, 33, 99)
    remembered: OrderedDict[tuple[int, int], str] = OrderedDict()
    assert [header_route(part, remembered) for part in parts] == [(channels.OBSTACLES_LIDAR, 33)] * len(parts)
    assert header_route(parts[1]) == ("", 33)  # its first fragment unseen
    assert header_route(b"RB") == ("", 0)
    bus.close()


def test_the_same_seed_repeats_the_same_faults() -> None:
    runs = []
    for name in ("faults-seed-a", "faults-seed-b"):
        link = Link(name, FaultRule(loss_pct=30, seed=11))
        link.send(500)
        runs.append([seq - min(link.delivered()) for seq in link.delivered()])
        link.close()
    assert runs[0] == runs[1]


def test_receive_waits_no_longer_than_the_next_release() -> None:
    faulty = FaultyTransport(MemTransport("faults-wait"), [FaultRule(delay_ms=30)])
    sender = MemTransport("faults-wait")
    faulty.listen(channels.WHEEL_SPEED)
    sender.send(channels.WHEEL_SPEED, b"RB" + bytes(60))
    got: list[bytes] = []
    assert faulty.receive(got.append, 0.0, 10) == 0 and faulty.held() == 1
    started = time.monotonic()
    while not got and time.monotonic() - started < 5.0:
        faulty.receive(got.append, 5.0, 10)
    assert got and time.monotonic() - started < 2.5, "a held datagram waited for the caller's whole timeout"
    faulty.close()
    sender.close()


def test_rules_round_trip_through_their_text_form() -> None:
    rules = (
        FaultRule(channels="OBSTACLES_.*", loss_pct=20, jitter_ms=20, seed=3),
        FaultRule(channels="GPS", sources=(31, 32), delay_ms=100, duplicate_pct=1.5, corrupt_pct=2, reorder_pct=5),
    )
    text = format_rules(rules)
    assert text.startswith("channels=OBSTACLES_.*,loss_pct=20,jitter_ms=20,seed=3;channels=GPS,sources=31|32,")
    assert parse_rules(text) == rules


@pytest.mark.parametrize(
    ("text", "complaint"),
    [
        ("loss_pct=150", r"\[0\]\.loss_pct: expected 0\.\.100"),
        ("loss=20", r"\[0\]\.loss: unknown key"),
        ("channels=GPS;delay_ms=soon", r"\[1\]\.delay_ms: expected a number"),
        ("channels=(", r"channels: '\(' is not a regular expression"),
        ("sources=0", r"sources: source id 0"),
        ("jitter_ms=nan", r"jitter_ms: expected a number"),
        ("seed=1.5", r"seed: expected an integer"),
        ("loss_pct", r"expected KEY=VALUE"),
    ],
)
def test_bad_rules_are_refused_naming_the_key(text: str, complaint: str) -> None:
    with pytest.raises(FaultConfigError, match=complaint):
        parse_rules(text)


def test_a_process_logs_what_its_faults_did_when_it_closes(capsys: pytest.CaptureFixture[str]) -> None:
    transport = open_transport("mem://faults-log?faults=loss_pct=100")
    sender = MemTransport("faults-log")
    transport.listen(channels.GPS)
    for _ in range(3):
        sender.send(channels.GPS, b"RB" + bytes(60))
    assert transport.receive(lambda *_: None, 0.0, 10) == 0
    transport.close()
    sender.close()
    assert "link faults: 3 matched, lost 3 (mem://faults-log?faults=loss_pct=100: faults)" in capsys.readouterr().err


def test_urls_and_the_environment_put_faults_on_a_transport(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("RASCAL_FAULTS", raising=False)
    assert isinstance(open_transport("mem://plain"), MemTransport)
    from_url = open_transport("mem://faulty?faults=channels=GPS,loss_pct=5")
    assert isinstance(from_url, FaultyTransport) and from_url.rules == (FaultRule(channels="GPS", loss_pct=5),)
    udp = open_transport("udpm://239.255.1.2:30000?ttl=0&faults=loss_pct=1")
    assert isinstance(udp, FaultyTransport)
    udp.close()
    monkeypatch.setenv("RASCAL_FAULTS", "delay_ms=5")
    from_env = open_transport("mem://env")
    assert isinstance(from_env, FaultyTransport) and from_env.rules == (FaultRule(delay_ms=5),)
    with pytest.raises(UrlError, match=r"\$RASCAL_FAULTS\[0\]\.delay_ms"):
        monkeypatch.setenv("RASCAL_FAULTS", "delay_ms=-1")
        open_transport("mem://env-bad")
    with pytest.raises(UrlError, match=r"faults\[0\]\.loss_pct"):
        open_transport("mem://url-bad?faults=loss_pct=x")
