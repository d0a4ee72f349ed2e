"""The asyncio shell: vehicle, camera, pipeline, mission and setpoints, and the run's reports.

`Service(config).run(stop)` connects to the autopilot over MAVSDK and opens the camera. Three
tasks then run until the mission is over (landed, or `stop` set):
- telemetry: MAVSDK streams into a `VehicleView` (poses on the autopilot's boot time);
- estimator: at `estimator.rate_hz`, the newest frame with the pose at its capture time goes
  through the `Pipeline` in a worker thread. A missing frame, a blank frame or a missing pose is
  a blind step, which predicts only;
- control: at `mission.setpoint_rate_hz`, the mission state machine advances on what was
  observed and its commands are carried out. While it streams, the planner's next point passes
  the safety gate and goes out as a local NED setpoint.

Every estimator step is a JSON line in `steps.jsonl`, and every state change, command, refusal
and gate action is one in `events.jsonl`. At the end the confirmed tracks are written as GeoJSON
and CSV with `summary.json` (the run folder: `companion.run_folder`). Each step's input is an
`Observation` stepped by `companion.drive`, as in replay; the setpoint geometry is
`companion.plan.setpoints`.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import gc
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion import mission as ms
from companion.camera.source import Frame, LatestFrameGrabber, open_source
from companion.config import ServiceConfig
from companion.drive import Observation, frame_observation, observe
from companion.errors import CompanionError
from companion.notify import Notifier
from companion.pipeline import Pipeline, StepRecord, camera_model
from companion.plan.gate import GateAction, GateLimits, Setpoint, gate
from companion.plan.planners import LawnMower, Planner, PlannerKind, make_planner
from companion.plan.search_track import SearchTrackParams
from companion.plan.setpoints import (
    Carrot,
    fence_keep_in,
    gate_limits,
    hold_setpoint,
    ramp,
    search_params,
    search_setpoint,
    vehicle_xy,
)
from companion.record.checkpoint import latest_checkpoint, save_checkpoint
from companion.record.frames import FrameRecorder
from companion.record.rotation import make_room
from companion.record.tlog import TlogWriter
from companion.report import TrackRecord, confirmed_tracks
from companion.run_folder import RunFolder
from companion.vehicle.events import UNKNOWN_PREFIX
from companion.vehicle.mavsdk_link import MavsdkLink, VehicleError
from companion.vehicle.modes import mission_mode
from companion.vehicle.plausibility import PositionGate
from companion.vehicle.signing import SigningRelay, load_signing_key
from companion.vehicle.view import VehicleView
from companion.view.live import LiveView
from companion.view.model import Status, Vehicle, yaw_deg
from companion.view.orthophoto import Orthophoto, load_orthophoto
from companion.vision.camera import CameraModel

__all__ = ["RunResult", "Service", "camera_model"]

FloatArray = NDArray[np.float64]
TELEMETRY_STALE_S = 0.8  # no telemetry (20 attitudes a second) for this long: the link is down
# ... and never less than this much wall time (a SITL's speed-up makes 0.8 s of its time short
# enough for a loaded computer to stall that long)
TELEMETRY_STALE_WALL_S = 0.4
BATTERY_LOW_PERCENT = 20.0
STREAM_SETTLE_S = 0.5  # PX4 accepts OFFBOARD only after setpoints have streamed (> 2 Hz)
ESTIMATOR_STOP_S = 2.0  # wall time the step under way may take to end when the mission stops
MIN_FLYING_M = 1.0  # higher above home than this: the vehicle is flying
STALL_TICKS = 3  # the control loop ran this many periods late: this process stalled
POSE_WAIT_S = 1.5  # a frame may wait this long for the telemetry of its capture time
POSE_POLL_S = 0.02
CHECKPOINT_EVERY_S = 5.0  # estimator time between checkpoints
RESUME_WITHIN_S = 600.0  # a restarted service carries on from a checkpoint younger than this
CAMERA_BLIND = ("no frame", "blank frame", "frozen frame")  # blind for the camera's sake

@dataclass
class RunResult:
    """What a run left behind."""

    out_dir: Path
    tracks: list[TrackRecord]
    mission_state: str
    counters: dict[str, int] = field(default_factory=dict)


async def _set_when(stop: asyncio.Event, wake: asyncio.Event) -> None:
    """Set `wake` once `stop` is set, so a waiting control loop ends at once."""
    await stop.wait()
    wake.set()


class Service:
    """The companion service for one flight."""

    def __init__(self, config: ServiceConfig, *, camera: CameraModel | None = None,
                 clock: Callable[[], float] = time.monotonic, time_scale: float = 1.0,
                 announce: Callable[[str], None] = lambda _: None,
                 notifier: Notifier | None = None) -> None:
        self.config = config
        self.notifier = notifier or Notifier.from_environment()
        self.time_scale = time_scale  # clock seconds per wall second (a SITL's speed-up)
        self.camera = camera or camera_model(config.camera)
        self.clock = clock
        self.announce = announce
        self.pipeline = Pipeline(config, self.camera)
        self.view = VehicleView(clock, config.pose.max_gap_s, PositionGate(
            config.pose.glitch_gate_m, config.pose.glitch_accept_after_s))
        self._glitch_reported = False
        self.counters = {"steps": 0, "blind_steps": 0, "frames_used": 0, "setpoints": 0,
                         "setpoints_clamped": 0, "setpoints_refused": 0, "command_errors": 0}
        self.mission = ms.Mission(self._mission_config())
        self._stream: ms.Stream | None = None
        self._previous: Setpoint | None = None
        self._carrot = Carrot()
        self._planner: Planner | None = None  # made when the search starts, from where we are
        self._limits: GateLimits | None = None
        self._keep_in = fence_keep_in(config.safety, self.pipeline.frame)
        self._folder: RunFolder | None = None
        self._announced: set[int] = set()
        self._streaming_since_s: float | None = None
        self._last_step_wall_s = -math.inf  # when the pipeline last finished a step
        self._last_watchdog_wall_s = -math.inf
        self._ready_sent = False
        self._frames: FrameRecorder | None = None
        self._checkpoint_due_s = -math.inf
        self._checkpoint_found: tuple[Path, dict[str, Any]] | None = None
        self.live: LiveView | None = None  # the operator's page, while it is served

    # -- configuration -----------------------------------------------------------------------

    def _mission_config(self) -> ms.MissionConfig:
        m, s = self.config.mission, self.config.search
        return ms.MissionConfig(
            auto_arm_takeoff=m.auto_arm_takeoff, auto_offboard=m.auto_offboard,
            arm_retry_s=m.arm_retry_s, offboard_retry_s=m.offboard_retry_s,
            takeoff_alt_m=s.altitude_m,
            resume_on_pilot_offboard=m.resume_on_pilot_offboard,
            end=m.end, sweeps=s.sweeps if s.planner == "lawnmower" else 1,
            time_limit_s=m.time_limit_s, end_action=m.end_action)

    def _make_planner(self, start_xy: FloatArray) -> Planner:
        """The configured planner; a lawn mower's passes each end where the search started, and
        its lanes keep the clearance inside the geofence."""
        s, world = self.config.search, self.pipeline.frame.world
        search = self._search_params() if s.planner == PlannerKind.SEARCH_TRACK else None
        return make_planner(s.planner, world, world.clip(start_xy), s.lane_spacing_m, s.sweeps,
                            search, self._keep_in)

    def _search_params(self) -> SearchTrackParams:
        """What the search-and-track planner knows in this flight (setpoints.search_params)."""
        p = self.pipeline
        return search_params(self.config.search, self.config.estimator.footprint_margin_m,
                             p.camera, p.params, p.frame.area_xy_m)

    # -- the run -----------------------------------------------------------------------------

    async def run(self, stop: asyncio.Event | None = None) -> RunResult:
        """Fly the mission until it is over or `stop` is set; write the reports."""
        stop = stop or asyncio.Event()
        o = self.config.output
        folder = self._folder = RunFolder.create(Path(o.dir), datetime.now(UTC))
        out = folder.path
        self._event("start", out_dir=str(out))
        for removed in make_room(Path(o.dir), max_total_bytes=int(o.max_runs_mb * 1e6),
                                 min_free_bytes=int(o.min_free_mb * 1e6), keep=[out],
                                 log=self._log):
            self._event("run_removed", path=str(removed.path), bytes=removed.bytes)
        self._resume(out)
        tlog = TlogWriter(out / "flight.tlog")
        if o.frames != "off":
            self._frames = FrameRecorder(
                out / "frames", budget_bytes=int(o.frames_budget_mb * 1e6),
                min_free_bytes=int(o.min_free_mb * 1e6), image_format=o.frames,
                jpeg_quality=o.jpeg_quality, log=self._log)
        folder.write_snapshot(self.config, self.camera)
        # What exists now (modules, libraries, the configuration) lives as long as the flight:
        # the garbage collector need not scan it again, which keeps its pauses short.
        gc.collect()
        gc.freeze()
        try:
            await self._start_view()
            await self._fly(stop, folder, tlog)
            await self._close_view()  # the pages' last picture is the final estimate
            tracks = self._write_reports(folder)
            self._event("end", state=self.mission.state.value, confirmed=len(tracks),
                        **self.counters)
        except Exception as exc:
            self._event("error", error=f"{type(exc).__name__}: {exc}")
            raise
        finally:
            gc.unfreeze()
            await self._close_view()
            self.notifier.stopping()
            self.notifier.close()
            tlog.close()
            self.counters["tlog_messages"] = tlog.written
            if self._frames is not None:
                self.counters["frames_kept"] = self._frames.kept
                self._frames.close()
            folder.close()
        return RunResult(out, tracks, self.mission.state.value, dict(self.counters))

    async def _fly(self, stop: asyncio.Event, folder: RunFolder, tlog: TlogWriter) -> None:
        c, v = self.config.camera, self.config.vehicle
        source = open_source(c.source, c.kind)
        grabber = LatestFrameGrabber(source, self.clock).start()

        def record(system_id: int, component_id: int, name: str, fields_json: str) -> None:
            tlog.submit(time.time(), system_id, component_id, name, fields_json)

        relay = None
        warm_up = asyncio.get_running_loop().run_in_executor(None, self._warm_up)
        try:
            url = v.connection
            if v.signing_key_file is not None:  # MAVSDK cannot sign: a relay signs for it
                relay = SigningRelay(v.connection, load_signing_key(Path(v.signing_key_file)))
                url = relay.start()
                self._event("signing_relay", url=url, vehicle=v.connection)
            async with MavsdkLink.connect(url, v.connect_timeout_s,
                                          v.telemetry_rate_hz) as link:
                self._event("connected", url=v.connection)
                try:
                    async with asyncio.TaskGroup() as group:
                        wake = asyncio.Event()  # a control tick is due now, not on schedule
                        self.view.on_mode_change = lambda: self._mode_event(wake)
                        self.view.on_text = self._autopilot_text
                        tasks = [group.create_task(link.run_telemetry(self.view, record)),
                                 group.create_task(_set_when(stop, wake))]
                        done = asyncio.Event()
                        estimator = group.create_task(
                            self._estimate(grabber, folder, done, warm_up))
                        await self._control(link, stop, wake)
                        done.set()  # the step under way ends and is logged, unless it hangs
                        await asyncio.wait([estimator], timeout=ESTIMATOR_STOP_S)
                        for task in [*tasks, estimator]:
                            task.cancel()
                except ExceptionGroup as failed:  # a task died: report its own error
                    raise failed.exceptions[0] from failed
                finally:
                    self.counters["telemetry_malformed"] = link.malformed
        finally:
            if relay is not None:
                relay.stop()
                self.counters.update({f"signing_{name}": n for name, n in
                                      dataclasses.asdict(relay.counters).items()})
            grabber.stop()
            self.counters["frames_dropped"] = grabber.dropped
            self.counters["frame_errors"] = grabber.errors
            self.counters["frames_corrupt"] = getattr(source, "corrupt_frames", 0)
            self.counters.update({f"rejected_{k}": v for k, v in self.view.rejected.items()})

    async def _start_view(self) -> None:
        """Serve the operator's page (view.enabled); an address that cannot be taken, or an
        orthophoto that cannot be read, is logged and the flight goes on without it."""
        v = self.config.view
        if not v.enabled:
            return
        orthophoto, notes = await self._load_orthophoto()
        live = LiveView(self.config, self.pipeline.frame, self.pipeline.params.tracks, self._log,
                        orthophoto=orthophoto, notes=notes)
        try:
            await live.start()
        except CompanionError as exc:
            self._log(f"view: not served: {exc}")
            self._event("view_failed", error=str(exc))
            return
        self.live = live
        self._log(f"view: serving the operator's page at {live.server.url}")
        self._event("view", url=live.server.url, token=v.token_file is not None)

    async def _load_orthophoto(self) -> tuple[Orthophoto | None, list[str]]:
        """The configured orthophoto (off the event loop), or None and the page's note why."""
        path = self.config.view.orthophoto
        if path is None:
            return None, []
        loop = asyncio.get_running_loop()
        try:
            ortho = await loop.run_in_executor(None, partial(
                load_orthophoto, Path(path), self.pipeline.frame,
                self.config.safety.geofence_latlon))
        except Exception as exc:  # a field service flies on without its background image
            reason = str(exc) if isinstance(exc, CompanionError) else (
                f"view.orthophoto: {path}: cannot be read ({type(exc).__name__}: {exc})")
            self._log(f"view: warning: the orthophoto is not shown: {reason}")
            self._event("view_orthophoto_failed", error=reason)
            return None, [f"The orthophoto is not shown: {reason}"]
        w, h = ortho.size_px
        self._log(f"view: orthophoto {ortho.name}: {w} x {h} px at "
                  f"{ortho.resolution_m:.2f} m per pixel")
        return ortho, []

    async def _close_view(self) -> None:
        """Stop serving the page (once); its counters join the run's."""
        live, self.live = self.live, None
        if live is not None:
            await live.close()
            self.counters.update(live.counters())

    def _view_vehicle(self) -> Vehicle | None:
        """The vehicle for the page: its newest pose on the grid, heading and height."""
        view, frame = self.view, self.pipeline.frame
        sample = view.poses.newest()
        if sample is None:
            return None
        xy = vehicle_xy(frame, sample.lat_deg, sample.lon_deg)
        return Vehicle((float(xy[0]), float(xy[1])), yaw_deg(sample.q_wxyz), sample.alt_rel_m)

    def _view_status(self, record: StepRecord, frames_dropped: int) -> Status:
        """The service's status for the page: mission, link, camera, counters, home."""
        origin = self.view.local_origin()
        home = None
        if origin is not None:
            hx, hy = vehicle_xy(self.pipeline.frame, origin.lat_deg, origin.lon_deg)
            home = (float(hx), float(hy))
        return Status(self.mission.state.value, self._inputs().connected,
                      record.blind not in CAMERA_BLIND,
                      {**self.counters, "frames_dropped": frames_dropped}, home)

    def _step_status(self, status: Status) -> dict[str, Any]:
        """What steps.jsonl keeps of the page's status at a step, for the replay view: the
        mission state, link and camera health, and home (UTM) once known."""
        home = status.home_xy_m
        home_utm = None if home is None else [
            round(float(v), 3) for v in self.pipeline.frame.to_utm(np.array(home))]
        return {"mission": status.mission, "link_ok": status.link_ok,
                "camera_ok": status.camera_ok, "home_utm": home_utm}

    def _resume(self, out: Path) -> None:
        """Find the checkpoint of a run that stopped a short while ago (a restart?)."""
        found = latest_checkpoint(Path(self.config.output.dir), exclude=out,
                                  max_age_s=RESUME_WITHIN_S, now_wall_s=time.time(), log=self._log)
        self._checkpoint_found = found

    def _resume_if_flying(self, in_air: bool) -> None:
        """Once the vehicle is first seen: flying means the service restarted mid-flight. Then
        carry on the checkpoint's estimate and take no automatic step (arm, take-off, offboard):
        the pilot selects OFFBOARD to resume. On the ground it is a new flight."""
        found, self._checkpoint_found = self._checkpoint_found, None
        if found is None:
            return
        path, data = found
        if not in_air:
            self._log(f"checkpoint of {path.parent.name} not resumed: the vehicle is on the "
                      "ground, a new flight")
            return
        self.mission = dataclasses.replace(self.mission, auto_arm_spent=True,
                                           auto_offboard_spent=True)
        refused = self.pipeline.restore(data)
        if refused is not None:
            self._log(f"checkpoint {path} {refused}: not resumed")
            return
        state = self.pipeline.state
        confirmed = 0 if state is None else int(state.tracks.confirmed.sum())
        self._log(f"resumed the estimate of {path.parent.name}: {confirmed} confirmed tracks; "
                  "no automatic arm, take-off or offboard after a restart")
        self._event("resumed", checkpoint=str(path), confirmed=confirmed)

    def _event(self, event: str, **fields: Any) -> None:
        if self._folder is not None:
            self._folder.write_event({"t_s": round(self.clock(), 6), "event": event, **fields})

    def _mode_event(self, wake: asyncio.Event) -> None:
        """Each flight mode and arming state the autopilot reports, logged when it was seen;
        the control loop runs at once."""
        st = self.view.status
        if st is not None:
            self._event("mode", mode=st.flight_mode.name, armed=st.armed)
        wake.set()

    def _autopilot_text(self, text: str) -> None:
        """The autopilot's own words (why it refused an arm, say): into the journal; events
        the service has no text for only into the run's events."""
        if text.startswith(UNKNOWN_PREFIX):
            self._event("autopilot_event", id=text.removeprefix(UNKNOWN_PREFIX))
        else:
            self._log(text if text.startswith("autopilot") else f"autopilot: {text}")

    def _log(self, line: str) -> None:
        """A line for the operator (the journal) and the run's events."""
        self.announce(line)
        self._event("log", message=line)

    # -- estimator ---------------------------------------------------------------------------

    def _warm_up(self) -> float:
        """Compile the estimator's kernels (or load them from numba's cache) before the first
        step needs them; the seconds it took."""
        started = time.perf_counter()
        self.pipeline.warm_up()
        return time.perf_counter() - started

    async def _estimate(self, grabber: LatestFrameGrabber, folder: RunFolder,
                        done: asyncio.Event, warm_up: asyncio.Future[float]) -> None:
        """One step per period on the newest frame (no backlog builds up), until done is set."""
        period_s = 1.0 / self.config.estimator.rate_hz
        loop = asyncio.get_running_loop()
        self._log(f"estimator: ready (kernels compiled or loaded in {await warm_up:.1f} s)")
        next_s = self.clock()
        while not done.is_set():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(done.wait(),
                                       max(next_s - self.clock(), 0.0) / self.time_scale)
            if done.is_set():
                return
            next_s = max(next_s + period_s, self.clock())
            frame = await loop.run_in_executor(None, grabber.get,
                                               0.5 * period_s / self.time_scale)
            try:
                record = await self._estimator_step(frame, loop)
            except CompanionError as exc:  # unusable input: a blind step, and fly on
                boot_s = self.view.boot_time_now()
                self._event("step_error", error=str(exc))
                record = None if boot_s is None else observe(
                    self.pipeline, Observation.nothing(boot_s, "bad input"))
            if record is None:
                continue
            self._last_step_wall_s = time.monotonic()
            self.counters["steps"] += 1
            self.counters["blind_steps"] += record.blind is not None
            status = self._view_status(record, grabber.dropped)
            step_json = record.to_json(self.pipeline.frame)
            step_json.update(self._step_status(status))
            folder.write_step(step_json)
            state = self.pipeline.state
            if self.live is not None:
                await self.live.after_step(step_json, state, self._view_vehicle(), status)
            if state is not None and state.t_s >= self._checkpoint_due_s:  # off the event loop
                self._checkpoint_due_s = state.t_s + CHECKPOINT_EVERY_S
                await loop.run_in_executor(None, save_checkpoint, folder.path,
                                           self.pipeline.checkpoint())

    async def _estimator_step(self, frame: Frame | None,
                              loop: asyncio.AbstractEventLoop) -> StepRecord | None:
        boot_now_s = self.view.boot_time_now()
        if boot_now_s is None:
            return None  # no telemetry yet: no time base
        if frame is None:
            return observe(self.pipeline, Observation.nothing(boot_now_s, "no frame"))
        capture_s = frame.capture_time_s
        if capture_s is None:  # a camera that knows no boot time: map its receive time
            capture_s = (frame.receive_time_s + (boot_now_s - self.clock())
                         - self.config.camera.latency_s)
        await self._wait_for_pose(capture_s)
        obs = frame_observation(self.view, capture_s, frame.image, self.config.pose)
        if obs.blind is not None:
            return observe(self.pipeline, obs)
        started = time.perf_counter()
        record = await loop.run_in_executor(None, observe, self.pipeline, obs)
        self.counters["frames_used"] += record.blind is None
        record.extra["latency_ms"] = round(1e3 * (self.clock() - frame.receive_time_s), 2)
        record.extra["process_ms"] = round(1e3 * (time.perf_counter() - started), 2)
        if self._frames is not None and record.blind is None:
            kept = await loop.run_in_executor(None, self._frames.write, frame.image, capture_s)
            if kept is not None:
                record.extra["input"]["frame"] = kept
        return record

    async def _wait_for_pose(self, capture_s: float) -> None:
        """Wait up to POSE_WAIT_S for the telemetry of a frame's capture time, which a slow
        link delivers after the frame."""
        deadline_s = self.clock() + POSE_WAIT_S
        while True:
            latest_s = self.view.latest_boot_s
            if (self.view.poses.at(capture_s) is not None or latest_s is None
                    or latest_s >= capture_s or self.clock() >= deadline_s):
                return
            await asyncio.sleep(POSE_POLL_S / self.time_scale)

    # -- control -----------------------------------------------------------------------------

    def _inputs(self) -> ms.MissionInputs:
        st, view = self.view.status, self.view
        now_s = view.boot_time_now()
        fresh = (now_s is not None and view.latest_boot_s is not None
                 and now_s - view.latest_boot_s
                 < max(TELEMETRY_STALE_S, TELEMETRY_STALE_WALL_S * self.time_scale))
        here = view.poses.newest()
        state = self.pipeline.state
        confirmed = 0 if state is None else int(state.tracks.confirmed.sum())
        passes = 0
        if isinstance(self._planner, LawnMower):
            passes = self._carrot.progress * self.config.search.sweeps // len(self._planner.path_xy)
        elif self._planner is not None and self._planner.finished(self._carrot.progress):
            passes = 1  # the search-and-track planner's own stop rule: the area is covered
        return ms.MissionInputs(
            connected=st is not None and fresh,
            health_ok=st is not None and st.position_ok,
            armed=st is not None and st.armed,
            in_air=st is not None and st.in_air,
            flight_mode=mission_mode(st),
            battery_low=st is not None and st.battery_percent < BATTERY_LOW_PERCENT,
            position_ok=fresh and view.local_origin() is not None,
            coverage_passes=passes, confirmed_targets=confirmed,
            expected_targets=self.config.search.expected_targets,
            setpoints_streaming=self._streaming_since_s is not None
            and self.clock() - self._streaming_since_s >= STREAM_SETTLE_S,
            alt_rel_m=None if here is None else here.alt_rel_m,
            autopilot=ms.Autopilot.ARDUPILOT if view.ardupilot else ms.Autopilot.PX4)

    async def _control(self, link: MavsdkLink, stop: asyncio.Event, wake: asyncio.Event) -> None:
        """Tick at the setpoint rate, and at once when `wake` is set (a change of mode)."""
        period_s = 1.0 / self.config.mission.setpoint_rate_hz
        final = (ms.State.DONE, ms.State.FAILSAFE)
        last_tick_s = next_s = self.clock()
        early = False  # this tick was woken ahead of the schedule: it sends no setpoint
        while not stop.is_set():
            wake.clear()
            now_s = self.clock()
            # After a stall of this process (a loaded computer) the telemetry that came in
            # meanwhile is still queued: judge the link one tick later, not now.
            stalled, last_tick_s = now_s - last_tick_s > STALL_TICKS * period_s, now_s
            inputs = self._inputs()
            before = self.mission.state
            if self._checkpoint_found is not None and inputs.connected:
                here = self.view.poses.newest()
                if here is not None:  # the first position decides: flying or on the ground
                    self._resume_if_flying(inputs.in_air or here.alt_rel_m > MIN_FLYING_M)
            if not stalled:
                self.mission, commands = ms.advance(self.mission, inputs, now_s)
                self._tell_systemd(inputs, before)
                for command in commands:
                    await self._execute(link, command)
            if self._stream is not None and not early:
                await self._send_setpoint(link, period_s)
            await self._announce_targets(link)
            self._report_glitch()
            st = self.view.status
            if self.mission.state in final and st is not None and not st.armed:
                return  # landed and disarmed after the end
            # Ticks keep to a schedule, so the time the tick took does not stretch the period;
            # after a stall the schedule restarts from now rather than sending a burst.
            if not early:
                next_s = max(next_s + period_s, self.clock())
            try:
                await asyncio.wait_for(wake.wait(), (next_s - self.clock()) / self.time_scale)
                early = True
            except TimeoutError:
                early = False

    def _report_glitch(self) -> None:
        """A line when positions start being refused as implausible, and when they stop."""
        refusing = self.view.gate.refusing_since_s is not None
        if refusing != self._glitch_reported:
            self._glitch_reported = refusing
            self._log("position: implausible jump (GPS glitch?): positions refused, frames blind"
                      if refusing else "position: plausible again")

    def _tell_systemd(self, inputs: ms.MissionInputs, before: ms.State) -> None:
        """READY once connected, STATUS on every state change, WATCHDOG while the pipeline runs."""
        state = self.mission.state
        if inputs.connected and not self._ready_sent:
            self._ready_sent = True
            self.notifier.ready(f"connected to {self.config.vehicle.connection}")
        if state is not before:
            confirmed = inputs.confirmed_targets
            self.notifier.status(f"{state.value}: {confirmed} targets confirmed")
        interval_s = self.notifier.watchdog_interval_s
        if interval_s is None:
            return
        now_s = time.monotonic()
        wall_period_s = 1.0 / self.config.estimator.rate_hz / self.time_scale
        alive = now_s - self._last_step_wall_s < max(5.0 * wall_period_s, 2.0)
        if alive and now_s - self._last_watchdog_wall_s >= interval_s:
            self.notifier.watchdog()
            self._last_watchdog_wall_s = now_s

    async def _execute(self, link: MavsdkLink, command: ms.Command) -> None:
        kind = command.kind
        self._event("command", kind=kind.value, text=command.text or None,
                    stream=command.stream.value if command.stream else None)
        if kind is ms.CommandKind.STATUSTEXT:
            self.announce(command.text)
        try:
            if kind is ms.CommandKind.STOP_SETPOINTS:
                link.release()  # at once, and without asking for any mode
                self._stream, self._previous = None, None
                self._carrot = Carrot(None, self._carrot.progress)  # the plan's progress stays
                self._streaming_since_s = None
            elif kind is ms.CommandKind.START_SETPOINTS:
                self._stream = command.stream
            elif kind is ms.CommandKind.ARM:
                await link.arm()
            elif kind is ms.CommandKind.TAKEOFF:
                await link.take_off(command.takeoff_alt_m or self.config.search.altitude_m)
            elif kind is ms.CommandKind.START_OFFBOARD:
                await link.start_offboard()
            elif kind is ms.CommandKind.HOLD:
                await link.hold()
            elif kind is ms.CommandKind.LAND:
                await link.land()
            elif kind is ms.CommandKind.RTL:
                await link.return_to_launch()
            elif kind is ms.CommandKind.STATUSTEXT:
                severity = (command.severity or ms.Severity.INFO).name.lower()
                await link.status_text(command.text, severity)
        except VehicleError as exc:
            self.counters["command_errors"] += 1
            self._event("command_failed", kind=kind.value, error=str(exc))

    async def _announce_targets(self, link: MavsdkLink) -> None:
        """One STATUSTEXT per newly confirmed target: its id and position (any GCS shows it)."""
        state, frame = self.pipeline.state, self.pipeline.frame
        if state is None:
            return
        tracks = state.tracks
        for i in np.flatnonzero(tracks.confirmed):
            track_id = int(tracks.ids[i])
            if track_id in self._announced:
                continue
            self._announced.add(track_id)
            lat, lon = frame.to_latlon(tracks.means[i, :2])[0]
            text = f"target {track_id}: {lat:.6f} {lon:.6f}"
            self._event("target", id=track_id, lat_deg=float(lat), lon_deg=float(lon))
            self.announce(text)
            with contextlib.suppress(VehicleError):
                await link.status_text(text, "notice")

    # -- setpoints ---------------------------------------------------------------------------

    def _target_xy(self, vehicle_xy_m: FloatArray, dt_s: float) -> FloatArray:
        """The search-frame point the vehicle should be at now: a carrot along the plan, kept
        the clearance inside the geofence."""
        state = self.pipeline.state
        if state is None:
            return vehicle_xy_m if self._carrot.xy_m is None else self._carrot.xy_m
        if self._planner is None:
            self._planner = self._make_planner(vehicle_xy_m)
        target, self._carrot = self._carrot.advance(
            self._planner, vehicle_xy_m, state.mixture, state.tracks, self.pipeline.frame.world,
            self.config.search.speed_m_s, dt_s, state.t_s)
        return self._keep_in.nearest(target)

    async def _send_setpoint(self, link: MavsdkLink, dt_s: float) -> None:
        view, origin = self.view, self.view.local_origin()
        sample = view.poses.newest()
        if origin is None or sample is None or view.local_ned_m is None or view.home_amsl_m is None:
            return
        if self._limits is None:
            self._limits = gate_limits(self.config.safety, origin, view.home_amsl_m)
        vehicle_ned = np.array(view.local_ned_m)
        yaw_deg = self.config.search.heading_deg
        if self._stream is ms.Stream.HOLD_HERE:
            wanted = hold_setpoint(vehicle_ned, yaw_deg)
        else:
            frame = self.pipeline.frame
            target_xy = self._target_xy(vehicle_xy(frame, sample.lat_deg, sample.lon_deg), dt_s)
            wanted = search_setpoint(frame, origin, target_xy,
                                     view.home_amsl_m + self.config.search.altitude_m, yaw_deg)
        previous = self._previous
        wanted = ramp(wanted, vehicle_ned if previous is None else np.array(
            [previous.north_m, previous.east_m, previous.down_m]), self._limits, dt_s)
        result = gate(self._limits, wanted, previous, vehicle_ned, dt_s)
        if result.action is not GateAction.PASS:
            self.counters[f"setpoints_{result.action.value}"] += 1
            self._event("gate", action=result.action.value, reasons=list(result.reasons))
        if result.setpoint is None:
            return
        sp = result.setpoint
        await link.set_setpoint(sp.north_m, sp.east_m, sp.down_m, sp.yaw_deg)
        if self._streaming_since_s is None:
            self._streaming_since_s = self.clock()
        self._previous = sp
        self.counters["setpoints"] += 1
        self._event("setpoint", north_m=round(sp.north_m, 3), east_m=round(sp.east_m, 3),
                    down_m=round(sp.down_m, 3), mode=self.mission.state.value)

    # -- reports -----------------------------------------------------------------------------

    def _write_reports(self, folder: RunFolder) -> list[TrackRecord]:
        state, frame = self.pipeline.state, self.pipeline.frame
        records = [] if state is None else confirmed_tracks(
            state.tracks, frame.origin_utm_m, frame.utm.epsg, frame.to_latlon, state.t_s,
            self.pipeline.params.tracks)
        summary = {"state": self.mission.state.value, "confirmed": len(records),
                   "counters": self.counters, "utm_epsg": frame.utm.epsg,
                   "tracks": [r.id for r in records]}
        # no matplotlib: the run's data is all there anyway
        folder.write_reports(records, summary, plots=self.config.output.plots,
                             area_en_m=frame.to_utm(frame.area_xy_m),
                             on_plots_skipped=lambda why: self._event("plots_skipped", reason=why))
        return records
