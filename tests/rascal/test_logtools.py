"""`rascal log info | echo | play`: summaries, JSON lines, and playback that live receivers accept."""

from __future__ import annotations

import json
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import pytest

from protocol import channels
from protocol.auth import Keyring, load_keyring
from protocol.codec import Codec, Envelope
from protocol.messages import ImuSample, Obstacle, ObstacleList, TimeSync
from rascal.bustools import to_jsonable
from rascal.logplay import Renumber, restamp
from rascal.logtools import main, summarize
from rascal.recording import RecordingWriter
from rascal.runtime.bus import Bus
from rascal.runtime.clock import MasterClock
from tests.rascal.test_recording import make_recording

STEP_NS = 20_000_000
IMU_COUNT = 40


def imu(i: int) -> ImuSample:
    return ImuSample(0.01 * i, 0.0, 9.81, 0.0, 0.0, -0.02 * i)


def obstacles(i: int) -> ObstacleList:
    # Every other list is 60 obstacles (4.4 kB): it goes out as fragments.
    count = 60 if i % 2 else 2
    return ObstacleList(1, 0, tuple(Obstacle(float(i), float(k), 1.0, 1.0, 1.0, 0.0, 0.9, 5.0) for k in range(count)))


@pytest.fixture
def session(tmp_path: Path, key_file: Path) -> Path:
    """40 IMU samples 20 ms apart, 4 obstacle lists and a time request, signed with the
    deployment key and recorded an hour ago: far too old for any synchronised receiver to take
    as they are."""
    t0 = time.time_ns() - 3600 * 1_000_000_000
    messages: list[tuple[str, Any, int]] = []
    for i in range(IMU_COUNT):
        messages.append((channels.IMU, imu(i), t0 + i * STEP_NS))
        if i % 10 == 5:
            messages.append((channels.OBSTACLES_LIDAR, obstacles(i // 10), t0 + i * STEP_NS + 1_000_000))
        if i == 1:
            messages.append((channels.TIME_SYNC, TimeSync(0, 31, 123), t0 + i * STEP_NS + 2_000_000))
    path = tmp_path / "session.mcap"
    make_recording(path, messages, load_keyring(key_file))
    return path


# -- info ---------------------------------------------------------------------------------------


def test_info_summarises_channels_rates_sources_and_the_check(session: Path, capsys: pytest.CaptureFixture) -> None:
    summary = summarize(session)
    assert summary.messages == IMU_COUNT + 4 + 1
    assert summary.duration_s == pytest.approx((IMU_COUNT - 1) * STEP_NS / 1e9)
    imu_channel = summary.channels[channels.IMU]
    assert (imu_channel.messages, imu_channel.sources) == (IMU_COUNT, {31})
    assert imu_channel.rate_hz() == pytest.approx(1e9 / STEP_NS)
    assert summary.sequences.problems() == []

    assert main(["info", str(session), "--strict"]) == 0
    out = capsys.readouterr().out
    assert "(finished)" in out and "made_by=test" in out
    assert "sequence check: OK" in out
    row = next(line.split() for line in out.splitlines() if line.strip().startswith("IMU "))
    assert row == ["IMU", "ImuSample", "31", "40", "50.0", "110", "0", "0"]


def test_info_strict_fails_when_the_file_misses_what_the_bus_accepted(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    codec = Codec(Keyring.generate())
    writer = RecordingWriter(tmp_path / "run.mcap", {})
    for seq in (1, 2, 4):  # the bus accepted 3 and lost none: the recorder dropped one
        data = codec.encode(b"IMU", imu(seq), 7, seq, 10**18 + seq, 10**18 + seq)
        writer.write(codec.open(data), data, 10**18 + seq)
    writer.close({"received/IMU": "4", "lost/IMU": "0", "rejected/7/bad_mac": "2"})
    assert main(["info", str(tmp_path / "run.mcap"), "--strict"]) == 1
    out = capsys.readouterr().out
    assert "IMU: 3 recorded, 4 received" in out and "IMU: 1 missing sequence number(s), the bus lost 0" in out
    assert "7/bad_mac=2" in out


def test_info_on_something_else_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    (tmp_path / "notes.txt").write_text("not a recording")
    assert main(["info", str(tmp_path / "notes.txt")]) == 2
    assert "not a readable MCAP file" in capsys.readouterr().err
    assert main(["info", str(tmp_path / "missing.mcap")]) == 2
    assert "No such file" in capsys.readouterr().err


# -- echo ---------------------------------------------------------------------------------------


def test_echo_prints_json_lines_of_the_chosen_channels(session: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["echo", str(session), "--channels", "IMU", "--count", "3"]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [line["msg"] for line in lines] == [to_jsonable(imu(i)) for i in range(3)]
    assert {line["channel"] for line in lines} == {channels.IMU}
    assert all(line["source"] == 31 and line["age_ms"] == 3.0 for line in lines)
    assert lines[1]["log_time_ns"] - lines[0]["log_time_ns"] == STEP_NS

    assert main(["echo", str(session), "--channels", "OBSTACLES_.*"]) == 0
    lists = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [len(line["msg"]["obstacles"]) for line in lists] == [2, 60, 2, 60]


# -- play ---------------------------------------------------------------------------------------


def test_restamp_keeps_channel_and_body_and_signs_with_the_current_key() -> None:
    old, new = Codec(Keyring.generate()), Codec(Keyring.generate(key_id=3))
    recorded = old.encode(b"IMU", imu(1), 21, 5, 1_000, 2_000)
    opened = new.open(restamp(recorded, 99, 7_000, 8_000, new.keyring))
    assert (opened.source_id, opened.seq, opened.t_meas_ns, opened.t_pub_ns, opened.channel) == (
        21,
        99,
        7_000,
        8_000,
        "IMU",
    )
    assert bytes(opened.body) == bytes(old.open(recorded).body)
    assert Codec(None).open(restamp(recorded, 1, 1, 1, None)).seq == 1  # the unsigned mode


def test_renumbering_keeps_gaps_and_collapses_restarts_and_reordering() -> None:
    renumber = Renumber(base=1_000)
    assert [renumber(5, "IMU", seq) for seq in (10, 11, 14, 2_000_014, 2_000_013, 2_000_015)] == [
        1_000,
        1_001,
        1_004,  # two lost live: still two missing
        1_005,  # a restarted publisher's jump
        1_006,  # a late message
        1_007,
    ]
    assert renumber(6, "IMU", 77) == 1_000  # streams are separate


def _listen(bus_url: str, key_file: Path) -> tuple[Bus, dict[str, list[tuple[Any, Envelope]]]]:
    """A synchronised receiver (the master's clock): it checks freshness as the stack's do."""
    listener = Bus.open(bus_url, source_id=50, clock=MasterClock(), keyring=load_keyring(key_file))
    heard: dict[str, list[tuple[Any, Envelope]]] = defaultdict(list)
    for channel in (channels.IMU, channels.OBSTACLES_LIDAR, channels.TIME_SYNC):
        listener.subscribe(channel, lambda msg, env: heard[env.channel].append((msg, env)))
    return listener, heard


def _play_while_listening(listener: Bus, argv: list[str]) -> int:
    codes: list[int] = []
    player = threading.Thread(target=lambda: codes.append(main(argv)))
    player.start()
    while player.is_alive():
        listener.poll(0.01)
    listener.poll(0.2)
    player.join()
    return codes[0]


def test_play_republishes_with_the_recorded_timing_and_receivers_accept_it(
    session: Path, bus_url: str, key_file: Path, capsys: pytest.CaptureFixture
) -> None:
    listener, heard = _listen(bus_url, key_file)
    argv = ["play", str(session), "--bus", bus_url, "--sync-wait", "0"]

    # The recorded bytes as they are: an hour old, so stale for every synchronised receiver.
    assert _play_while_listening(listener, [*argv, "--exact", "--speed", "0"]) == 0
    assert not heard[channels.IMU] and not heard[channels.OBSTACLES_LIDAR]
    assert listener.rejects == {(31, "stale"): IMU_COUNT + 4}

    assert _play_while_listening(listener, [*argv, "--speed", "2"]) == 0
    listener.close()
    assert "played 44 messages on 2 channels" in capsys.readouterr().out
    assert [msg for msg, _env in heard[channels.IMU]] == [imu(i) for i in range(IMU_COUNT)]
    assert [msg for msg, _env in heard[channels.OBSTACLES_LIDAR]] == [obstacles(i) for i in range(4)]
    # The recorded time request stays out (the live time service owns shared time); the
    # player's own requests to the master are all the listener heard there.
    assert all(env.source_id != 31 for _msg, env in heard[channels.TIME_SYNC])
    assert listener.rejects == {(31, "stale"): IMU_COUNT + 4}  # nothing new rejected
    envelopes = [env for _msg, env in heard[channels.IMU]]
    assert {env.source_id for env in envelopes} == {31}
    assert all(env.t_pub_ns - env.t_meas_ns == 2_000_000 for env in envelopes)  # as old as when recorded
    assert [env.seq - envelopes[0].seq for env in envelopes] == list(range(IMU_COUNT))
    # Sent on the recorded schedule at twice the speed: never early, and not much late.
    span_s = (envelopes[-1].t_pub_ns - envelopes[0].t_pub_ns) / 1e9
    recorded_span_s = (IMU_COUNT - 1) * STEP_NS / 1e9 / 2
    assert recorded_span_s * 0.95 <= span_s <= recorded_span_s + 1.0
