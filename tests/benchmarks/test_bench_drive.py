"""The drive benchmark's seeded copies of the default deployment, and its pass/fail rule."""

from __future__ import annotations

from pathlib import Path

from benchmarks.bench_drive import meets_targets, seeded_deployment
from modules.sim.scenario import load_scenario
from rascal.deployment import load_deployment

GOOD = {
    "finished": True,
    "collisions": 0,
    "corridor_exits": 0,
    "hazard_entries": 0,
    "speed_ratio": 0.81,
    "cross_track_rms_m": 0.12,
}


def test_a_seeded_copy_changes_only_the_seed_and_the_bus(tmp_path: Path) -> None:
    default = load_deployment()
    copy = load_deployment(seeded_deployment(2007, tmp_path))
    assert copy.scenario is not None and default.scenario is not None
    seeded, original = load_scenario(copy.scenario), load_scenario(default.scenario)
    assert seeded.seed == 2007 and original.seed != 2007
    assert seeded.route.length_m == original.route.length_m
    assert [o.name for o in seeded.world.obstacles] == [o.name for o in original.world.obstacles]
    assert seeded.world.obstacles != original.world.obstacles  # the random ones moved
    assert copy.course == default.course
    assert copy.bus != default.bus and copy.bus.endswith("?ttl=0") and copy.bus.startswith("udpm://239.255.")
    assert [(m.label, m.source_id) for m in copy.modules] == [(m.label, m.source_id) for m in default.modules]


def test_every_target_must_be_met() -> None:
    assert meets_targets(GOOD)
    for key, bad in (
        ("finished", False),
        ("collisions", 1),
        ("corridor_exits", 1),
        ("hazard_entries", 1),
        ("speed_ratio", 0.79),
        ("cross_track_rms_m", 0.31),
    ):
        assert not meets_targets({**GOOD, key: bad}), key
    assert not meets_targets({"seed": 1, "finished": False})
