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
    "bad URL after the verb": (["bus", "list", "--duration", "0.1", "--bus", "foo://x"], "unknown scheme"),
    "unknown channel (info)": (["bus", "info", "NO_SUCH_CHANNEL"], "unknown channel 'NO_SUCH_CHANNEL'"),
    "bad window (hz)": (["bus", "hz", "GPS", "--window", "0", "--duration", "0.1"], "--window must be positive"),
    "unknown channel (record)": (["log", "record", "GSP", "--duration", "0.1"], "did you mean GPS"),
    "unwritable output (record)": (
        ["log", "record", "-o", "/dev/null/x.mcap", "--bus", "mem://rec", "--duration", "0.1"],
        "/dev/null",
    ),
    "unknown type (interface)": (["interface", "show", "ObstacleLst"], "did you mean ObstacleList"),
    "--bus for run": (["--bus", "udpm://239.1.2.3:7000", "run"], "--bus does not apply"),
    "bad URL for a delegated tool": (["spoof", "forge", "--bus", "foo://x"], "only udpm://"),
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


@pytest.mark.parametrize("where", ["before", "after"])
def test_a_missing_key_file_given_as_an_option_is_one_line_and_exit_2(
    where: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    option = ["--key-file", str(tmp_path / "absent.key")]
    tool = ["time", "status", "--duration", "0.1"]
    assert main([*option, *tool] if where == "before" else [*tool, *option]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "absent.key: key file not found" in err, err


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0 and capsys.readouterr().out.startswith("rascal ")
