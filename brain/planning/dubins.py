"""Dubins curves: the shortest forward path between two poses for a vehicle that turns no
tighter than a radius (Dubins 1957), from the six words of turns and straights (Shkel and
Lumelsky's closed forms). Hybrid A*'s analytic expansion tries one to the goal.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

from brain.pose import Pose

_DUBINS_WORDS = ("LSL", "RSR", "LSR", "RSL", "RLR", "LRL")


def dubins_points(start: Pose, goal: Pose, radius_m: float, chord_m: float) -> Iterator[tuple[float, float]]:
    """Points of the shortest Dubins curve from ``start`` to ``goal`` (forward, turns of
    ``radius_m``), its pieces split into equal chords of at most ``chord_m``, from the start on
    (lazily: a collision check stops early); nothing when no curve exists."""
    word = _dubins_shortest(start, goal, radius_m)
    if word is None:
        return
    east, north, heading = start
    yield east, north
    for letter, length in zip(*word, strict=True):
        metres = length * radius_m
        if metres < 1e-9:
            continue  # a piece the word does not need: no repeated point
        pieces = math.ceil(metres / chord_m - 1e-9)
        curvature = {"L": 1.0 / radius_m, "S": 0.0, "R": -1.0 / radius_m}[letter]
        for m in range(1, pieces):
            yield _along(east, north, heading, curvature, metres * m / pieces)
        east, north = _along(east, north, heading, curvature, metres)
        heading += curvature * metres
        yield east, north


def _along(east: float, north: float, heading: float, curvature: float, s: float) -> tuple[float, float]:
    """Where an arc (or line) of ``curvature`` from the pose is after ``s`` metres."""
    if curvature == 0.0:
        return east + s * math.cos(heading), north + s * math.sin(heading)
    end = heading + curvature * s
    return (
        east + (math.sin(end) - math.sin(heading)) / curvature,
        north - (math.cos(end) - math.cos(heading)) / curvature,
    )


def _dubins_shortest(start: Pose, goal: Pose, radius_m: float) -> tuple[str, tuple[float, float, float]] | None:
    """The shortest Dubins word and its three lengths in radii (Shkel and Lumelsky's formulas)."""
    de, dn = (goal[0] - start[0]) / radius_m, (goal[1] - start[1]) / radius_m
    d = math.hypot(de, dn)
    theta = math.atan2(dn, de)
    alpha, beta = (start[2] - theta) % math.tau, (goal[2] - theta) % math.tau
    best = None
    for word in _DUBINS_WORDS:
        lengths = _dubins_word(word, alpha, beta, d)
        if lengths is not None and (best is None or sum(lengths) < sum(best[1])):
            best = (word, lengths)
    return best


def _dubins_word(word: str, a: float, b: float, d: float) -> tuple[float, float, float] | None:
    sa, sb, ca, cb, cab = math.sin(a), math.sin(b), math.cos(a), math.cos(b), math.cos(a - b)
    tau = math.tau
    if word == "LSL":
        p2 = 2.0 + d * d - 2.0 * cab + 2.0 * d * (sa - sb)
        if p2 < 0.0:
            return None
        turn = math.atan2(cb - ca, d + sa - sb)
        return (-a + turn) % tau, math.sqrt(p2), (b - turn) % tau
    if word == "RSR":
        p2 = 2.0 + d * d - 2.0 * cab + 2.0 * d * (sb - sa)
        if p2 < 0.0:
            return None
        turn = math.atan2(ca - cb, d - sa + sb)
        return (a - turn) % tau, math.sqrt(p2), (-b + turn) % tau
    if word == "LSR":
        p2 = -2.0 + d * d + 2.0 * cab + 2.0 * d * (sa + sb)
        if p2 < 0.0:
            return None
        p = math.sqrt(p2)
        turn = math.atan2(-ca - cb, d + sa + sb) - math.atan2(-2.0, p)
        return (-a + turn) % tau, p, (-b + turn) % tau
    if word == "RSL":
        p2 = -2.0 + d * d + 2.0 * cab - 2.0 * d * (sa + sb)
        if p2 < 0.0:
            return None
        p = math.sqrt(p2)
        turn = math.atan2(ca + cb, d - sa - sb) - math.atan2(2.0, p)
        return (a - turn) % tau, p, (b - turn) % tau
    if word == "RLR":
        cosine = (6.0 - d * d + 2.0 * cab + 2.0 * d * (sa - sb)) / 8.0
        if abs(cosine) > 1.0:
            return None
        p = (tau - math.acos(cosine)) % tau
        t = (a - math.atan2(ca - cb, d - sa + sb) + p / 2.0) % tau
        return t, p, (a - b - t + p) % tau
    cosine = (6.0 - d * d + 2.0 * cab + 2.0 * d * (sb - sa)) / 8.0  # LRL
    if abs(cosine) > 1.0:
        return None
    p = (tau - math.acos(cosine)) % tau
    t = (-a - math.atan2(ca - cb, d + sa - sb) + p / 2.0) % tau
    return t, p, (b - a - t + p) % tau
