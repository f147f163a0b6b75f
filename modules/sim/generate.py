"""Hard but fair scenarios on any course: ``rascal scenario generate RDDF --seed N -o FILE``.

Courses never seen must still be drivable: the generator scatters rocks, boulders, shrubs, the
odd abandoned car and narrow gates between two rocks along the corridor, lays washes (ditches)
and berms across part of the road, and adds seeded GPS jumps. Each thing is drawn at a random
place and kept only if the scenario stays fair (``modules/sim/fairness.py``: a free lane of the
vehicle's width + 1.0 m from start to finish); where nothing fits, e.g. in a corridor barely wider
than the lane, fewer or smaller things are placed, or none. The output is an ordinary scenario
file, deterministic for a seed, that the loader checks again.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from brain.corridor import Course, CoursePath
from modules.sim.fairness import LANE_WIDTH_M, Blocker, Stations, blockers, find_unfairness
from modules.sim.scenario import hazard_from_table, obstacle_from_table
from modules.sim.world import World

START_CLEAR_M = 20.0  # the vehicle starts at rest on the first waypoint: nothing on top of it
FINISH_CLEAR_M = 10.0
SPACING_M = 10.0  # along the course between things: room to move across to the next lane
EDGE_M = 0.1  # obstacle centres stay this far inside the corridor's edge
ATTEMPTS = 40  # random places tried for each thing before it is left out
DIGITS = 3  # millimetres: the file holds exactly what was checked

Table = dict[str, Any]
Placed = list[tuple[str, Table]]  # ("obstacle" or "hazard", its table in the scenario file)


@dataclass(frozen=True)
class Options:
    """What to put on the course; None counts mean one per 2 km (rounded)."""

    seed: int
    obstacles_per_km: float = 8.0
    washes: int | None = None
    berms: int | None = None
    gps_jumps_per_hour: float = 12.0
    name: str | None = None


@dataclass(frozen=True)
class Generated:
    """The scenario file's text, what it holds, and what was asked for (where less fitted)."""

    text: str
    obstacles: int
    washes: int
    berms: int
    asked: dict[str, int]


def generate(rddf: Path, output: Path, options: Options) -> Generated:
    """A fair scenario on the course in ``rddf``, to be written to ``output`` (for the path to the
    RDDF it names). Raises OSError or ValueError (`brain.rddf.RddfError`) for a bad course."""
    course = Course.from_file(rddf)
    rng = np.random.default_rng(options.seed)
    placer = _Placer(course, rng)
    per_two_km = math.floor(placer.route.length_m / 2000.0 + 0.5)
    asked = {
        "washes": per_two_km if options.washes is None else options.washes,
        "berms": per_two_km if options.berms is None else options.berms,
        "obstacles": round(options.obstacles_per_km * placer.route.length_m / 1000.0),
    }
    placed: Placed = []
    for kind, name, count in (("ditch", "wash", asked["washes"]), ("berm", "berm", asked["berms"])):
        for i in range(count):
            placed += placer.place(lambda half, kind=kind, name=f"{name}_{i}": _across(rng, name, half, kind))
    placed += _obstacles(placer, rng, asked["obstacles"])
    placed.sort(key=lambda item: (item[0] == "hazard", item[1]["at_m"]))
    obstacles = [t for kind, t in placed if kind == "obstacle"]
    hazards = [t for kind, t in placed if kind == "hazard"]
    head = {
        "name": options.name or f"{rddf.stem}-{options.seed}",
        "rddf": _rddf_reference(rddf, output),
        "seed": options.seed,
    }
    text = _toml(head, obstacles, hazards, options, rddf.name)
    washes = sum(t["kind"] == "ditch" for t in hazards)
    return Generated(text, len(obstacles), washes, len(hazards) - washes, asked)


class _Placer:
    """Draws places along the course and keeps what leaves the scenario fair."""

    def __init__(self, course: Course, rng: np.random.Generator) -> None:
        self.route: CoursePath = course.interpolate()
        self.stations = Stations.along(course)
        self.rng = rng
        self.blocking: list[Blocker] = []
        self.taken: list[float] = []

    def place(self, draw: Callable[[float], Placed]) -> Placed:
        """``draw(half_width_m)``'s things at the first random place where they are fair (drawn
        anew for each place tried), or nothing after ATTEMPTS places."""
        first, last = START_CLEAR_M, self.route.length_m - FINISH_CLEAR_M
        if last <= first:
            return []
        for _ in range(ATTEMPTS):
            at = round(float(self.rng.uniform(first, last)), 1)
            if any(abs(at - other) < SPACING_M for other in self.taken):
                continue
            index = int(np.searchsorted(self.route.s_m, at).clip(0, len(self.route.s_m) - 1))
            things = [(kind, {"at_m": at, **table}) for kind, table in draw(float(self.route.half_width_m[index]))]
            if not things:
                continue
            new = blockers(
                World(
                    obstacles=tuple(obstacle_from_table(self.route, t) for kind, t in things if kind == "obstacle"),
                    hazards=tuple(hazard_from_table(self.route, t) for kind, t in things if kind == "hazard"),
                )
            )
            if find_unfairness(self.stations, self.blocking + new) is None:
                self.blocking += new
                self.taken.append(at)
                return things
        return []


def _obstacles(placer: _Placer, rng: np.random.Generator, count: int) -> Placed:
    """``count`` obstacles (a gate is two), as many as fit in twice that many tries."""
    kinds: list[tuple[float, Callable[[str], Callable[[float], Placed]]]] = [
        (0.35, lambda name: _single(rng, f"rock_{name}", _rock)),
        (0.25, lambda name: _single(rng, f"boulder_{name}", _boulder)),
        (0.25, lambda name: _single(rng, f"shrub_{name}", _shrub)),
        (0.05, lambda name: _single(rng, f"car_{name}", _car)),
        (0.10, lambda name: lambda half: _gate(rng, f"gate_{name}", half)),
    ]
    weights = np.array([w for w, _ in kinds])
    placed: Placed = []
    for i in range(2 * count):
        if len(placed) >= count:
            break
        # A gate only where two more obstacles are wanted; a rock instead.
        choice = int(rng.choice(len(kinds), p=weights / weights.sum()))
        if choice == len(kinds) - 1 and count - len(placed) < 2:
            choice = 0
        placed += placer.place(kinds[choice][1](str(i)))
    return placed


def _single(
    rng: np.random.Generator, name: str, make: Callable[[np.random.Generator], tuple[Table, float]]
) -> Callable[[float], Placed]:
    """One obstacle at an offset that leaves the lane on at least one side of it."""

    def draw(half: float) -> Placed:
        table, extent = make(rng)
        left = (-half + EDGE_M, min(half - EDGE_M, half - extent - LANE_WIDTH_M))  # lane on its left
        right = (max(-half + EDGE_M, -half + extent + LANE_WIDTH_M), half - EDGE_M)
        ranges = [(low, high) for low, high in (left, right) if high > low]
        if not ranges:
            return []
        sizes = np.array([high - low for low, high in ranges])
        low, high = ranges[int(rng.choice(len(ranges), p=sizes / sizes.sum()))]
        return [("obstacle", {"name": name, "offset_m": _round(rng.uniform(low, high)), **table})]

    return draw


def _rock(rng: np.random.Generator) -> tuple[Table, float]:
    """A box rock turned a little from the course; its half extent across the course."""
    length = rng.uniform(0.4, 1.6)
    width = rng.uniform(0.4, length)
    yaw = rng.uniform(-0.6, 0.6)
    table = {"shape": "box", "length_m": length, "width_m": width, "yaw_rad": yaw, "height_m": rng.uniform(0.3, 1.4)}
    return _rounded(table), (length * abs(math.sin(yaw)) + width * abs(math.cos(yaw))) / 2


def _boulder(rng: np.random.Generator) -> tuple[Table, float]:
    radius = _round(rng.uniform(0.2, 0.8))
    return {"shape": "cylinder", "radius_m": radius, "height_m": _round(rng.uniform(0.3, 1.5))}, radius


def _shrub(rng: np.random.Generator) -> tuple[Table, float]:
    radius = _round(rng.uniform(0.3, 1.0))
    table = {"shape": "cylinder", "radius_m": radius, "height_m": _round(rng.uniform(0.4, 1.2))}
    return {**table, "texture": "vegetation"}, radius


def _car(rng: np.random.Generator) -> tuple[Table, float]:
    yaw = rng.uniform(-0.3, 0.3)
    table = {"shape": "box", "length_m": 4.2, "width_m": 1.8, "yaw_rad": yaw, "height_m": 1.5, "texture": "metal"}
    return _rounded(table), (4.2 * abs(math.sin(yaw)) + 1.8 * abs(math.cos(yaw))) / 2


def _gate(rng: np.random.Generator, name: str, half: float) -> Placed:
    """Two rocks square to the course with a gap of the lane and a little more between them."""
    widths = rng.uniform(0.6, 1.6, size=2)
    gap = LANE_WIDTH_M + rng.uniform(0.2, 0.8)
    low = -half + EDGE_M + gap / 2 + widths[1] / 2
    high = half - EDGE_M - gap / 2 - widths[0] / 2
    if high <= low:
        return []
    centre = rng.uniform(low, high)
    placed: Placed = []
    for side, sign, width in (("left", 1.0, widths[0]), ("right", -1.0, widths[1])):
        rock = {"shape": "box", "length_m": rng.uniform(0.6, 1.6), "width_m": width, "height_m": rng.uniform(0.8, 1.5)}
        placed.append(
            (
                "obstacle",
                {"name": f"{name}_{side}", "offset_m": _round(centre + sign * (gap + width) / 2)} | _rounded(rock),
            )
        )
    return placed


def _across(rng: np.random.Generator, name: str, half: float, kind: str) -> Placed:
    """A ditch or berm from beyond one edge of the road across it, leaving the lane and a little
    more at the other edge: a ditch all of the way, a berm part of it."""
    free = LANE_WIDTH_M + rng.uniform(0.2, 1.2)
    reach = (2 * half - free) * (1.0 if kind == "ditch" else rng.uniform(0.3, 1.0))
    if reach < 1.0:
        return []
    beyond = rng.uniform(0.5, 2.5)
    side = 1.0 if rng.random() < 0.5 else -1.0  # the edge it starts beyond
    if kind == "ditch":
        length, size = {"length_m": rng.uniform(1.5, 3.0)}, {"depth_m": rng.uniform(0.4, 1.0)}
    else:
        length, size = {"length_m": rng.uniform(2.0, 5.0)}, {"height_m": rng.uniform(0.3, 0.8)}
    across = {"offset_m": side * (half - (reach - beyond) / 2), "width_m": reach + beyond}
    return [("hazard", _rounded({"name": name, "kind": kind} | across | length | size))]


def _round(value: float) -> float:
    return round(float(value), DIGITS)


def _rounded(table: Table) -> Table:
    return {key: _round(value) if isinstance(value, float) else value for key, value in table.items()}


def _rddf_reference(rddf: Path, output: Path) -> str:
    """The RDDF as the scenario names it: relative beside or below the scenario (the loader reads
    it relative to the scenario's folder), absolute anywhere else."""
    course, folder = rddf.resolve(), output.resolve().parent
    return course.relative_to(folder).as_posix() if course.is_relative_to(folder) else str(course)


def _toml(head: Table, obstacles: list[Table], hazards: list[Table], options: Options, rddf_name: str) -> str:
    counts = "".join(
        f" --{key} {value}"
        for key, value in (("washes", options.washes), ("berms", options.berms))
        if value is not None
    )
    lines = [
        f"# Generated by `rascal scenario generate {rddf_name} --seed {options.seed} "
        f"--obstacles-per-km {options.obstacles_per_km:g}{counts} --gps-jumps {options.gps_jumps_per_hour:g}`.",
        f"# Fair: every obstacle and hazard leaves a free lane of {LANE_WIDTH_M:g} m (modules/sim/fairness.py).",
        "",
        "[scenario]",
        *_pairs(head),
    ]
    for name, tables in (("obstacle", obstacles), ("hazard", hazards)):
        for table in tables:
            first = {key: table[key] for key in ("name", "shape", "kind", "at_m", "offset_m") if key in table}
            lines += ["", f"[[{name}]]", *_pairs(first | table)]
    if options.gps_jumps_per_hour > 0:
        jumps = {"per_hour": float(options.gps_jumps_per_hour), "magnitude_m": [5.0, 20.0], "duration_s": [1.0, 4.0]}
        lines += ["", "[gps_jumps]", *_pairs(jumps)]
    return "\n".join(lines) + "\n"


def _pairs(table: Table) -> list[str]:
    return [f"{key} = {_value(value)}" for key, value in table.items()]


def _value(value: Any) -> str:
    if isinstance(value, str):
        return json.dumps(value)  # a JSON string is a TOML basic string
    if isinstance(value, list):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    return repr(value)


def add_scenario_commands(commands: Any) -> None:
    """Register ``scenario generate`` on the `rascal` command's subparsers."""
    scenario = commands.add_parser("scenario", help="simulation scenarios")
    tools = scenario.add_subparsers(dest="tool", required=True)
    gen = tools.add_parser("generate", help="a hard but fair scenario (obstacles, washes, berms) on any RDDF")
    gen.add_argument("rddf", type=Path, help="RDDF file of the course")
    gen.add_argument("--seed", type=int, required=True, help="random seed: the same seed gives the same file")
    gen.add_argument("-o", "--output", type=Path, required=True, help="scenario TOML file to write")
    gen.add_argument("--obstacles-per-km", type=_not_negative, default=8.0, help="obstacles per km (%(default)s)")
    gen.add_argument("--washes", type=_count, help="ditches across the road (default: one per 2 km)")
    gen.add_argument("--berms", type=_count, help="berms across part of the road (default: one per 2 km)")
    gen.add_argument("--gps-jumps", type=_not_negative, default=12.0, help="GPS jumps per hour (%(default)s)")
    gen.add_argument("--name", help="scenario name (default: the RDDF's name and the seed)")
    gen.set_defaults(handler=_generate)


def _not_negative(text: str) -> float:
    value = float(text)
    if not 0.0 <= value < math.inf:
        raise argparse.ArgumentTypeError(f"{text} is not a number >= 0")
    return value


def _count(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text} is negative")
    return value


def _generate(args: argparse.Namespace) -> int:
    options = Options(args.seed, args.obstacles_per_km, args.washes, args.berms, args.gps_jumps, args.name)
    try:
        result = generate(args.rddf, args.output, options)
        args.output.write_text(result.text, encoding="utf-8")
    except (OSError, ValueError) as exc:  # RddfError is a ValueError
        print(f"rascal scenario generate: {exc}", file=sys.stderr)
        return 2
    asked = result.asked
    print(
        f"wrote {args.output}: {result.obstacles} of {asked['obstacles']} obstacles, "
        f"{result.washes} of {asked['washes']} washes, {result.berms} of {asked['berms']} berms"
    )
    return 0
