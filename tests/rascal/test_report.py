"""The run report: from a recorded drive (run.mcap + summary.json) to five images that show what
happened where it happened: the track's pixels lie on the course where the vehicle drove, in the
colour of its speed; the hazard the brain mapped is red on the course map; the speed chart's true
speed is a flat line at the speed driven; every image is written as PNG and SVG, and no text
covers another; `rascal report RUN_DIR` rebuilds them."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from brain.course_config import load_course
from brain.fusion.snapshot import encode_snapshot
from brain.grid import GridWindow
from brain.planning.frame import CorridorFrame
from protocol import channels
from protocol.messages import ActuatorCommand, ModuleStatus, PathPoint, SimTruth, VehicleState
from protocol.messages import Path as PlannedPath
from rascal.cli import main
from rascal.plotting import SPEED_CMAP, speed_norm
from rascal.report import build_report, report_run
from rascal.report_chart import CHART_PX, JITTER, TRUE, render_cross_track, render_speed, render_timing
from rascal.report_data import read_run
from rascal.report_track import HAZARD, render_final_map, render_track
from rascal.runtime.deployment import load_deployment
from tests.rascal.plot_checks import (
    assert_png,
    assert_svg,
    bgr,
    data_pixels,
    overlapping,
    png_of,
    svg_texts,
    text_boxes,
)
from tests.rascal.test_recording import make_recording

# A figure too small for its texts still draws, with this warning: the layout gave up.
pytestmark = pytest.mark.filterwarnings("error:constrained_layout not applied")

T0_NS = 1_700_000_000_000_000_000
# About 320 m: east, then north-east; 25 mph limit, 40 ft boundary; one rock on the way.
RDDF = "1,34.8650000,-116.8900000,40,25\n2,34.8650000,-116.8880000,40,25\n3,34.8660000,-116.8870000,40,25\n"
SCENARIO = """
[scenario]
rddf = "course.rddf"

[[obstacle]]
name = "rock"
shape = "cylinder"
at_m = 120.0
offset_m = 0.8
radius_m = 0.6
height_m = 1.0
"""
SPEED_MPS = 5.0
DRIVE_S = 40.0
MS = 1_000_000
HAZARD_AT = (60.0, -4.0)  # station, offset: something the brain mapped (nothing is there in the scenario)


def _drive(frame: CorridorFrame) -> list[tuple[str, object, int]]:
    """40 s at 5 m/s, weaving 1.5 m about the centre line; the navigation estimate 0.2 m to the
    left; a planned path along the centre line at 5 Hz; a map with one hazard at 1 Hz; heartbeats."""
    messages: list[tuple[str, object, int]] = []
    hazard_e, hazard_n = frame.to_enu(*HAZARD_AT)
    for k in range(int(DRIVE_S * 100)):
        t_s = k / 100.0
        t_ns = T0_NS + round(t_s * 1e9)
        s = 2.0 + SPEED_MPS * t_s
        d = 1.5 * math.sin(s / 20.0)
        east, north = (float(v) for v in frame.to_enu(s, d))
        yaw = float(frame.heading_at(s))
        messages.append(
            (channels.SIM_TRUTH, SimTruth(east, north, yaw, SPEED_MPS, 0.0, 0.0, s, 0, scenario_time_s=t_s), t_ns)
        )
        if k % 2 == 0:
            nav_e, nav_n = (float(v) for v in frame.to_enu(s, d + 0.2))
            state = VehicleState(nav_e, nav_n, 0.0, yaw, SPEED_MPS, 0.0, 0.0, 0.0, (0.0,) * 25, 3)
            messages.append((channels.VEHICLE_STATE, state, t_ns + 1000))
        if k % 20 == 0:
            ahead = np.arange(s, s + 40.0, 2.0)
            pe, pn = frame.to_enu(ahead, np.zeros_like(ahead))
            points = tuple(PathPoint(float(e), float(n), SPEED_MPS) for e, n in zip(pe, pn, strict=True))
            # Planned from inputs measured 60 ms before it was logged; the command below follows it.
            messages.append((channels.PATH, PlannedPath(k, points, False, t_ns + 2000 - 60 * MS), t_ns + 2000))
            messages.append((channels.ACTUATOR_COMMAND, ActuatorCommand(0.2, 0.0, 0.0), t_ns + 5000))
        if k % 100 == 0:
            window = GridWindow(east - 20.0, north - 20.0, 0.4, 100, 100)
            probability = np.full(window.shape, 0.5, dtype=np.float32)
            probability[40:60, 40:60] = 0.1  # seen clear round the vehicle
            col, row = (
                int((float(hazard_e) - window.origin_east_m) / 0.4),
                int((float(hazard_n) - window.origin_north_m) / 0.4),
            )
            if 2 <= row < 98 and 2 <= col < 98:
                probability[row - 2 : row + 3, col - 2 : col + 3] = 1.0
            messages.append((channels.MAP_SNAPSHOT, encode_snapshot(window, probability), t_ns + 3000))
            status = ModuleStatus("sim", 1, t_s, 10_000_000, 1_000_000 + 50_000 * (k // 100), 0, 0, 0, (), 2, 0, 0)
            messages.append((channels.MODULE_STATUS, status, t_ns + 4000))
    return messages


@pytest.fixture
def run_dir(tmp_path: Path) -> Path:
    (tmp_path / "course.rddf").write_text(RDDF)
    (tmp_path / "scenario.toml").write_text(SCENARIO)
    deploy = tmp_path / "deploy.toml"
    deploy.write_text(
        '[deployment]\nname = "short"\nbus = "udpm://239.255.1.2:7700?ttl=0"\n'
        'scenario = "scenario.toml"\ncourse = "course.rddf"\n[modules.time_service]\n'
    )
    course = load_course(tmp_path / "course.rddf")
    run = tmp_path / "runs" / "20260101-000000"
    run.mkdir(parents=True)
    make_recording(run / "run.mcap", _drive(CorridorFrame(course.interpolate())))
    drive = {"finished": False, "completion": 0.62, "route_length_m": 327.0, "time_s": DRIVE_S, "collisions": 0}
    summary = {"deployment": "short", "deployment_file": str(deploy), "finished": False, "drive": drive}
    (run / "summary.json").write_text(json.dumps(summary))
    return run


def _colour_pixels(image: np.ndarray, colour: str, tolerance: int = 12) -> np.ndarray:
    """(row, column) of every pixel within ``tolerance`` of ``colour`` in each channel."""
    return np.argwhere(np.all(np.abs(image.astype(int) - bgr(colour)) <= tolerance, axis=-1))


def test_the_report_writes_every_image_as_png_and_svg(run_dir: Path) -> None:
    report = build_report(run_dir)
    assert set(report.images) == {"track", "map", "speed", "cross_track", "timing"}
    # Each path's input, measured 60 ms before the path was logged, to the first command after it,
    # published 1 ms before it was logged 3 us after the path (the recording's stamps): 59 ms.
    assert report.latency_ms["p50"] == report.latency_ms["p99"] == 59.0
    assert report.latency_ms["samples"] == DRIVE_S * 100 // 20
    for name, (png, svg) in report.images.items():
        assert (png.name, svg.name) == (f"{name}.png", f"{name}.svg")
        assert_png(png)
        assert_svg(svg)
    texts = svg_texts(assert_svg(report.images["track"][1]))
    assert "START" in texts and "FINISH" in texts and "east (m)" in texts, "the SVG keeps its labels as text"


def test_the_course_map_draws_the_drive_where_it_happened(run_dir: Path) -> None:
    data = read_run(run_dir)
    figure = render_track(data, "a run")
    ax = figure.axes[0]
    track = png_of(figure)
    assert max(track.shape[:2]) <= 1600
    assert ax.get_aspect() == 1.0, "a metre is as long east as north"
    # Every track sample lies on a pixel of its speed's colour.
    truth = data.truth
    assert truth is not None and len(truth) == DRIVE_S * 10
    expected = bgr(SPEED_CMAP(speed_norm(float(data.course.speed_limit_mps.max()))(SPEED_MPS)))
    pixels = data_pixels(figure, ax, truth.east_m, truth.north_m)
    on_track = [np.abs(track[y, x].astype(int) - expected).max() <= 40 for x, y in pixels[5:-5:10]]
    assert np.mean(on_track) >= 0.9, "the track is drawn where the vehicle drove, in its speed's colour"
    ((hazard_x, hazard_y),) = data_pixels(figure, ax, *data.frame.to_enu(*HAZARD_AT))
    b, _g, r = track[hazard_y, hazard_x].astype(int)
    assert r - b > 80, "the hazard the brain mapped is red on the course map"
    ((far_x, far_y),) = data_pixels(figure, ax, *data.frame.to_enu(300.0, -8.0))
    assert np.abs(track[far_y, far_x].astype(int) - expected).max() > 40, "no track where the vehicle never went"
    assert overlapping(text_boxes(figure)) == [], "no text over another"


def test_the_charts_show_speed_offset_and_timing(run_dir: Path) -> None:
    data = read_run(run_dir)
    # The final map: its hazard cells are red.
    final = render_final_map(data, "a run")
    assert final is not None and len(_colour_pixels(png_of(final), HAZARD, 30)) > 50

    # Speed: the true speed is a flat line over the two thirds of the course driven.
    figure = render_speed(data)
    speed = png_of(figure)
    assert speed.shape[:2] == (CHART_PX[1], CHART_PX[0])
    red = _colour_pixels(speed, TRUE)
    row = np.bincount(red[:, 0]).argmax()
    line = red[np.abs(red[:, 0] - row) <= 2]
    assert len(line) >= 0.8 * len(red) and len(line) > 500, "one flat line (and the legend's swatch)"
    (left, _), (right, _) = data_pixels(figure, figure.axes[0], [2.0, 2.0 + SPEED_MPS * DRIVE_S], [0.0, 0.0])
    assert abs(np.ptp(line[:, 1]) - (right - left)) < 0.05 * (right - left), "from where it started to where it got"

    # Cross-track: the weave is in the top panel and the distance to the path in the bottom one.
    cross = png_of(render_cross_track(data))
    assert cross.shape[:2] == (2 * CHART_PX[1], CHART_PX[0])
    weave = _colour_pixels(cross[: CHART_PX[1]], TRUE)
    assert len(weave) > 500 and np.ptp(weave[:, 0]) > 40, "a 1.5 m weave moves the line up and down"
    assert len(_colour_pixels(cross[CHART_PX[1] :], TRUE)) > 500
    assert (
        data.paths
        and data.nav is not None
        and np.allclose(data.nav.d_m, 1.5 * np.sin(data.nav.s_m / 20) + 0.2, atol=0.05)
    )

    # Timing: one row (sim), its jitter bar drawn.
    timing_figure = render_timing(data)
    timing = png_of(timing_figure)
    assert timing.shape[1] == CHART_PX[0] and len(_colour_pixels(timing, JITTER, 5)) > 100
    assert data.modules["sim"].heartbeats == DRIVE_S and data.modules["sim"].jitter_ms[-1] == pytest.approx(2.95)
    for chart in (final, figure, timing_figure):
        assert overlapping(text_boxes(chart)) == [], "no text over another"


def test_rascal_report_rebuilds_the_images(run_dir: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["report", str(run_dir)]) == 0
    out = capsys.readouterr().out
    assert "track, map" in out and "(.png, .svg)" in out and "62.0 % of 327 m" in out
    for image in (run_dir / "report").iterdir():
        image.unlink()
    assert main(["report", str(run_dir), "--deployment", str(run_dir.parents[1] / "deploy.toml")]) == 0
    assert len(list((run_dir / "report").glob("*.png"))) == len(list((run_dir / "report").glob("*.svg"))) == 5


def test_a_report_without_images_still_summarises_the_run(run_dir: Path) -> None:
    """`rascal run --no-images`: the drive line and the latency, and not one file drawn."""
    bare = build_report(run_dir, images=False)
    assert bare.images == {} and not (run_dir / "report").exists()
    assert bare.latency_ms["p50"] == 59.0 and "62.0 % of 327 m" in bare.drive
    console = Console(record=True, width=200)
    assert report_run(run_dir, load_deployment(run_dir.parents[1] / "deploy.toml"), console, images=False) == bare
    assert f"rascal report {run_dir}" in console.export_text()


def test_what_is_not_a_run_gets_a_clear_error(tmp_path: Path, run_dir: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["report", str(tmp_path / "nothing")]) == 2
    assert "no summary.json" in capsys.readouterr().err
    (run_dir / "run.mcap").write_bytes(b"not mcap at all")
    assert main(["report", str(run_dir)]) == 2
    assert "not a readable MCAP file" in capsys.readouterr().err
    console = Console(record=True, width=200)
    assert report_run(run_dir, load_deployment(run_dir.parents[1] / "deploy.toml"), console) is None
    assert "no report:" in console.export_text()


def test_a_run_without_the_simulator_or_a_map_still_gets_its_report(run_dir: Path) -> None:
    """A real vehicle (or a host that hears no simulator): the navigation estimate stands in."""
    course = load_course(run_dir.parents[1] / "course.rddf")
    kept = [
        m
        for m in _drive(CorridorFrame(course.interpolate()))
        if m[0] not in (channels.SIM_TRUTH, channels.MAP_SNAPSHOT)
    ]
    (run_dir / "run.mcap").unlink()
    make_recording(run_dir / "run.mcap", kept)
    summary = json.loads((run_dir / "summary.json").read_text())
    (run_dir / "summary.json").write_text(json.dumps({**summary, "drive": None}))
    report = build_report(run_dir)
    assert set(report.images) == {"track", "speed", "cross_track", "timing"}, "no map without a snapshot"
    assert report.drive.startswith("not finished: course 327 m")
    cross = assert_png(report.images["cross_track"][0])
    assert len(_colour_pixels(cross[CHART_PX[1] :], TRUE)) > 500, "the estimate's distance from the path"
