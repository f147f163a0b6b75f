"""The drive leaderboard's plan, scoring, targets, table and JSON file, on canned drive measures
(no processes); and, slow, the quick suite's smallest drive end to end."""

from __future__ import annotations

import io
import json
import math
import time
import tomllib
from pathlib import Path
from typing import Any

import pytest
from rich.console import Console

from benchmarks.bench_drive import (
    SUITES,
    Drive,
    Prepared,
    main,
    plan,
    prepare,
    record,
    run_drive,
)
from benchmarks.leaderboard import (
    drive_table,
    driving_score,
    infraction_table,
    leaderboard,
    passed,
    target_table,
    targets,
    totals,
    write_json,
)
from benchmarks.report import print_table
from brain.corridor import Course
from brain.rddf import load_rddf
from tests.brain.rddf_samples import rddf_text, waypoints_at

CLEAN = {
    "finished": True,
    "completion": 0.9988,
    "progress_m": 2000.0,
    "time_s": 250.0,
    "speed_ratio": 0.85,
    "cross_track_rms_m": 0.1,
    "collisions": 0,
    "corridor_exits": 0,
    "hazard_entries": 0,
    "stalls": 0,
}


def _prepared(length_m: float, narrow_m: float = 0.0) -> Prepared:
    return Prepared(Path("deploy.toml"), length_m, length_m / 8.0, 4.0, 16.0, narrow_m, 10, 2)


def _record(name: str, kind: str, seed: int, length_m: float, **measures: Any) -> dict[str, Any]:
    drive = Drive(name, kind, seed, length_m)
    return record(drive, _prepared(length_m, narrow_m=length_m / 4), measures, 300.0, f"runs/{name}")


def _clean_suite() -> list[dict[str, Any]]:
    """The standard suite's shape, every drive clean: 10 seeds, 2 km generated each, the default."""
    records = [_record("default-2005", "default", 2005, 2600.0, **{**CLEAN, "progress_m": 2597.0})]
    records += [_record(f"gen-{s}", "generated", s, 2000.0, **CLEAN) for s in range(2005, 2015)]
    return records


def test_completion_is_whole_at_the_finish_and_each_infraction_multiplies_the_score() -> None:
    assert driving_score(CLEAN) == 1.0
    assert driving_score({**CLEAN, "finished": False, "completion": 0.4}) == pytest.approx(0.4)
    assert driving_score({}) == 0.0  # a drive that wrote no measures
    bad = {**CLEAN, "collisions": 1, "corridor_exits": 2, "hazard_entries": 1, "stalls": 1}
    assert driving_score(bad) == pytest.approx(0.5 * 0.7**2 * 0.6 * 0.7)


def test_totals_weigh_by_route_length_and_distance_driven() -> None:
    records = [
        _record("a", "generated", 1, 1000.0, **{**CLEAN, "progress_m": 1000.0, "speed_ratio": 0.9}),
        _record(
            "b",
            "generated",
            2,
            3000.0,
            **{**CLEAN, "finished": False, "completion": 0.5, "progress_m": 1500.0, "collisions": 1},
        ),
        _record("c", "real", 2, 1000.0),  # wrote nothing: no progress, no speed, no tracking
    ]
    records[1]["measures"].update(speed_ratio=0.8, cross_track_rms_m=0.2)
    total = totals(records)
    assert total["route_km"] == pytest.approx(5.0) and total["driven_km"] == pytest.approx(2.5)
    assert total["completion"] == pytest.approx((1000 + 0.5 * 3000) / 5000)
    assert total["driving_score"] == pytest.approx((1000 + 0.25 * 3000) / 5000)
    assert total["speed_ratio"] == pytest.approx((0.9 * 1000 + 0.8 * 1500) / 2500)
    assert total["cross_track_rms_m"] == pytest.approx(math.sqrt((0.01 * 1000 + 0.04 * 1500) / 2500))
    assert total["infractions"]["collisions"] == 1 and total["per_km"]["collisions"] == pytest.approx(0.4)
    assert total["seeds"] == 2 and total["generated_km"] == pytest.approx(4.0) and total["clean"] == 1


def test_a_clean_standard_suite_meets_every_target() -> None:
    records = _clean_suite()
    found = targets(records, totals(records), coverage=True)
    assert passed(found) and all(t.passed for t in found)


@pytest.mark.parametrize(
    ("change", "target"),
    [
        ({"finished": False, "completion": 0.98}, "route completion"),
        ({"collisions": 1}, "collisions"),
        ({"hazard_entries": 1}, "ditch/berm entries"),
        ({"stalls": 1}, "stalls"),
        ({"speed_ratio": 0.5}, "speed ratio"),
    ],
)
def test_a_missed_target_fails_and_names_the_drive(change: dict[str, Any], target: str) -> None:
    records = _clean_suite()
    records[3] = _record("gen-bad", "generated", 2007, 2000.0, **{**CLEAN, **change})
    if target == "speed ratio":
        for r in records:
            r["measures"]["speed_ratio"] = 0.5
    found = {t.name: t for t in targets(records, totals(records), coverage=True)}
    assert found[target].passed is False and not passed(found.values())
    if target != "speed ratio":
        assert found[target].failing == ("gen-bad",)
    assert [name for name, t in found.items() if not t.passed] == [target]


def test_corridor_exits_may_be_one_per_fifty_km_and_cost_score() -> None:
    records = [_record(f"g{s}", "generated", s, 2000.0, **CLEAN) for s in range(25)]  # 50 km
    records[0] = _record("g0", "generated", 0, 2000.0, **{**CLEAN, "corridor_exits": 1})
    found = {t.name: t for t in targets(records, totals(records), coverage=False)}
    assert found["corridor exits"].passed and found["driving score"].passed
    records[1] = _record("g1", "generated", 1, 2000.0, **{**CLEAN, "corridor_exits": 1})
    found = {t.name: t for t in targets(records, totals(records), coverage=False)}
    assert found["corridor exits"].passed is False and found["corridor exits"].failing == ("g0", "g1")


def test_coverage_is_checked_for_the_standard_suites_only() -> None:
    records = [_record("gen-2005", "generated", 2005, 300.0, **{**CLEAN, "progress_m": 300.0})]
    total = totals(records)
    quick = {t.name: t for t in targets(records, total, coverage=False)}
    assert {quick[n].passed for n in ("generated courses", "seeds", "narrow stretches")} == {None}
    assert passed(quick.values())
    standard = {t.name: t for t in targets(records, total, coverage=True)}
    assert standard["generated courses"].passed is False and standard["seeds"].passed is False
    assert standard["narrow stretches"].passed  # a quarter of each canned course is narrow


def _printed(*tables: Any) -> str:
    out = io.StringIO()
    console = Console(file=out, width=300)  # not a terminal: plain aligned text
    for table in tables:
        print_table(console, table)
    return out.getvalue()


def test_the_tables_show_each_drive_the_totals_and_the_verdicts() -> None:
    records = [*_clean_suite()[:2], _record("crashed", "real", 2009, 1000.0)]
    records[1] = _record("gen-2005", "generated", 2005, 2000.0, **{**CLEAN, "stalls": 1})
    board = leaderboard(records, "standard", [2005, 2009], [], "machine")
    total = board["totals"]
    table = drive_table(records, total)
    assert [row[0] for row in table.rows] == ["default-2005", "gen-2005", "crashed", "total (3 drives)"]
    assert table.rows[1][table.columns.index("stalls")] == "1"
    assert table.rows[1][table.columns.index("score %")] == "70.0"
    assert table.rows[2][table.columns.index("speed %")] == "-"  # no measures
    text = _printed(table, infraction_table(total), target_table(targets(records, total, coverage=True)))
    assert "stall" in text and "x 0.7" in text
    assert "FAIL: gen-2005" in text and "FAIL: crashed" in text


def test_the_json_file_is_strict_and_holds_everything(tmp_path: Path) -> None:
    records = [*_clean_suite()[:1], _record("crashed", "real", 2009, 1000.0)]
    records[0]["measures"]["cross_track_rms_m"] = math.nan
    path = tmp_path / "out" / "leaderboard.json"
    write_json(leaderboard(records, "quick", [2005], ["a note"], "machine"), path)

    def refuse(constant: str) -> None:
        raise ValueError(constant)

    board = json.loads(path.read_text(), parse_constant=refuse)
    assert [d["name"] for d in board["drives"]] == ["default-2005", "crashed"]
    assert board["drives"][0]["measures"]["cross_track_rms_m"] is None
    assert board["penalties"] == {"collisions": 0.5, "corridor_exits": 0.7, "hazard_entries": 0.6, "stalls": 0.7}
    assert board["notes"] == ["a note"] and board["passed"] is False
    assert {t["name"] for t in board["targets"]} >= {"route completion", "driving score", "corridor exits"}
    assert board["totals"]["route_km"] == pytest.approx(3.6)


def _real_dir(tmp_path: Path) -> Path:
    """A stand-in for ../shared/data/rddf: one long course, one short loop, one broken file."""
    real = tmp_path / "real"
    real.mkdir()
    (real / "long.rddf").write_text(rddf_text(waypoints_at([(0.0, 0.0), (300.0, 0.0), (300.0, 400.0)])))
    (real / "short.rddf").write_text(rddf_text(waypoints_at([(0.0, 0.0), (80.0, 0.0)])))
    (real / "broken.txt").write_text("not a course\n")
    return real


def test_the_suites_plan_their_drives(tmp_path: Path) -> None:
    drives, notes = plan(SUITES["quick"], tmp_path / "absent")
    assert [(d.kind, d.seed, d.length_m) for d in drives] == [("generated", 2005, 300.0)]
    assert notes == [f"real RDDF stretches left out: {tmp_path / 'absent'} is absent"]
    drives, notes = plan(SUITES["standard"], _real_dir(tmp_path))
    kinds = [d.kind for d in drives]
    assert notes == [] and kinds == ["default"] + ["generated"] * 10 + ["real"]
    assert sum(d.length_m for d in drives if d.kind == "generated") == pytest.approx(20000.0)
    assert len({d.seed for d in drives}) == 10 and drives[-1].source.endswith("long.rddf")


def test_prepare_writes_a_deployment_for_the_course_and_its_scenario(tmp_path: Path) -> None:
    real = _real_dir(tmp_path)
    short = prepare(Drive("gen", "generated", 2005, 300.0), tmp_path, bus="udpm://239.255.9.9:30000?ttl=0")
    longer = prepare(Drive("gen2", "generated", 2005, 2000.0), tmp_path)
    head = tomllib.loads(short.deployment.read_text())["deployment"]
    assert head["bus"] == "udpm://239.255.9.9:30000?ttl=0"
    assert Course(load_rddf(head["course"])).length_m == pytest.approx(300.0, abs=0.01)
    assert tomllib.loads(Path(head["scenario"]).read_text())["scenario"]["seed"] == 2005
    assert short.route_length_m == pytest.approx(300.0, abs=1.0) and short.obstacles >= 1
    assert longer.duration_s > short.duration_s > short.min_drive_time_s  # the timeout grows with the course
    assert longer.narrow_m > 0 and 3.7 <= longer.min_width_m <= 6.0
    cut = prepare(Drive("real", "real", 2006, 500.0, str(real / "long.rddf")), tmp_path)
    assert cut.route_length_m == pytest.approx(300.0, abs=1.0)  # whole waypoints: 300 m is nearest 500 m


def test_plan_only_drives_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    runs = tmp_path / "runs"
    assert main(["--suite", "quick", "--plan", "--runs-dir", str(runs), "--real-rddf-dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "gen-2005-0.3km" in out and "estimate min" in out and "no course of 300 m" in out
    assert not runs.exists()


@pytest.mark.slow
def test_the_quick_suites_smallest_drive_end_to_end(bus_url: str, key_file: Path, tmp_path: Path) -> None:
    """A generated 300 m course driven by the whole stack under rascal run, scored (about 45 s on 2 cores)."""
    (drive,) = plan(SUITES["quick"], tmp_path / "absent")[0]
    prepared = prepare(drive, tmp_path, bus=bus_url)
    start = time.monotonic()
    result = run_drive(drive, prepared, tmp_path / "runs")
    assert time.monotonic() - start < prepared.duration_s  # ended at the finish, not by the timeout
    log = (tmp_path / "runs" / drive.name / "rascal-run.log").read_text()[-3000:]
    assert result["measures"].get("finished"), log
    assert result["completion"] == 1.0 and result["driving_score"] == driving_score(result["measures"])
    board = leaderboard([result], "quick", [drive.seed], [], "machine")
    write_json(board, tmp_path / "leaderboard.json")
    assert json.loads((tmp_path / "leaderboard.json").read_text())["drives"][0]["name"] == drive.name
