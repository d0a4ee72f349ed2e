"""`companion-sitl SCENARIO --external-autopilot URL`: the SITL camera over a real autopilot SITL.

No mock autopilot runs. An ArduPilot Copter SITL or a PX4 SIH, reached over MAVLink at URL with
pymavlink (loopback only), gives the vehicle's pose; the scenario's tags are rendered from it
and served as MJPEG, each frame stamped on the autopilot's boot clock, as the mock SITL does.

- Pose sources, best first: ArduPilot's SIMSTATE (the simulator's truth: lat/lng in degE7,
  roll, pitch, yaw; its height from SIM_STATE's true altitude, else from GLOBAL_POSITION_INT),
  PX4 SIH's HIL_STATE_QUATERNION (its truth), else the autopilot's own estimate,
  GLOBAL_POSITION_INT + ATTITUDE. SIM_STATE's float latitude loses about 0.35 m: not used.
- Heights: the ground is flat at the altitude of the scenario's `[geo] origin`, which is the
  autopilot's home; the camera's height is the AMSL altitude minus that altitude.
- Times: the boot clock is `time_boot_ms` (ATTITUDE, GLOBAL_POSITION_INT, SYSTEM_TIME).
  SIMSTATE has no time stamp, and HIL_STATE_QUATERNION's `time_usec` stands still on PX4 SIH:
  their receive time is mapped to boot time as the service's VehicleView does (receive time +
  the largest offset of the recent samples, the least delayed one). Frames fall due at the
  camera's rate on that clock, and each frame's pose is interpolated at its capture time.
- The link: a 1 Hz ground-station heartbeat (system GCS_SYSTEM_ID) and SET_MESSAGE_INTERVAL for
  the messages above, again for any stream that stops for STREAM_TIMEOUT_S.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from types import TracebackType
from typing import Any, TextIO

import numpy as np
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.errors import ConfigError, InputError
from companion.geo import LocalNed
from companion.rotation import quaternion_from_euler
from companion.sim.scenario import Scenario
from companion.vehicle.pose_buffer import PoseBuffer
from companion.vision.camera import BodyPose
from sitl.camera import Renderer
from sitl.faults import CAMERA_FAULTS, FaultPlan
from sitl.runner import CameraLoop, FrameCounts, Shot, render_scene
from sitl.stream import MjpegServer
from sitl.workers import Workers
from sitl.world import TargetWorld

__all__ = ["ESTIMATE", "HIL_STATE", "SIMSTATE", "SOURCES", "BootClock", "ExternalAutopilot",
           "ExternalSitl", "camera_faults_only", "parse_autopilot_url", "run_external"]

URL_KEY = "--external-autopilot"
SIMSTATE = "SIMSTATE"
HIL_STATE = "HIL_STATE_QUATERNION"
ESTIMATE = "GLOBAL_POSITION_INT+ATTITUDE"
SOURCES = (SIMSTATE, HIL_STATE, ESTIMATE)  # best first

GCS_SYSTEM_ID = 254  # not 255: ArduPilot's GCS failsafe (SYSID_MYGCS) keeps watching the real GCS
GCS_COMPONENT_ID = mavlink.MAV_COMP_ID_MISSIONPLANNER
POSE_RATE_HZ = 50.0
_STREAMS_HZ = {  # per autopilot (HEARTBEAT.autopilot): message id -> rate requested
    mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA: {
        mavlink.MAVLINK_MSG_ID_SIMSTATE: POSE_RATE_HZ,
        mavlink.MAVLINK_MSG_ID_SIM_STATE: POSE_RATE_HZ,
        mavlink.MAVLINK_MSG_ID_ATTITUDE: POSE_RATE_HZ,
        mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: POSE_RATE_HZ,
        mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
    },
    mavlink.MAV_AUTOPILOT_PX4: {
        mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION: POSE_RATE_HZ,
        mavlink.MAVLINK_MSG_ID_ATTITUDE: POSE_RATE_HZ,
        mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: POSE_RATE_HZ,
        mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
    },
}
_ANY_STREAMS_HZ = {k: v for rates in _STREAMS_HZ.values() for k, v in rates.items()}
_AUTOPILOT_NAMES = {mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA: "ArduPilot",
                    mavlink.MAV_AUTOPILOT_PX4: "PX4"}

STREAM_TIMEOUT_S = 2.0  # a stream silent this long (wall) is requested again
NEVER_SEEN_REQUESTS = 3  # a message that never came is given up after this many requests
SOURCE_LIVE_S = 1.0  # a pose source whose newest sample is older than this is not used
POSE_WAIT_WALL_S = 0.25  # how long a frame waits for a pose sample at or after its time
TRUE_ALT_MAX_AGE_S = 0.5  # SIM_STATE's altitude goes with a SIMSTATE received this soon after
CLOCK_SAMPLES = 200  # as VehicleView: the boot clock's offset is the largest of these
REBOOT_JUMP_S = 1.0  # a boot time this far behind the newest means the autopilot rebooted
STATUS_POSE_MAX_AGE_S = 2.0  # a status line shows a pose only as recent as this (wall)
FAR_FROM_ORIGIN_M = 100.0  # a first pose farther than this from [geo] origin gets a warning
_HEARTBEAT_PERIOD_S = 1.0
_RECEIVE_TIMEOUT_S = 0.05
_CLOCK_WAIT_WALL_S = 0.05

_URL = re.compile(r"^(?P<scheme>[a-z]+):(//)?(?P<host>[^:/]*):(?P<port>[0-9]+)$")
_SCHEMES = {"udpin": "udpin", "udp": "udpin", "udpout": "udpout", "tcp": "tcp",
            "tcpin": "tcpin"}
_LOOPBACK = ("127.0.0.1", "localhost")


# -- arguments --------------------------------------------------------------------------------

def parse_autopilot_url(url: str) -> str:
    """The pymavlink device for a loopback MAVLink URL (`udpin:127.0.0.1:14560`, `udpin://...`,
    udpout, tcp, tcpin); ConfigError naming --external-autopilot for anything else."""
    m = _URL.match(url.strip())
    if m is None or m["scheme"] not in _SCHEMES:
        raise ConfigError(URL_KEY, f"{url!r}: write udpin:127.0.0.1:PORT (or udpout:, tcp:, "
                                   "tcpin: with a loopback host and a port)")
    if m["host"] not in _LOOPBACK:
        raise ConfigError(URL_KEY, f"{url!r}: loopback only (127.0.0.1 or localhost), "
                                   f"got host {m['host']!r}")
    port = int(m["port"])
    if not 1 <= port <= 65535:
        raise ConfigError(URL_KEY, f"{url!r}: the port must be in [1, 65535], got {port}")
    return f"{_SCHEMES[m['scheme']]}:127.0.0.1:{port}"


def camera_faults_only(plan: FaultPlan) -> FaultPlan:
    """`plan` when all its faults are the camera's; ConfigError naming --faults otherwise."""
    kinds = [name for name, value in (("loss", plan.loss_to_autopilot + plan.loss_from_autopilot),
                                      ("latency", plan.latency_s)) if value > 0.0]
    kinds += [e.kind for e in plan.events if e.kind not in CAMERA_FAULTS]
    if kinds:
        raise ConfigError("--faults", f"{', '.join(dict.fromkeys(kinds))}: not with "
                                      f"{URL_KEY} (the autopilot is not simulated here); camera "
                                      f"faults only: drop=P, {', '.join(CAMERA_FAULTS)}")
    return plan


# -- the boot clock ---------------------------------------------------------------------------

class BootClock:
    """The autopilot's boot time from receive times: boot = receive + the largest recent offset.

    observe() takes time-stamped samples; once `known`, now_s() and boot_at() map receive times
    (receive_clock, seconds) to boot seconds. A sample more than REBOOT_JUMP_S behind the newest
    (a reboot) starts over. wall_s() divides by the boot clock's measured rate (a sped-up SITL).
    Thread-safe.
    """

    def __init__(self, receive_clock: Callable[[], float] = time.monotonic,
                 samples: int = CLOCK_SAMPLES) -> None:
        self._clock = receive_clock
        self._samples: deque[tuple[float, float]] = deque(maxlen=samples)  # (receive, boot)
        self._lock = threading.Lock()
        self.latest_boot_s: float | None = None
        self.reboots = 0

    @property
    def known(self) -> bool:
        """Whether a time-stamped sample has been seen."""
        with self._lock:
            return bool(self._samples)

    def observe(self, boot_s: float, receive_s: float | None = None) -> None:
        """A sample stamped boot_s (seconds) received at receive_s (default: now)."""
        receive = self._clock() if receive_s is None else receive_s
        if not (math.isfinite(boot_s) and boot_s >= 0.0):
            return
        with self._lock:
            if self.latest_boot_s is not None and boot_s < self.latest_boot_s - REBOOT_JUMP_S:
                self._samples.clear()
                self.latest_boot_s = None
                self.reboots += 1
            self.latest_boot_s = boot_s if self.latest_boot_s is None else max(
                self.latest_boot_s, boot_s)
            self._samples.append((receive, boot_s))

    def boot_at(self, receive_s: float) -> float:
        """The boot time at receive time receive_s; InputError before any sample."""
        with self._lock:
            if not self._samples:
                raise InputError("no time-stamped message from the autopilot yet")
            return receive_s + max(boot - rx for rx, boot in self._samples)

    def now_s(self) -> float:
        """The boot time now; InputError before any sample."""
        return self.boot_at(self._clock())

    def rate(self) -> float:
        """Boot seconds per receive second over the samples held (1 until they span 1 s)."""
        with self._lock:
            if len(self._samples) < 2:
                return 1.0
            (rx0, boot0), (rx1, boot1) = self._samples[0], self._samples[-1]
        if rx1 - rx0 < 1.0 or boot1 <= boot0:
            return 1.0
        return min(max((boot1 - boot0) / (rx1 - rx0), 0.05), 50.0)

    def wall_s(self, sim_s: float) -> float:
        """Receive-clock duration of sim_s boot seconds."""
        return sim_s / self.rate()


# -- the autopilot's pose ---------------------------------------------------------------------

class ExternalAutopilot:
    """An autopilot SITL's pose over MAVLink, read in a thread; wait_pose() interpolates it.

    `geo` is the scenario's local frame (its `[geo] origin`) and ground_amsl_m the flat
    ground's altitude. The connection is opened at construction (ConfigError if it cannot be).
    """

    def __init__(self, url: str, geo: LocalNed, ground_amsl_m: float,
                 receive_clock: Callable[[], float] = time.monotonic) -> None:
        self.url = url
        self.device = parse_autopilot_url(url)
        self.geo = geo
        self.ground_amsl_m = ground_amsl_m
        self.clock = BootClock(receive_clock)
        self._receive_clock = receive_clock
        self._buffers = {s: PoseBuffer() for s in SOURCES}
        self._newest = {s: [-math.inf, -math.inf] for s in SOURCES}  # position, attitude
        self._cond = threading.Condition()
        self.target: tuple[int, int] | None = None  # (system, component) of the autopilot
        self.autopilot_type: int | None = None  # HEARTBEAT.autopilot
        self.received: Counter[str] = Counter()  # from the autopilot, by message type
        self.rejected = 0  # samples with unusable values
        self.requests: Counter[int] = Counter()  # SET_MESSAGE_INTERVAL sent, by message id
        self.gcs_heartbeats = 0
        self._last_rx: dict[int, float] = {}  # message id -> receive time
        self._last_request: dict[int, float] = {}  # message id -> time of its last request
        self._next_heartbeat_s = -math.inf
        self._true_alt: tuple[float, float] | None = None  # (receive, alt AMSL) of SIM_STATE
        self._workers = Workers()
        self._stopping = self._workers.stopping
        os.environ["MAVLINK20"] = "1"  # mavutil picks the MAVLink 2 dialect by this
        try:
            self._conn: Any = mavutil.mavlink_connection(
                self.device, dialect="ardupilotmega", source_system=GCS_SYSTEM_ID,
                source_component=GCS_COMPONENT_ID, autoreconnect=True, retries=0)
        except OSError as exc:
            raise ConfigError(URL_KEY, f"{url!r}: cannot open it: {exc}") from exc
        self._conn.mav.robust_parsing = True

    @property
    def autopilot_name(self) -> str:
        """ArduPilot, PX4, or the MAV_AUTOPILOT number; '?' before its heartbeat."""
        if self.autopilot_type is None:
            return "?"
        return _AUTOPILOT_NAMES.get(self.autopilot_type, f"autopilot {self.autopilot_type}")

    def start(self) -> ExternalAutopilot:
        """Read the link in a thread; returns self."""
        self._workers.start(("sitl-external-link", self._loop))
        return self

    def stop(self) -> None:
        """Stop the thread and close the connection. Idempotent."""
        self._workers.stop()
        self._conn.close()

    # -- the link thread ----------------------------------------------------------------------

    def _loop(self) -> None:
        while not self._stopping.is_set():
            try:
                msg = self._conn.recv_match(blocking=True, timeout=_RECEIVE_TIMEOUT_S)
            except OSError:  # a TCP peer went away: pymavlink reconnects
                msg = None
                self._stopping.wait(_RECEIVE_TIMEOUT_S)
            now_s = self._receive_clock()
            if msg is not None:
                self._handle(msg, now_s)
            self._tick(now_s)

    def _send(self, send: Callable[..., object], *args: object) -> None:
        with contextlib.suppress(OSError):  # nobody to send to yet, or the peer is gone
            send(*args)

    def _tick(self, now_s: float) -> None:
        mav = self._conn.mav
        if now_s >= self._next_heartbeat_s:
            self._send(mav.heartbeat_send, mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID,
                       0, 0, mavlink.MAV_STATE_ACTIVE)
            self.gcs_heartbeats += 1
            self._next_heartbeat_s = now_s + _HEARTBEAT_PERIOD_S
        if self.target is None:
            return
        rates = _STREAMS_HZ.get(self.autopilot_type or -1, _ANY_STREAMS_HZ)
        system, component = self.target
        for msg_id, rate_hz in rates.items():
            silent = now_s - max(self._last_rx.get(msg_id, -math.inf),
                                 self._last_request.get(msg_id, -math.inf)) > STREAM_TIMEOUT_S
            if silent and (msg_id in self._last_rx
                           or self.requests[msg_id] < NEVER_SEEN_REQUESTS):
                self._send(mav.command_long_send, system, component,
                           mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, 1e6 / rate_hz,
                           0, 0, 0, 0, 0)
                self.requests[msg_id] += 1
                self._last_request[msg_id] = now_s

    def _handle(self, msg: Any, rx_s: float) -> None:
        kind = msg.get_type()
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        if kind == "HEARTBEAT":
            if (self.target is None and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID
                    and msg.type != mavlink.MAV_TYPE_GCS):
                self.target, self.autopilot_type = source, int(msg.autopilot)
            return
        if source != self.target:
            return
        self.received[kind] += 1
        self._last_rx[msg.get_msgId()] = rx_s
        try:
            self._sample(kind, msg, rx_s)
        except InputError:  # a NaN, a latitude of 200, a quaternion that is no rotation
            self.rejected += 1

    def _sample(self, kind: str, msg: Any, rx_s: float) -> None:
        if kind == "SYSTEM_TIME":
            self.clock.observe(msg.time_boot_ms / 1e3, rx_s)
        elif kind == "ATTITUDE":
            self.clock.observe(msg.time_boot_ms / 1e3, rx_s)
            self._add(ESTIMATE, msg.time_boot_ms / 1e3, None,
                      quaternion_from_euler(msg.roll, msg.pitch, msg.yaw))
        elif kind == "GLOBAL_POSITION_INT":
            self.clock.observe(msg.time_boot_ms / 1e3, rx_s)
            if (msg.lat, msg.lon) != (0, 0):  # ArduPilot before its GPS fix
                self._add(ESTIMATE, msg.time_boot_ms / 1e3,
                          (msg.lat / 1e7, msg.lon / 1e7, msg.alt / 1e3), None)
        elif kind == "SIM_STATE":
            self._true_alt = (rx_s, float(msg.alt))
        elif kind == "SIMSTATE" and self.clock.known:
            alt_m = self._simstate_alt_m(rx_s)
            if alt_m is not None:
                t_s = self.clock.boot_at(rx_s)
                self._add(SIMSTATE, t_s, (msg.lat / 1e7, msg.lng / 1e7, alt_m),
                          quaternion_from_euler(msg.roll, msg.pitch, msg.yaw))
        elif kind == "HIL_STATE_QUATERNION" and self.clock.known:
            # Its time_usec is not the boot clock: on PX4 v1.15 SIH it stands still while the
            # boot time runs (measured: -2 s of offset every 2 s). Stamped on arrival instead.
            t_s = self.clock.boot_at(rx_s)
            q = msg.attitude_quaternion
            self._add(HIL_STATE, t_s, (msg.lat / 1e7, msg.lon / 1e7, msg.alt / 1e3),
                      (float(q[0]), float(q[1]), float(q[2]), float(q[3])))

    def _simstate_alt_m(self, rx_s: float) -> float | None:
        """The true altitude (SIM_STATE) to go with a SIMSTATE, else the estimated one."""
        if self._true_alt is not None and abs(rx_s - self._true_alt[0]) <= TRUE_ALT_MAX_AGE_S:
            return self._true_alt[1]
        with self._cond:
            estimate = self._buffers[ESTIMATE].at(self.clock.boot_at(rx_s))
        return None if estimate is None else estimate.alt_amsl_m

    def _add(self, source: str, t_s: float, position: tuple[float, float, float] | None,
             q_wxyz: tuple[float, float, float, float] | None) -> None:
        with self._cond:
            buffer, newest = self._buffers[source], self._newest[source]
            if position is not None:
                lat, lon, alt_m = position
                buffer.add_position(t_s, lat, lon, alt_m, alt_m - self.ground_amsl_m)
                newest[0] = t_s if t_s < newest[0] - REBOOT_JUMP_S else max(newest[0], t_s)
            if q_wxyz is not None:
                buffer.add_attitude(t_s, q_wxyz)
                newest[1] = t_s if t_s < newest[1] - REBOOT_JUMP_S else max(newest[1], t_s)
            self._cond.notify_all()

    # -- what it knows ------------------------------------------------------------------------

    def _live(self, t_s: float) -> list[str]:
        return [s for s in SOURCES if min(self._newest[s]) >= t_s - SOURCE_LIVE_S]

    def wait_pose(self, t_s: float, timeout_wall_s: float = POSE_WAIT_WALL_S
                  ) -> tuple[str, BodyPose] | None:
        """(source, pose) at boot time t_s from the best live source, None if none has it.

        Waits up to timeout_wall_s for that source's samples to reach t_s, so the pose is
        interpolated rather than extrapolated.
        """
        deadline_s = self._receive_clock() + timeout_wall_s
        with self._cond:
            while (live := self._live(t_s)) and min(self._newest[live[0]]) < t_s:
                remaining_s = deadline_s - self._receive_clock()
                if remaining_s <= 0.0:
                    break
                self._cond.wait(remaining_s)
            found = [(s, sample) for s in self._live(t_s)
                     if (sample := self._buffers[s].at(t_s)) is not None]
        if not found:
            return None
        source, sample = found[0]
        north, east, _ = self.geo.geodetic_to_ned(sample.lat_deg, sample.lon_deg,
                                                  self.ground_amsl_m)
        down_m = self.ground_amsl_m - sample.alt_amsl_m
        return source, BodyPose(t_s, float(north), float(east), down_m, sample.q_wxyz)


# -- the camera over it -----------------------------------------------------------------------

class ExternalSitl:
    """The scenario's camera over an external autopilot SITL; a context manager.

    The world (tags, decoys) is the mock SITL's for the same scenario and seed. Scenario time
    (moving targets, the fault plan) is the autopilot's boot time since the first frame, summed
    over its reboots.
    """

    def __init__(self, scenario: Scenario, url: str, *, faults: FaultPlan | None = None,
                 host: str = "127.0.0.1", camera_port: int = 0) -> None:
        self.scenario = scenario
        parse_autopilot_url(url)  # a bad URL is refused before any socket is bound
        self.faults = camera_faults_only(faults or FaultPlan())
        seeds = np.random.SeedSequence(scenario.seed).spawn(3)  # as sitl.runner.Sitl
        self.world = TargetWorld(scenario, np.random.default_rng(seeds[0]))
        self.renderer = Renderer(scenario.camera, texture_seed=scenario.seed)
        self.stream = MjpegServer(host, camera_port)
        try:
            self.autopilot = ExternalAutopilot(url, scenario.geo.local_ned(),
                                               scenario.geo.origin[2])
        except BaseException:
            self.stream.stop()
            raise
        self.frames = FrameCounts()
        self.last_source: str | None = None
        self.last_pose: BodyPose | None = None
        self._camera_rng = np.random.default_rng(seeds[2])
        self._elapsed_s = 0.0
        self._last_due_s: float | None = None
        self._last_pose_wall_s = -math.inf
        self._workers = Workers()
        self._stopping = self._workers.stopping

    @property
    def camera_url(self) -> str:
        """The MJPEG stream (cv2.VideoCapture or MjpegReader opens it)."""
        return self.stream.url

    def start(self) -> ExternalSitl:
        """Serve the camera, read the autopilot, render once its clock is known."""
        self.stream.start()
        self.autopilot.start()
        self._workers.start(("sitl-camera", self._camera))
        return self

    def stop(self) -> None:
        """Stop every thread and close every socket. Idempotent."""
        self._workers.stop()
        self.autopilot.stop()
        self.stream.stop()

    def __enter__(self) -> ExternalSitl:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    def _camera(self) -> None:
        while not self.autopilot.clock.known:
            if self._stopping.wait(_CLOCK_WAIT_WALL_S):
                return
        CameraLoop(self.stream, self.scenario.camera, self.autopilot.clock, self._shot,
                   self.faults.camera_fault, self.faults.frame_drop, self._camera_rng,
                   self.frames).run(self._stopping)

    def _shot(self, due_s: float) -> Shot | None:
        """The frame due at boot time due_s, from the pose interpolated there; None: no pose."""
        if self._last_due_s is not None and due_s > self._last_due_s:
            self._elapsed_s += due_s - self._last_due_s
        self._last_due_s = due_s
        found = self.autopilot.wait_pose(due_s)
        if found is None:
            return None
        self.last_source, pose = found
        self.last_pose = pose
        self._last_pose_wall_s = time.monotonic()
        t_s = self._elapsed_s
        return Shot(due_s, t_s, lambda: render_scene(self.scenario, self.world, self.renderer,
                                                     pose, t_s, self._camera_rng))

    def status(self, t_s: float) -> str:
        """One status line: pose source and position, boot time, frames."""
        ap, f = self.autopilot, self.frames
        frames = (f"frames {f.published} (late {f.late}, no pose {f.offline}, "
                  f"dropped {f.dropped})")
        if ap.target is None:
            return f"t {t_s:7.1f} s  waiting for the autopilot on {ap.url}  {frames}"
        pose, boot = self.last_pose, ap.clock.latest_boot_s
        if pose is None or self.last_source is None:
            where = "no pose yet"
        elif time.monotonic() - self._last_pose_wall_s > STATUS_POSE_MAX_AGE_S:
            where = "no pose now (the streams stopped?)"
        else:
            where = (f"pose {self.last_source}  N {pose.north_m:7.1f} E {pose.east_m:7.1f} "
                     f"h {-pose.down_m:5.1f} m")
        boot_text = "boot time unknown" if boot is None else f"boot {boot:9.2f} s"
        return f"t {t_s:7.1f} s  {ap.autopilot_name}  {where}  {boot_text}  {frames}"

    def far_from_origin_m(self) -> float | None:
        """How far the last pose is from the scenario's [geo] origin (None: no pose yet)."""
        pose = self.last_pose
        return None if pose is None else math.hypot(pose.north_m, pose.east_m)


def run_external(scenario: Scenario, url: str, stop: threading.Event, *,
                 faults: FaultPlan | None = None, host: str = "127.0.0.1", camera_port: int = 0,
                 duration_s: float | None = None, status_every_s: float = 10.0,
                 out: TextIO | None = None, err: TextIO | None = None) -> int:
    """Serve the camera over the autopilot at `url` until `stop` is set or duration_s (wall)
    is over; prints where to connect on `out`, status lines on `err`; returns 0."""
    out, err = out or sys.stdout, err or sys.stderr
    with ExternalSitl(scenario, url, faults=faults, host=host, camera_port=camera_port) as ext:
        print(f"scenario {scenario.name}, external autopilot (real time on its clock)", file=out)
        print(f"autopilot {url}", file=out)
        print(f"camera {ext.camera_url}", file=out, flush=True)
        start_s = time.monotonic()
        next_status_s = 0.0
        warned = False
        while not stop.is_set():
            t_s = time.monotonic() - start_s
            if duration_s is not None and t_s >= duration_s:
                break
            far_m = ext.far_from_origin_m()
            if not warned and far_m is not None:
                warned = True
                if far_m > FAR_FROM_ORIGIN_M:
                    lat, lon, alt = scenario.geo.origin
                    print(f"companion-sitl: warning: the vehicle is {far_m:.0f} m from the "
                          f"scenario's [geo] origin: start the autopilot with its home there "
                          f"({lat}, {lon}, {alt} m)", file=err, flush=True)
            if status_every_s > 0.0 and t_s >= next_status_s:
                print(ext.status(t_s), file=err, flush=True)
                next_status_s = t_s + status_every_s
            stop.wait(0.05)
    return 0
