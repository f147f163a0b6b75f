"""rascal run --view in a real browser: headless Chromium (Debian's) loads the live page during a
short drive by real processes over the signed loopback bus, and the test reads the page over the
DevTools protocol: the vehicle moves on the canvas, the health panel lists every module (and a
restart when one is killed), and the page keeps up with 10 Hz map snapshots (it goes on drawing
maps newer than any it had, never working through a queue of old ones). A screenshot is kept
in the test's directory."""

from __future__ import annotations

import base64
import itertools
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import ROOT
from tests.integration.test_closed_loop import RDDF, SCENARIO
from tests.integration.test_supervisor import pids_of
from tests.rascal.test_view import free_port

websocket = pytest.importorskip("websocket", reason="websocket-client (a dev dependency) is not installed")

pytestmark = pytest.mark.slow

CHROMIUM = "chromium"
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--window-size=1200,800",
    "--remote-debugging-address=127.0.0.1",
    "--remote-debugging-port=0",  # Chromium picks one and writes it to DevToolsActivePort
]
# The lighter stack that still closes the loop: two horizontal lidars and no stereo.
MODULES = """
[modules.time_service]
[modules.sim]
[modules.nav_sensors]
[modules.lidar_h_left]
module = "lidar"
source_id = 21
set = { sensor = "lidar_h_left" }
[modules.lidar_h_right]
module = "lidar"
source_id = 22
set = { sensor = "lidar_h_right" }
[modules.ins]
[modules.brain]
set = { sensors = ["lidar_h_left", "lidar_h_right"], snapshot_rate_hz = 10.0 }
[modules.control]
[modules.health]
"""
EXPECTED_MODULES = {
    "time_service", "sim", "nav_sensors", "lidar_h_left", "lidar_h_right", "ins", "brain", "control", "health",
    "supervisor", "recorder", "viewer",
}  # fmt: skip
MOVED_PX = 20.0
MAPS_WANTED = 30


@pytest.fixture(scope="session")
def chromium() -> str:
    """Debian's Chromium, installed with apt-get when missing and we are root (CI is)."""
    found = shutil.which(CHROMIUM)
    if found:
        return found
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        pytest.skip("chromium is not installed and cannot be installed here (needs root and apt-get)")
    for command in (["apt-get", "update"], ["apt-get", "install", "-y", CHROMIUM]):
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        result = subprocess.run(command, capture_output=True, text=True, timeout=1200, check=False, env=env)
        assert result.returncode == 0, f"{' '.join(command)} failed:\n{result.stdout[-2000:]}\n{result.stderr[-2000:]}"
    found = shutil.which(CHROMIUM)
    assert found, "apt-get installed chromium but it is not on PATH"
    return found


class DevTools:
    """The smallest DevTools protocol client: one page target, commands answered in order."""

    def __init__(self, ws_url: str) -> None:
        self.ws = websocket.create_connection(ws_url, timeout=30, suppress_origin=True)
        self.ids = itertools.count(1)

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        message_id = next(self.ids)
        self.ws.send(json.dumps({"id": message_id, "method": method, "params": params}))
        while True:
            reply = json.loads(self.ws.recv())
            if reply.get("id") == message_id:
                assert "error" not in reply, reply
                return reply["result"]

    def evaluate(self, expression: str) -> Any:
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        assert "exceptionDetails" not in result, result
        return result["result"].get("value")

    def close(self) -> None:
        self.ws.close()


@pytest.fixture
def browser(chromium: str, tmp_path: Path) -> Iterator[tuple[subprocess.Popen[bytes], Path]]:
    profile = tmp_path / "chromium-profile"
    profile.mkdir()
    log = (tmp_path / "chromium.log").open("wb")
    child = subprocess.Popen(
        [chromium, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "about:blank"],
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,  # its renderers join its process group, which is ended with it
    )
    try:
        yield child, profile
    finally:
        if child.poll() is None:
            os.killpg(child.pid, signal.SIGTERM)
        try:
            child.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(child.pid, signal.SIGKILL)
            child.wait()


def page_target(child: subprocess.Popen[bytes], profile: Path, log: Path) -> str:
    """The DevTools WebSocket URL of the browser's page."""
    active = profile / "DevToolsActivePort"
    deadline = time.monotonic() + 60
    while True:
        assert child.poll() is None and time.monotonic() < deadline, log.read_text()[-3000:]
        if active.exists() and active.read_text().strip():
            port = int(active.read_text().split()[0])
            try:
                targets = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5).read())
            except OSError:
                targets = []
            pages = [t for t in targets if t.get("type") == "page"]
            if pages:
                return str(pages[0]["webSocketDebuggerUrl"])
        time.sleep(0.2)


def write_deployment(tmp_path: Path, bus_url: str) -> Path:
    (tmp_path / "course.rddf").write_text(RDDF)
    (tmp_path / "scenario.toml").write_text(SCENARIO)
    head = f'[deployment]\nname = "view"\nbus = "{bus_url}"\nscenario = "scenario.toml"\ncourse = "course.rddf"\n'
    deploy = tmp_path / "deploy.toml"
    deploy.write_text(head + MODULES)
    return deploy


def wait_for(what: str, check: Any, timeout_s: float, run: subprocess.Popen[bytes], run_log: Path) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert run.poll() is None, run_log.read_text()[-3000:]
        value = check()
        if value:
            return value
        time.sleep(0.25)
    raise AssertionError(f"{what}: not within {timeout_s} s\n{run_log.read_text()[-3000:]}")


def test_the_live_view_in_chromium_follows_a_drive(
    bus_url: str, key_file: Path, tmp_path: Path, browser: tuple[subprocess.Popen[bytes], Path]
) -> None:
    deploy = write_deployment(tmp_path, bus_url)
    port = free_port()
    run_log = tmp_path / "run.log"
    command = [sys.executable, "-m", "rascal.cli", "run", str(deploy), "--duration", "180", "--no-images"]
    run = subprocess.Popen(
        [*command, "--runs-dir", str(tmp_path / "runs"), "--view", "--view-port", str(port)],
        cwd=ROOT,
        stdout=run_log.open("wb"),
        stderr=subprocess.STDOUT,
    )
    devtools = None
    try:
        url = f"http://127.0.0.1:{port}/"

        def moving() -> bool:
            try:
                state = json.loads(urllib.request.urlopen(url + "state.json", timeout=2).read())
            except OSError:
                return False
            vehicle = state["scene"] and state["scene"]["vehicle"]
            return bool(vehicle) and vehicle["speed"] > 0.5 and state["map"] is not None

        wait_for("the vehicle drives and the map is served", moving, 120.0, run, run_log)
        child, profile = browser
        devtools = DevTools(page_target(child, profile, tmp_path / "chromium.log"))
        devtools.call("Page.enable")
        devtools.call("Page.navigate", url=url)

        def view() -> dict[str, Any] | None:
            return devtools.evaluate("window.rascalView ? JSON.parse(JSON.stringify(window.rascalView)) : null")

        first = wait_for(
            "the page draws the vehicle", lambda: (v := view()) and v["vehiclePx"] and v, 30.0, run, run_log
        )
        samples = [first]

        def moved_with_maps() -> bool:
            samples.append(view() or {})
            latest = samples[-1]
            return math.dist(first["vehiclePx"], latest["vehiclePx"]) >= MOVED_PX and (
                latest["mapReceived"] >= MAPS_WANTED
            )

        wait_for("the vehicle moves on the canvas", moved_with_maps, 90.0, run, run_log)

        def panel() -> set[str]:
            rows = devtools.evaluate("[...document.querySelectorAll('#modules tbody tr')].map(r => r.dataset.module)")
            return set(rows) if set(rows) >= EXPECTED_MODULES else set()

        rows = wait_for("the health panel lists every module", panel, 30.0, run, run_log)
        # A restart, as the supervisor reports it: the health monitor is killed (the drive does
        # not need it) and its row counts the restart, the events list says why.
        (health,) = pids_of("health", bus_url)
        os.kill(health, signal.SIGKILL)

        def restart_shown() -> bool:
            restarts = devtools.evaluate(
                "Object.fromEntries([...document.querySelectorAll('#modules tbody tr')]"
                ".map(r => [r.dataset.module, r.cells[6].textContent]))"
            )
            events = devtools.evaluate("document.getElementById('events').textContent")
            return restarts.get("health") == "1" and "health exited with signal SIGKILL" in events

        wait_for("the health panel shows the restart", restart_shown, 60.0, run, run_log)
        # Keeping up: once 30 maps have come, the page goes on to draw one that arrived after
        # that moment, however slowly the loaded machine lets it draw. A page that queued maps
        # and could not keep up would still be drawing old ones (latest-only is why it can't).
        mark = view() or {}
        caught_up = wait_for(
            "the page draws a map newer than those it had",
            lambda: (v := view()) and v["mapRenderedIndex"] > mark["mapReceived"] and v,
            30.0,
            run,
            run_log,
        )
        samples.append(caught_up)
        shot = devtools.call("Page.captureScreenshot", format="png")
        screenshot = tmp_path / "view.png"
        screenshot.write_bytes(base64.b64decode(shot["data"]))
        last = view() or {}
    finally:
        if devtools is not None:
            devtools.close()
        if run.poll() is None:
            run.send_signal(signal.SIGINT)  # rascal run stops the vehicle, then its modules
        try:
            run.wait(timeout=60)
        except subprocess.TimeoutExpired:
            run.kill()
            run.wait()
    print(f"screenshot: {screenshot}")
    print(
        f"page: {last['frames']} frames; maps received {last['mapReceived']}, rendered {last['mapRendered']}, "
        f"skipped by the server {last['mapSkippedByServer']}, decode {last['lastDecodeMs']} ms; "
        f"backlog now {last['backlog']}, max {last['maxBacklog']}; "
        f"render lag last {last['lastRenderLagMs']} ms, max {last['maxRenderLagMs']} ms; "
        f"vehicle {first['vehiclePx']} -> {last['vehiclePx']} px; modules {sorted(rows)}"
    )
    assert screenshot.stat().st_size > 10_000 and screenshot.read_bytes()[:4] == b"\x89PNG"
    assert run.returncode == 0, run_log.read_text()[-3000:]
    assert last["errors"] == []
    assert last["mapReceived"] >= MAPS_WANTED and last["lastRenderLagMs"] is not None
    rendered = [sample["mapRendered"] for sample in samples if sample]
    assert rendered == sorted(rendered) and rendered[-1] > rendered[0]
