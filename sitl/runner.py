"""One SITL mission: the scenario's world, a mock autopilot on MAVLink and a rendered camera stream.

`Sitl(scenario, ...)` wires them together on loopback; `start()` runs three threads (the
autopilot, the camera, the fault schedule) and `stop()` ends them all. The camera renders, at
its frame rate in simulated time, what the downward camera sees from the vehicle's true pose and
serves it as MJPEG over HTTP, each frame stamped with the autopilot's boot time of that pose.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.sim.scenario import Scenario
from companion.vision.camera import BodyPose, CameraModel
from sitl.autopilot import AutopilotConfig, Failsafe, MockAutopilot, Snapshot
from sitl.camera import Renderer
from sitl.clock import SimClock
from sitl.faults import FaultEvent, FaultKind, FaultPlan
from sitl.link import UdpLink
from sitl.modes import Behaviour, Flavour
from sitl.stream import MjpegServer
from sitl.vehicle import VehicleLimits
from sitl.workers import Workers
from sitl.world import TargetWorld, clutter_tags

__all__ = ["CameraLoop", "FrameClock", "FrameCounts", "Shot", "Sitl", "autopilot_config",
           "render_scene"]

PX4_OFFBOARD_PORT = 14540  # where PX4 SITL sends MAVLink for an offboard API (MAVSDK)
_PILOT_MODES = {
    "posctl": Behaviour.POSITION, "altctl": Behaviour.ALTITUDE, "manual": Behaviour.MANUAL,
    "hold": Behaviour.HOLD, "land": Behaviour.LAND, "rtl": Behaviour.RTL,
}
_SCHEDULE_POLL_WALL_S = 0.01
CLOCK_JUMP_S = 1.0  # a camera clock that goes back by more than this restarts the schedule


@dataclass(frozen=True, slots=True)
class EstimateErrors:
    """A flavour's estimate errors (1-sigma, slowly varying) and whether it has a rangefinder."""

    heading_deg: float
    attitude_deg: float
    position_m: float
    height_m: float
    rangefinder: bool


# What a SITL mission flies when its scenario says nothing. ArduPilot's are as measured (within
# 0.6 degrees and 2 cm of SITL's truth). PX4 SIH's estimate wandered 5-10 degrees off in heading
# and 2-4 degrees in roll during a search (docs/sitl.md); with that, the service does not yet
# hold one track per tag, so PX4 missions fly a fifth of that heading error unless asked
# (`vehicle.heading_error_deg`). SIH simulates a downward rangefinder (SIH_DISTSNSR_MAX 100 m).
MEASURED_ERRORS: dict[Flavour, EstimateErrors] = {
    Flavour.PX4: EstimateErrors(heading_deg=1.5, attitude_deg=1.0, position_m=0.15,
                                height_m=0.5, rangefinder=True),
    Flavour.ARDUPILOT: EstimateErrors(heading_deg=0.4, attitude_deg=0.3, position_m=0.02,
                                      height_m=0.05, rangefinder=False),
}


def autopilot_config(scenario: Scenario) -> AutopilotConfig:
    """The mock autopilot the scenario's [vehicle] table describes, booting at robot.start
    (the keys left out: the flavour's measured values)."""
    v = scenario.vehicle
    x_m, y_m = scenario.robot.start_xy
    measured = MEASURED_ERRORS[Flavour(v.flavour)]

    def given(value: float | None, default: float) -> float:
        return default if value is None else value

    return AutopilotConfig(
        flavour=Flavour(v.flavour),
        home_ned=(y_m, x_m),
        home_yaw_deg=v.heading_deg,
        ekf_origin_offset_ned=v.ekf_origin_offset_m,
        takeoff_alt_m=v.takeoff_altitude_m,
        rtl_alt_m=v.rtl_altitude_m,
        offboard_loss_timeout_s=v.offboard_loss_timeout_s,
        offboard_failsafe=Failsafe(v.offboard_failsafe),
        armable_after_s=v.armable_after_s,
        gps_fix_after_s=v.gps_fix_after_s,
        arm_unstable_s=v.arm_unstable_s,
        takeoff_spoolup_s=v.takeoff_spoolup_s,
        rel_alt_bias_m=v.rel_alt_bias_m,
        position_noise_m=v.position_noise_m,
        gps_drift_m_per_sqrt_s=v.gps_drift_m_per_sqrt_s,
        heading_error_deg=given(v.heading_error_deg, measured.heading_deg),
        attitude_error_deg=given(v.attitude_error_deg, measured.attitude_deg),
        position_error_m=given(v.position_error_m, measured.position_m),
        height_error_m=given(v.height_error_m, measured.height_m),
        error_time_constant_s=v.error_time_constant_s,
        rangefinder=measured.rangefinder if v.rangefinder is None else v.rangefinder,
        rangefinder_max_m=v.rangefinder_max_m,
        battery_flight_s=v.battery_flight_s,
        battery_low_percent=v.battery_low_percent,
        limits=VehicleLimits(max_speed_h_m_s=v.max_speed_m_s, max_accel_m_s2=v.max_accel_m_s2,
                             max_yaw_rate_deg_s=v.max_yaw_rate_deg_s),
        seed=scenario.seed,
    )


@dataclass
class FrameCounts:
    """What the camera did so far."""

    published: int = 0
    dropped: int = 0  # by a fault
    late: int = 0  # skipped because rendering fell behind the frame rate
    offline: int = 0  # not taken while the autopilot rebooted (no time base)


class Sitl:
    """A whole SITL mission on loopback; a context manager that starts and stops it."""

    def __init__(
        self,
        scenario: Scenario,
        *,
        speedup: float = 1.0,
        faults: FaultPlan | None = None,
        host: str = "127.0.0.1",
        mavlink_port: int = PX4_OFFBOARD_PORT,
        gcs_port: int | None = None,
        camera_port: int = 0,
        signing_key: bytes | None = None,
    ) -> None:
        self.scenario = scenario
        self.faults = faults or FaultPlan()
        seeds = np.random.SeedSequence(scenario.seed).spawn(3)
        self.clock = SimClock(speedup)
        self.world = TargetWorld(scenario, np.random.default_rng(seeds[0]))
        remotes = [(host, mavlink_port)] + ([(host, gcs_port)] if gcs_port is not None else [])
        link = UdpLink(remotes, np.random.default_rng(seeds[1]), bind=(host, 0))
        link.faults.loss_in = self.faults.loss_to_autopilot
        link.faults.loss_out = self.faults.loss_from_autopilot
        link.faults.latency_s = self.faults.latency_s
        config = autopilot_config(scenario)
        if signing_key is not None:  # the autopilot signs and rejects unsigned frames
            config = dataclasses.replace(config, signing_key=signing_key)
        self.autopilot = MockAutopilot(config, link, self.clock, scenario.geo.local_ned())
        self.renderer = Renderer(scenario.camera, texture_seed=scenario.seed)
        self.stream = MjpegServer(host, camera_port)
        self.frames = FrameCounts()
        self.mavlink_url = f"udpin://{host}:{mavlink_port}"
        self._camera_rng = np.random.default_rng(seeds[2])
        self._events: list[FaultEvent] = list(self.faults.events)
        self._applied = 0
        self._lock = threading.Lock()
        self._workers = Workers()
        self._stopping = self._workers.stopping

    @property
    def camera_url(self) -> str:
        """The MJPEG stream (cv2.VideoCapture or MjpegReader opens it)."""
        return self.stream.url

    # -- lifecycle ----------------------------------------------------------------------------

    def start(self) -> Sitl:
        """Serve the camera, boot the autopilot, run the camera and the fault schedule."""
        self.stream.start()
        self.autopilot.start()
        self._workers.start(("sitl-camera", self._camera_loop), ("sitl-faults", self._fault_loop))
        return self

    def stop(self) -> None:
        """Stop every thread and close every socket. Idempotent."""
        self._workers.stop()
        self.autopilot.stop()
        self.stream.stop()

    def __enter__(self) -> Sitl:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    # -- faults -------------------------------------------------------------------------------

    def inject(self, kind: FaultKind, duration_s: float = 0.0, arg: str = "") -> FaultEvent:
        """Start a fault now (what `--faults` schedules: see sitl.faults)."""
        event = FaultEvent(kind, self.clock.now_s(), duration_s, arg)
        with self._lock:
            self._events.append(event)
        return event

    def _fault_loop(self) -> None:
        while not self._stopping.is_set():
            now = self.clock.now_s()
            with self._lock:
                due = [e for e in self._events[self._applied:] if e.at_s <= now]
                pending = [e for e in self._events[self._applied:] if e.at_s > now]
                self._events[self._applied:] = due + pending
                self._applied += len(due)
            for event in due:
                self._apply(event)
            self._stopping.wait(_SCHEDULE_POLL_WALL_S)

    def _apply(self, event: FaultEvent) -> None:
        ap = self.autopilot
        if event.kind is FaultKind.CUT:
            ap.link.faults.cut_until_s = event.at_s + event.duration_s
        elif event.kind is FaultKind.GPS:
            north_m, east_m = event.gps_offset_ne_m()
            ap.gps_glitch((north_m, east_m, 0.0), event.duration_s)
        elif event.kind is FaultKind.BATTERY:
            ap.set_battery_percent(float(event.arg))
        elif event.kind is FaultKind.PILOT:
            if event.arg in ("arm", "disarm"):
                ap.pilot_arm(event.arg == "arm")
            else:
                ap.pilot_set_mode(_PILOT_MODES[event.arg])
        elif event.kind is FaultKind.REBOOT:
            ap.reboot(event.duration_s)
        # camera faults act frame by frame (_camera_fault)

    def _camera_fault(self, t_s: float) -> FaultKind | None:
        with self._lock:
            return FaultPlan(events=tuple(self._events)).camera_fault(t_s)

    # -- the camera ---------------------------------------------------------------------------

    def _camera_loop(self) -> None:
        CameraLoop(self.stream, self.scenario.camera, self.clock, self._shot,
                   self._camera_fault, self.faults.frame_drop, self._camera_rng,
                   self.frames).run(self._stopping)

    def _shot(self, due_s: float) -> Shot | None:
        """The frame due now, from the autopilot's true state; None while it reboots."""
        snap = self.autopilot.snapshot()
        if not snap.online:
            return None
        return Shot(snap.t_s, snap.clock_s, lambda: self._render(snap))

    def _render(self, snap: Snapshot) -> np.ndarray:
        v = snap.vehicle
        north_m, east_m, down_m = (float(c) for c in v.position_ned)
        pose = BodyPose(snap.t_s, north_m, east_m, down_m, v.quaternion_wxyz())
        return render_scene(self.scenario, self.world, self.renderer, pose, snap.clock_s,
                            self._camera_rng)


def render_scene(scenario: Scenario, world: TargetWorld, renderer: Renderer, pose: BodyPose,
                 scenario_t_s: float, rng: np.random.Generator) -> NDArray[np.uint8]:
    """The frame seen from `pose`: the world's tags at scenario_t_s, misses and clutter drawn."""
    s = scenario
    tags = world.tags(scenario_t_s)
    # Misses are per frame; the clutter rate is per step dt, spread over the step's frames.
    frames_per_step = max(s.camera.rate_hz * s.dt_s, 1.0)
    hidden = {t.tag_id for t in tags if rng.random() > s.sensor.p_detect}
    distractors = clutter_tags(
        s.camera, pose, world.target_count, s.targets.tag_size_m,
        s.sensor.clutter_prob / frames_per_step, s.sensor.clutter_rate / frames_per_step, rng,
    )
    return renderer.render(pose, tags, rng, distractors=distractors, hidden=hidden)


class FrameClock(Protocol):
    """The clock a camera's frames fall due on."""

    def now_s(self) -> float:
        """The time now."""

    def wall_s(self, sim_s: float) -> float:
        """Wall-clock duration of a duration on this clock."""


@dataclass(frozen=True, slots=True)
class Shot:
    """A frame to take: its capture time (autopilot boot time base), scenario time, drawing."""

    capture_time_s: float  # what the frame is stamped with
    scenario_t_s: float  # time since the start, for the fault plan
    draw: Callable[[], NDArray[np.uint8]]  # renders the image (not called when dropped)


class CameraLoop:
    """Publishes `camera`'s frames on `stream` at its rate on `clock`, through the camera faults.

    take(due_s) gives the frame due at clock time due_s (None: no pose, counted offline);
    fault(t_s) the camera fault in effect at a scenario time; frame_drop is the probability
    a frame is lost. Counts go into `frames`. A clock that goes back (an autopilot reboot)
    restarts the schedule.
    """

    def __init__(self, stream: MjpegServer, camera: CameraModel, clock: FrameClock,
                 take: Callable[[float], Shot | None], fault: Callable[[float], FaultKind | None],
                 frame_drop: float, rng: np.random.Generator,
                 frames: FrameCounts | None = None) -> None:
        self.stream = stream
        self.shape_px = (camera.height_px, camera.width_px)
        self.period_s = 1.0 / camera.rate_hz
        self.clock = clock
        self.take = take
        self.fault = fault
        self.frame_drop = frame_drop
        self.rng = rng
        self.frames = frames if frames is not None else FrameCounts()

    def run(self, stopping: threading.Event) -> None:
        """Publish frames until `stopping` is set."""
        period_s, frames = self.period_s, self.frames
        next_s = self.clock.now_s()
        last: NDArray[np.uint8] | None = None
        while not stopping.is_set():
            now_s = self.clock.now_s()
            if next_s - now_s > period_s + CLOCK_JUMP_S:  # the clock went back
                next_s = now_s
            if next_s > now_s:
                stopping.wait(self.clock.wall_s(next_s - now_s))
                continue
            behind = math.floor((now_s - next_s) / period_s)
            if behind > 0:
                frames.late += behind
                next_s += behind * period_s
            due_s, next_s = next_s, next_s + period_s
            shot = self.take(due_s)
            if shot is None:
                frames.offline += 1
                continue
            fault = self.fault(shot.scenario_t_s)
            if fault is FaultKind.DROP or self.rng.random() < self.frame_drop:
                frames.dropped += 1
                continue
            if fault is FaultKind.FREEZE and last is not None:
                image = last
            elif fault is FaultKind.BLACK:
                image = np.zeros(self.shape_px, np.uint8)
            else:
                image = shot.draw()
            last = image
            if fault is FaultKind.CORRUPT:
                self.stream.publish_jpeg(self._garbled(image), shot.capture_time_s)
            else:
                self.stream.publish(image, shot.capture_time_s)
            frames.published += 1

    def _garbled(self, image: NDArray[np.uint8]) -> bytes:
        """A broken JPEG: half the time not decodable at all, else with garbage scan data."""
        ok, encoded = cv2.imencode(".jpg", image)
        data = bytearray(encoded.tobytes() if ok else b"")
        keep = 2 if self.rng.random() < 0.5 else len(data) // 3  # SOI / SOI + header
        noise = self.rng.integers(0, 256, len(data) - keep, dtype=np.uint8)
        data[keep:] = noise.tobytes()
        return bytes(data)
