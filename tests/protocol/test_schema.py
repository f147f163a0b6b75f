"""Message layouts: pinned fingerprints, round trips, evolution rules and body validation."""

from __future__ import annotations

import math
import typing
from typing import Any, NamedTuple

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from protocol import messages as m
from protocol.codec import decode_body
from protocol.errors import ProtocolError, Reason
from protocol.schema import fingerprint, info_for_class, info_for_id, registered
from tests.protocol.wire_samples import SAMPLES, type_id_of

# The wire contract. A change here is a protocol change that old peers will misread: do it only
# on purpose, together with SPEC.md (and VERSION if the change is not an append-with-default).
GOLDEN: dict[int, tuple[str, str]] = {
    1: ("TimeSync", "989ed9c660e9faf8"),
    2: ("ModuleStatus", "d376bc08719cce38"),
    3: ("HealthEvent", "862133c3f7431b67"),
    4: ("ConfigUpdate", "4d3e3bc247c2030a"),
    10: ("ImuSample", "5e9a35ebcb95e93b"),
    11: ("GpsFix", "dd830c13e945f763"),
    12: ("WheelSpeed", "24c5300df6fb3739"),
    13: ("MagHeading", "2fa849d972a77e4c"),
    20: ("VehicleState", "fda7a68816b554f1"),
    21: ("ObstacleList", "85175bc0e15949c0"),
    22: ("SurfaceProfile", "84559fb4ccd5d120"),
    23: ("LaneBorders", "8ff4b3d6abcaa405"),
    24: ("GroundSweep", "7a5b86b4a0099cbd"),
    30: ("Path", "3387f977ed5b627c"),
    31: ("ActuatorCommand", "783779b677412cc1"),
    32: ("StopCommand", "3b3c936b4632a3d6"),
    40: ("MapSnapshot", "e05fe0c760424aea"),
    90: ("SimTruth", "9b774763b7816aa9"),
}

INFOS = registered()
WITH_DEFAULTS = [info for info in INFOS if info.cls._field_defaults]
NON_FINITE = [math.nan, math.inf, -math.inf]


def pack(value: Any) -> bytes:
    return msgpack.packb(value, use_bin_type=True)


def sample_of(cls: type) -> Any:
    return next(sample for sample in SAMPLES if type(sample) is cls)


def hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def n_required(cls: type) -> int:
    return len(cls._fields) - len(cls._field_defaults)


def assert_bad_body(type_id: int, body: Any) -> None:
    with pytest.raises(ProtocolError) as caught:
        decode_body(type_id, pack(body))
    assert caught.value.reason is Reason.BAD_BODY, caught.value


# -- fingerprints ------------------------------------------------------------------------------


def test_registered_layouts_match_the_golden_fingerprints() -> None:
    """Every registered message's (type_id, name, fingerprint) is exactly the pinned one."""
    actual = {info.type_id: (info.cls.__name__, info.fingerprint) for info in INFOS}
    assert actual == GOLDEN, (
        "A wire layout changed (or a message was added/removed). If that is deliberate, bump it "
        "deliberately: update GOLDEN here and SPEC.md, and bump protocol VERSION unless the change only "
        "appends fields with defaults. Differences: "
        + repr(
            {
                tid: (GOLDEN.get(tid), actual.get(tid))
                for tid in GOLDEN.keys() | actual.keys()
                if GOLDEN.get(tid) != actual.get(tid)
            }
        )
    )


def test_fingerprint_changes_iff_the_layout_changes() -> None:
    """Same name and fields give the same fingerprint; appending, renaming or retyping a field
    (including inside a nested record) gives a different one."""

    def make(*fields: tuple[str, Any], name: str = "WheelSpeed") -> type:
        return NamedTuple(name, list(fields))  # type: ignore[misc]

    base = fingerprint(m.WheelSpeed)
    assert fingerprint(make(("speed_mps", float), ("odometer_m", float))) == base
    changed = [
        make(("speed_mps", float), ("odometer_m", float), ("extra", int)),
        make(("speed_mps", float), ("odometer_km", float)),
        make(("speed_mps", float), ("odometer_m", int)),
        make(("odometer_m", float), ("speed_mps", float)),
        make(("speed_mps", float), ("odometer_m", float), name="WheelSpeed2"),
    ]
    assert all(fingerprint(cls) != base for cls in changed)
    point = make(("east_m", float), ("north_m", float), ("speed_mps", int), name="PathPoint")
    nested = make(("path_id", int), ("points", tuple[point, ...]), ("slow_mode", bool), name="Path")
    assert fingerprint(nested) != fingerprint(m.Path)


def test_every_registered_type_has_a_sample() -> None:
    """The samples below cover every registered message type (so the round trips cover them all)."""
    assert {type(sample) for sample in SAMPLES} == {info.cls for info in INFOS}


# -- round trips -------------------------------------------------------------------------------


@pytest.mark.parametrize("sample", SAMPLES, ids=lambda s: type(s).__name__)
def test_every_message_round_trips_through_its_body_encoding(sample: Any) -> None:
    """decode(encode(msg)) == msg, with the registered class at top level and in nested records."""
    info = info_for_class(type(sample))
    decoded = decode_body(info.type_id, pack(sample))
    assert decoded == sample
    assert type(decoded) is type(sample)
    for name, tp in hints(type(sample)).items():
        (item,) = typing.get_args(tp)[:1] or (None,)
        if item is not None and hasattr(item, "_fields"):
            assert all(type(record) is item for record in getattr(decoded, name))


def _strategy(tp: Any) -> st.SearchStrategy[Any]:
    if tp is float:
        return st.floats(allow_nan=False, allow_infinity=False)
    if tp is bool:
        return st.booleans()
    if tp is int:
        return st.integers(-(2**63), 2**63 - 1)
    if tp is str:
        return st.text(max_size=40)
    if tp is bytes:
        return st.binary(max_size=40)
    if typing.get_origin(tp) is tuple:
        return st.lists(_strategy(typing.get_args(tp)[0]), max_size=12).map(tuple)
    return st.builds(tp, **{name: _strategy(t) for name, t in hints(tp).items()})


ANY_MESSAGE = st.one_of([_strategy(info.cls) for info in INFOS])


@settings(max_examples=400, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(ANY_MESSAGE)
def test_any_message_with_finite_values_round_trips(msg: Any) -> None:
    """Every message of in-range values (any finite float, however large) decodes to itself."""
    assert decode_body(info_for_class(type(msg)).type_id, pack(msg)) == msg


def test_finite_floats_whose_sum_overflows_are_accepted() -> None:
    """Large finite values are valid: 1e308 + 1e308 overflowing in a checksum is not a NaN."""
    big = 1.5e308
    for msg in [
        m.WheelSpeed(big, big),
        m.ImuSample(big, big, -big, -big, big, 0.0),
        m.SurfaceProfile(1, big, (big, big, big), (-big, -big)),
        m.ObstacleList(1, 0, (m.Obstacle(big, big, big, big, big, big, big, big),)),
        m.Path(1, (m.PathPoint(big, big, 1.0), m.PathPoint(big, big, 1.0)), False),
    ]:
        assert decode_body(info_for_class(type(msg)).type_id, pack(msg)) == msg


# -- evolution ---------------------------------------------------------------------------------


@pytest.mark.parametrize("sample", SAMPLES, ids=lambda s: type(s).__name__)
def test_extra_trailing_fields_are_ignored(sample: Any) -> None:
    """A body from a newer layout (more trailing fields, of any type) decodes to the known fields."""
    newer = (*sample, 7, "appended", [1.5, 2.5], {"k": b"v"}, None)
    assert decode_body(type_id_of(type(sample)), pack(newer)) == sample


def test_nested_records_with_extra_trailing_fields_are_ignored() -> None:
    """Nested records from a newer layout (one more field each) decode to the known fields."""
    sample = sample_of(m.ObstacleList)
    newer = (sample.sensor, sample.frame, [(*obstacle, 0.5) for obstacle in sample.obstacles])
    assert decode_body(type_id_of(m.ObstacleList), pack(newer)) == sample
    borders = sample_of(m.LaneBorders)
    newer = (borders.sensor, [(*border, "note", 3) for border in borders.borders])
    assert decode_body(type_id_of(m.LaneBorders), pack(newer)) == borders


@pytest.mark.parametrize("info", WITH_DEFAULTS, ids=lambda i: i.cls.__name__)
def test_missing_trailing_fields_with_defaults_decode_to_the_defaults(info: Any) -> None:
    """A body from an older layout (without the appended, defaulted fields) gets the defaults."""
    sample = sample_of(info.cls)
    for count in range(n_required(info.cls), len(sample)):
        decoded = decode_body(info.type_id, pack(tuple(sample)[:count]))
        expected = info.cls(*tuple(sample)[:count])  # the NamedTuple fills the defaults
        assert decoded == expected
        assert all(getattr(decoded, name) == info.cls._field_defaults[name] for name in info.cls._fields[count:])


@pytest.mark.parametrize("info", INFOS, ids=lambda i: i.cls.__name__)
def test_missing_required_fields_are_bad_body(info: Any) -> None:
    """A body with fewer fields than the required (non-defaulted) ones is BAD_BODY, at every length."""
    sample = sample_of(info.cls)
    for count in range(n_required(info.cls)):
        assert_bad_body(info.type_id, tuple(sample)[:count])


def test_nested_records_missing_required_fields_are_bad_body() -> None:
    """A nested record one field short is BAD_BODY (records have no defaults)."""
    obstacles = sample_of(m.ObstacleList)
    assert_bad_body(type_id_of(m.ObstacleList), (1, 0, [tuple(o)[:-1] for o in obstacles.obstacles]))
    assert_bad_body(type_id_of(m.ObstacleList), (1, 0, [tuple(obstacles.obstacles[0]), (1.0,) * 7]))
    assert_bad_body(type_id_of(m.Path), (1, [(1.0, 2.0)], False))
    assert_bad_body(type_id_of(m.LaneBorders), (1, [(1, 0.0, 0.0, 0.0, 0.0, 1.0)]))


# -- validation --------------------------------------------------------------------------------

# A value of the wrong type for each declared field type (bool is an int, int a float: both
# legitimately pass, so the wrong values avoid them).
WRONG_FOR: dict[Any, list[Any]] = {
    float: ["1.0", b"\x00", None, [1.0], {"x": 1.0}],
    int: [1.5, "1", None, [1], b"1"],
    bool: [1, 0.0, "true", None],
    str: [b"text", 1, None, ["a"]],
    bytes: ["text", 1, None],
}
WRONG_FOR_SEQUENCE = [1.0, "abc", None, {"a": 1}, b"\x01\x02"]


def _wrong_values(tp: Any) -> list[Any]:
    return WRONG_FOR_SEQUENCE if typing.get_origin(tp) is tuple else WRONG_FOR[tp]


FIELDS = [(info, index, name) for info in INFOS for index, name in enumerate(info.cls._fields)]


@pytest.mark.parametrize("info,index,name", FIELDS, ids=[f"{i.cls.__name__}.{n}" for i, _, n in FIELDS])
def test_a_field_of_the_wrong_type_is_bad_body(info: Any, index: int, name: str) -> None:
    """Replacing any one field of a valid body with a value of another type gives BAD_BODY."""
    sample = list(sample_of(info.cls))
    for wrong in _wrong_values(hints(info.cls)[name]):
        body = sample.copy()
        body[index] = wrong
        assert_bad_body(info.type_id, body)


def test_sequence_elements_of_the_wrong_type_are_bad_body() -> None:
    """An element of the wrong type anywhere in an array field (scalars or records) is BAD_BODY."""
    status = list(sample_of(m.ModuleStatus))
    status[8] = ["GPS", 3]
    assert_bad_body(type_id_of(m.ModuleStatus), status)
    for wrong in ["x", None, [1.0], b"1", {"a": 1}]:
        assert_bad_body(type_id_of(m.SurfaceProfile), (1, 0.0, (1.0, wrong, 2.0), ()))
        assert_bad_body(type_id_of(m.VehicleState), (*sample_of(m.VehicleState)[:8], (0.0,) * 24 + (wrong,), 1))
        record = [1.0] * 8
        record[3] = wrong
        assert_bad_body(type_id_of(m.ObstacleList), (1, 0, [[2.0] * 8, record]))
        assert_bad_body(type_id_of(m.ObstacleList), (1, 0, [[2.0] * 8, wrong]))
        assert_bad_body(type_id_of(m.Path), (1, [[1.0, 2.0, 3.0], [wrong, 2.0, 3.0]], True))
        assert_bad_body(type_id_of(m.LaneBorders), (1, [[wrong, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0]]))
    assert_bad_body(type_id_of(m.LaneBorders), (1, [[1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0]]))  # side is an int


def test_ext_types_and_timestamps_are_bad_body_anywhere() -> None:
    """msgpack ext values (an ExtType is a tuple in Python) never pass as a field or record."""
    ext = msgpack.ExtType(5, b"\x00" * 8)
    stamp = msgpack.Timestamp(1, 0)
    for value in (ext, stamp):
        assert_bad_body(type_id_of(m.WheelSpeed), (value, 1.0))
        assert_bad_body(type_id_of(m.SurfaceProfile), (1, 0.0, value, ()))
        assert_bad_body(type_id_of(m.ObstacleList), (1, 0, value))
        assert_bad_body(type_id_of(m.ObstacleList), (1, 0, [value]))
        assert_bad_body(type_id_of(m.LaneBorders), (1, value))
        assert_bad_body(type_id_of(m.ModuleStatus), (*sample_of(m.ModuleStatus)[:8], value, 0, 0, 0))
    with pytest.raises(ProtocolError) as caught:
        decode_body(type_id_of(m.WheelSpeed), pack(ext))
    assert caught.value.reason is Reason.BAD_BODY


FLOAT_FIELDS = [
    (info, index, name) for info in INFOS for index, (name, tp) in enumerate(hints(info.cls).items()) if tp is float
]


@pytest.mark.parametrize("info,index,name", FLOAT_FIELDS, ids=[f"{i.cls.__name__}.{n}" for i, _, n in FLOAT_FIELDS])
def test_non_finite_top_level_floats_are_bad_body(info: Any, index: int, name: str) -> None:
    """NaN, +inf or -inf in any top-level float field is BAD_BODY."""
    for bad in NON_FINITE:
        body = list(sample_of(info.cls))
        body[index] = bad
        assert_bad_body(info.type_id, body)


@pytest.mark.parametrize("bad", NON_FINITE, ids=repr)
def test_non_finite_floats_in_float_arrays_are_bad_body(bad: float) -> None:
    """NaN/inf anywhere in a float array field (first, middle, last, alone) is BAD_BODY."""
    ranges = [2.0, 3.0, 4.0]
    for position in range(3):
        values = ranges.copy()
        values[position] = bad
        assert_bad_body(type_id_of(m.SurfaceProfile), (1, 0.0, values, ranges))
        assert_bad_body(type_id_of(m.SurfaceProfile), (1, 0.0, ranges, values))
    assert_bad_body(type_id_of(m.SurfaceProfile), (1, 0.0, [bad], []))
    state = sample_of(m.VehicleState)
    assert_bad_body(type_id_of(m.VehicleState), (*state[:8], (*state.covariance[:-1], bad), state.quality))


@pytest.mark.parametrize("bad", NON_FINITE, ids=repr)
def test_non_finite_floats_inside_nested_records_are_bad_body(bad: float) -> None:
    """NaN/inf in any float field of any nested record (obstacles, path points, lane borders) is
    BAD_BODY, on the fast path (current layout) and the slow path (other layouts) alike."""
    obstacles = [list(o) for o in sample_of(m.ObstacleList).obstacles[:3]]
    for field in range(8):
        for extra in ([], [0.5]):  # the current layout, and a newer one with an appended field
            records = [record + extra for record in obstacles]
            records[1] = records[1].copy()
            records[1][field] = bad
            assert_bad_body(type_id_of(m.ObstacleList), (1, 0, records))
    for field in range(3):
        point = [1.0, 2.0, 3.0]
        point[field] = bad
        assert_bad_body(type_id_of(m.Path), (5, [[0.0, 0.0, 1.0], point], False))
    for field in range(1, 7):
        border = list(sample_of(m.LaneBorders).borders[0])
        border[field] = bad
        assert_bad_body(type_id_of(m.LaneBorders), (1, [border]))


@pytest.mark.parametrize("body", [b"", b"\xc1", b"\x93\x01\x02", b"\x92\x01\x02\x03", b"\xd9\x02\xff\xfe"], ids=repr)
def test_malformed_msgpack_is_bad_body(body: bytes) -> None:
    """Bytes that are not exactly one msgpack value (empty, reserved byte, short, trailing data,
    invalid UTF-8) are BAD_BODY."""
    with pytest.raises(ProtocolError) as caught:
        decode_body(type_id_of(m.WheelSpeed), body)
    assert caught.value.reason is Reason.BAD_BODY


@pytest.mark.parametrize("body", [{"speed_mps": 1.0}, 1.0, "1.0", None, [[1.0, 2.0]]], ids=repr)
def test_a_body_that_is_not_a_field_array_is_bad_body(body: Any) -> None:
    """Maps, scalars, nil and wrongly nested arrays are not a message body."""
    assert_bad_body(type_id_of(m.WheelSpeed), body)


def test_an_unknown_type_id_is_unknown_type() -> None:
    """A type id nobody registered is UNKNOWN_TYPE, from the registry and from decode_body."""
    for type_id in (0, 5, 999, 0xFFFF):
        with pytest.raises(ProtocolError) as caught:
            decode_body(type_id, pack([1.0, 2.0]), source_id=9)
        assert caught.value.reason is Reason.UNKNOWN_TYPE
        with pytest.raises(ProtocolError):
            info_for_id(type_id)


def test_body_errors_carry_the_source_id() -> None:
    """decode_body attributes a BAD_BODY to the sending source, for per-source statistics."""
    with pytest.raises(ProtocolError) as caught:
        decode_body(type_id_of(m.WheelSpeed), pack([math.nan, 1.0]), source_id=77)
    assert caught.value.source_id == 77
