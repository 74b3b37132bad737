"""Live timelines to a rerun viewer (``fleetbrake watch --rerun ADDR``).

::

    live = LiveTimelines("127.0.0.1:9876")          # or rerun+http://host:port/proxy
    live.after_unit(db_path, [("logs/SGG-0001_20240301T000000Z.csv", "SGG-0001")])
    live.close()

After each unit of the watching service, the new timeline of each file it ingested (the
samples' time range of that file: speed, pressure, measured and predicted sensor temperature,
the open-loop contact prediction, the virtual sensor's contact estimate with its band, the
unexplained power, events and flags as text logs at their times) is read from the warehouse
(read-only, right after the unit's commit, as ``fleetbrake record`` reads it) and streamed to
the viewer over rerun's gRPC protocol, through the same
:func:`fleetbrake.viz.compose.log_recording` as the ``.rrd`` recordings: the same entity paths
and blueprint. Each wagon is one recording in the viewer (its recording id derived from the
wagon id, so that every unit, and a restarted service, adds to the same one).

The unit is never held up by the viewer: the reading is done by :meth:`after_unit` (on the
service's thread, while it holds no database), the sending on a thread of its own. A viewer
that is not there (or goes away) costs a warning per failed attempt; whatever was queued then
is dropped (the ``.rrd`` of ``fleetbrake record`` has it), and the next unit tries again.
An event or flag already sent is not sent again when a later file's range overlaps it.
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
import uuid
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import polars as pl
import rerun as rr

from fleetbrake.errors import ConfigError, FleetbrakeError
from fleetbrake.viz.blueprint import blueprint
from fleetbrake.viz.compose import log_recording
from fleetbrake.viz.data import RecordData, instant, load_record_data, open_read_only
from fleetbrake.warehouse.connection import sql

__all__ = [
    "APPLICATION_ID",
    "LiveAddressError",
    "LiveTimelines",
    "recording_id",
    "viewer_url",
]

logger = logging.getLogger(__name__)

APPLICATION_ID = "fleetbrake_live"
"""The rerun application of the live recordings (one recording per wagon)."""

_NAMESPACE = uuid.UUID("5d2c1f0e-8a4b-4f5e-9c3d-1b7a6e2f0c48")
_SCHEMES = ("rerun://", "rerun+http://", "rerun+https://")


class LiveAddressError(ConfigError):
    """``--rerun ADDR`` is not a rerun viewer's address (exit 2); the message names it."""


def viewer_url(address: str) -> str:
    """The gRPC URL of a viewer given as ``HOST:PORT``, ``PORT`` (on 127.0.0.1) or a full
    ``rerun+http://HOST:PORT/proxy`` URL (``rerun://`` and ``rerun+https://`` too)."""
    text = address.strip()
    if text.isdigit():
        text = f"127.0.0.1:{text}"
    if "://" not in text:
        text = f"rerun+http://{text}/proxy"
    if not text.startswith(_SCHEMES):
        raise LiveAddressError(
            f"--rerun {address!r}: the scheme must be one of {', '.join(_SCHEMES)}"
        )
    parts = urlsplit(text)
    try:
        port = parts.port
    except ValueError:
        port = None
    if not parts.hostname or port is None or parts.path != "/proxy":
        raise LiveAddressError(
            f"--rerun {address!r}: not a viewer's address (HOST:PORT, or "
            "rerun+http://HOST:PORT/proxy)"
        )
    return text


def recording_id(wagon_id: str) -> uuid.UUID:
    """The live recording of ``wagon_id``: the same at every unit and every service start."""
    return uuid.uuid5(_NAMESPACE, wagon_id)


@dataclass(frozen=True)
class _Timeline:
    """One file's new timeline, read and ready to send."""

    wagon_id: str
    path: str
    data: RecordData


class LiveTimelines:
    """Streams each unit's new timelines to the rerun viewer at ``address`` (see the module).

    ``flush_timeout_s``: how long one timeline may take to reach the viewer before the attempt
    counts as failed; ``max_queued``: timelines waiting to be sent (more are dropped, with a
    warning, while the viewer is slow)."""

    def __init__(
        self, address: str, *, flush_timeout_s: float = 10.0, max_queued: int = 64
    ) -> None:
        self.url = viewer_url(address)
        self.flush_timeout_s = flush_timeout_s
        self._queue: queue.Queue[_Timeline | None] = queue.Queue(maxsize=max_queued)
        self._sent_events: set[str] = set()
        self._sent_flags: set[str] = set()
        self._lock = threading.Lock()
        self.sent = 0
        """Timelines the viewer received."""
        self.failed = 0
        """Timelines not sent (the viewer not there, or too slow)."""
        self._thread = threading.Thread(target=self._send_loop, name="rerun-live", daemon=True)
        self._thread.start()

    # ---- the service's side ----------------------------------------------------------------

    def after_unit(
        self,
        db_path: str | os.PathLike[str],
        files: Iterable[tuple[str, str | None]],
        *,
        wait_s: float = 5.0,
    ) -> int:
        """Read the new timeline of each ``(path, wagon_id)`` the unit ingested and queue it
        for the viewer. Never raises: what cannot be read is logged (warning) and skipped.
        Returns the number of timelines queued."""
        wanted = sorted({(path, wagon) for path, wagon in files if wagon})
        if not wanted:
            return 0
        began = time.perf_counter()
        try:
            timelines = self._read(Path(db_path), wanted, wait_s)
        except FleetbrakeError as error:
            logger.warning("rerun live: cannot read the new timelines: %s", error)
            return 0
        except Exception:  # the viewer is a convenience: it never stops the service
            logger.exception("rerun live: cannot read the new timelines")
            return 0
        queued = 0
        for timeline in timelines:
            try:
                self._queue.put_nowait(timeline)
                queued += 1
            except queue.Full:
                self._unsend([timeline])
                with self._lock:
                    self.failed += 1
                logger.warning(
                    "rerun live: %s: the viewer at %s is behind; this file's timeline is not "
                    "streamed",
                    timeline.path,
                    self.url,
                )
        logger.debug(
            "rerun live: %d timelines read in %.3f s", len(timelines), time.perf_counter() - began
        )
        return queued

    def close(self, timeout_s: float = 15.0) -> None:
        """Send what is queued (for up to ``timeout_s``), then stop the sending thread."""
        deadline = time.monotonic() + timeout_s
        while self._thread.is_alive():
            try:
                self._queue.put(None, timeout=0.1)
                break
            except queue.Full:
                if time.monotonic() >= deadline:
                    return
        self._thread.join(max(0.0, deadline - time.monotonic()))

    def _read(
        self, db_path: Path, wanted: Sequence[tuple[str, str]], wait_s: float
    ) -> list[_Timeline]:
        out: list[_Timeline] = []
        with open_read_only(db_path, wait_s) as wh:
            spans = {
                row[0]: (row[1], row[2])
                for row in wh.con.sql(
                    sql("q_live_file_spans"), params={"paths": [p for p, _ in wanted]}
                ).fetchall()
            }
            for path, wagon_id in wanted:
                span = spans.get(path)
                if span is None or span[0] is None:
                    continue  # nothing of it stored (replaced since, or no samples)
                window = (instant(span[0]), instant(span[1]))
                data = load_record_data(wh, wagon_id, window=window)
                out.append(_Timeline(wagon_id, path, self._unsent(data)))
        return out

    def _unsent(self, data: RecordData) -> RecordData:
        """``data`` without the events and flags already sent or queued (a range overlapping
        two files' windows is sent once); those left are counted as sent from now on (until
        their sending fails)."""
        with self._lock:
            events, flags = data.events, data.flags
            if events.height:
                events = events.filter(~pl.col("event_id").is_in(list(self._sent_events)))
            if flags.height:
                flags = flags.filter(~pl.col("flag_id").is_in(list(self._sent_flags)))
            self._sent_events.update(_column(events, "event_id"))
            self._sent_flags.update(_column(flags, "flag_id"))
        return replace(data, events=events, flags=flags)

    def _unsend(self, timelines: Sequence[_Timeline]) -> None:
        """The events and flags of ``timelines``, which did not reach the viewer, are to be
        sent with a later timeline again."""
        with self._lock:
            for timeline in timelines:
                self._sent_events.difference_update(_column(timeline.data.events, "event_id"))
                self._sent_flags.difference_update(_column(timeline.data.flags, "flag_id"))

    # ---- the sending thread ----------------------------------------------------------------

    def _send_loop(self) -> None:
        while True:
            timeline = self._queue.get()
            if timeline is None:
                return
            try:
                self._send(timeline)
            except Exception as error:
                dropped = self._drop_queued()
                self._unsend([timeline, *dropped])
                with self._lock:
                    self.failed += 1 + len(dropped)
                logger.warning(
                    "rerun live: the viewer at %s did not take %s's timeline (%s)%s; trying "
                    "again at the next unit",
                    self.url,
                    timeline.path,
                    error,
                    f" ({len(dropped)} more dropped)" if dropped else "",
                )
            else:
                with self._lock:
                    self.sent += 1

    def _drop_queued(self) -> list[_Timeline]:
        """Take the timelines queued behind a failed one off the queue (keeping a stop
        request)."""
        dropped: list[_Timeline] = []
        stop = False
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            if item is None:
                stop = True
            else:
                dropped.append(item)
        if stop:
            self._queue.put_nowait(None)
        return dropped

    def _send(self, timeline: _Timeline) -> None:
        rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id(timeline.wagon_id))
        try:
            rec.connect_grpc(self.url, default_blueprint=blueprint())
            log_recording(rec, f"{timeline.wagon_id} live", timeline.data, start=False)
            rec.flush(timeout_sec=self.flush_timeout_s)
        finally:
            rec.disconnect()
        logger.debug("rerun live: %s sent to %s", timeline.path, self.url)


def _column(frame: pl.DataFrame, name: str) -> list[Any]:
    return frame[name].to_list() if frame.height and name in frame.columns else []
