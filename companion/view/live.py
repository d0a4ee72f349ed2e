"""The live view: the service's step state made into messages for the pages streaming now.

`LiveView.after_step` keeps the trails (path, track histories, recent scans) on every step,
which costs next to nothing; only while a page is connected is a message made, in a worker
thread so that the event loop (and the setpoint stream it runs) never waits for it.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import ServiceConfig
from companion.pipeline import SearchFrame
from companion.sat.filter import SatState
from companion.sat.tracks import TrackParams
from companion.view.model import Status, Trails, Vehicle, encode, scene_message, step_message
from companion.view.orthophoto import Orthophoto
from companion.view.server import ViewServer, load_token

__all__ = ["LiveView"]


class LiveView:
    """The view server of a flight and the trails its messages show."""

    def __init__(self, config: ServiceConfig, frame: SearchFrame, params: TrackParams,
                 log: Callable[[str], None] = lambda _: None, *,
                 orthophoto: Orthophoto | None = None, notes: list[str] | None = None) -> None:
        v = config.view
        token = None if v.token_file is None else load_token(Path(v.token_file))
        scene = scene_message(frame, config.safety.geofence_latlon, mode="live",
                              rate_hz=config.estimator.rate_hz,
                              expected_targets=config.search.expected_targets, notes=notes,
                              orthophoto=None if orthophoto is None else orthophoto.scene())
        self.server = ViewServer(scene, bind=v.bind, port=v.port, token=token,
                                 max_clients=v.max_clients, log=log,
                                 orthophoto_png=None if orthophoto is None else orthophoto.png)
        self.frame, self.params = frame, params
        self.trails = Trails()
        self.seq = 0
        self._building = False
        self.build_cpu_s = 0.0  # CPU time making messages (worker threads)
        self.trails_cpu_s = 0.0  # CPU time keeping the trails (the event loop)
        self._next: tuple[int, dict[str, Any], SatState | None, Vehicle | None, Status,
                          Trails] | None = None

    async def start(self) -> None:
        """Listen (ConfigError naming view.bind or view.port if the address is taken)."""
        await self.server.start()

    async def close(self) -> None:
        """The pages get the last message, then the server stops."""
        await self.server.close()

    def _message(self, seq: int, record: dict[str, Any], state: SatState | None,
                 vehicle: Vehicle | None, status: Status, trails: Trails) -> str:
        started = time.thread_time()
        try:
            return encode(step_message(seq, self.frame, state, record, trails, self.params,
                                       vehicle, status))
        finally:
            self.build_cpu_s += time.thread_time() - started

    def counters(self) -> dict[str, int]:
        """What the view did in the flight: pages, messages, drops and its CPU time (ms)."""
        s = self.server.stats
        cpu_s = self.build_cpu_s + self.trails_cpu_s + s.send_cpu_s
        return {"view_pages": s.connected, "view_messages_sent": s.messages_sent,
                "view_pages_dropped_slow": s.dropped_slow,
                "view_refused_token": s.refused_token, "view_refused_full": s.refused_full,
                "view_cpu_ms": round(1e3 * cpu_s)}

    async def after_step(self, record: dict[str, Any], state: SatState | None,
                         vehicle: Vehicle | None, status: Status) -> None:
        """Add a step (its record as in steps.jsonl) to the trails; pages get its message,
        with the service's status."""
        started = time.thread_time()
        self.seq += 1
        xy = None if vehicle is None else vehicle.xy_m
        meas = record.get("measurements_utm") or []
        detections = (self.frame.from_utm(np.asarray(meas, dtype=np.float64)) if meas
                      else np.zeros((0, 2)))
        t_s = float(record.get("t_s", 0.0))
        self.trails = self.trails.after(t_s, xy, detections, record.get("blind"), state)
        self.trails_cpu_s += time.thread_time() - started
        if not self.server.has_clients:
            return  # nobody to show it to
        self._next = (self.seq, record, state, vehicle, status, self.trails)
        if self._building:
            return  # made when the message under way is out
        self._building = True
        loop = asyncio.get_running_loop()
        try:
            while self._next is not None:
                job, self._next = self._next, None
                text = await loop.run_in_executor(None, self._message, *job)
                self.server.publish(text)
        finally:
            self._building = False
