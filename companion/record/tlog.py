"""The MAVLink traffic the service saw, as a standard telemetry log (.tlog).

A .tlog is what pymavlink, MAVExplorer and QGroundControl read: each packet is prefixed with
its receive time as 8 big-endian bytes of microseconds since the Unix epoch. MAVSDK hands the
service parsed messages (MavlinkDirect: name, sender, fields as JSON), not raw bytes. So
`TlogWriter.write` encodes each message again with pymavlink's dialect, as MAVLink 2 from its
original system and component. Every record is flushed as it is written: a crash loses at most
the record being written, and pymavlink's reader stops cleanly at a half-written last one.
`submit` hands a message over to the writer's own thread, which parses, encodes and writes it,
so the service's event loop never waits for the disk or the encoder.
"""

from __future__ import annotations

import json
import queue
import struct
import threading
from pathlib import Path
from typing import Any, BinaryIO

from pymavlink.dialects.v20 import ardupilotmega as mavlink

__all__ = ["TlogWriter"]

_NAMES = {cls.msgname: cls for cls in mavlink.mavlink_map.values()}


def _field(value: Any, fieldtype: str, length: int) -> Any:
    """A JSON field value as pymavlink packs it."""
    if fieldtype == "char":
        return (value or "").encode("utf-8")[: max(length, 1)]
    if length:
        items = list(value or [])
        return items + [0] * (length - len(items))
    return value if value is not None else 0


class TlogWriter:
    """Appends MAVLink messages to a .tlog file, flushing each one."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fh: BinaryIO = path.open("ab")
        self._mav = mavlink.MAVLink(None)
        self.written = 0
        self.skipped = 0  # messages the dialect does not know or whose fields do not fit
        self._queue: queue.SimpleQueue[tuple[float, int, int, str, str] | None] = (
            queue.SimpleQueue())
        self._thread: threading.Thread | None = None

    def submit(self, time_unix_s: float, system_id: int, component_id: int, name: str,
               fields_json: str) -> None:
        """Queue one received message (its fields as JSON) for the writer thread."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._drain, name="tlog", daemon=True)
            self._thread.start()
        self._queue.put((time_unix_s, system_id, component_id, name, fields_json))

    def _drain(self) -> None:
        while (item := self._queue.get()) is not None:
            t_s, system_id, component_id, name, fields_json = item
            try:
                fields = json.loads(fields_json)
            except ValueError:
                self.skipped += 1
                continue
            self.write(t_s, system_id, component_id, name, fields)

    def write(self, time_unix_s: float, system_id: int, component_id: int, name: str,
              fields: dict[str, Any]) -> None:
        """One received message, stamped with its receive time (Unix seconds)."""
        cls = _NAMES.get(name)
        if cls is None:
            self.skipped += 1
            return
        lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))
        try:
            args = [_field(fields.get(f), t, lengths[f])
                    for f, t in zip(cls.fieldnames, cls.fieldtypes, strict=True)]
            message = cls(*args)
            self._mav.srcSystem, self._mav.srcComponent = system_id, component_id
            packet = message.pack(self._mav)
        except (struct.error, TypeError, ValueError):
            self.skipped += 1
            return
        self._fh.write(struct.pack(">Q", int(time_unix_s * 1e6)) + packet)
        self._fh.flush()
        self.written += 1

    def close(self) -> None:
        """Write what is queued, then close the file."""
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join()
            self._thread = None
        self._fh.close()
