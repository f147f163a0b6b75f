"""Codec: authenticity and framing of whole messages (forgery, tampering, truncation, limits)."""

from __future__ import annotations

from typing import Any

import msgpack
import pytest

from protocol import messages as m
from protocol.auth import TAG_BYTES, Keyring
from protocol.codec import (
    FLAG_FRAGMENT,
    FLAG_SIGNATURE,
    FLAG_SIGNED,
    HEADER,
    HEADER_BYTES,
    VERSION,
    Codec,
    Opened,
    check_channel,
    decode_body,
)
from protocol.errors import ProtocolError, Reason
from protocol.schema import info_for_class
from protocol.signing import SIGNATURE_BYTES
from tests.protocol.wire_samples import SAMPLES, T0_NS, WRONG_KEY, keyring, seal

GPS = m.GpsFix(35.0533, -117.5694, 712.4, 0.35, 0.41, 0.9, m.NavQuality.DGPS, 11)
CHANNEL = b"GPS"
SOURCE = 12

# Byte offsets of the header fields (see the layout in protocol.codec).
MAGIC_AT = range(0, 2)
VERSION_AT = 2
FLAGS_AT = 3
KEY_ID_AT = range(8, 10)
CHANNEL_LEN_AT = 10


def encode(codec: Codec, msg: Any = GPS, seq: int = 1000, channel: bytes = CHANNEL) -> bytes:
    return codec.encode(channel, msg, SOURCE, seq, T0_NS - 5_000_000, T0_NS)


def reason_of(codec: Codec, data: bytes) -> Reason:
    """Why the full receive path (open, then decode the body) rejects ``data``."""
    with pytest.raises(ProtocolError) as caught:
        opened = codec.open(data)
        decode_body(opened.type_id, opened.body, opened.source_id)
    return caught.value.reason


def with_byte(data: bytes, offset: int, value: int) -> bytes:
    return data[:offset] + bytes([value]) + data[offset + 1 :]


# -- accepted ----------------------------------------------------------------------------------


@pytest.mark.parametrize("sample", SAMPLES, ids=lambda s: type(s).__name__)
def test_signed_messages_open_to_the_same_header_and_body(sample: Any) -> None:
    """encode -> open -> decode_body gives back every header field and the message."""
    codec = Codec(keyring())
    opened = codec.open(codec.encode(b"SOME/channel_1", sample, 65535, 2**64 - 1, -(2**63), 2**63 - 1))
    assert isinstance(opened, Opened)
    type_id = info_for_class(type(sample)).type_id
    assert opened[:6] == (type_id, 65535, 2**64 - 1, -(2**63), 2**63 - 1, "SOME/channel_1")
    assert decode_body(opened.type_id, opened.body) == sample


def test_unsigned_mode_accepts_unsigned_messages() -> None:
    """Codec(None) sends without a tag or the SIGNED flag and accepts what it sends."""
    codec = Codec(None)
    data = encode(codec)
    assert data[FLAGS_AT] == 0
    assert len(data) == len(encode(Codec(keyring()))) - TAG_BYTES
    opened = codec.open(data)
    assert (opened.source_id, opened.seq, opened.channel) == (SOURCE, 1000, "GPS")
    assert decode_body(opened.type_id, opened.body) == GPS


def test_key_rotation_receiver_with_two_keys_accepts_either() -> None:
    """A receiver holding keys {1, 2} accepts messages signed with key 1 and with key 2."""
    receiver = Codec(keyring(1, 2))
    for sender in (Codec(keyring(1)), Codec(keyring(2)), Codec(keyring(1, 2, active=2))):
        assert decode_body(11, receiver.open(encode(sender)).body) == GPS


def test_key_rotation_retired_key_is_unknown() -> None:
    """Once key 1 is retired (receiver holds only {2}), messages signed with it are UNKNOWN_KEY."""
    assert reason_of(Codec(keyring(2)), encode(Codec(keyring(1)))) is Reason.UNKNOWN_KEY


# -- rejected ----------------------------------------------------------------------------------


def test_forged_message_with_the_wrong_key_is_bad_mac() -> None:
    """A message signed with another key under a valid key id is BAD_MAC, attributed to its source."""
    forger = Codec(Keyring({1: WRONG_KEY}, 1))
    with pytest.raises(ProtocolError) as caught:
        Codec(keyring()).open(encode(forger))
    assert caught.value.reason is Reason.BAD_MAC
    assert caught.value.source_id == SOURCE


def _expected_tamper_reason(offset: int, flipped: int, size: int) -> Reason:
    """Which check must catch a changed byte: the ones before the MAC, else the MAC."""
    if offset in MAGIC_AT:
        return Reason.BAD_MAGIC
    if offset == VERSION_AT:
        return Reason.BAD_VERSION
    if offset == FLAGS_AT:
        if flipped == FLAG_SIGNED | FLAG_SIGNATURE:  # a signature would have to precede the tag
            return (
                Reason.TRUNCATED if HEADER_BYTES + len(CHANNEL) > size - TAG_BYTES - SIGNATURE_BYTES else Reason.BAD_MAC
            )
        return Reason.BAD_HEADER if flipped & ~FLAG_SIGNED else Reason.UNSIGNED
    if offset in KEY_ID_AT:
        return Reason.UNKNOWN_KEY
    if offset == CHANNEL_LEN_AT and HEADER_BYTES + flipped > size - TAG_BYTES:
        return Reason.TRUNCATED  # the channel would overlap the tag
    return Reason.BAD_MAC


@pytest.mark.parametrize("sample", [GPS, SAMPLES[2], SAMPLES[11]], ids=lambda s: type(s).__name__)
def test_any_single_byte_change_in_a_signed_message_is_rejected(sample: Any) -> None:
    """Flipping any one bit, or all bits, of any byte (header, channel, body or tag) of a signed
    message is rejected, by the first check that covers that byte."""
    codec = Codec(keyring())
    data = encode(codec, sample)
    for offset, original in enumerate(data):
        for mask in (*(1 << bit for bit in range(8)), 0xFF):
            flipped = original ^ mask
            reason = reason_of(codec, with_byte(data, offset, flipped))
            assert reason is _expected_tamper_reason(offset, flipped, len(data)), (offset, mask, reason)


def test_unsigned_message_is_rejected_when_a_keyring_is_set() -> None:
    """With a keyring, an unsigned message is UNSIGNED, however well-formed."""
    assert reason_of(Codec(keyring()), encode(Codec(None))) is Reason.UNSIGNED


def test_a_stripped_signature_is_rejected() -> None:
    """Clearing the SIGNED flag and dropping the tag of a genuine message is UNSIGNED."""
    data = encode(Codec(keyring()))
    stripped = with_byte(data, FLAGS_AT, 0)[:-TAG_BYTES]
    assert reason_of(Codec(keyring()), stripped) is Reason.UNSIGNED


def test_an_unknown_key_id_is_unknown_key() -> None:
    """A key id the receiver does not hold is UNKNOWN_KEY, whatever the key."""
    receiver = Codec(keyring(1, 2))
    for key_id in (0, 3, 7, 0xFFFF):
        assert reason_of(receiver, encode(Codec(keyring(key_id)))) is Reason.UNKNOWN_KEY


def test_every_truncation_of_a_signed_message_is_rejected() -> None:
    """Every proper prefix is rejected: TRUNCATED while there is no room for header, channel
    and tag, BAD_MAC after that (the tag then covers the wrong bytes)."""
    codec = Codec(keyring())
    data = encode(codec)
    no_room = HEADER_BYTES + len(CHANNEL) + TAG_BYTES
    for length in range(len(data)):
        expected = Reason.TRUNCATED if length < no_room else Reason.BAD_MAC
        assert reason_of(codec, data[:length]) is expected, length


def test_every_truncation_of_an_unsigned_message_is_rejected() -> None:
    """Without a MAC, every proper prefix is still rejected: TRUNCATED inside the header,
    BAD_HEADER while no body byte is left, BAD_BODY for a cut msgpack body."""
    codec = Codec(None)
    data = encode(codec)
    body_start = HEADER_BYTES + len(CHANNEL)
    for length in range(len(data)):
        if length < HEADER_BYTES:
            expected = Reason.TRUNCATED
        elif length <= body_start:
            expected = Reason.BAD_HEADER
        else:
            expected = Reason.BAD_BODY
        assert reason_of(codec, data[:length]) is expected, length


def test_an_oversized_message_is_rejected_before_any_work() -> None:
    """A message over the receiver's limit is OVERSIZED, even if genuinely signed."""
    big = m.SurfaceProfile(1, 0.0, tuple(float(i) for i in range(300)), ())
    data = Codec(keyring()).encode(b"SURFACE_PROFILE", big, SOURCE, 1, 0, 0)
    assert reason_of(Codec(keyring(), max_message_bytes=len(data) - 1), data) is Reason.OVERSIZED
    assert Codec(keyring(), max_message_bytes=len(data)).open(data).seq == 1


def test_encoding_an_oversized_message_is_a_local_error() -> None:
    """The sender refuses to build a message over its limit (ValueError, not a datagram)."""
    big = m.SurfaceProfile(1, 0.0, tuple(float(i) for i in range(300)), ())
    with pytest.raises(ValueError, match="limit"):
        Codec(keyring(), max_message_bytes=1000).encode(b"SURFACE_PROFILE", big, SOURCE, 1, 0, 0)


@pytest.mark.parametrize("version", [0, 2, 0xFF])
def test_a_wrong_version_is_bad_version(version: int) -> None:
    """Any version byte other than ours is BAD_VERSION (checked before the MAC), signed or not."""
    for codec in (Codec(keyring()), Codec(None)):
        data = with_byte(encode(codec), VERSION_AT, version)
        assert reason_of(codec, data) is Reason.BAD_VERSION
    assert VERSION == 1


@pytest.mark.parametrize("magic", [b"RC", b"BR", b"\x00\x00", b"rb"])
def test_bad_magic_is_bad_magic(magic: bytes) -> None:
    """Anything but "RB" in the first two bytes is BAD_MAGIC, signed or not."""
    for codec in (Codec(keyring()), Codec(None)):
        assert reason_of(codec, magic + encode(codec)[2:]) is Reason.BAD_MAGIC


@pytest.mark.parametrize("flags", [FLAG_FRAGMENT, FLAG_SIGNED | FLAG_FRAGMENT, 0x04, 0x80, 0xFF])
def test_unknown_or_fragment_flags_on_a_whole_message_are_bad_header(flags: int) -> None:
    """A whole message may only carry the SIGNED flag; any other bit is BAD_HEADER."""
    for keys in (keyring(), None):
        assert reason_of(Codec(keys), seal(msgpack.packb([1.0, 2.0]), keys=keys, flags=flags)) is Reason.BAD_HEADER


@pytest.mark.parametrize("keys", [keyring(), None], ids=["signed", "unsigned"])
def test_bad_channel_fields_are_bad_header(keys: Keyring | None) -> None:
    """Genuinely signed but malformed channel fields are BAD_HEADER: empty, over 64 bytes,
    longer than the message, non-ASCII, or leaving no body."""
    codec = Codec(keys)
    body = msgpack.packb([1.0, 2.0])
    assert reason_of(codec, seal(body, keys=keys, channel=b"", type_id=12)) is Reason.BAD_HEADER
    assert reason_of(codec, seal(body, keys=keys, channel=b"C" * 65, type_id=12)) is Reason.BAD_HEADER
    assert reason_of(codec, seal(body, keys=keys, channel=b"\xc3\xa9t\xc3\xa9", type_id=12)) is Reason.BAD_HEADER
    assert reason_of(codec, seal(b"", keys=keys, channel=b"WHEEL_SPEED", type_id=12)) is Reason.BAD_HEADER
    # A channel length past the end: a signed message then has no room left for its tag.
    past_end = seal(body, keys=keys, channel=b"AB", channel_len=60, type_id=12)
    assert reason_of(codec, past_end) is (Reason.TRUNCATED if keys else Reason.BAD_HEADER)
    # The same body under a well-formed header is fine: only the channel fields were wrong.
    assert decode_body(12, codec.open(seal(body, keys=keys, channel=b"WHEEL_SPEED", type_id=12)).body) == (1.0, 2.0)


def test_header_only_and_empty_datagrams_are_truncated() -> None:
    """Datagrams shorter than the fixed header are TRUNCATED, and so is a signed one without a tag."""
    codec = Codec(keyring())
    for data in (b"", b"R", b"RB", HEADER.pack(b"RB", VERSION, FLAG_SIGNED, 10, 1, 1, 0, 0, 0, 0, 0)[:-1]):
        assert reason_of(codec, data) is Reason.TRUNCATED
    head_only = HEADER.pack(b"RB", VERSION, FLAG_SIGNED, 10, 1, 1, 3, 0, 0, 0, 0) + b"IMU"
    assert reason_of(codec, head_only) is Reason.TRUNCATED


def test_rejections_after_the_header_name_the_source() -> None:
    """Errors found once the header is parsed carry the claimed source id, for statistics."""
    signed = Codec(keyring())
    cases = [
        (signed, with_byte(encode(signed), VERSION_AT, 9)),
        (signed, encode(Codec(None))),
        (signed, encode(Codec(keyring(5)))),
        (signed, encode(Codec(Keyring({1: WRONG_KEY}, 1)))),
    ]
    for codec, data in cases:
        with pytest.raises(ProtocolError) as caught:
            codec.open(data)
        assert caught.value.source_id == SOURCE, caught.value


@pytest.mark.parametrize("name", ["", "a b", "é", "x" * 65, "semi;colon", "new\nline"])
def test_invalid_channel_names_are_refused_locally(name: str) -> None:
    """check_channel refuses names outside 1-64 of [A-Za-z0-9_./-] with ValueError."""
    with pytest.raises(ValueError):
        check_channel(name)


def test_valid_channel_names_are_their_ascii_bytes() -> None:
    """check_channel returns the wire bytes of a valid name."""
    assert check_channel("OBSTACLES_LIDAR") == b"OBSTACLES_LIDAR"
    assert check_channel("a/b.c-d_" + "x" * 56) == ("a/b.c-d_" + "x" * 56).encode()
