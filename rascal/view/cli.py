"""``rascal view [RUN.mcap] [--port P] [--foxglove]``: the bird's-eye view in the browser.

Without a file it follows the live bus; with one it replays the recording at its recorded pace
(``--speed``), then keeps showing the end of it until Ctrl-C or ``--duration``. The corridor
comes from ``--course`` or the deployment's course.
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import random
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from protocol import channels
from protocol.auth import KeyFileError, default_keyring, load_keyring
from protocol.codec import decode_body
from protocol.errors import ProtocolError
from protocol.schema import info_for_class
from protocol.transport import UrlError
from rascal.bustools import TOOL_SOURCE_IDS
from rascal.logread import END_METADATA, Datagram, RecordingError, Scan, body_of, iter_datagrams
from rascal.runtime.bus import Bus
from rascal.runtime.clock import SharedClock
from rascal.runtime.deployment import DEFAULT_DEPLOYMENT, DeploymentError, load_deployment
from rascal.runtime.module import Runtime
from rascal.view.module import HEALTH_PERIOD_S, TRAIL_PERIOD_S, Publisher, Viewer, ViewerConfig, course_of, open_outputs
from rascal.view.server import ViewServerError
from rascal.view.state import DRAWN_CHANNELS, ViewState

DRAWN_TYPE_IDS = {channel: info_for_class(channels.CHANNEL_TYPES[channel]).type_id for channel in DRAWN_CHANNELS}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rascal view", description=__doc__.splitlines()[0])
    parser.add_argument("recording", nargs="?", type=Path, help="replay this MCAP recording instead of the live bus")
    parser.add_argument("--port", type=int, default=8090, help="HTTP port of the page (0: any free port)")
    parser.add_argument("--host", default="127.0.0.1", help="address to serve on (default: loopback only)")
    parser.add_argument("--allow-host", action="append", default=[], metavar="NAME",
                        help="a host name the page may be reached by (IPs and localhost always work)")  # fmt: skip
    parser.add_argument("--deployment", default=str(DEFAULT_DEPLOYMENT), help="deployment TOML: bus and course")
    parser.add_argument("--course", help="RDDF file drawn as the corridor (default: the deployment's)")
    parser.add_argument("--origin", help="ENU origin 'lat,lon[,alt]' (default: the deployment's)")
    parser.add_argument("--bus", help="bus URL (default: $RASCAL_BUS_URL, else the deployment's)")
    parser.add_argument("--foxglove", action="store_true", help="also serve Foxglove's live protocol")
    parser.add_argument("--foxglove-port", type=int, default=8765, help="port of the Foxglove server")
    parser.add_argument("--speed", type=float, default=1.0, help="replay speed (recordings only)")
    parser.add_argument("--duration", type=float, help="end after this many seconds")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    for name in ("speed", "duration"):
        value = getattr(args, name)
        if value is not None and not (math.isfinite(value) and value > 0):
            parser.error(f"--{name} must be a positive number")
    try:
        deployment = load_deployment(args.deployment)
    except DeploymentError as exc:
        parser.error(str(exc))
    course = args.course if args.course is not None else str(deployment.course or "")
    config = ViewerConfig(
        host=args.host,
        port=args.port,
        allowed_hosts=tuple(args.allow_host),
        course=course,
        origin=args.origin if args.origin is not None else deployment.origin,
        foxglove=args.foxglove,
        foxglove_port=args.foxglove_port,
    )
    try:
        if args.recording is not None:
            return replay(args.recording, config, args.speed, args.duration)
        bus_url = args.bus or os.environ.get("RASCAL_BUS_URL") or deployment.bus
        keyring = load_keyring(deployment.key_file) if deployment.key_file else default_keyring()
        clock = SharedClock()
        bus = Bus.open(bus_url, source_id=random.randint(*TOOL_SOURCE_IDS), clock=clock, keyring=keyring)
    except (RecordingError, KeyFileError, UrlError, OSError, ValueError, ViewServerError) as exc:
        print(f"rascal view: {exc}", file=sys.stderr)
        return 2
    runtime = Runtime(bus, clock)
    runtime.run(Viewer(config, runtime), args.duration)
    return 0


def replay(path: Path, config: ViewerConfig, speed: float, duration_s: float | None) -> int:
    """Show a recording at ``speed`` times its recorded pace, then hold its last picture."""
    state = ViewState(course_of(config))
    scan = Scan()
    datagrams = iter_datagrams(path, scan=scan)
    first = next(datagrams, None)  # a file that is no recording fails here, before anything is served
    server, foxglove = open_outputs(config)
    publisher = Publisher(state, server.hub, foxglove, source=f"replaying {path.name}")
    print(f"rascal view: replaying {path} on {server.url}" + (f", Foxglove on {foxglove.url}" if foxglove else ""),
          flush=True)  # fmt: skip
    stop = _stop_flag()
    started = time.monotonic()
    end = math.inf if duration_s is None else started + duration_s
    clock = _ReplayClock(publisher, config.frame_rate_hz)
    first_log_ns = first.log_time_ns if first is not None else 0
    try:
        for datagram in itertools.chain([first] if first is not None else [], datagrams):
            due = started + (datagram.log_time_ns - first_log_ns) / 1e9 / speed
            if not clock.wait_until(min(due, end), stop) or time.monotonic() >= end:
                break
            _feed(state, datagram)
            clock.rejected = _rejects(scan)
        clock.rejected = _rejects(scan)
        clock.publish_all()
        print(f"rascal view: end of {path}; still serving (Ctrl-C to stop)", flush=True)
        clock.wait_until(end, stop)
    finally:
        server.close()
        if foxglove is not None:
            foxglove.close()
    return 0


def _feed(state: ViewState, datagram: Datagram) -> None:
    state.count(datagram.channel, datagram.log_time_ns)
    if DRAWN_TYPE_IDS.get(datagram.channel) != datagram.type_id:
        return  # not drawn, or a type this channel does not carry
    try:
        msg = decode_body(datagram.type_id, body_of(datagram.data))
    except ProtocolError:
        state.bad["undecodable"] = state.bad.get("undecodable", 0) + 1
        return
    state.handle(datagram.channel, msg, datagram.t_meas_ns, datagram.log_time_ns)


def _rejects(scan: Scan) -> dict[str, int]:
    rejected: dict[str, int] = {}
    for key, value in scan.metadata.get(END_METADATA, {}).items():
        if key.startswith("rejected/") and key.count("/") == 2:
            reason = key.rsplit("/", 1)[1]
            rejected[reason] = rejected.get(reason, 0) + int(value)
    return rejected


class _ReplayClock:
    """Publishes frames on wall-clock periods while the replay waits for its next message."""

    def __init__(self, publisher: Publisher, frame_rate_hz: float) -> None:
        self.publisher = publisher
        self.rejected: dict[str, int] = {}
        self.periods = {"frame": 1.0 / frame_rate_hz, "trail": TRAIL_PERIOD_S, "health": HEALTH_PERIOD_S}
        self.due = dict.fromkeys(self.periods, time.monotonic())

    def wait_until(self, when: float, stop: list[bool]) -> bool:
        """Publish whatever falls due before ``when``; False if asked to stop."""
        while not stop[0]:
            now = time.monotonic()
            for name, due in self.due.items():
                if now >= due:
                    self._publish(name)
                    self.due[name] = max(due + self.periods[name], now)
            if now >= when:
                return True
            time.sleep(max(0.0, min(when, *self.due.values()) - time.monotonic()))
        return False

    def publish_all(self) -> None:
        for name in self.periods:
            self._publish(name)

    def _publish(self, name: str) -> None:
        if name == "frame":
            self.publisher.frame()
        elif name == "trail":
            self.publisher.trail()
        else:
            self.publisher.health(self.rejected)


def _stop_flag() -> list[bool]:
    flag = [False]

    def stop(*_: object) -> None:
        flag[0] = True

    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, stop)
    return flag
