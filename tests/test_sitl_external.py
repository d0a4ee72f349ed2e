"""companion-sitl --external-autopilot: the SITL camera over an autopilot SITL read on MAVLink.

No firmware runs here: `FakeAutopilot` is a small test-only autopilot SITL on loopback UDP. It
heartbeats, streams only what SET_MESSAGE_INTERVAL asks for (of the messages it offers), and
reports a scripted true pose: SIMSTATE/SIM_STATE as ArduPilot's SITL, HIL_STATE_QUATERNION as
PX4's SIH, and GLOBAL_POSITION_INT + ATTITUDE as an estimate that is off by ESTIMATE_ERROR_M.
"""

from __future__ import annotations

import contextlib
import math
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import pytest
from numpy.typing import NDArray
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.rotation import quaternion_from_euler
from companion.sim.scenario import Scenario, load_scenario
from companion.vision.camera import BodyPose, project_points
from companion.vision.tags import TagDetector, detect_centres
from sitl.cli import main, sitl_scenarios
from sitl.external import ESTIMATE, HIL_STATE, SIMSTATE, ExternalSitl, parse_autopilot_url
from sitl.link import free_udp_port
from sitl.stream import MjpegReader

pytestmark = pytest.mark.sitl

FloatArray = NDArray[np.float64]

BOOT_AGE_S = 1234.5  # the fake autopilot booted this long before the test: a clock of its own
ESTIMATE_ERROR_M = 3.0  # its GLOBAL_POSITION_INT is this far north of the truth
SEND_PERIOD_S = 0.005
PERIOD_S = 8.0  # of the scripted circle
TAG_NE_M = (12.0, 14.0)  # field-5-tags' tag 2
CENTRE_TOL_PX = 2.0
LAG_TOL_S = 2.0  # a frame read this long after its capture on a loaded machine still passes
STAMP_TOL_S = 0.002  # capture times are whole multiples of the frame period, to the microsecond
ARDUPILOT_OFFERS = frozenset({mavlink.MAVLINK_MSG_ID_SIMSTATE, mavlink.MAVLINK_MSG_ID_SIM_STATE,
                              mavlink.MAVLINK_MSG_ID_ATTITUDE,
                              mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
                              mavlink.MAVLINK_MSG_ID_SYSTEM_TIME})
PLAIN_OFFERS = frozenset({mavlink.MAVLINK_MSG_ID_ATTITUDE,
                          mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT})
PX4_OFFERS = frozenset({mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION, *PLAIN_OFFERS})


@dataclass(frozen=True)
class TruePose:
    """The fake vehicle's true pose: NED about the scenario's origin, Euler angles in rad."""

    north_m: float
    east_m: float
    height_m: float
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float = 0.0

    def body(self, t_s: float) -> BodyPose:
        """As the camera's BodyPose at boot time t_s."""
        return BodyPose.from_euler(t_s, self.north_m, self.east_m, -self.height_m,
                                   self.roll_rad, self.pitch_rad, self.yaw_rad)


def circling(boot_s: float) -> TruePose:
    """Circles above tag 2 at 8 m, yawing and rolling a little (up to 2.4 m/s)."""
    a = 2.0 * math.pi * boot_s / PERIOD_S
    return TruePose(TAG_NE_M[0] + 2.0 * math.sin(a), TAG_NE_M[1] + 1.5 * math.cos(a), 8.0,
                    0.04 * math.cos(a), 0.03 * math.sin(a), 0.25 * math.sin(a))


class FakeAutopilot:
    """A test-only autopilot SITL on loopback: streams what it is asked for, of `offers`."""

    def __init__(self, scenario: Scenario, port: int, *, offers: frozenset[int],
                 autopilot: int = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                 pose: Callable[[float], TruePose] = circling) -> None:
        self.geo = scenario.geo.local_ned()
        self.ground_m = scenario.geo.origin[2]
        self.offers, self.autopilot, self.pose = offers, autopilot, pose
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.dest = ("127.0.0.1", port)
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.rx = mavlink.MAVLink(None)
        self.rx.robust_parsing = True
        self.t0 = time.monotonic() - BOOT_AGE_S
        self.intervals: dict[int, float] = {}
        self.next_due: dict[int, float] = {}
        self.requested: Counter[int] = Counter()
        self.gcs_heartbeats = 0
        self.lock = threading.Lock()
        self.stopping = threading.Event()
        self.thread = threading.Thread(target=self._loop, daemon=True)

    def boot_s(self) -> float:
        """Its boot clock now."""
        return time.monotonic() - self.t0

    def reboot(self) -> None:
        """Boot again: the boot clock restarts at 0 and every stream stops until asked for."""
        with self.lock:
            self.intervals.clear()
            self.next_due.clear()
            self.t0 = time.monotonic()

    def __enter__(self) -> FakeAutopilot:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stopping.set()
        self.thread.join(timeout=5.0)
        self.sock.close()

    def _loop(self) -> None:
        next_heartbeat_s = 0.0
        while not self.stopping.wait(SEND_PERIOD_S):
            self._receive()
            now_s = self.boot_s()
            if now_s >= next_heartbeat_s:
                self._send(self.mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, self.autopilot,
                                                     0, 0, mavlink.MAV_STATE_STANDBY))
                next_heartbeat_s = now_s + 1.0
            with self.lock:
                due = [i for i, period in self.intervals.items()
                       if now_s >= self.next_due.get(i, 0.0)]
                for msg_id in due:
                    self.next_due[msg_id] = now_s + self.intervals[msg_id]
            t_ms = int(now_s * 1e3)
            for msg_id in due:
                self._send(self._message(msg_id, t_ms))

    def _receive(self) -> None:
        while True:
            try:
                data, _ = self.sock.recvfrom(65535)
            except (BlockingIOError, ConnectionError):
                return
            for msg in self.rx.parse_buffer(data) or []:
                if msg.get_type() == "HEARTBEAT" and msg.type == mavlink.MAV_TYPE_GCS:
                    self.gcs_heartbeats += 1
                elif (msg.get_type() == "COMMAND_LONG"
                      and msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL):
                    msg_id = int(msg.param1)
                    self.requested[msg_id] += 1
                    offered = msg_id in self.offers
                    if offered:
                        with self.lock:
                            self.intervals[msg_id] = msg.param2 / 1e6
                    self._send(self.mav.command_ack_encode(
                        msg.command, mavlink.MAV_RESULT_ACCEPTED if offered
                        else mavlink.MAV_RESULT_DENIED))

    def _send(self, msg: mavlink.MAVLink_message) -> None:
        with contextlib.suppress(OSError):  # nobody listening yet
            self.sock.sendto(msg.pack(self.mav), self.dest)

    def _message(self, msg_id: int, t_ms: int) -> mavlink.MAVLink_message:
        p = self.pose(t_ms / 1e3)
        lat, lon, _ = (float(c) for c in self.geo.ned_to_geodetic(p.north_m, p.east_m, 0.0))
        alt_m = self.ground_m + p.height_m
        lat_e7, lon_e7 = round(lat * 1e7), round(lon * 1e7)
        q = quaternion_from_euler(p.roll_rad, p.pitch_rad, p.yaw_rad)
        m = self.mav
        if msg_id == mavlink.MAVLINK_MSG_ID_SIMSTATE:
            return m.simstate_encode(p.roll_rad, p.pitch_rad, p.yaw_rad, 0, 0, -9.8, 0, 0, 0,
                                     lat_e7, lon_e7)
        if msg_id == mavlink.MAVLINK_MSG_ID_SIM_STATE:  # lat/lon as ArduPilot: float degE7
            return m.sim_state_encode(*q, p.roll_rad, p.pitch_rad, p.yaw_rad, 0, 0, -9.8, 0, 0, 0,
                                      float(lat_e7), float(lon_e7), alt_m, 0, 0, 0, 0, 0)
        if msg_id == mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION:
            return m.hil_state_quaternion_encode(t_ms * 1000, q, 0, 0, 0, lat_e7, lon_e7,
                                                 round(alt_m * 1e3), 0, 0, 0, 0, 0, 0, 0, 0)
        if msg_id == mavlink.MAVLINK_MSG_ID_ATTITUDE:
            return m.attitude_encode(t_ms, p.roll_rad, p.pitch_rad, p.yaw_rad, 0, 0, 0)
        if msg_id == mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            lat_est, lon_est, _ = self.geo.ned_to_geodetic(p.north_m + ESTIMATE_ERROR_M,
                                                           p.east_m, 0.0)
            return m.global_position_int_encode(
                t_ms, round(float(lat_est) * 1e7), round(float(lon_est) * 1e7),
                round(alt_m * 1e3), round(p.height_m * 1e3), 0, 0, 0, 0)
        assert msg_id == mavlink.MAVLINK_MSG_ID_SYSTEM_TIME
        return m.system_time_encode(int(time.time() * 1e6), t_ms)


@pytest.fixture(scope="module")
def scenario() -> Scenario:
    return load_scenario(sitl_scenarios()["field-5-tags"])


@pytest.fixture(scope="module")
def detector() -> TagDetector:
    return TagDetector(families="tag36h11", quad_decimate=1.0, nthreads=1)


def _until(condition: Callable[[], bool], timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.01)


def _expected_centres(scenario: Scenario, ext: ExternalSitl, pose: BodyPose,
                      margin_px: float = 6.0) -> dict[int, FloatArray]:
    """The world's tags wholly in view from `pose`: id -> projected centre."""
    camera, out = scenario.camera, {}
    for tag in ext.world.tags(0.0):
        corners, front = project_points(camera, pose, tag.corners_ned(10))
        inside = ((corners >= margin_px).all()
                  and (corners[:, 0] <= camera.width_px - 1 - margin_px).all()
                  and (corners[:, 1] <= camera.height_px - 1 - margin_px).all())
        if front.all() and inside:
            centre, _ = project_points(camera, pose, np.array([[tag.north_m, tag.east_m, 0.0]]))
            out[tag.tag_id] = centre[0]
    return out


def _check_frames(scenario: Scenario, ext: ExternalSitl, fake: FakeAutopilot,
                  detector: TagDetector, count: int,
                  drawn_from: Callable[[float], TruePose] = circling) -> list[FloatArray]:
    """Reads `count` frames and checks their stamps, and their tags against the pose
    `drawn_from` gives at the capture time; returns the centres of tag 2 seen."""
    period_s = 1.0 / scenario.camera.rate_hz
    seen: list[FloatArray] = []
    stamps: list[float] = []
    with MjpegReader(ext.camera_url) as reader:
        frames: Iterator[tuple[NDArray[np.uint8], float]] = iter(reader)
        for _ in range(count):
            image, capture_s = next(frames)
            boot_now_s = fake.boot_s()
            # On the autopilot's boot clock (BOOT_AGE_S from this process's), before it was
            # received; the slack is for a loaded machine (the pose check below is the tight one).
            assert boot_now_s - LAG_TOL_S < capture_s <= boot_now_s
            stamps.append(capture_s)
            expected = _expected_centres(scenario, ext, drawn_from(capture_s).body(capture_s))
            ids, centres = detect_centres(detector, image)
            found = {int(i): c for i, c in zip(ids, centres, strict=True) if int(i) in expected}
            for tag_id, centre in found.items():
                assert np.linalg.norm(centre - expected[tag_id]) < CENTRE_TOL_PX, tag_id
            if 2 in found:
                seen.append(found[2])
    steps = np.diff(stamps) / period_s
    assert (steps >= 1.0 - 1e-3).all()
    assert np.abs(steps - np.round(steps)).max() * period_s < STAMP_TOL_S
    return seen


def test_simstate_is_the_pose_frames_carry_boot_times_and_show_the_tags_there(
        scenario: Scenario, detector: TagDetector) -> None:
    port = free_udp_port()
    with (ExternalSitl(scenario, f"udpin:127.0.0.1:{port}") as ext,
          FakeAutopilot(scenario, port, offers=ARDUPILOT_OFFERS) as fake):
        _until(lambda: ext.frames.published >= 2)
        assert ext.last_source == SIMSTATE
        seen = _check_frames(scenario, ext, fake, detector, 20)
        assert len(seen) >= 15
        # The circle moves tag 2 across the image by tens of pixels.
        assert np.linalg.norm(np.ptp(np.array(seen), axis=0)) > 40.0
        assert fake.gcs_heartbeats >= 1
        for msg_id in (mavlink.MAVLINK_MSG_ID_SIMSTATE, mavlink.MAVLINK_MSG_ID_SIM_STATE,
                       mavlink.MAVLINK_MSG_ID_ATTITUDE,
                       mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT):
            assert fake.requested[msg_id] >= 1
        assert ext.autopilot.requests[mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION] == 0
        status = ext.status(1.0)
        assert "ArduPilot" in status and "pose SIMSTATE" in status
        latest_boot_s = ext.autopilot.clock.latest_boot_s
        assert latest_boot_s is not None and abs(latest_boot_s - fake.boot_s()) < 0.5


def test_hil_state_quaternion_is_px4_sihs_pose(scenario: Scenario,
                                               detector: TagDetector) -> None:
    port = free_udp_port()
    with (ExternalSitl(scenario, f"udpin:localhost:{port}") as ext,
          FakeAutopilot(scenario, port, offers=PX4_OFFERS,
                        autopilot=mavlink.MAV_AUTOPILOT_PX4) as fake):
        _until(lambda: ext.frames.published >= 2)
        assert ext.last_source == HIL_STATE
        assert len(_check_frames(scenario, ext, fake, detector, 8)) >= 5
        assert ext.autopilot.requests[mavlink.MAVLINK_MSG_ID_SIMSTATE] == 0


def test_without_simstate_it_falls_back_to_global_position_int_and_attitude(
        scenario: Scenario, detector: TagDetector) -> None:
    port = free_udp_port()
    with (ExternalSitl(scenario, f"udpin://127.0.0.1:{port}") as ext,
          FakeAutopilot(scenario, port, offers=PLAIN_OFFERS) as fake):
        _until(lambda: ext.frames.published >= 2)
        assert ext.last_source == ESTIMATE

        def estimate(boot_s: float) -> TruePose:  # ESTIMATE_ERROR_M north of the truth
            p = circling(boot_s)
            return TruePose(p.north_m + ESTIMATE_ERROR_M, p.east_m, p.height_m, p.roll_rad,
                            p.pitch_rad, p.yaw_rad)

        assert len(_check_frames(scenario, ext, fake, detector, 8, drawn_from=estimate)) >= 5
        assert "pose GLOBAL_POSITION_INT+ATTITUDE" in ext.status(1.0)
        assert fake.requested[mavlink.MAVLINK_MSG_ID_SIMSTATE] >= 1  # asked, never offered


def test_after_a_reboot_the_streams_are_requested_again_on_the_new_boot_clock(
        scenario: Scenario) -> None:
    port = free_udp_port()
    with (ExternalSitl(scenario, f"udpin:127.0.0.1:{port}") as ext,
          FakeAutopilot(scenario, port, offers=ARDUPILOT_OFFERS) as fake):
        _until(lambda: ext.frames.published >= 2)
        before = fake.requested[mavlink.MAVLINK_MSG_ID_SIMSTATE]
        fake.reboot()
        _until(lambda: ext.frames.offline >= 1)  # the streams stopped: no pose, no frame
        _until(lambda: fake.requested[mavlink.MAVLINK_MSG_ID_SIMSTATE] > before)
        with MjpegReader(ext.camera_url) as reader:
            frames = iter(reader)
            while (capture_s := next(frames)[1]) > BOOT_AGE_S:  # queued before the reboot
                pass
            assert 0.0 < capture_s <= fake.boot_s()
        assert ext.autopilot.clock.reboots == 1
        _until(lambda: ext.last_source == SIMSTATE)  # the estimate may come back first


@pytest.mark.parametrize(("args", "message"), [
    (["--external-autopilot", "udpin:10.1.2.3:14560"],
     "companion-sitl: --external-autopilot: 'udpin:10.1.2.3:14560': loopback only "
     "(127.0.0.1 or localhost), got host '10.1.2.3'"),
    (["--external-autopilot", "udpin:0.0.0.0:14560"], "loopback only"),
    (["--external-autopilot", "serial:/dev/ttyUSB0:57600"], "write udpin:127.0.0.1:PORT"),
    (["--external-autopilot", "udpin:127.0.0.1"], "write udpin:127.0.0.1:PORT"),
    (["--external-autopilot", "udpin:127.0.0.1:70000"], "the port must be in [1, 65535]"),
    (["--external-autopilot", "udpin:127.0.0.1:14560", "--speedup", "2"],
     "companion-sitl: --speedup: not with --external-autopilot"),
    (["--external-autopilot", "udpin:127.0.0.1:14560", "--gcs-port", "14550"],
     "--gcs-port: not with --external-autopilot"),
    (["--external-autopilot", "udpin:127.0.0.1:14560", "--faults", "freeze@5+1,cut@5+1,loss=3"],
     "companion-sitl: --faults: loss, cut: not with --external-autopilot"),
])
def test_bad_arguments_exit_2_with_one_line(args: list[str], message: str,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["field-5-tags", *args]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert len(err.splitlines()) == 1 and message in err


def test_parse_autopilot_url_forms() -> None:
    assert parse_autopilot_url("udpin:localhost:14560") == "udpin:127.0.0.1:14560"
    assert parse_autopilot_url("udp://127.0.0.1:14550") == "udpin:127.0.0.1:14550"
    assert parse_autopilot_url("tcp:127.0.0.1:5760") == "tcp:127.0.0.1:5760"


def test_command_prints_where_to_connect_serves_and_stops_on_sigterm(
        scenario: Scenario) -> None:
    port = free_udp_port()
    url = f"udpin:127.0.0.1:{port}"
    cmd = [sys.executable, "-m", "sitl", "field-5-tags", "--external-autopilot", url,
           "--status-every", "0.5", "--faults", "drop=10"]
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        assert proc.stdout is not None
        lines = [proc.stdout.readline().strip() for _ in range(3)]
        assert lines[0] == "scenario field-5-tags, external autopilot (real time on its clock)"
        assert lines[1] == f"autopilot {url}"
        assert lines[2].startswith("camera http://127.0.0.1:")
        with FakeAutopilot(scenario, port, offers=ARDUPILOT_OFFERS) as fake, \
                MjpegReader(lines[2].split()[1]) as reader:
            image, capture_s = next(iter(reader))
            assert image.shape == (480, 640)
            assert fake.boot_s() - LAG_TOL_S < capture_s <= fake.boot_s()
            assert proc.stderr is not None
            deadline = time.monotonic() + 5.0
            while "pose SIMSTATE" not in (line := proc.stderr.readline()):  # a status line
                assert line and time.monotonic() < deadline, line
            assert line.startswith("t ") and "ArduPilot" in line
            proc.send_signal(signal.SIGTERM)
            _, err = proc.communicate(timeout=10)
    assert proc.returncode == 0
    assert "Traceback" not in err
