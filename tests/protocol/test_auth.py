"""Keys: the MAC primitive, key rotation, and the key file (round trip, permissions, errors)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from protocol import auth
from protocol.auth import KEY_BYTES, TAG_BYTES, KeyFileError, Keyring, load_keyring, write_keyring
from tests.protocol.wire_samples import key_bytes, keyring

HEX_1 = key_bytes(1).hex()
HEX_2 = key_bytes(2).hex()


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
    path.write_text(f'[keys]\n7 = "{HEX_2}"\n3 = "{HEX_1}"\n')
    ring = load_keyring(path)
    assert ring.active == 3
    assert ring.keys == {3: key_bytes(1), 7: key_bytes(2)}


def test_keys_may_be_written_in_upper_case_hex(tmp_path: Path) -> None:
    """Hex digits are case-insensitive."""
    path = tmp_path / "bus.key"
    path.write_text(f'active = 1\n[keys]\n1 = "{HEX_1.upper()}"\n')
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
    path.write_text(text, encoding="utf-8")
    with pytest.raises(KeyFileError) as caught:
        load_keyring(path)
    assert str(path) in str(caught.value)
    assert entry in str(caught.value)


def test_a_key_file_that_is_not_utf8_is_invalid_toml(tmp_path: Path) -> None:
    """A binary (non-UTF-8) key file raises KeyFileError naming the file, not UnicodeDecodeError."""
    path = tmp_path / "bus.key"
    path.write_bytes(b"\xff\xfe[keys]\n1 = \xe9\n")
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
