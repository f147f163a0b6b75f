"""Keys and authentication: keyed BLAKE2b-128 over a message's header and body, keyed
BLAKE2b-64 over a fragment's header and data; and the signing keys of command authority.

Keyed BLAKE2b (RFC 7693) is a MAC by construction, needs no HMAC wrapper, and costs ~1 us for a
300 B message here against ~2.4 us for HMAC-SHA256. The deployment's key file (the master file)::

    # rascal bus keys (keep private: chmod 600)
    active = 1
    signing_master = "<64 hex digits: 32 random bytes>"
    [keys]
    1 = "<64 hex digits: 32 random bytes>"

Several MAC keys allow rotation: receivers accept any listed key id, senders tag with ``active``.
``signing_master`` derives every source's Ed25519 key (protocol/signing.py); it is separate from
the MAC keys, so holding those derives nothing. A file without it is a legacy file: MAC only, no
signatures, no authority.

A module key file, which the supervisor writes for each module it starts, holds the MAC keys, the
module's own ``source_id`` and ``signing_seed`` and the authority it enforces: ``[public]`` (source
id -> Ed25519 public key, hex) for every source with authority, and ``[authority]`` (governed
channel -> source ids). Never the master, nor another source's seed.

A key file that another user owns, or that group or others may access, is refused.
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import os
import secrets
import stat
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from protocol.authority import GOVERNED_CHANNELS, Authority
from protocol.signing import PUBLIC_KEY_BYTES, SEED_BYTES, Signer, derive_seed

TAG_BYTES = 16
# Each fragment's own tag: short, since a forger gets one online guess per datagram, and a
# different digest size makes it a different function from the message tag (RFC 7693 2.5).
FRAGMENT_TAG_BYTES = 8
KEY_BYTES = 32
SIGNING_MASTER_BYTES = 32
MODULE_ENTRIES = ("source_id", "signing_seed", "public", "authority")
DEFAULT_KEY_FILE = Path(os.environ.get("XDG_CONFIG_HOME", Path.home() / ".config")) / "rascal" / "bus.key"


class KeyFileError(ValueError):
    """The key file is missing, malformed or open to other users; the message names the file and
    the entry or the fix."""


# repr=False: a Keyring's repr reaches logs, tracebacks and test output, so it is written by hand.
@dataclass(frozen=True, repr=False)
class Keyring:
    """MAC keys by id (1..65535) and the id used for tags; and which signing keys this node holds:
    the master (derives every source's: operator tools, the supervisor, tests), or one source's
    own seed with the authority it enforces (a module key file), or none (a legacy file)."""

    # Immutable bytes, held as long as the process runs: Python cannot wipe them.
    keys: dict[int, bytes]
    active: int
    signing_master: bytes | None = None
    source_id: int | None = None
    signing_seed: bytes | None = None
    authority: Authority | None = None
    # Keyed hash states by key id, made once; copy() one before use.
    keyed: dict[int, hashlib.blake2b] = field(init=False, repr=False, compare=False)
    fragment_keyed: dict[int, hashlib.blake2b] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.active not in self.keys:
            raise KeyFileError(f"active key id {self.active} is not among the keys {sorted(self.keys)}")
        own = (self.source_id, self.signing_seed, self.authority)
        if any(part is not None for part in own) and (None in own or self.signing_master is not None):
            raise KeyFileError("a module keyring has source_id, signing_seed and authority, and no signing_master")
        # Keying BLAKE2b costs a compression of the key block; copying a keyed state is cheaper
        # (~0.4 us a message on the 80 k msg/s path).
        keyed = {key_id: hashlib.blake2b(key=key, digest_size=TAG_BYTES) for key_id, key in self.keys.items()}
        object.__setattr__(self, "keyed", keyed)
        fragment_keyed = {
            key_id: hashlib.blake2b(key=key, digest_size=FRAGMENT_TAG_BYTES) for key_id, key in self.keys.items()
        }
        object.__setattr__(self, "fragment_keyed", fragment_keyed)

    def __repr__(self) -> str:
        kind = ""
        if self.signing_master is not None:
            kind = ", signing master"
        elif self.source_id is not None:
            kind = f", module source_id={self.source_id}"
        return f"Keyring(key_ids={sorted(self.keys)}, active={self.active}{kind})"

    @property
    def legacy(self) -> bool:
        """A key file from before command authority: MAC keys only."""
        return self.signing_master is None and self.signing_seed is None

    def signer(self, source_id: int) -> Signer | None:
        """The signing key of ``source_id``, if this keyring holds it."""
        if self.signing_master is not None:
            return Signer(source_id, derive_seed(self.signing_master, source_id))
        if self.signing_seed is not None and source_id == self.source_id:
            return Signer(source_id, self.signing_seed)
        return None

    def for_module(self, source_id: int, authority: Authority) -> Keyring:
        """What a module key file holds for ``source_id``: the MAC keys, that source's own seed
        and the authority it enforces (needs the master)."""
        if self.signing_master is None:
            raise KeyFileError("only a key file with signing_master can derive module keys")
        seed = derive_seed(self.signing_master, source_id)
        return Keyring(dict(self.keys), self.active, None, source_id, seed, authority)

    def sign(self, data: bytes | memoryview) -> bytes:
        hasher = self.keyed[self.active].copy()
        hasher.update(data)
        return hasher.digest()

    def verify(self, key_id: int, data: bytes | memoryview, tag: bytes | memoryview) -> bool:
        keyed = self.keyed.get(key_id)
        if keyed is None:
            return False
        hasher = keyed.copy()
        hasher.update(data)
        return hmac.compare_digest(hasher.digest(), tag)

    def sign_fragment(self, data: bytes | memoryview) -> bytes:
        return _tag(self.fragment_keyed[self.active], data)

    def verify_fragment(self, key_id: int, data: bytes | memoryview, tag: bytes | memoryview) -> bool:
        keyed = self.fragment_keyed.get(key_id)
        return keyed is not None and hmac.compare_digest(_tag(keyed, data), tag)

    @classmethod
    def generate(cls, key_id: int = 1) -> Keyring:
        return cls({key_id: secrets.token_bytes(KEY_BYTES)}, key_id, secrets.token_bytes(SIGNING_MASTER_BYTES))


def _tag(keyed: hashlib.blake2b, data: bytes | memoryview) -> bytes:
    hasher = keyed.copy()
    hasher.update(data)
    return hasher.digest()


def load_keyring(path: Path) -> Keyring:
    """Read a master, module or legacy key file, naming the file and the offending entry on any error."""
    try:
        # TOML is UTF-8 by definition, whatever the locale says.
        doc = tomllib.loads(_read_private(path).decode("utf-8"))
    except FileNotFoundError:
        raise KeyFileError(f"{path}: key file not found (create one with `rascal keygen {path}`)") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise KeyFileError(f"{path}: not valid TOML: {exc}") from exc
    unknown = set(doc) - {"active", "keys", "signing_master", *MODULE_ENTRIES}
    if unknown:
        raise KeyFileError(
            f"{path}: unknown key(s) {sorted(unknown)}; expected 'active', [keys] and 'signing_master' "
            f"(a master file) or {list(MODULE_ENTRIES)} (a module key file)"
        )
    entries = doc.get("keys")
    if not isinstance(entries, dict) or not entries:
        raise KeyFileError(f"{path}: [keys] table with at least one key is required")
    keys: dict[int, bytes] = {}
    for name, value in entries.items():
        key_id = _source_or_key_id(path, f"keys.{name}", name, keys)
        keys[key_id] = _hex_bytes(path, f"keys.{name}", value, KEY_BYTES)
    active = doc.get("active", min(keys))
    # bool is an int subclass, and True == 1: "active = true" must not pass as key id 1.
    if not isinstance(active, int) or isinstance(active, bool) or active not in keys:
        raise KeyFileError(f"{path}: active = {active!r} is not one of the key ids {sorted(keys)}")
    module_entries = sorted(set(doc) & set(MODULE_ENTRIES))
    if "signing_master" in doc:
        if module_entries:
            raise KeyFileError(f"{path}: signing_master: a master file holds no {module_entries}")
        return Keyring(keys, active, _hex_bytes(path, "signing_master", doc["signing_master"], SIGNING_MASTER_BYTES))
    if module_entries:
        return _module_keyring(path, doc, keys, active)
    return Keyring(keys, active)


def _module_keyring(path: Path, doc: dict[str, Any], keys: dict[int, bytes], active: int) -> Keyring:
    missing = [name for name in MODULE_ENTRIES if name not in doc]
    if missing:
        raise KeyFileError(f"{path}: {missing[0]}: missing (a module key file needs {list(MODULE_ENTRIES)})")
    source_id = doc["source_id"]
    if not isinstance(source_id, int) or isinstance(source_id, bool) or not 0 < source_id < 0x10000:
        raise KeyFileError(f"{path}: source_id = {source_id!r}: expected an integer 1..65535")
    seed = _hex_bytes(path, "signing_seed", doc["signing_seed"], SEED_BYTES)
    public: dict[int, bytes] = {}
    for name, value in _table(path, doc, "public").items():
        public[_source_or_key_id(path, f"public.{name}", name, public)] = _hex_bytes(
            path, f"public.{name}", value, PUBLIC_KEY_BYTES
        )
    table: dict[str, frozenset[int]] = {}
    for channel, sources in _table(path, doc, "authority").items():
        if channel not in GOVERNED_CHANNELS:
            raise KeyFileError(f"{path}: authority.{channel}: not a governed channel {list(GOVERNED_CHANNELS)}")
        if not isinstance(sources, list) or not all(
            isinstance(sid, int) and not isinstance(sid, bool) and 0 < sid < 0x10000 for sid in sources
        ):
            raise KeyFileError(f"{path}: authority.{channel}: expected a list of source ids 1..65535")
        unknown = sorted(set(sources) - set(public))
        if unknown:
            raise KeyFileError(f"{path}: authority.{channel}: no [public] key for source(s) {unknown}")
        table[channel] = frozenset(sources)
    return Keyring(keys, active, None, source_id, seed, Authority(table, public))


def _table(path: Path, doc: dict[str, Any], name: str) -> dict[str, Any]:
    value = doc[name]
    if not isinstance(value, dict):
        raise KeyFileError(f"{path}: [{name}]: expected a table")
    return value


def _source_or_key_id(path: Path, where: str, name: str, seen: dict[int, bytes]) -> int:
    # isascii: str.isdigit() also accepts digits int() cannot parse, such as "²".
    if not (name.isascii() and name.isdigit()) or not 0 < int(name) < 0x10000:
        raise KeyFileError(f"{path}: {where}: id must be an integer 1..65535")
    if int(name) in seen:
        # "1" and "01" are different TOML keys but the same id: never pick one silently.
        raise KeyFileError(f"{path}: {where}: id {int(name)} is given twice")
    return int(name)


def _hex_bytes(path: Path, where: str, value: Any, size: int) -> bytes:
    try:
        raw = bytes.fromhex(value) if isinstance(value, str) else b""
    except ValueError:
        raw = b""
    if len(raw) != size:
        raise KeyFileError(f"{path}: {where}: expected {size * 2} hex digits")
    return raw


def _read_private(path: Path) -> bytes:
    """The key file's bytes, once it is known to be a regular file that only this user can read
    or change. The open file is checked, not the path, so the file checked is the file read."""
    # O_NONBLOCK: a FIFO in the key file's place must fail the check, not hang the open.
    fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC | os.O_NONBLOCK)
    try:
        _check_private(path, os.fstat(fd))
        with open(fd, "rb", closefd=False) as file:
            return file.read()
    finally:
        os.close(fd)


def _check_private(path: Path, status: os.stat_result) -> None:
    if not stat.S_ISREG(status.st_mode):
        raise KeyFileError(f"{path}: not a regular file")
    uid = os.geteuid()
    if status.st_uid != uid:
        # Its owner can change the keys, and root is no exception: root reads only its own key file.
        raise KeyFileError(
            f"{path}: key file is owned by uid {status.st_uid}, not by uid {uid} that uses it "
            f"(make it this user's own: `chown {uid} {path}`)"
        )
    mode = stat.S_IMODE(status.st_mode)
    if mode & 0o077:
        raise KeyFileError(
            f"{path}: key file mode {mode:04o} gives group or others access to the keys "
            f"(make it owner-only: `chmod 600 {path}`)"
        )


def write_keyring(path: Path, keyring: Keyring, *, overwrite: bool = False) -> None:
    """Write a key file readable only by its owner; atomically, so concurrent readers never see
    half a file. Without ``overwrite`` an existing file wins (FileExistsError)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(16)}.tmp")
    # A fresh file under a name nobody can guess: a file or symlink planted at a predictable name
    # would be truncated, or followed to write the keys wherever its planter chose.
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
    try:
        with os.fdopen(fd, "w") as out:
            out.write("\n".join(_key_file_lines(keyring)) + "\n")
        if overwrite:
            os.replace(tmp, path)
        else:
            os.link(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _key_file_lines(keyring: Keyring) -> list[str]:
    authority = keyring.authority
    if authority is None:
        lines = ["# rascal bus keys (keep private)", f"active = {keyring.active}"]
    else:
        lines = [f"# rascal module key file of source {keyring.source_id}: its own signing key only (keep private)"]
        lines += [f"active = {keyring.active}", f"source_id = {keyring.source_id}"]
        lines.append(f'signing_seed = "{keyring.signing_seed.hex()}"')  # type: ignore[union-attr]
    if keyring.signing_master is not None:
        lines.append(f'signing_master = "{keyring.signing_master.hex()}"')
    lines.append("[keys]")
    lines += [f'{key_id} = "{key.hex()}"' for key_id, key in sorted(keyring.keys.items())]
    if authority is not None:
        lines.append("[public]")
        lines += [f'{source_id} = "{key.hex()}"' for source_id, key in sorted(authority.public_keys.items())]
        lines.append("[authority]")
        lines += [f"{channel} = {sorted(sources)}" for channel, sources in authority.table.items()]
    return lines


def default_keyring() -> Keyring:
    """The key for localhost use: ``$RASCAL_KEY_FILE``, else the per-user default, created on first use."""
    named = os.environ.get("RASCAL_KEY_FILE")
    if named:
        return load_keyring(Path(named))
    if not DEFAULT_KEY_FILE.exists():
        with contextlib.suppress(FileExistsError):  # another process created it first: use theirs
            write_keyring(DEFAULT_KEY_FILE, Keyring.generate())
    return load_keyring(DEFAULT_KEY_FILE)
