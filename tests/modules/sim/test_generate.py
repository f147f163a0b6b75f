"""`rascal scenario generate`: hard but fair scenarios on any course, deterministic for a seed."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import pytest

from modules.sim.fairness import Stations, blockers, find_unfairness
from modules.sim.generate import Options, generate
from modules.sim.scenario import DEFAULT_SCENARIO, Scenario, load_scenario
from modules.sim.world import Shape
from rascal.cli import main

DEFAULT_RDDF = DEFAULT_SCENARIO.with_name("mojave.rddf")
RACE_RDDFS = Path("/work/shared/data/rddf")  # real race RDDFs, read in place where this machine has them
BUSY = Options(seed=0, obstacles_per_km=40.0, washes=2, berms=2)


def generated(rddf: Path, out: Path, options: Options) -> Scenario:
    out.write_text(generate(rddf, out, options).text)
    scenario = load_scenario(out)  # checks the fairness rule again
    assert find_unfairness(Stations.along(scenario.course), blockers(scenario.world)) is None
    return scenario


def straight_rddf(tmp_path: Path, offset_ft: float, length_m: float = 400.0) -> Path:
    lat, lon = 34.865, -116.89
    end = lon + length_m / (111_320.0 * math.cos(math.radians(lat)))
    path = tmp_path / f"straight-{offset_ft:g}.rddf"
    path.write_text(f"1,{lat},{lon},{offset_ft},25\n2,{lat},{end:.7f},{offset_ft},25\n")
    return path


@pytest.mark.parametrize("seed", range(5))
def test_the_default_course_gets_what_was_asked_for_and_it_is_fair(tmp_path: Path, seed: int) -> None:
    scenario = generated(DEFAULT_RDDF, tmp_path / "s.toml", Options(seed))
    world = scenario.world
    assert len(world.obstacles) == round(8.0 * scenario.route.length_m / 1000)  # 8 per km, 2.6 km
    assert sorted(h.kind.value for h in world.hazards) == ["berm", "ditch"]  # one each per 2 km
    assert any(f.sensors == ("gps",) for f in world.faults)
    assert all(o.shape in (Shape.BOX, Shape.CYLINDER) for o in world.obstacles)


def test_a_seed_gives_the_same_file_and_another_seed_another(tmp_path: Path) -> None:
    out = tmp_path / "s.toml"
    first = generate(DEFAULT_RDDF, out, Options(7)).text
    assert generate(DEFAULT_RDDF, out, Options(7)).text == first
    assert generate(DEFAULT_RDDF, out, Options(8)).text != first


def test_the_generator_never_opts_out_of_fairness(tmp_path: Path) -> None:
    head = tomllib.loads(generate(DEFAULT_RDDF, tmp_path / "s.toml", BUSY).text)["scenario"]
    assert "fair" not in head


def race_rddfs() -> list[Path | None]:
    return sorted(RACE_RDDFS.iterdir()) if RACE_RDDFS.is_dir() else [None]


@pytest.mark.parametrize("rddf", race_rddfs(), ids=lambda p: p.name if p else "none")
def test_every_race_rddf_gets_busy_fair_scenarios(tmp_path: Path, rddf: Path | None) -> None:
    if rddf is None:
        pytest.skip(f"no race RDDFs at {RACE_RDDFS} on this machine")
    for seed in range(3):
        scenario = generated(rddf, tmp_path / "s.toml", Options(seed, 40.0, washes=2, berms=2))
        assert scenario.world.obstacles or scenario.route.length_m < 60.0


def test_a_3_7_m_corridor_still_gets_obstacles_beside_the_lane(tmp_path: Path) -> None:
    rddf = straight_rddf(tmp_path, offset_ft=1.85 / 0.3048)
    for seed in range(3):
        scenario = generated(rddf, tmp_path / "s.toml", Options(seed, 40.0, washes=2, berms=2))
        assert len(scenario.world.obstacles) >= 10


def test_a_corridor_no_wider_than_the_lane_gets_nothing(tmp_path: Path) -> None:
    scenario = generated(straight_rddf(tmp_path, offset_ft=3.6), tmp_path / "s.toml", BUSY)
    assert scenario.world.obstacles == () and scenario.world.hazards == ()


def test_the_command_writes_a_file_that_loads(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rddf = straight_rddf(tmp_path, offset_ft=20.0)
    out = tmp_path / "scenario.toml"
    assert main(["scenario", "generate", str(rddf), "--seed", "3", "-o", str(out), "--name", "test"]) == 0
    assert capsys.readouterr().out.startswith(f"wrote {out}: ")
    assert tomllib.loads(out.read_text())["scenario"]["rddf"] == rddf.name  # beside it: relative
    assert load_scenario(out).name == "test"
    elsewhere = tmp_path / "elsewhere" / "scenario.toml"
    elsewhere.parent.mkdir()
    assert main(["scenario", "generate", str(rddf), "--seed", "3", "-o", str(elsewhere), "--gps-jumps", "0"]) == 0
    assert tomllib.loads(elsewhere.read_text())["scenario"]["rddf"] == str(rddf.resolve())  # absolute
    assert load_scenario(elsewhere).world.faults == ()


@pytest.mark.parametrize("content", ["1,34.0,-116.0,30,30\n", "1,34.0,-116.0,30\n2,34.1,-116.0,30,30\n", None])
def test_a_bad_rddf_is_one_clear_line_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: str | None
) -> None:
    rddf = tmp_path / "bad.rddf"
    if content is not None:
        rddf.write_text(content)
    out = tmp_path / "s.toml"
    assert main(["scenario", "generate", str(rddf), "--seed", "1", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("rascal scenario generate: ") and "bad.rddf" in err
    assert not out.exists()
