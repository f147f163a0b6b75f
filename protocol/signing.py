"""Ed25519 signing keys per source, derived from the deployment's signing master.

A source's private key is the Ed25519 key whose 32-byte seed is

    BLAKE2b(key = signing_master, person = b"rascal-ed25519", digest_size = 32,
            data = source_id as u16 little-endian)

so whoever holds the master derives every source's key, while a source's own seed tells nothing
about the master or any other source's seed (BLAKE2b is a PRF under its key). Unlike the MAC key,
which every node shares and so could use to forge anything it verifies, a receiver holds only
public keys: it checks a command's signature but cannot make one.
"""

from __future__ import annotations

import hashlib
from typing import NamedTuple

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

SIGNATURE_BYTES = 64
SEED_BYTES = 32
PUBLIC_KEY_BYTES = 32
KDF_PERSON = b"rascal-ed25519"


class Signed(NamedTuple):
    """A received message's signature and the bytes it covers (header, channel and body)."""

    data: bytes | memoryview
    signature: bytes | memoryview


def derive_seed(signing_master: bytes, source_id: int) -> bytes:
    """The Ed25519 seed of ``source_id`` (the KDF above)."""
    if not 0 < source_id < 0x10000:
        raise ValueError(f"source_id {source_id} out of range 1..65535")
    return hashlib.blake2b(
        source_id.to_bytes(2, "little"), key=signing_master, person=KDF_PERSON, digest_size=SEED_BYTES
    ).digest()


class Signer:
    """One source's private key. Its repr names the source only."""

    __slots__ = ("_key", "source_id")

    def __init__(self, source_id: int, seed: bytes) -> None:
        self.source_id = source_id
        self._key = Ed25519PrivateKey.from_private_bytes(seed)

    def __repr__(self) -> str:
        return f"Signer(source_id={self.source_id})"

    def sign(self, data: bytes | memoryview) -> bytes:
        return self._key.sign(data)

    @property
    def public_key(self) -> bytes:
        return self._key.public_key().public_bytes_raw()


def public_key_of(signing_master: bytes, source_id: int) -> bytes:
    """The raw 32-byte public key of ``source_id``."""
    return Signer(source_id, derive_seed(signing_master, source_id)).public_key


class Verifier:
    """One source's public key, parsed once."""

    __slots__ = ("_key",)

    def __init__(self, public_key: bytes) -> None:
        self._key = Ed25519PublicKey.from_public_bytes(public_key)

    def verify(self, signed: Signed) -> bool:
        try:
            self._key.verify(signed.signature, signed.data)
        except InvalidSignature:
            return False
        return True
