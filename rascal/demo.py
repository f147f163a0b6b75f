"""`rascal demo`: the most complete end-to-end job this stack can do today.

Starts the time service, the simulator on the default scenario, the simulated navigation sensors,
the four lidars and the health monitor as separate processes on the signed loopback bus; drives
the vehicle a few metres with a steady throttle (there is no planner or controller yet); shows
the traffic with the bus tools; then silences every lidar at once, as RASCAL's overheated USB
hub did in 2005, and shows the health monitor noticing. Logs go to ``runs/<timestamp>/``.
"""

from __future__ import annotations

import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path

from rich.rule import Rule

from protocol import channels
from protocol.auth import default_keyring
from protocol.transport import default_url
from rascal.bustools import bus_echo, bus_hz, bus_list, make_console, time_status

LIDARS = {"lidar_h_left": 21, "lidar_h_right": 22, "lidar_v_left": 23, "lidar_v_right": 24}
WATCHED = (channels.IMU, channels.GPS, channels.OBSTACLES_LIDAR, channels.SURFACE_PROFILE)
DEMO_MODULES: dict[str, tuple[str, list[str]]] = {
    "time_service": ("time_service", []),
    "sim": ("sim", []),
    "nav_sensors": ("nav_sensors", []),
    **{name: ("lidar", ["--source-id", str(source), "--set", f"sensor={name}"]) for name, source in LIDARS.items()},
    "health": (
        "health",
        ["--set", "watch=" + ",".join(f"{c}:0.5" for c in WATCHED), "--set", "heartbeat_timeout_s=2.0"],
    ),
}
GENTLE_THROTTLE = '{"throttle": 0.25, "brake": 0.0, "steering_rad": 0.0}'


def start(label: str, module: str, args: list[str], url: str, log_dir: Path) -> subprocess.Popen[bytes]:
    log = (log_dir / f"{label}.log").open("wb")
    command = [sys.executable, "-m", f"modules.{module}", "--bus", url, *args]
    return subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)


def drive(url: str, seconds: float) -> subprocess.Popen[bytes]:
    """A stand-in driver: a steady gentle throttle, straight ahead, at the control rate."""
    count = str(int(seconds * 20))
    command = [
        sys.executable,
        "-m",
        "rascal.cli",
        "--bus",
        url,
        "bus",
        "pub",
        channels.ACTUATOR_COMMAND,
        GENTLE_THROTTLE,
        "--rate",
        "20",
        "--count",
        count,
    ]
    return subprocess.Popen(command, stdout=subprocess.DEVNULL)


def run_demo(url: str | None = None, runs_dir: Path = Path("runs")) -> int:
    console = make_console()
    url = url or default_url()
    default_keyring()  # create the per-user key before the modules race to do it
    run_dir = runs_dir / datetime.now().strftime("%Y%m%d-%H%M%S")
    run_dir.mkdir(parents=True, exist_ok=True)
    console.print(f"bus {url}, logs in {run_dir}/")
    processes = {label: start(label, module, args, url, run_dir) for label, (module, args) in DEMO_MODULES.items()}
    driver: subprocess.Popen[bytes] | None = None
    try:
        time.sleep(2.0)
        driver = drive(url, 12.0)
        console.print(Rule("rascal bus list  (3 s)"))
        stats = bus_list(url, 3.0, console)
        console.print(Rule(f"rascal bus hz {channels.IMU}"))
        bus_hz(url, channels.IMU, 2.0, 1.0, console)
        console.print(Rule(f"rascal bus echo {channels.OBSTACLES_LIDAR} --count 1"))
        bus_echo(url, channels.OBSTACLES_LIDAR, 2.0, 1, console)
        console.print(Rule("rascal time status"))
        time_status(url, 2.0, console)
        console.print(Rule("fault: every lidar goes silent at once (RASCAL, 2005); the health monitor notices"))
        for name in LIDARS:
            processes[name].terminate()
        events = bus_echo(url, channels.HEALTH, 5.0, 6, console)
        failed = [name for name, p in processes.items() if p.poll() not in (None, 0) and name not in LIDARS]
        console.print(Rule("result"))
        wanted = {*WATCHED, channels.WHEEL_SPEED, channels.MAG_HEADING}
        missing = sorted(wanted - set(stats))
        console.print(f"channels seen: {sorted(stats)}; health events after the fault: {events}")
        ok = not failed and not missing and events >= 1
        if failed:
            console.print(f"[red]exited early: {failed}; see their logs in {run_dir}/")
        if missing:
            console.print(f"[red]never heard: {missing}")
        console.print("[green]demo OK" if ok else "[red]demo FAILED")
        return 0 if ok else 1
    finally:
        stop([*processes.values(), *([driver] if driver else [])])


def stop(children: list[subprocess.Popen[bytes]]) -> None:
    for child in children:
        if child.poll() is None:
            child.terminate()
    for child in children:
        try:
            child.wait(timeout=5)
        except subprocess.TimeoutExpired:
            child.kill()
