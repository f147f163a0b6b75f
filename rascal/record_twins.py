"""JSON twins added to a finished raw recording, after the run rather than during it.

``rascal run``'s recorder writes only the signed messages (about 5 us each); decoding every one
to JSON as it comes would cost the recorder four times that, for a reader (Foxglove) that opens
the file after the run anyway. This rewrites the file with each message's ``<CHANNEL>.json``
twin beside it, as the recorder itself would have written them (rascal/recording.py), keeping
its metadata, and replaces it only once the new file is complete. The foxglove-schema channels
are regenerated from the raw ones as the recorder wrote them (rascal/record_foxglove.py: they
depend only on the messages and their receive times), with the corridor of the course the run
metadata names.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

from brain.corridor import Course
from brain.course_config import load_course
from protocol.codec import Opened
from rascal.logread import Datagram, body_of, iter_datagrams, read_metadata
from rascal.record_foxglove import FoxgloveOptions
from rascal.recording import END_METADATA, RUN_METADATA, RecordingWriter


def add_json_twins(path: Path) -> int:
    """Rewrite ``path`` with JSON twins; returns the messages it holds. RecordingError or
    OSError leave the original untouched."""
    metadata = read_metadata(path)
    partial = path.with_name(f"{path.stem}.twins-partial{path.suffix}")
    partial.unlink(missing_ok=True)  # left by an interrupted earlier attempt
    run_info = metadata.get(RUN_METADATA, {})
    foxglove = FoxgloveOptions(course=_course(run_info))
    writer = RecordingWriter(partial, run_info, json_channels=True, foxglove=foxglove)
    try:
        for datagram in iter_datagrams(path):
            writer.write(_opened(datagram), datagram.data, datagram.log_time_ns)
        writer.close(metadata.get(END_METADATA, {}))
        os.replace(writer.path, path)
    finally:
        if not writer.closed:
            with contextlib.suppress(OSError, ValueError):
                writer.close({})
        writer.path.unlink(missing_ok=True)
    return writer.messages


def _course(run_info: dict[str, str]) -> Course | None:
    """The course the recorder drew, if the run names one that still loads (else no corridor)."""
    if not run_info.get("course"):
        return None
    try:
        return load_course(run_info["course"], run_info.get("origin", ""))
    except (OSError, ValueError):
        return None


def _opened(datagram: Datagram) -> Opened:
    # Authenticated when it was recorded: the recorder writes nothing its bus did not accept.
    return Opened(
        datagram.type_id,
        datagram.source_id,
        datagram.seq,
        datagram.t_meas_ns,
        datagram.t_pub_ns,
        datagram.channel,
        body_of(datagram.data),
    )
