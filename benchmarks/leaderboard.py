"""The drive leaderboard's scoring, targets, tables and JSON (benchmarks/bench_drive.py drives).

Scoring (from each run's summary.json, the referee's drive measures): route completion is the
share of the route driven, 100 % once the referee saw the finish (stopped within 5 m of the end,
where control stops); each infraction multiplies the drive's score by its penalty factor, so
driving score = completion x 0.5^collisions x 0.7^corridor exits x 0.6^ditch/berm entries x
0.7^stalls (a stall: under 0.1 m/s for over 30 s before the finish). Totals weigh completion and
score by route length, speed ratio and cross-track RMS by the distance driven (where they were
measured); infractions per km are over the km driven. Targets (issue 23): route completion >= 99 %
on every drive, 0 collisions, 0 ditch/berm entries, no stall, at most 1 corridor exit per 50 km,
driving score >= 95 %, speed >= 80 % of what the RDDF and the curvature allow; and, for the
standard and full suites, >= 20 km of generated courses over >= 10 seeds with narrow stretches
(3.7-6 m corridors). Output: a table per drive with a totals row, the infractions per km, the
targets with pass/fail, and a JSON file (``--json``, by default ``leaderboard.json`` in the runs dir).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from benchmarks.report import Table
from brain.course_gen import NARROW_WIDTH_M
from modules.referee.measures import drove_safely

MIN_SPEED_RATIO = 0.80
MAX_CROSS_TRACK_RMS_M = 0.3  # issue 7's per-drive rule (the "clean" column)

# CARLA's leaderboard multiplies by 0.50 (pedestrian), 0.60 (vehicle), 0.65 (static) per collision,
# 0.7 per red light: ours, a collision with anything is the worst, a stall or an exit the mildest.
PENALTIES = {"collisions": 0.5, "corridor_exits": 0.7, "hazard_entries": 0.6, "stalls": 0.7}
INFRACTIONS = {
    "collisions": "collision",
    "corridor_exits": "corridor exit",
    "hazard_entries": "ditch/berm entry",
    "stalls": "stall",
}
MIN_COMPLETION = 0.99
MIN_DRIVING_SCORE = 0.95
MAX_EXITS_PER_KM = 1 / 50
MIN_GENERATED_KM = 20.0
MIN_SEEDS = 10
NARROW_MIN_WIDTH_M = 3.7


def completion(measures: Mapping[str, Any]) -> float:
    """Share of the route driven: all of it once the referee saw the finish."""
    return 1.0 if measures.get("finished") else float(measures.get("completion", 0.0))


def driving_score(measures: Mapping[str, Any]) -> float:
    """Completion times each infraction's penalty factor."""
    return completion(measures) * math.prod(p ** int(measures.get(kind, 0)) for kind, p in PENALTIES.items())


def meets_targets(measures: Mapping[str, Any]) -> bool:
    """Issue 7's rule for one drive: finished with no infraction, speed and tracking on target."""
    return bool(
        drove_safely(measures)
        and measures.get("stalls", 0) == 0
        and float(measures.get("speed_ratio", 0.0)) >= MIN_SPEED_RATIO
        and float(measures.get("cross_track_rms_m", 1e9)) <= MAX_CROSS_TRACK_RMS_M
    )


def totals(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """The suite's totals: completion and score weighted by route length, speed and tracking by
    the distance driven, infractions counted and per km driven."""
    route = [float(r["course"]["route_length_m"]) for r in records]
    driven = [float(r["measures"].get("progress_m", 0.0)) for r in records]
    measured = [(d, r["measures"]) for d, r in zip(driven, records, strict=True) if d > 0.0]
    driven_km = sum(driven) / 1000
    counts = {kind: sum(r["infractions"][kind] for r in records) for kind in PENALTIES}
    rms = [
        (d, float(m["cross_track_rms_m"])) for d, m in measured if math.isfinite(m.get("cross_track_rms_m", math.nan))
    ]
    return {
        "drives": len(records),
        "seeds": len({r["seed"] for r in records}),
        "route_km": sum(route) / 1000,
        "driven_km": driven_km,
        "generated_km": sum(x for x, r in zip(route, records, strict=True) if r["kind"] == "generated") / 1000,
        "narrow_km": sum(float(r["course"]["narrow_m"]) for r in records) / 1000,
        "completion": _weighted([r["completion"] for r in records], route),
        "driving_score": _weighted([r["driving_score"] for r in records], route),
        "infractions": counts,
        "per_km": {kind: _per_km(n, driven_km) for kind, n in counts.items()},
        "speed_ratio": _weighted([float(m.get("speed_ratio", 0.0)) for _, m in measured], [d for d, _ in measured]),
        "cross_track_rms_m": math.sqrt(_weighted([x**2 for _, x in rms], [d for d, _ in rms])) if rms else math.nan,
        "time_s": sum(float(r["measures"].get("time_s", 0.0)) for r in records),
        "wall_s": sum(float(r["wall_s"]) for r in records),
        "clean": sum(bool(r["clean"]) for r in records),
    }


def _weighted(values: Sequence[float], weights: Sequence[float]) -> float:
    total = sum(weights)
    return sum(v * w for v, w in zip(values, weights, strict=True)) / total if total > 0 else 0.0


def _per_km(count: int, km: float) -> float:
    if km > 0:
        return count / km
    return math.inf if count else 0.0


@dataclass(frozen=True)
class Target:
    name: str
    measured: str
    required: str
    passed: bool | None  # None: does not apply to this suite
    failing: tuple[str, ...] = ()  # the drives that missed it


def targets(records: Sequence[Mapping[str, Any]], total: Mapping[str, Any], coverage: bool) -> list[Target]:
    """Issue 23's targets on the totals (route completion on every drive); the coverage ones
    (km, seeds, narrow stretches) only where ``coverage``."""

    def drives_with(kind: str) -> tuple[str, ...]:
        return tuple(r["name"] for r in records if r["infractions"][kind])

    short = tuple(r["name"] for r in records if r["completion"] < MIN_COMPLETION)
    lowest = min((r["completion"] for r in records), default=0.0)
    count = total["infractions"]
    found = [
        Target("route completion", f"{lowest:.1%} lowest", f">= {MIN_COMPLETION:.0%} each", not short, short),
        *(
            Target(name, str(count[kind]), "0", count[kind] == 0, drives_with(kind))
            for kind, name in (
                ("collisions", "collisions"),
                ("hazard_entries", "ditch/berm entries"),
                ("stalls", "stalls"),
            )
        ),
        Target(
            "corridor exits",
            f"{count['corridor_exits']} in {total['driven_km']:.1f} km",
            "<= 1 per 50 km",
            total["per_km"]["corridor_exits"] <= MAX_EXITS_PER_KM,
            drives_with("corridor_exits"),
        ),
        Target(
            "driving score",
            f"{total['driving_score']:.1%}",
            f">= {MIN_DRIVING_SCORE:.0%}",
            total["driving_score"] >= MIN_DRIVING_SCORE,
        ),
        Target(
            "speed ratio",
            f"{total['speed_ratio']:.1%}",
            f">= {MIN_SPEED_RATIO:.0%} of allowed",
            total["speed_ratio"] >= MIN_SPEED_RATIO,
        ),
    ]

    def covered(ok: bool) -> bool | None:
        return ok if coverage else None

    found += [
        Target(
            "generated courses",
            f"{total['generated_km']:.1f} km",
            f">= {MIN_GENERATED_KM:g} km",
            covered(total["generated_km"] >= MIN_GENERATED_KM),
        ),
        Target("seeds", str(total["seeds"]), f">= {MIN_SEEDS}", covered(total["seeds"] >= MIN_SEEDS)),
        Target(
            "narrow stretches",
            f"{total['narrow_km']:.2f} km",
            f"> 0 km {NARROW_MIN_WIDTH_M:g}-{NARROW_WIDTH_M:g} m wide",
            covered(total["narrow_km"] > 0),
        ),
    ]
    return found


def passed(found: Iterable[Target]) -> bool:
    return all(t.passed is not False for t in found)


# -- output ----------------------------------------------------------------------------------


def drive_table(records: Sequence[Mapping[str, Any]], total: Mapping[str, Any]) -> Table:
    out = Table(
        "drive leaderboard: score = completion x "
        + " x ".join(f"{PENALTIES[kind]:g}/{name}" for kind, name in INFRACTIONS.items()),
        [
            "drive",
            "seed",
            "km",
            "width m",
            "done %",
            "score %",
            "collisions",
            "exits",
            "ditch/berm",
            "stalls",
            "speed %",
            "RMS m",
            "time s",
            "wall s",
            "clean",
        ],
    )
    for r in records:
        m, c = r["measures"], r["course"]
        measured = (
            [f"{100 * float(m['speed_ratio']):.1f}", f"{m['cross_track_rms_m']:.2f}", f"{m['time_s']:.0f}"]
            if m
            else ["-"] * 3
        )
        out.add(
            r["name"],
            str(r["seed"]),
            f"{c['route_length_m'] / 1000:.2f}",
            f"{c['min_width_m']:.1f}-{c['max_width_m']:.1f}",
            f"{100 * r['completion']:.1f}",
            f"{100 * r['driving_score']:.1f}",
            *(str(r["infractions"][kind]) if m else "-" for kind in PENALTIES),
            *measured,
            f"{r['wall_s']:.0f}",
            "yes" if r["clean"] else "no",
        )
    out.add(
        f"total ({total['drives']} drives)",
        f"{total['seeds']} seeds",
        f"{total['route_km']:.2f}",
        f"{total['narrow_km']:.2f} narrow",
        f"{100 * total['completion']:.1f}",
        f"{100 * total['driving_score']:.1f}",
        *(str(total["infractions"][kind]) for kind in PENALTIES),
        f"{100 * total['speed_ratio']:.1f}",
        f"{total['cross_track_rms_m']:.2f}",
        f"{total['time_s']:.0f}",
        f"{total['wall_s']:.0f}",
        f"{total['clean']}/{total['drives']}",
    )
    return out


def infraction_table(total: Mapping[str, Any]) -> Table:
    out = Table(f"infractions over {total['driven_km']:.2f} km driven", ["kind", "count", "per km", "penalty each"])
    for kind, name in INFRACTIONS.items():
        out.add(name, str(total["infractions"][kind]), f"{total['per_km'][kind]:.3f}", f"x {PENALTIES[kind]:g}")
    return out


def target_table(found: Sequence[Target]) -> Table:
    out = Table("targets (issue 23)", ["target", "measured", "required", "result"])
    for t in found:
        result = "n/a (quick suite)" if t.passed is None else "pass" if t.passed else "FAIL"
        out.add(t.name, t.measured, t.required, result + (f": {', '.join(t.failing)}" if t.failing else ""))
    return out


def leaderboard(
    records: Sequence[Mapping[str, Any]], suite: str, seeds: Sequence[int], notes: Sequence[str], machine: str
) -> dict[str, Any]:
    """The JSON file's content."""
    total = totals(records)
    found = targets(records, total, coverage=suite != "quick")
    return {
        "benchmark": "drive leaderboard",
        "machine": machine,
        "suite": suite,
        "seeds": list(seeds),
        "penalties": PENALTIES,
        "notes": list(notes),
        "drives": list(records),
        "totals": total,
        "targets": [asdict(t) for t in found],
        "passed": passed(found),
    }


def _json_safe(value: Any) -> Any:
    """NaN and infinity as null: the file stays strict JSON."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def write_json(board: Mapping[str, Any], path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(_json_safe(dict(board)), indent=2, allow_nan=False) + "\n")
