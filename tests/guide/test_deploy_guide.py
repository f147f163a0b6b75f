"""docs/DEPLOY.md: every `rascal ...` command line in its code blocks is accepted by the CLI's parser."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from rascal.cli import main

GUIDE = Path(__file__).resolve().parents[2] / "docs" / "DEPLOY.md"


def rascal_lines() -> list[str]:
    lines = []
    for block in re.findall(r"```sh\n(.*?)```", GUIDE.read_text(), re.S):
        for line in block.splitlines():
            line = line.split("  #")[0].strip()
            if line.startswith("rascal ") or line.startswith(".venv/bin/rascal "):
                lines.append(line)
    return lines


def test_the_guide_has_commands() -> None:
    assert len(rascal_lines()) >= 8


@pytest.mark.parametrize("line", rascal_lines())
def test_each_command_line_parses(line: str, capsys: pytest.CaptureFixture[str]) -> None:
    """Each verb exists (the line plus --help exits 0) and each flag shown is in that verb's help."""
    argv = shlex.split(line)[1:]
    asks_version = argv == ["--version"]
    with pytest.raises(SystemExit) as exited:
        main([*argv, *([] if asks_version else ["--help"])])
    out = capsys.readouterr().out
    assert exited.value.code in (0, None), out
    if asks_version:
        return
    assert "usage:" in out
    for flag in (word.split("=")[0] for word in argv if word.startswith("-")):
        assert re.search(rf"(^|[\s\[,]){re.escape(flag)}\b", out, re.M), f"{flag} not in the help of {line!r}"
