"""Scenario files: the default course meets the brief; bad files get errors naming the key."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from modules.sim.scenario import DEFAULT_SCENARIO, ScenarioError, load_scenario
from modules.sim.world import FaultKind, HazardKind, Shape


@pytest.fixture(scope="module")
def mojave():
    return load_scenario(DEFAULT_SCENARIO)


def test_default_course_is_at_least_2_km(mojave) -> None:
    assert mojave.route.length_m >= 2000


def test_default_has_25_obstacles_all_inside_the_corridor(mojave) -> None:
    obstacles = mojave.world.obstacles
    assert len(obstacles) >= 25
    assert all(mojave.course.corridor.contains(o.east_m, o.north_m) for o in obstacles)


def test_default_has_a_power_pole_a_ditch_and_a_narrow_passage(mojave) -> None:
    by_name = {o.name: o for o in mojave.world.obstacles}
    pole = by_name["power_pole"]
    assert pole.shape is Shape.CYLINDER and pole.height_m > 5 and pole.radius_m < 0.3
    assert any(h.kind is HazardKind.DITCH for h in mojave.world.hazards)
    left, right = by_name["passage_left_rock"], by_name["passage_right_rock"]
    gap = math.dist((left.east_m, left.north_m), (right.east_m, right.north_m)) - (left.width_m + right.width_m) / 2
    assert 2.0 < gap < 4.0  # room for the 1.2 m vehicle, but not much


def test_default_has_a_sharp_turn(mojave) -> None:
    heading = np.unwrap(np.arctan2(np.diff(mojave.route.north_m), np.diff(mojave.route.east_m)))
    turned = np.abs(heading[100:] - heading[:-100])  # heading change over 100 m
    assert np.degrees(turned.max()) > 80


def test_random_placement_is_deterministic_for_a_seed(mojave) -> None:
    again = load_scenario(DEFAULT_SCENARIO)
    assert again.world.obstacles == mojave.world.obstacles


def write(tmp_path: Path, body: str) -> Path:
    (tmp_path / "course.rddf").write_text(DEFAULT_SCENARIO.with_name("mojave.rddf").read_text())
    path = tmp_path / "bad.toml"
    path.write_text('[scenario]\nrddf = "course.rddf"\n' + body)
    return path


@pytest.mark.parametrize(
    ("body", "complaint"),
    [
        ("colour = 1\n", r"scenario\.colour: unknown key; known: \['fair'"),
        ("[colours]\nsky = 1\n", r"bad\.toml: colours: unknown key"),
        ("[[obstacle]]\nshape = 'cone'\nat_m = 10.0\nheight_m = 1.0\n", r"obstacle\[0\]\.shape: 'cone' is not one of"),
        ("[[obstacle]]\nshape = 'cylinder'\nat_m = 10.0\nheight_m = 1.0\n", r"obstacle\[0\]\.radius_m: missing"),
        (
            "[[obstacle]]\nshape = 'cylinder'\nat_m = 10.0\nheight_m = 1.0\nradius_m = -1\n",
            r"radius_m: expected 0\.02\.\.20, got -1",
        ),
        ("[[obstacle]]\nshape = 'cylinder'\nat_m = 99999.0\nheight_m = 1.0\nradius_m = 1\n", r"obstacle\[0\]\.at_m"),
        (
            "[[obstacle]]\nshape = 'cylinder'\nat_m = 10.0\noffset_m = 40.0\nheight_m = 1.0\nradius_m = 1\n",
            "stands outside the corridor",
        ),
        (
            "[[hazard]]\nkind = 'ditch'\nat_m = 10.0\nlength_m = 2.0\nwidth_m = 5.0\n",
            r"hazard\[0\]\.depth_m: missing",
        ),
        ("[[fault]]\nsensors = ['radar']\nkind = 'silence'\nstart_s = 1.0\n", r"unknown sensor\(s\) \['radar'\]"),
        ("[[fault]]\nsensors = ['gps']\nkind = 'silence'\nstart_s = 5.0\nend_s = 1.0\n", r"fault\[0\]\.end_s"),
        ("[random_obstacles]\ncount = 500\nmin_gap_m = 50.0\n", r"random_obstacles\.count: only"),
        ("[road]\nhalf_width_m = 'wide'\n", r"road\.half_width_m: expected a number"),
    ],
)
def test_bad_scenarios_are_refused_by_name(tmp_path: Path, body: str, complaint: str) -> None:
    with pytest.raises(ScenarioError, match=complaint):
        load_scenario(write(tmp_path, body))


def test_a_bad_rddf_is_reported_through_the_scenario(tmp_path: Path) -> None:
    (tmp_path / "course.rddf").write_text("1,34.0,-116.0,30,30\n")
    path = tmp_path / "s.toml"
    path.write_text('[scenario]\nrddf = "course.rddf"\n')
    with pytest.raises(ScenarioError, match=r"scenario\.rddf"):
        load_scenario(path)


def test_invalid_toml_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "s.toml"
    path.write_text("[scenario\n")
    with pytest.raises(ScenarioError, match="not valid TOML"):
        load_scenario(path)


def test_fault_schedule_is_loaded_with_times(tmp_path: Path) -> None:
    path = write(tmp_path, "[[fault]]\nsensors = ['lidars']\nkind = 'silence'\nstart_s = 60.0\n")
    [fault] = load_scenario(path).world.faults
    assert fault.kind is FaultKind.SILENCE and not fault.active(59.9, 0.0) and fault.active(60.0, 0.0)
    assert fault.active(1e6, 1e6)


def test_a_fault_can_be_placed_on_the_course_by_progress(tmp_path: Path) -> None:
    path = write(tmp_path, "[[fault]]\nsensors = ['gps']\nkind = 'outage'\nstart_s = 0.0\nfrom_m = 40.0\nto_m = 80.0\n")
    [fault] = load_scenario(path).world.faults
    assert not fault.active(100.0, 39.9) and fault.active(100.0, 40.0) and not fault.active(100.0, 80.0)
    assert load_scenario(path).world.faults_for("gps", 5.0, 50.0) == [fault]
    for bad, message in (("from_m = -1.0", "from_m"), ("from_m = 40.0\nto_m = 30.0", "to_m")):
        write(tmp_path, f"[[fault]]\nsensors = ['gps']\nkind = 'outage'\nstart_s = 0.0\n{bad}\n")
        with pytest.raises(ScenarioError, match=message):
            load_scenario(path)


def test_gps_jumps_are_seeded_faults_at_the_configured_rate(tmp_path: Path) -> None:
    path = write(tmp_path, "[gps_jumps]\nper_hour = 60.0\nmagnitude_m = [5.0, 20.0]\nhorizon_s = 36000.0\n")
    jumps = load_scenario(path).world.faults
    assert all(f.kind is FaultKind.JUMP and f.sensors == ("gps",) and 5 <= f.magnitude <= 20 for f in jumps)
    assert len(jumps) == pytest.approx(600, rel=0.15)  # 60 an hour for 10 hours
    assert jumps == load_scenario(path).world.faults
    assert all(a.end_s <= b.start_s for a, b in itertools.pairwise(jumps))
