"""Bad input to the bus and time tools is one line on stderr and exit 2, never a traceback and
never a silent success (issue 27): bad bus URLs, a missing key file, unknown channels, bad JSON,
a message receivers would reject."""

from __future__ import annotations

from pathlib import Path

import pytest

from rascal.cli import main

CASES = {
    "unknown scheme": (["--bus", "foo://x", "bus", "list", "--duration", "0.1"], "unknown scheme"),
    "not multicast": (["--bus", "udpm://10.1.2.3:7667", "bus", "hz", "PATH"], "not an IPv4 multicast group"),
    "bad port": (["--bus", "udpm://239.255.76.67:99999", "time", "status"], "99999"),
    "unknown channel (echo)": (["bus", "echo", "NO_SUCH_CHANNEL"], "unknown channel 'NO_SUCH_CHANNEL'"),
    "misspelt channel (hz)": (["bus", "hz", "obstacles_lidr"], "did you mean OBSTACLES_LIDAR"),
    "unknown channel (pub)": (["bus", "pub", "NO_SUCH_CHANNEL", "{}"], "not declared"),
    "not JSON": (["bus", "pub", "STOP", "{mode: 1"], "not JSON"),
    "wrong field type": (["bus", "pub", "STOP", '["x", 3]'], "not a valid StopCommand"),
    "unknown field": (["bus", "pub", "STOP", '{"mode": 1, "speed": 3}'], "has no field(s) ['speed']"),
    "unknown type": (["bus", "pub", "MY_CHANNEL", "{}", "--type", "Nope"], "unknown message type 'Nope'"),
}


@pytest.mark.parametrize("argv, says", CASES.values(), ids=CASES.keys())
def test_bad_input_is_one_line_and_exit_2(argv: list[str], says: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and says in err and "Traceback" not in err, err


def test_a_missing_key_file_is_one_line_and_exit_2(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("RASCAL_KEY_FILE", str(tmp_path / "absent.key"))
    assert main(["bus", "list", "--duration", "0.1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "key file not found" in err and "rascal keygen" in err, err


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0 and capsys.readouterr().out.startswith("rascal ")
