"""The C fast path (protocol/_fastpath.c) against its pure-Python twins.

C takes only the common case and hands everything else back to Python, so each piece is held to:
where C gives an answer it is Python's answer, and where Python refuses, C does not accept. The
last tests run the same traffic through a whole Bus with and without C (in a subprocess with
``RASCAL_PURE_PYTHON=1``), and the protocol tests in pure-Python mode, so the fallback that
machines without a compiler run stays tested too.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import random
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import msgpack
import pytest

from protocol import channels, codec, fastpath
from protocol.auth import Keyring
from protocol.codec import FLAG_SIGNED, Codec, Opened
from protocol.errors import ProtocolError
from protocol.framing import fragment
from protocol.replay import PythonReplayGuard, ReplayGuard, ReplayLimits
from protocol.schema import _compile_decoder, info_for_class, registered
from protocol.transport import MemTransport
from rascal.runtime.bus import Bus
from rascal.runtime.clock import ManualClock
from tests.protocol.test_fuzz import Traffic
from tests.protocol.wire_samples import BIG_SAMPLES, CHANNEL_OF, SAMPLES, T0_NS, keyring

PROJECT_ROOT = Path(__file__).resolve().parents[2]
native = fastpath.native
needs_native = pytest.mark.skipif(native is None, reason=f"the bus runs {fastpath.describe()}")


def test_the_fast_path_is_built_where_a_compiler_is() -> None:
    """An install on a machine with a C compiler must not fall back silently."""
    if fastpath.pure_python_asked():
        assert native is None
        return
    if shutil.which("cc") is None and shutil.which("gcc") is None:
        pytest.skip("no C compiler here, so no fast path to check")
    assert native is not None, "protocol/_fastpath.c was not built: reinstall with `pip install -e .`"
    assert fastpath.describe() == "C fast path"


# -- tags, seal and open ----------------------------------------------------------------------


@needs_native
def test_the_c_tag_is_hashlib_s_keyed_blake2b_128() -> None:
    """Every length from 0 to 400 B (block edges at 128 and 256) and 2,000 random ones, with keys
    of 1 to 64 bytes."""
    rng = random.Random(1)
    for length in [*range(401), *(rng.randrange(70_000) for _ in range(2_000))]:
        key = rng.randbytes(rng.choice((32, 32, 1, 17, 64)))
        data = rng.randbytes(length)
        assert native.Mac(key).digest(data) == hashlib.blake2b(data, key=key, digest_size=16).digest(), length
    with pytest.raises(ValueError):
        native.Mac(b"")
    with pytest.raises(ValueError):
        native.Mac(bytes(65))


def _pure(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(codec, "native", None)


@needs_native
@pytest.mark.parametrize("signed", [True, False], ids=["signed", "unsigned"])
def test_sealed_messages_are_byte_for_byte_those_of_python(signed: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    keys = keyring() if signed else None
    fast = [
        Codec(keys).encode(CHANNEL_OF[type(s)].encode(), s, 7, 1 + i, -5 - i, T0_NS + i) for i, s in enumerate(SAMPLES)
    ]
    _pure(monkeypatch)
    slow = [
        Codec(keys).encode(CHANNEL_OF[type(s)].encode(), s, 7, 1 + i, -5 - i, T0_NS + i) for i, s in enumerate(SAMPLES)
    ]
    assert fast == slow


def _python_open(opener: Codec, data: bytes) -> Opened | ProtocolError:
    saved, codec.native = codec.native, None
    try:
        return opener.open(data)
    except ProtocolError as error:
        return error
    finally:
        codec.native = saved


def _fast_open(opener: Codec, data: bytes) -> Opened | ProtocolError | None:
    try:
        return native.open(data, Opened, opener.verifying_macs, opener.max_message_bytes)
    except ProtocolError as error:
        return error


@needs_native
@pytest.mark.parametrize("signed", [True, False], ids=["signed", "unsigned"])
def test_open_agrees_with_python_on_mutated_datagrams(signed: bool) -> None:
    """20,000 datagrams from the fuzzer's generators (genuine, replayed, bit-flipped, truncated,
    rewritten headers, random bytes, resealed bodies...). A wrong tag C refuses itself, with
    Python's error, so the tag is never computed twice."""
    keys = keyring() if signed else None
    opener = Codec(keys)
    traffic = Traffic(random.Random(11 + signed), keys, ManualClock(T0_NS))
    counts = {"same": 0, "left to python": 0, "refused alike": 0}
    for _ in range(20_000):
        for data in traffic.batch():
            fast = _fast_open(opener, data)
            slow = _python_open(opener, data)
            if isinstance(fast, ProtocolError):
                assert isinstance(slow, ProtocolError) and fast.reason.value == "bad_mac", data.hex()
                assert (fast.reason, str(fast), fast.source_id) == (slow.reason, str(slow), slow.source_id)
                counts["refused alike"] += 1
            elif fast is None:
                signed_in_unsigned_mode = keys is None and len(data) > 3 and data[3] & FLAG_SIGNED
                assert isinstance(slow, ProtocolError) or signed_in_unsigned_mode, data.hex()
                counts["left to python"] += 1
            else:
                assert isinstance(slow, Opened), (slow, data.hex())
                assert fast[:6] == slow[:6] and bytes(fast.body) == bytes(slow.body)
                assert type(fast) is Opened and type(fast.body) is memoryview
                counts["same"] += 1
    assert counts["same"] > 2_000 and counts["left to python"] > 2_000, counts
    assert (counts["refused alike"] > 1_000) == signed, counts


@needs_native
@pytest.mark.parametrize("signed", [True, False], ids=["signed", "unsigned"])
def test_fragments_are_always_left_to_python(signed: bool) -> None:
    """C has no reassembly: every fragment, tagged or not, authentic or forged, comes back None
    from open() and from a Receiver, so the Python reassembler and its tag check see it."""
    keys = keyring() if signed else None
    opener = Codec(keys)
    data = opener.encode(b"PATH", BIG_SAMPLES[1], 7, 1, T0_NS, T0_NS)
    receiver = native.Receiver(opener.verifying_macs, opener.max_message_bytes, {}, ReplayGuard(ReplayLimits()), tuple)
    for tagged_with in (keys, keyring(), None):
        for part in fragment(data, 7, 1, keyring=tagged_with):
            assert native.open(part, Opened, opener.verifying_macs, opener.max_message_bytes) is None
            assert receiver.accept(part, T0_NS, T0_NS, True) is None
            assert isinstance(_python_open(opener, part), ProtocolError)


@needs_native
def test_a_wrong_tag_is_refused_as_bad_mac_by_open_and_the_receiver() -> None:
    """C words this one error itself (besides the replay guard's): the datagram is not handed
    back to Python, which would compute the tag again."""
    opener = Codec(keyring())
    sample = SAMPLES[0]
    forged = Codec(Keyring.generate()).encode(CHANNEL_OF[type(sample)].encode(), sample, 7, 1, T0_NS, T0_NS)
    receiver = native.Receiver(opener.verifying_macs, opener.max_message_bytes, {}, ReplayGuard(ReplayLimits()), tuple)
    for refuse in (
        lambda: native.open(forged, Opened, opener.verifying_macs, opener.max_message_bytes),
        lambda: receiver.accept(forged, T0_NS, T0_NS, True),
    ):
        with pytest.raises(ProtocolError) as caught:
            refuse()
        assert (caught.value.reason.value, caught.value.source_id, str(caught.value)) == ("bad_mac", 7, "bad_mac")


# -- typed decode ----------------------------------------------------------------------------

ODD_VALUES = [None, True, 0, -1, 2**64 - 1, 0.5, math.nan, math.inf, "", "x", b"", b"\x00", (), (1.0,), ("a",)]


def _mutations(raw: tuple, rng: random.Random) -> list[Any]:
    """Bodies as msgpack could deliver them: the genuine one, then others a peer could send."""
    out: list[Any] = [raw, raw[:-1], (*raw, 1), list(raw), 0, "body"]
    for _ in range(12):
        edited = list(raw)
        index = rng.randrange(len(raw)) if raw else 0
        if raw and isinstance(raw[index], tuple) and raw[index] and rng.random() < 0.6:
            inner = list(raw[index])
            at = rng.randrange(len(inner))
            if isinstance(inner[at], tuple) and inner[at]:
                record = list(inner[at])
                record[rng.randrange(len(record))] = rng.choice(ODD_VALUES)
                inner[at] = tuple(record) if rng.random() < 0.8 else record
            else:
                inner[at] = rng.choice(ODD_VALUES)
            edited[index] = tuple(inner)
        elif raw:
            edited[index] = rng.choice(ODD_VALUES)
        out.append(tuple(edited))
    return out


def _slow_decode(decoder: Any, raw: Any) -> Any:
    try:
        return decoder(raw)
    except ProtocolError as error:
        return error


@needs_native
def test_decode_agrees_with_python_on_every_type_and_odd_bodies() -> None:
    rng = random.Random(5)
    decoded = left = 0
    for sample in SAMPLES + BIG_SAMPLES:
        info = info_for_class(type(sample))
        raw = msgpack.unpackb(msgpack.packb(sample), use_list=False)
        assert native.decode(info.plan, raw) == sample, type(sample).__name__
        slow_decoder = _compile_decoder(type(sample))
        for body in _mutations(raw, rng):
            fast, slow = native.decode(info.plan, body), _slow_decode(slow_decoder, body)
            if fast is None:
                left += 1
                continue
            assert not isinstance(slow, ProtocolError), (type(sample).__name__, body)
            assert fast == slow and type(fast) is type(slow) is info.cls
            assert [type(value) for value in fast] == [type(value) for value in slow]
            decoded += 1
    assert decoded > 50 and left > 200, (decoded, left)


def _python_read(decoder: Any, body: bytes) -> Any:
    """codec.unpack_body + the Python decoder, or the ProtocolError they raise."""
    try:
        return decoder(codec.unpack_body(body))
    except ProtocolError as error:
        return error


@needs_native
def test_reading_bodies_straight_into_types_agrees_with_msgpack_and_python() -> None:
    """Genuine bodies (float64 and float32 encodings), then 60,000 with flipped bits, rewritten
    bytes, cuts and extra bytes: C reads what msgpack + Python read, or leaves it to them."""
    rng = random.Random(9)
    read = left = 0
    for sample in SAMPLES + BIG_SAMPLES:
        info = info_for_class(type(sample))
        slow_decoder = _compile_decoder(type(sample))
        genuine = [msgpack.packb(sample), msgpack.packb(sample, use_single_float=True)]
        for body in genuine:
            assert native.decode_body(info.plan, body) == _python_read(slow_decoder, body)
        for _ in range(60_000 // len(SAMPLES + BIG_SAMPLES)):
            edited = bytearray(rng.choice(genuine))
            move = rng.random()
            if move < 0.4:
                edited[rng.randrange(len(edited))] ^= 1 << rng.randrange(8)
            elif move < 0.7:
                edited[rng.randrange(len(edited))] = rng.choice(
                    (0xC0, 0xC2, 0xC3, 0xCA, 0xCB, 0xD9, 0xDC, rng.randrange(256))
                )
            elif move < 0.85:
                del edited[rng.randrange(len(edited)) :]
            else:
                edited += rng.randbytes(rng.randint(1, 3))
            body = bytes(edited)
            fast, slow = native.decode_body(info.plan, body), _python_read(slow_decoder, body)
            if fast is None:
                left += 1
                continue
            assert not isinstance(slow, ProtocolError), (type(sample).__name__, body.hex())
            assert fast == slow and type(fast) is type(slow)
            assert [type(value) for value in fast] == [type(value) for value in slow], body.hex()
            read += 1
    assert read > 5_000 and left > 20_000, (read, left)


@needs_native
def test_every_registered_type_has_a_plan_the_fast_path_reads() -> None:
    for info in registered():
        cls, codes, subplans = info.plan
        assert cls is info.cls and len(codes) == len(info.cls._fields) == len(subplans)


# -- replay guard ----------------------------------------------------------------------------


def _outcome(guard: Any, *args: Any) -> Any:
    try:
        return guard.check(*args)
    except ProtocolError as error:
        return (error.reason, str(error), error.source_id)


@needs_native
def test_the_c_replay_guard_keeps_python_s_rules() -> None:
    """Same answers and errors, op for op, over 30,000 checks on few streams (eviction at 5),
    with a clock moving on and publishers restarting below their old numbers."""
    limits = ReplayLimits(max_age_ns=1_000, max_future_ns=500, max_streams=5)
    fast, slow = ReplayGuard(limits), PythonReplayGuard(limits)
    assert type(fast) is not PythonReplayGuard and fast.limits is limits
    rng = random.Random(3)
    seqs = {key: 10**15 for key in range(8)}
    clock = 10_000
    new_lives = old_lives_refused = 0
    for step in range(30_000):
        key = rng.randrange(8)
        source_id, channel = key % 3 + 1, f"CH{key // 3}"
        move = rng.random()
        if move < 0.02:
            fast.forget(source_id, channel)
            slow.forget(source_id, channel)
            continue
        clock += rng.choice((0, 1, 100))
        if move < 0.55:
            seqs[key] += rng.choice((1, 1, 1, 2, 5, 63, 64, 70, 1_000_001))
            seq = seqs[key]
        elif move < 0.6:  # a restart with the wall clock stepped back
            seqs[key] -= rng.choice((64, 10**7))
            seq = seqs[key]
        else:
            seq = seqs[key] - rng.choice((0, 1, 2, 30, 63, 64, 65, 10**6))
        now = rng.choice((None, clock, clock))
        t_pub = clock + rng.choice((0, 0, -1, -999, -1_000, -1_001, 500, 501))
        if rng.random() < 0.01:
            t_pub = clock + rng.choice((-(2**62), 2**62))
        args = (source_id, channel, seq, t_pub, now)
        floor = getattr(slow._streams.get((source_id, channel)), "floor", None)
        outcome = _outcome(slow, *args)
        assert _outcome(fast, *args) == outcome, (step, args)
        assert len(fast) == len(slow)
        new_lives += floor is not None and slow._streams[(source_id, channel)].floor != floor
        old_lives_refused += "before its source restarted" in str(outcome)
    assert new_lives > 300 and old_lives_refused > 300, (new_lives, old_lives_refused)


# -- the whole bus, with and without C -------------------------------------------------------


def bus_outcomes(signed: bool, datagrams: int, seed: int) -> list[str]:
    """What a typed-only Bus (no raw handlers, so the C Receiver takes the plain datagrams) does
    with each of the fuzzer's datagrams: the messages and envelopes it delivers, what it rejects;
    then its channel statistics."""
    keys = keyring() if signed else None
    clock = ManualClock(T0_NS)
    traffic = Traffic(random.Random(seed), keys, clock)
    hub = f"fastpath-{seed}-{signed}"
    bus, tap = Bus(MemTransport(hub), 900, keys, clock), MemTransport(hub)
    delivered: list[str] = []
    for name in channels.CHANNEL_TYPES:
        bus.subscribe(name, lambda msg, envelope: delivered.append(repr((msg, envelope))))
    outcomes = []
    for _ in range(datagrams):
        for data in traffic.batch():
            rejects_before = dict(bus.rejects)
            tap.send(channels.IMU, data)
            bus.poll()
            rejected = sorted(f"{key}" for key, n in bus.rejects.items() if n != rejects_before.get(key, 0))
            outcomes.append(" | ".join(delivered + rejected) or "-")
            delivered.clear()
    stats = {name: (st.messages, st.bytes, st.lost, sorted(st.sources)) for name, st in sorted(bus.stats.items())}
    outcomes.append(f"stats {stats}")
    bus.close()
    tap.close()
    return outcomes


@needs_native
@pytest.mark.slow
@pytest.mark.parametrize("signed", [True, False], ids=["signed", "unsigned"])
def test_a_bus_with_the_fast_path_does_what_a_pure_python_bus_does(signed: bool) -> None:
    datagrams, seed = 20_000, 21
    script = (
        "import json, tests.protocol.test_fastpath as t; "
        f"print(json.dumps(t.bus_outcomes({signed}, {datagrams}, {seed})))"
    )
    env = {**os.environ, fastpath.PURE_PYTHON_ENV: "1"}
    result = subprocess.run(
        [sys.executable, "-c", script], cwd=PROJECT_ROOT, env=env, capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr[-3000:]
    pure = json.loads(result.stdout)
    fast = bus_outcomes(signed, datagrams, seed)
    assert len(fast) == len(pure)
    for index, (got, want) in enumerate(zip(fast, pure, strict=True)):
        assert got == want, f"datagram #{index}: C {got!r}, Python {want!r}"
    assert sum("Envelope(" in outcome for outcome in fast) > 500


@needs_native
@pytest.mark.slow
def test_the_protocol_tests_pass_in_pure_python_mode() -> None:
    """The fallback of machines without a compiler: tests/protocol with RASCAL_PURE_PYTHON=1."""
    env = {**os.environ, fastpath.PURE_PYTHON_ENV: "1"}
    result = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", "tests/protocol", "-k", "not fastpath"],
        cwd=PROJECT_ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stdout[-4000:]
    assert " passed" in result.stdout
