"""RDDF parsing: the real files load, format quirks are accepted, every malformed input is named and refused."""

from __future__ import annotations

from pathlib import Path

import pytest

from brain.rddf import MAX_LATERAL_OFFSET_FT, MAX_SPEED_LIMIT_MPH, RddfError, Waypoint, load_rddf, parse_rddf
from tests.brain.rddf_samples import REAL_RDDF_DIR, real_rddf_params

GOOD = [
    "1, 37.542735, -122.056998, 12, 25",
    "2, 37.543055, -122.057120, 12, 25",
    "3, 37.543043, -122.057391, 16, 25",
]
EXPECTED = [
    Waypoint(1, 37.542735, -122.056998, 12.0, 25.0),
    Waypoint(2, 37.543055, -122.057120, 12.0, 25.0),
    Waypoint(3, 37.543043, -122.057391, 16.0, 25.0),
]


def with_line(number: int, text: str) -> str:
    """GOOD with its line ``number`` (1-based) replaced by ``text``."""
    lines = list(GOOD)
    lines[number - 1] = text
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("path", real_rddf_params())
def test_every_real_file_loads(path: Path) -> None:
    waypoints = load_rddf(path)
    assert len(waypoints) >= 2
    numbers = [w.number for w in waypoints]
    assert numbers == sorted(set(numbers))


def test_real_phase_line_file_keeps_its_numbers_and_phase_line() -> None:
    path = REAL_RDDF_DIR / "overbot_waypts_fragment_with_phaseline.txt"
    if not path.is_file():
        pytest.skip(f"{path} is not there")
    waypoints = load_rddf(path)
    assert [w.number for w in waypoints] == [10, 11, 12]
    assert [w.phase_line for w in waypoints] == [None, (9, 45, 0), None]


@pytest.mark.parametrize("ending", ["\n", "\r\n", "\r", "\r\r\n"], ids=["LF", "CRLF", "CR", "CRCRLF"])
def test_line_endings_parse_alike_and_count_lines_alike(ending: str) -> None:
    assert parse_rddf(ending.join(GOOD), "c.rddf") == EXPECTED
    with pytest.raises(RddfError) as caught:
        parse_rddf(ending.join([*GOOD, "4, x, 0, 1, 1"]), "c.rddf")
    assert caught.value.line == 4


def test_padding_comments_blank_lines_and_no_final_newline_are_accepted() -> None:
    text = (
        "#  Waypoint file created on Thu Apr 21 15:38:53 2005\n"
        "\n"
        "1,\t37.542735, \t\t-122.056998, \t\t12, \t25\n"
        "   # 2, 0, 0, 1, 1   (a commented-out waypoint)\n"
        "##   16, 37.417794, -122.242251, 8, 10\n"
        "   \t  \n"
        "  2 , 37.543055 ,-122.057120,12,25  \n"
        "3,37.543043,-122.057391,16,25"
    )
    assert parse_rddf(text, "c.rddf") == EXPECTED


def test_fractional_values_and_phase_lines_parse() -> None:
    text = (
        "10,38.2228914,-110.4790771,13.30,12.5,####,####,####\n"
        "11,38.2224215,-110.4793187,20,55,9,45,0\n"
        "13,38.2216479,-110.47997,.5,7.,  ####, #### ,####\n"
    )
    assert parse_rddf(text, "c.rddf") == [
        Waypoint(10, 38.2228914, -110.4790771, 13.3, 12.5, None),
        Waypoint(11, 38.2224215, -110.4793187, 20.0, 55.0, (9, 45, 0)),
        Waypoint(13, 38.2216479, -110.47997, 0.5, 7.0, None),
    ]


def test_zero_speed_marks_the_finish_on_the_last_waypoint() -> None:
    assert parse_rddf(with_line(3, "3, 37.543043, -122.057391, 16, 0"), "c.rddf")[-1].speed_limit_mph == 0.0


def test_load_rddf_names_the_path_and_skips_a_byte_order_mark(tmp_path: Path) -> None:
    path = tmp_path / "course.rddf"
    path.write_bytes(b"\xef\xbb\xbf" + "\n".join(GOOD).encode())
    assert load_rddf(path) == EXPECTED
    path.write_bytes("\n".join([*GOOD, "4, 37.5, -122.0, 12, abc"]).encode())
    with pytest.raises(RddfError, match=r"course\.rddf line 4, field 'speed_limit_mph': 'abc' is not a number"):
        load_rddf(path)


def test_load_rddf_names_the_line_of_a_byte_that_is_not_text(tmp_path: Path) -> None:
    path = tmp_path / "course.rddf"
    path.write_bytes("\n".join(GOOD).encode() + b"\n4, 37.5\xff, -122.0, 12, 5\n")
    with pytest.raises(RddfError) as caught:
        load_rddf(path)
    assert caught.value.line == 4


BAD_LINES = [
    # (line replaced, its replacement, field named, words in the message)
    (2, "2, abc, -122.057120, 12, 25", "lat_deg", "'abc' is not a number"),
    (2, "2, , -122.057120, 12, 25", "lat_deg", "'' is not a number"),
    (2, "2, nan, -122.057120, 12, 25", "lat_deg", "not a number"),
    (2, "2, 37.5, -122.057120, 12, inf", "speed_limit_mph", "not a number"),
    (2, "2, 3_7.5, -122.057120, 12, 25", "lat_deg", "not a number"),
    (2, "2, 90.0001, -122.057120, 12, 25", "lat_deg", "outside"),
    (2, "2, 37.5, -180.5, 12, 25", "lon_deg", "outside"),
    (2, "2, 37.5, -122.0, 0, 25", "lateral_offset_ft", "outside"),
    (2, "2, 37.5, -122.0, -3, 25", "lateral_offset_ft", "outside"),
    (2, f"2, 37.5, -122.0, {MAX_LATERAL_OFFSET_FT + 1:g}, 25", "lateral_offset_ft", "outside"),
    (2, "2, 37.5, -122.0, 12, -1", "speed_limit_mph", "outside"),
    (2, f"2, 37.5, -122.0, 12, {MAX_SPEED_LIMIT_MPH + 1:g}", "speed_limit_mph", "outside"),
    (2, "2, 37.5, -122.0, 12, 0", "speed_limit_mph", "not the last"),
    (2, "2.5, 37.5, -122.0, 12, 25", "number", "not a whole number"),
    (2, "x, 37.5, -122.0, 12, 25", "number", "not a whole number"),
    (2, "1, 37.5, -122.0, 12, 25", "number", "repeats line 1"),
    (3, "2, 37.5, -122.0, 12, 25", "number", "repeats line 2"),
    (3, "1, 37.5, -122.0, 12, 25", "number", "comes after 2 (line 2)"),
    (2, "0, 37.5, -122.0, 12, 25", "number", "numbers must increase"),
    (2, "2, 37.5, -122.0, 12", None, "got 4"),
    (2, "2, 37.5, -122.0, 12, 25, 1", None, "got 6"),
    (2, "2, 37.5, -122.0, 12, 25, 1, 2, 3, 4", None, "got 9"),
    (2, "2, 37.5, -122.0, 12, 25, ####, ####, ####", None, "8 fields, but the lines before have 5"),
    (2, "2 37.5 -122.0 12 25", None, "got 1"),
]


@pytest.mark.parametrize(("line", "replacement", "field", "words"), BAD_LINES)
def test_malformed_line_is_refused_with_its_line_and_field(
    line: int, replacement: str, field: str | None, words: str
) -> None:
    with pytest.raises(RddfError) as caught:
        parse_rddf(with_line(line, replacement), "c.rddf")
    error = caught.value
    assert (error.source, error.line, error.field) == ("c.rddf", line, field)
    expected_where = f"c.rddf line {line}" + (f", field '{field}'" if field else "")
    assert str(error).startswith(expected_where + ": ")
    assert words in str(error)


PHASE_BAD = [
    ("24, 0, 0", "phase_hour", "not within [0, 23]"),
    ("9, 60, 0", "phase_minute", "not within [0, 59]"),
    ("9, 45, 60", "phase_second", "not within [0, 59]"),
    ("9, 45, 1.5", "phase_second", "not a whole number"),
    ("9, ####, 0", "phase_minute", "give all three or none"),
    ("###, ####, ####", "phase_hour", "not a whole number"),
]


@pytest.mark.parametrize(("phase", "field", "words"), PHASE_BAD)
def test_malformed_phase_line_is_refused(phase: str, field: str, words: str) -> None:
    text = f"1, 37.5, -122.0, 12, 25, ####, ####, ####\n2, 37.6, -122.0, 12, 25, {phase}\n"
    with pytest.raises(RddfError) as caught:
        parse_rddf(text, "c.rddf")
    assert (caught.value.line, caught.value.field) == (2, field)
    assert words in str(caught.value)


@pytest.mark.parametrize(
    "text", ["", "# only a comment\n\n", GOOD[0] + "\n"], ids=["empty", "comments only", "one waypoint"]
)
def test_fewer_than_two_waypoints_is_refused(text: str) -> None:
    with pytest.raises(RddfError, match=r"^c\.rddf: [01] waypoint\(s\); a course needs at least 2"):
        parse_rddf(text, "c.rddf")


def test_an_error_on_the_last_line_refuses_the_whole_file() -> None:
    text = "\n".join([*GOOD, "4, 37.5, -122.0, 12"])
    with pytest.raises(RddfError):
        parse_rddf(text, "c.rddf")
