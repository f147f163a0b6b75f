"""Sans-IO message codec: typed message <-> signed datagram bytes. No sockets, no clock.

Layout (little-endian; SPEC.md is normative)::

    magic "RB" | version u8 | flags u8 | type_id u16 | source_id u16 | key_id u16 |
    channel_len u8 | reserved u8 | seq u64 | t_meas_ns i64 | t_pub_ns i64 |
    channel (channel_len bytes, ASCII) | body (msgpack array) |
    signature (64 B Ed25519, if SIGNATURE) | tag (16 B, if SIGNED)

The signature covers header, channel and body; the tag covers everything before it, the
signature included. SIGNATURE comes only with SIGNED.
"""

from __future__ import annotations

import re
import struct
from typing import Any, NamedTuple

import msgpack

from protocol.auth import TAG_BYTES, Keyring
from protocol.errors import ProtocolError, Reason
from protocol.fastpath import native
from protocol.schema import info_for_class, info_for_id
from protocol.signing import SIGNATURE_BYTES, Signed, Signer

_new = tuple.__new__
MAGIC = b"RB"
VERSION = 1
FLAGS_AT = 3  # byte offset of the flags, in a message's header and a fragment's alike
FLAG_SIGNED = 0x01
FLAG_FRAGMENT = 0x02
FLAG_SIGNATURE = 0x04
MESSAGE_FLAGS = FLAG_SIGNED | FLAG_SIGNATURE
HEADER = struct.Struct("<2sBBHHHBBQqq")
HEADER_BYTES = HEADER.size  # 36
HEADER_PREFIX = struct.Struct("<2sBBHHHBB")  # magic .. reserved
HEADER_TIMES = struct.Struct("<Qqq")  # seq, t_meas_ns, t_pub_ns
MAX_CHANNEL_BYTES = 64
CHANNEL_PATTERN = re.compile(r"[A-Za-z0-9_./-]{1,64}")
DEFAULT_MAX_MESSAGE_BYTES = 256 * 1024


class Envelope(NamedTuple):
    """Header of a received message, handed to subscribers beside the typed body."""

    channel: str
    source_id: int
    seq: int
    t_meas_ns: int
    t_pub_ns: int
    recv_ns: int
    type_id: int
    size: int
    recv_local_ns: int
    # The message's Ed25519 signature and what it covers; None when it carries none.
    signed: Signed | None = None


class Opened(NamedTuple):
    """An authenticated, not yet body-decoded message."""

    type_id: int
    source_id: int
    seq: int
    t_meas_ns: int
    t_pub_ns: int
    channel: str
    body: memoryview


def check_channel(channel: str) -> bytes:
    """Channel names are 1-64 chars of [A-Za-z0-9_./-]; returns the wire bytes."""
    if not CHANNEL_PATTERN.fullmatch(channel):
        raise ValueError(f"invalid channel name {channel!r}: use 1-64 of [A-Za-z0-9_./-]")
    return channel.encode("ascii")


class Codec:
    """Encodes and authenticates messages for one deployment.

    ``keyring=None`` is the explicit unsigned mode: messages go out unsigned and unsigned ones are
    accepted. With a keyring, unsigned or wrongly signed messages are rejected.
    """

    def __init__(self, keyring: Keyring | None, max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES) -> None:
        self.keyring = keyring
        self.max_message_bytes = max_message_bytes
        self._packer = msgpack.Packer(use_bin_type=True)
        self._flags = FLAG_SIGNED if keyring else 0
        self._key_id = keyring.active if keyring else 0
        # What the C fast path signs with and verifies against, by key id (None: unsigned mode).
        self.verifying_macs = None
        self._signing_mac = None
        if keyring is not None and native is not None:
            self.verifying_macs = {key_id: native.Mac(key) for key_id, key in keyring.keys.items()}
            self._signing_mac = self.verifying_macs[keyring.active]
        # The first 12 header bytes are fixed per (type, channel, source, flags): packed once.
        self._prefixes: dict[tuple[type, bytes, int, int], bytes] = {}

    def encode(
        self,
        channel: bytes,
        msg: Any,
        source_id: int,
        seq: int,
        t_meas_ns: int,
        t_pub_ns: int,
        signer: Signer | None = None,
    ) -> bytes:
        """Serialise ``msg`` (a registered message) into one message; may exceed a datagram.
        With ``signer`` it carries that source's Ed25519 signature (needs a keyring: SIGNED)."""
        if signer is not None and self.keyring is None:
            raise ValueError("a signature needs the signed mode: the tag covers it")
        flags = self._flags | FLAG_SIGNATURE if signer is not None else self._flags
        key = (type(msg), channel, source_id, flags)
        prefix = self._prefixes.get(key)
        if prefix is None:
            type_id = info_for_class(type(msg)).type_id
            prefix = self._prefixes[key] = HEADER_PREFIX.pack(
                MAGIC, VERSION, flags, type_id, source_id, self._key_id, len(channel), 0
            )
        if signer is not None:
            data = b"".join((prefix, HEADER_TIMES.pack(seq, t_meas_ns, t_pub_ns), channel, self._packer.pack(msg)))
            data += signer.sign(data)
            data += self.keyring.sign(data)  # type: ignore[union-attr]
        elif native is not None:
            data = native.seal(prefix, seq, t_meas_ns, t_pub_ns, channel, self._packer.pack(msg), self._signing_mac)
        else:
            data = b"".join((prefix, HEADER_TIMES.pack(seq, t_meas_ns, t_pub_ns), channel, self._packer.pack(msg)))
            if self.keyring is not None:
                data += self.keyring.sign(data)
        if len(data) > self.max_message_bytes:
            raise ValueError(f"{type(msg).__name__} is {len(data)} B, over the {self.max_message_bytes} B limit")
        return data

    def open(self, data: bytes) -> Opened:
        """Check framing and authenticity of one complete message; raise ProtocolError if bad."""
        if native is not None:
            # Raises bad_mac itself for a tag it found wrong: no tag is computed twice.
            opened: Opened | None = native.open(data, Opened, self.verifying_macs, self.max_message_bytes)
            if opened is not None:
                return opened
            # Refused before the tag, or unusual (signed in the unsigned mode, not bytes): Python says which.
        size = len(data)
        if size < HEADER_BYTES:
            raise ProtocolError(Reason.TRUNCATED, f"{size} B is shorter than the header")
        if size > self.max_message_bytes:
            raise ProtocolError(Reason.OVERSIZED, f"{size} B")
        (magic, version, flags, type_id, source_id, key_id, channel_len, _reserved, seq, t_meas_ns, t_pub_ns) = (
            HEADER.unpack_from(data)
        )
        if magic != MAGIC:
            raise ProtocolError(Reason.BAD_MAGIC)
        if version != VERSION:
            raise ProtocolError(Reason.BAD_VERSION, f"version {version}", source_id)
        # SIGNATURE needs SIGNED: the tag, checked first, covers the signature, so no one
        # without the MAC key can make a receiver spend a signature check.
        if flags & ~MESSAGE_FLAGS or (flags & FLAG_SIGNATURE and not flags & FLAG_SIGNED):
            raise ProtocolError(Reason.BAD_HEADER, f"flags {flags:#x}", source_id)
        body_start = HEADER_BYTES + channel_len
        view = memoryview(data)
        if flags & FLAG_SIGNED:
            tag_start = size - TAG_BYTES
            body_end = tag_start - SIGNATURE_BYTES if flags & FLAG_SIGNATURE else tag_start
            if body_end < body_start:
                raise ProtocolError(Reason.TRUNCATED, "no room for the tag (and signature)", source_id)
            if self.keyring is not None:
                if key_id not in self.keyring.keys:
                    raise ProtocolError(Reason.UNKNOWN_KEY, f"key id {key_id}", source_id)
                if not self.keyring.verify(key_id, view[:tag_start], view[tag_start:]):
                    raise ProtocolError(Reason.BAD_MAC, "", source_id)
        else:
            if self.keyring is not None:
                raise ProtocolError(Reason.UNSIGNED, "", source_id)
            body_end = size
        if not 0 < channel_len <= MAX_CHANNEL_BYTES or body_start >= body_end:
            raise ProtocolError(Reason.BAD_HEADER, f"channel length {channel_len}", source_id)
        try:
            channel = data[HEADER_BYTES:body_start].decode("ascii")
        except UnicodeDecodeError:
            raise ProtocolError(Reason.BAD_HEADER, "channel is not ASCII", source_id) from None
        # tuple.__new__ skips the NamedTuple's Python-level __new__: this runs for every datagram.
        return _new(Opened, (type_id, source_id, seq, t_meas_ns, t_pub_ns, channel, view[body_start:body_end]))


def body_span(data: bytes | memoryview) -> tuple[int, int]:
    """Where the body of a well-formed message (one that passed :meth:`Codec.open`, e.g. from a
    recording) starts and ends: after header and channel, before signature and tag."""
    flags = data[3]
    end = len(data) - TAG_BYTES if flags & FLAG_SIGNED else len(data)
    if flags & FLAG_SIGNATURE:
        end -= SIGNATURE_BYTES
    return HEADER_BYTES + data[10], end  # byte 10: the channel name's length


def signed_part(data: bytes) -> Signed | None:
    """The signature of a message that passed :meth:`Codec.open`, with the bytes it covers;
    None when it carries none."""
    if not data[3] & FLAG_SIGNATURE:
        return None
    end = len(data) - TAG_BYTES - SIGNATURE_BYTES
    view = memoryview(data)
    return Signed(view[:end], view[end : end + SIGNATURE_BYTES])


def unpack_body(body: bytes | memoryview, source_id: int | None = None) -> Any:
    """msgpack body -> raw arrays (tuples); ProtocolError if it is not valid msgpack."""
    try:
        return msgpack.unpackb(body, use_list=False, raw=False, strict_map_key=True)
    except (ValueError, msgpack.UnpackException) as exc:
        # msgpack raises ExtraData/FormatError/StackError (ValueError subclasses) or
        # UnicodeDecodeError (also a ValueError) for malformed input.
        raise ProtocolError(Reason.BAD_BODY, f"msgpack: {type(exc).__name__}", source_id) from None
    except TypeError:
        raise ProtocolError(Reason.BAD_BODY, "msgpack: unhashable map key", source_id) from None


def decode_body(type_id: int, body: bytes | memoryview, source_id: int | None = None) -> Any:
    """msgpack body -> typed message, validated; ProtocolError on anything malformed."""
    try:
        return info_for_id(type_id).decode(unpack_body(body, source_id))
    except ProtocolError as exc:
        exc.source_id = source_id
        raise
