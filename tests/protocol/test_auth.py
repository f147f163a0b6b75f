"""Keys: the MAC primitive, key rotation, and the key file (round trip, permissions, errors)."""

from __future__ import annotations

import hashlib
import os
import stat
from pathlib import Path

import pytest

from protocol import auth, fastpath
from protocol.auth import KEY_BYTES, TAG_BYTES, KeyFileError, Keyring, load_keyring, write_keyring
from tests.protocol.wire_samples import key_bytes, keyring

HEX_1 = key_bytes(1).hex()
HEX_2 = key_bytes(2).hex()


def write_key_file(path: Path, content: str | bytes) -> None:
    """A hand-written key file with the owner-only mode load_keyring requires."""
    path.write_bytes(content.encode() if isinstance(content, str) else content)
    path.chmod(0o600)


# -- the MAC -----------------------------------------------------------------------------------


def test_a_tag_verifies_only_with_the_same_key_and_data() -> None:
    """sign/verify agree for the signing key; another key, id, data or tag fails verification."""
    ring = keyring(1, 2)
    data = b"header and body" * 7
    tag = ring.sign(data)
    assert len(tag) == TAG_BYTES
    assert ring.verify(1, data, tag)
    assert ring.verify(1, memoryview(data), memoryview(tag))
    assert not ring.verify(2, data, tag)
    assert not ring.verify(3, data, tag)
    assert not ring.verify(1, data + b"!", tag)
    assert not ring.verify(1, data, tag[:-1])
    assert not ring.verify(1, data, bytes([tag[0] ^ 1]) + tag[1:])


def test_the_active_key_signs() -> None:
    """Keyrings with the same keys but another active id produce tags of that id's key."""
    data = b"x" * 40
    assert keyring(1, 2, active=2).sign(data) == keyring(2).sign(data) != keyring(1).sign(data)


def test_an_active_id_missing_from_the_keys_is_refused() -> None:
    """Keyring(keys, active) with active not among the keys raises KeyFileError."""
    with pytest.raises(KeyFileError, match="active key id 3"):
        Keyring({1: key_bytes(1)}, 3)


def test_generated_keys_are_random_32_byte_keys() -> None:
    """Keyring.generate makes a fresh 32-byte key under the requested id, different every time."""
    first, second = Keyring.generate(), Keyring.generate(9)
    assert (first.active, list(first.keys)) == (1, [1])
    assert (second.active, list(second.keys)) == (9, [9])
    assert len(first.keys[1]) == KEY_BYTES
    assert first.keys[1] != second.keys[9]


def test_a_keyring_never_shows_its_keys() -> None:
    """repr and str name the key ids and the active one, and nothing else."""
    ring = keyring(2, 1, active=2)
    assert repr(ring) == str(ring) == f"{ring}" == "Keyring(key_ids=[1, 2], active=2)"


@pytest.mark.skipif(fastpath.native is None, reason=f"the bus runs {fastpath.describe()}")
def test_c_macs_are_wiped_and_freed_many_times_over() -> None:
    """Every Mac freed runs the dealloc that wipes its keyed state; keyed, freed and keyed again,
    Macs still tag as hashlib does, the empty message (tagged at keying) included."""
    mac_type = fastpath.native.Mac
    for i in range(20_000):
        key = key_bytes(i % 7 + 1)
        mac = mac_type(key)
        data = bytes(i % 300)
        assert mac.digest(data) == hashlib.blake2b(data, key=key, digest_size=TAG_BYTES).digest()
        mac.__init__(key_bytes(9))  # keyed again in place
        assert mac.digest(b"") == hashlib.blake2b(b"", key=key_bytes(9), digest_size=TAG_BYTES).digest()
        del mac
        mac_type.__new__(mac_type)  # never keyed (all zeros), freed all the same


# -- the key file ------------------------------------------------------------------------------


def test_write_then_load_round_trips(tmp_path: Path) -> None:
    """load_keyring(write_keyring(ring)) has the same keys and active id."""
    ring = Keyring({1: key_bytes(1), 2: key_bytes(2), 65535: key_bytes(65535)}, 2)
    path = tmp_path / "sub" / "bus.key"
    write_keyring(path, ring)
    assert load_keyring(path) == ring


def test_the_key_file_is_private(tmp_path: Path) -> None:
    """The written key file has mode 0600, whatever the umask, and no temporary file is left."""
    path = tmp_path / "bus.key"
    old_umask = os.umask(0o000)
    try:
        write_keyring(path, keyring())
    finally:
        os.umask(old_umask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert [p.name for p in tmp_path.iterdir()] == ["bus.key"]


@pytest.mark.parametrize("planted", ["symlink", "dangling symlink", "file"])
def test_nothing_planted_at_the_temporary_name_is_followed_or_truncated(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, planted: str
) -> None:
    """Were the temporary name guessed, a symlink or file planted there makes the write fail
    (FileExistsError) without writing through it or truncating it, and it is left in place."""
    monkeypatch.setattr(auth.secrets, "token_hex", lambda nbytes=None: "guessed")
    planted_at = tmp_path / ".bus.key.guessed.tmp"
    target = tmp_path / "attacker-reads-this"
    if planted == "symlink":
        target.write_text("the planter's file\n")
    if planted == "file":
        planted_at.write_text("the planter's file\n")
    else:
        planted_at.symlink_to(target)
    with pytest.raises(FileExistsError):
        write_keyring(tmp_path / "bus.key", keyring())
    assert not (tmp_path / "bus.key").exists()
    assert os.path.lexists(planted_at)
    if planted == "dangling symlink":
        assert not target.exists()
    else:
        assert (target if planted == "symlink" else planted_at).read_text() == "the planter's file\n"


def test_temporary_names_are_unpredictable(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each write takes a fresh random name for its temporary file (and leaves none behind)."""
    names: list[str] = []
    real_open = os.open

    def recording_open(path: Path, flags: int, mode: int = 0o777) -> int:
        names.append(Path(path).name)
        return real_open(path, flags, mode)

    monkeypatch.setattr(auth.os, "open", recording_open)
    write_keyring(tmp_path / "bus.key", keyring(1))
    write_keyring(tmp_path / "bus.key", keyring(2), overwrite=True)
    assert len(names) == len(set(names)) == 2
    assert all(len(name) >= len(".bus.key..tmp") + 32 for name in names)
    assert [p.name for p in tmp_path.iterdir()] == ["bus.key"]


def test_a_failed_write_leaves_no_temporary_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An error after the temporary file is made (here: renaming it) removes it."""

    def fail(*_: object) -> None:
        raise OSError("disk on fire")

    monkeypatch.setattr(auth.os, "replace", fail)
    with pytest.raises(OSError, match="disk on fire"):
        write_keyring(tmp_path / "bus.key", keyring(), overwrite=True)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o604, 0o620, 0o602, 0o610, 0o601, 0o666])
def test_a_key_file_that_others_can_access_is_refused(tmp_path: Path, mode: int) -> None:
    """Any group or other permission bit refuses the file, with its name, its mode and the fix."""
    path = tmp_path / "bus.key"
    write_keyring(path, keyring())
    path.chmod(mode)
    with pytest.raises(KeyFileError) as caught:
        load_keyring(path)
    assert str(caught.value) == (
        f"{path}: key file mode {mode:04o} gives group or others access to the keys "
        f"(make it owner-only: `chmod 600 {path}`)"
    )


@pytest.mark.parametrize("mode", [0o600, 0o400, 0o700])
def test_owner_only_modes_are_accepted(tmp_path: Path, mode: int) -> None:
    path = tmp_path / "bus.key"
    write_keyring(path, keyring())
    path.chmod(mode)
    assert load_keyring(path) == keyring()


def test_the_file_behind_a_symlink_is_the_file_checked(tmp_path: Path) -> None:
    """A symlink is read through, and the mode checked is its target's (a link's own is 0777)."""
    target, link = tmp_path / "real.key", tmp_path / "bus.key"
    write_keyring(target, keyring())
    link.symlink_to(target)
    assert load_keyring(link) == keyring()
    target.chmod(0o644)
    with pytest.raises(KeyFileError, match=r"mode 0644.*chmod 600"):
        load_keyring(link)


def test_a_key_file_owned_by_another_user_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Owner-only means this (effective) user's own: root included, who could read any file."""
    path = tmp_path / "bus.key"
    write_keyring(path, keyring())
    other = os.geteuid() + 1
    monkeypatch.setattr(auth.os, "geteuid", lambda: other)
    with pytest.raises(KeyFileError) as caught:
        load_keyring(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: key file is owned by uid {other - 1}, not by uid {other}")
    assert f"chown {other} {path}" in message


@pytest.mark.parametrize("kind", ["directory", "fifo"])
def test_a_key_file_that_is_not_a_regular_file_is_refused(tmp_path: Path, kind: str) -> None:
    """A directory or a FIFO (which must not hang the reader) in the key file's place is refused."""
    path = tmp_path / "bus.key"
    if kind == "directory":
        path.mkdir(mode=0o700)
    else:
        os.mkfifo(path, 0o600)
    with pytest.raises(KeyFileError, match="not a regular file") as caught:
        load_keyring(path)
    assert str(path) in str(caught.value)


def test_an_existing_key_file_is_kept_unless_overwrite(tmp_path: Path) -> None:
    """Without overwrite an existing file wins (FileExistsError); with it the file is replaced."""
    path = tmp_path / "bus.key"
    write_keyring(path, keyring(1))
    with pytest.raises(FileExistsError):
        write_keyring(path, keyring(2))
    assert load_keyring(path) == keyring(1)
    write_keyring(path, keyring(2), overwrite=True)
    assert load_keyring(path) == keyring(2)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert [p.name for p in tmp_path.iterdir()] == ["bus.key"]


def test_active_defaults_to_the_lowest_key_id(tmp_path: Path) -> None:
    """A key file without ``active`` signs with its lowest key id."""
    path = tmp_path / "bus.key"
    write_key_file(path, f'[keys]\n7 = "{HEX_2}"\n3 = "{HEX_1}"\n')
    ring = load_keyring(path)
    assert ring.active == 3
    assert ring.keys == {3: key_bytes(1), 7: key_bytes(2)}


def test_keys_may_be_written_in_upper_case_hex(tmp_path: Path) -> None:
    """Hex digits are case-insensitive."""
    path = tmp_path / "bus.key"
    write_key_file(path, f'active = 1\n[keys]\n1 = "{HEX_1.upper()}"\n')
    assert load_keyring(path).keys[1] == key_bytes(1)


# (file text, the entry the message must name)
MALFORMED = {
    "bad hex": (f'[keys]\n1 = "{"zz" * 32}"\n', "keys.1"),
    "odd hex": (f'[keys]\n1 = "{HEX_1[:-1]}"\n', "keys.1"),
    "short key": (f'[keys]\n1 = "{HEX_1[:62]}"\n', "keys.1"),
    "long key": (f'[keys]\n1 = "{HEX_1}00"\n', "keys.1"),
    "empty key": ('[keys]\n4 = ""\n', "keys.4"),
    "key not a string": ("[keys]\n1 = 12345\n", "keys.1"),
    "key is a table": (f'[keys.1]\nvalue = "{HEX_1}"\n', "keys.1"),
    "id zero": (f'[keys]\n0 = "{HEX_1}"\n', "keys.0"),
    "id too big": (f'[keys]\n65536 = "{HEX_1}"\n', "keys.65536"),
    "id negative": (f'[keys]\n"-1" = "{HEX_1}"\n', "keys.-1"),
    "id not a number": (f'[keys]\nmain = "{HEX_1}"\n', "keys.main"),
    "id not ascii digits": (f'[keys]\n"²" = "{HEX_1}"\n', "keys.²"),
    "id written twice": (f'[keys]\n1 = "{HEX_1}"\n01 = "{HEX_2}"\n', "keys.01"),
    "unknown top-level key": (f'active = 1\nactve = 2\n[keys]\n1 = "{HEX_1}"\n', "actve"),
    "unknown table": (f'[keys]\n1 = "{HEX_1}"\n[extra]\nx = 1\n', "extra"),
    "no keys": ("active = 1\n", "[keys]"),
    "empty keys": ("active = 1\n[keys]\n", "[keys]"),
    "keys not a table": ('keys = "abc"\n', "[keys]"),
    "active unknown": (f'active = 2\n[keys]\n1 = "{HEX_1}"\n', "active"),
    "active a string": (f'active = "1"\n[keys]\n1 = "{HEX_1}"\n', "active"),
    "active a boolean": (f'active = true\n[keys]\n1 = "{HEX_1}"\n', "active"),
    "invalid toml": (f'active = \n[keys]\n1 = "{HEX_1}"\n', "not valid TOML"),
    "unterminated string": ('[keys]\n1 = "abc\n', "not valid TOML"),
    "empty file": ("", "[keys]"),
}


@pytest.mark.parametrize("text,entry", MALFORMED.values(), ids=MALFORMED.keys())
def test_a_malformed_key_file_names_the_file_and_the_entry(tmp_path: Path, text: str, entry: str) -> None:
    """Every malformed key file raises KeyFileError whose message names the file and the entry."""
    path = tmp_path / "bus.key"
    write_key_file(path, text)
    with pytest.raises(KeyFileError) as caught:
        load_keyring(path)
    assert str(path) in str(caught.value)
    assert entry in str(caught.value)


def test_a_key_file_that_is_not_utf8_is_invalid_toml(tmp_path: Path) -> None:
    """A binary (non-UTF-8) key file raises KeyFileError naming the file, not UnicodeDecodeError."""
    path = tmp_path / "bus.key"
    write_key_file(path, b"\xff\xfe[keys]\n1 = \xe9\n")
    with pytest.raises(KeyFileError, match="not valid TOML") as caught:
        load_keyring(path)
    assert str(path) in str(caught.value)


def test_a_missing_key_file_names_the_file(tmp_path: Path) -> None:
    """A missing key file raises KeyFileError naming the path and how to create it."""
    path = tmp_path / "nowhere" / "bus.key"
    with pytest.raises(KeyFileError, match="not found") as caught:
        load_keyring(path)
    assert str(path) in str(caught.value)
    assert "keygen" in str(caught.value)


def test_rascal_key_file_selects_the_key_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """default_keyring() loads $RASCAL_KEY_FILE when it is set (and fails loudly if it is bad)."""
    path = tmp_path / "named.key"
    write_keyring(path, keyring(1, 2, active=2))
    monkeypatch.setenv("RASCAL_KEY_FILE", str(path))
    assert auth.default_keyring() == keyring(1, 2, active=2)
    monkeypatch.setenv("RASCAL_KEY_FILE", str(tmp_path / "missing.key"))
    with pytest.raises(KeyFileError, match=r"missing\.key"):
        auth.default_keyring()


def test_the_default_key_file_is_created_once_and_private(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Without $RASCAL_KEY_FILE, the per-user key is created on first use (mode 0600) and reused."""
    path = tmp_path / "config" / "rascal" / "bus.key"
    monkeypatch.delenv("RASCAL_KEY_FILE", raising=False)
    monkeypatch.setattr(auth, "DEFAULT_KEY_FILE", path)
    first = auth.default_keyring()
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert auth.default_keyring() == first
    assert len(first.keys[first.active]) == KEY_BYTES
