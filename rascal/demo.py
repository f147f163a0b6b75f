"""`rascal demo`: the most complete end-to-end job this stack can do today.

Starts the time service, a synthetic obstacle sensor (beacon) and the health monitor as separate
processes on the signed loopback bus, shows them with the bus tools, then stops the sensor to
show that its silence is noticed. Logs go to ``runs/<timestamp>/``.
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

DEMO_MODULES = {
    "time_service": [],
    "beacon": ["--set", "rate_hz=20"],
    "health": ["--set", f"watch={channels.OBSTACLES_BEACON}:0.5", "--set", "heartbeat_timeout_s=2.0"],
}


def start_module(name: str, args: list[str], log_dir: Path) -> subprocess.Popen[bytes]:
    log = (log_dir / f"{name}.log").open("wb")
    return subprocess.Popen([sys.executable, "-m", f"modules.{name}", *args], stdout=log, stderr=subprocess.STDOUT)


def run_demo(url: str | None = None, runs_dir: Path = Path("runs")) -> int:
    console = make_console()
    url = url or default_url()
    default_keyring()  # create the per-user key before the modules race to do it
    run_dir = runs_dir / datetime.now().strftime("%Y%m%d-%H%M%S")
    run_dir.mkdir(parents=True, exist_ok=True)
    console.print(f"bus {url}, logs in {run_dir}/")
    processes = {name: start_module(name, ["--bus", url, *args], run_dir) for name, args in DEMO_MODULES.items()}
    try:
        time.sleep(1.5)
        console.print(Rule("rascal bus list  (3 s)"))
        stats = bus_list(url, 3.0, console)
        console.print(Rule(f"rascal bus hz {channels.OBSTACLES_BEACON}"))
        bus_hz(url, channels.OBSTACLES_BEACON, 2.0, 1.0, console)
        console.print(Rule(f"rascal bus echo {channels.OBSTACLES_BEACON} --count 1"))
        bus_echo(url, channels.OBSTACLES_BEACON, 2.0, 1, console)
        console.print(Rule("rascal time status"))
        time_status(url, 2.0, console)
        console.print(Rule("fault: the beacon stops; the health monitor notices"))
        processes["beacon"].terminate()
        processes["beacon"].wait(timeout=5)
        events = bus_echo(url, channels.HEALTH, 4.0, 2, console)
        for name, process in processes.items():
            if process.poll() is not None and name != "beacon":
                console.print(f"[red]{name} exited early with {process.returncode}; see {run_dir}/{name}.log")
                return 1
        seen = {name for name in stats if name in (channels.OBSTACLES_BEACON, channels.MODULE_STATUS)}
        ok = len(seen) == 2 and events >= 1
        console.print(Rule("result"))
        console.print(f"channels seen: {sorted(stats)}; health events after the fault: {events}")
        console.print("[green]demo OK" if ok else "[red]demo FAILED: expected beacon traffic and a health event")
        return 0 if ok else 1
    finally:
        for process in processes.values():
            if process.poll() is None:
                process.terminate()
        for process in processes.values():
            try:
                process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                process.kill()
