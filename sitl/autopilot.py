"""A mock PX4 or ArduPilot Copter autopilot that speaks MAVLink 2 over UDP on loopback.

It is what the real MAVSDK library connects to in the tests: heartbeats with the flavour's mode
encoding, AUTOPILOT_VERSION with the capability bits MAVSDK checks, command acks, the parameter
protocol for the parameters MAVSDK reads, telemetry at realistic rates with boot-time stamps,
and PX4's offboard rules: OFFBOARD is refused unless setpoints already stream, and a setpoint
stream that stops for COM_OF_LOSS_T leaves OFFBOARD to the configured failsafe. The ArduPilot
flavour uses Copter's mode numbers, GUIDED for offboard, streams nothing until asked, reports
local NED about its EKF origin, and refuses to arm in modes that forbid it.

With `AutopilotConfig.signing_key` set it enforces MAVLink 2 signing as a real autopilot with a
key does: it signs everything it sends (link id 0, wall-clock timestamps) and drops, before
handling, every received frame that is unsigned or whose signature is wrong, replayed or too old
(pymavlink's check, in the C library's order: see companion.vehicle.signing.check_signature),
except the flavour's unsigned allow-list: PX4 accepts HEARTBEAT, RADIO_STATUS, ADSB_VEHICLE and
COLLISION, ArduPilot RADIO_STATUS and RADIO (and anything on its USB port, not modelled: this
link is UDP). Drops are counted in `Snapshot.rejected_unsigned` / `rejected_bad_signature`.

One thread runs the loop (receive, simulate, send); the operator's actions and the faults are
methods that tests call from other threads.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import dataclass, field
from enum import Enum

import numpy as np
from numpy.typing import NDArray
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.geo import LocalNed
from companion.vehicle.signing import Signature, check_signature, new_signer
from sitl.clock import SimClock
from sitl.link import UdpLink
from sitl.modes import COPTER_ARMABLE, PX4_ARMABLE, Behaviour, Flavour, decode, encode
from sitl.vehicle import Target, VehicleLimits, VehicleState, step

FloatArray = NDArray[np.float64]

FORCE_MAGIC = 21196.0  # param2 of ARM_DISARM that forces it (PX4 and ArduPilot)
PREFLIGHT_DISARM_S = 10.0  # PX4 COM_DISARM_PRFLT: armed on the ground without taking off
LANDED_DISARM_S = 2.0  # PX4 COM_DISARM_LAND
LAND_SPEED_M_S = 0.7
REACHED_M = 0.3
STREAMING_WINDOW_S = 1.0  # offboard needs setpoints above 2 Hz: two within this window...
STREAMING_FRESH_S = 0.5  # ...and the last one this recent


class Failsafe(Enum):
    """What the autopilot does when the offboard setpoints stop (COM_OBL_RC_ACT)."""

    HOLD = "hold"
    LAND = "land"
    RTL = "rtl"


# Default telemetry rates (Hz) of PX4's onboard link; an ArduPilot sends none until asked.
PX4_RATES_HZ: dict[int, float] = {
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 2.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 20.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 20.0,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 10.0,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 10.0,
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: 5.0,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 5.0,
    mavlink.MAVLINK_MSG_ID_BATTERY_STATUS: 1.0,
    mavlink.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    mavlink.MAVLINK_MSG_ID_VFR_HUD: 4.0,
}
# ArduPilot's REQUEST_DATA_STREAM groups.
DATA_STREAMS: dict[int, tuple[int, ...]] = {
    mavlink.MAV_DATA_STREAM_EXTENDED_STATUS: (
        mavlink.MAVLINK_MSG_ID_SYS_STATUS, mavlink.MAVLINK_MSG_ID_GPS_RAW_INT,
        mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, mavlink.MAVLINK_MSG_ID_BATTERY_STATUS,
    ),
    mavlink.MAV_DATA_STREAM_POSITION: (
        mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
    ),
    mavlink.MAV_DATA_STREAM_EXTRA1: (
        mavlink.MAVLINK_MSG_ID_ATTITUDE, mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION,
    ),
    mavlink.MAV_DATA_STREAM_EXTRA2: (mavlink.MAVLINK_MSG_ID_VFR_HUD,),
}
SENSORS = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mavlink.MAV_SYS_STATUS_SENSOR_GPS | mavlink.MAV_SYS_STATUS_SENSOR_RC_RECEIVER
    | mavlink.MAV_SYS_STATUS_AHRS | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
)
CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
)
SENDABLE = frozenset({
    mavlink.MAVLINK_MSG_ID_HEARTBEAT, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
    mavlink.MAVLINK_MSG_ID_VFR_HUD, *PX4_RATES_HZ,
})  # what _send_message can send
# What a signing autopilot still accepts unsigned (PX4 docs/en/mavlink/message_signing.md of 2026;
# ArduPilot libraries/GCS_MAVLink/GCS_Signing.cpp accept_list).
UNSIGNED_ACCEPTED: dict[Flavour, frozenset[int]] = {
    Flavour.PX4: frozenset({
        mavlink.MAVLINK_MSG_ID_HEARTBEAT, mavlink.MAVLINK_MSG_ID_RADIO_STATUS,
        mavlink.MAVLINK_MSG_ID_ADSB_VEHICLE, mavlink.MAVLINK_MSG_ID_COLLISION,
    }),
    Flavour.ARDUPILOT: frozenset({mavlink.MAVLINK_MSG_ID_RADIO_STATUS,
                                  mavlink.MAVLINK_MSG_ID_RADIO}),
}
TYPEMASK_POSITION = 0b111  # bits set: ignore x, y, z
TYPEMASK_VELOCITY = 0b111000
TYPEMASK_YAW = 1 << 10


@dataclass
class AutopilotConfig:
    """How the mock autopilot behaves (the scenario's [vehicle] table fills it)."""

    flavour: Flavour = Flavour.PX4
    system_id: int = 1
    component_id: int = 1
    home_ned: tuple[float, float] = (0.0, 0.0)  # where it boots, in the world's NED frame
    home_yaw_deg: float = 0.0
    ekf_origin_offset_ned: tuple[float, float] = (4.0, -3.0)  # ArduPilot: EKF origin - home
    takeoff_alt_m: float = 2.5  # MIS_TAKEOFF_ALT
    rtl_alt_m: float = 30.0  # RTL_RETURN_ALT
    offboard_loss_timeout_s: float = 1.0  # COM_OF_LOSS_T
    offboard_failsafe: Failsafe = Failsafe.HOLD  # COM_OBL_RC_ACT
    armable_after_s: float = 2.0  # estimator settling after boot (a real ArduPilot: ~27 s)
    position_noise_m: float = 0.0  # white noise on the reported position, per axis
    gps_drift_m_per_sqrt_s: float = 0.0  # random walk of the reported position
    battery_flight_s: float = 1800.0  # flight time on a full battery
    battery_low_percent: float = 20.0  # below: the battery failsafe returns home
    limits: VehicleLimits = field(default_factory=VehicleLimits)
    physics_dt_s: float = 0.02
    seed: int = 0
    signing_key: bytes | None = None  # 32 bytes: sign everything, reject unsigned frames


@dataclass(frozen=True, slots=True)
class Snapshot:
    """The autopilot's state at one instant, for tests and the camera."""

    t_s: float  # simulation time since this boot
    boot: int  # increments on every reboot
    behaviour: Behaviour
    armed: bool
    vehicle: VehicleState  # true state, world NED
    battery_percent: float
    clock_s: float  # the SITL clock's time of this state (boot time + t_s)
    online: bool  # False while rebooting: silent, no time base
    last_setpoint_clock_s: float  # SITL clock time of the last setpoint received (-inf: none)
    setpoints_streaming: bool  # fast enough for OFFBOARD to be accepted now
    rejected_unsigned: int = 0  # signing on: unsigned frames dropped (all boots)
    rejected_bad_signature: int = 0  # signing on: wrong key, replayed or too old (all boots)
    behaviour_reported_clock_s: float | None = None  # first heartbeat with this behaviour


@dataclass
class _Setpoint:
    target: Target
    t_s: float


class MockAutopilot:
    """The simulated autopilot, its vehicle and its link; `start()` runs it in a thread."""

    def __init__(
        self, config: AutopilotConfig, link: UdpLink, clock: SimClock, geo: LocalNed
    ) -> None:
        self.config = config
        self.link = link
        self.clock = clock
        self.geo = geo
        self._rng = np.random.default_rng(config.seed)
        self._lock = threading.RLock()
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self._boot = 0
        self._reboot_until_s = -1.0
        self._glitch: tuple[FloatArray, float] = (np.zeros(3), -1.0)
        self.statustexts: list[str] = []
        self.texts_received: list[tuple[int, int, str]] = []  # (component, severity, text)
        self._last_setpoint_clock_s = -math.inf
        self._rejected_unsigned = 0
        self._rejected_bad_signature = 0
        self._reset(0.0)

    # -- lifecycle ----------------------------------------------------------------------------

    def _reset(self, now_s: float) -> None:
        cfg = self.config
        self._mav = mavlink.MAVLink(None, srcSystem=cfg.system_id, srcComponent=cfg.component_id)
        self._mav.robust_parsing = True
        self._rx = self._mav  # what parses received bytes
        if cfg.signing_key is not None:  # a reboot forgets the streams (RAM), as the C library
            self._mav = new_signer(cfg.signing_key, cfg.system_id, cfg.component_id)
            self._rx = mavlink.MAVLink(None)  # no key: the check is _signature_ok's
            self._rx.robust_parsing = True
        self._boot_wall_s = now_s
        self._t_s = 0.0
        self._vehicle = VehicleState.at_rest(
            cfg.home_ned[0], cfg.home_ned[1], math.radians(cfg.home_yaw_deg)
        )
        self._armed = False
        self._armed_at_s = 0.0
        self._landed_at_s = 0.0
        pilot = Behaviour.POSITION if cfg.flavour is Flavour.PX4 else Behaviour.MANUAL
        self._behaviour = pilot
        self._behaviour_reported_clock_s: float | None = None
        self._mode_target: Target | None = None
        self._rtl_phase = 0
        self._guided_takeoff_alt: float | None = None
        self._setpoint: _Setpoint | None = None
        self._setpoint_times: deque[float] = deque(maxlen=16)
        self._battery_used_s = 0.0
        self._battery_failsafe_done = False
        self._drift = np.zeros(3)
        self._params: dict[str, float] = {
            "MIS_TAKEOFF_ALT": cfg.takeoff_alt_m,
            "RTL_RETURN_ALT": cfg.rtl_alt_m,
            "COM_OF_LOSS_T": cfg.offboard_loss_timeout_s,
            "COM_OBL_RC_ACT": float(list(Failsafe).index(cfg.offboard_failsafe)),
        }
        if cfg.flavour is Flavour.PX4:
            self._intervals = {k: 1.0 / v for k, v in PX4_RATES_HZ.items()}
        else:
            self._intervals = {}
        self._next_due: dict[int, float] = {}
        self._next_heartbeat = 0.0
        home = np.array([cfg.home_ned[0], cfg.home_ned[1], 0.0])
        offset = np.array([*cfg.ekf_origin_offset_ned, 0.0])
        self._local_origin = home + offset if cfg.flavour is Flavour.ARDUPILOT else home
        self._home = home

    def start(self) -> None:
        """Run the loop in a thread."""
        self._stopping.clear()
        self._thread = threading.Thread(target=self._loop, name="sitl-autopilot", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the loop and close the link."""
        self._stopping.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self.link.close()

    def __enter__(self) -> MockAutopilot:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- what tests and the camera read --------------------------------------------------------

    def snapshot(self) -> Snapshot:
        """The state now."""
        with self._lock:
            return Snapshot(self._t_s, self._boot, self._behaviour, self._armed, self._vehicle,
                            self._battery_percent(), self._boot_wall_s + self._t_s,
                            self._reboot_until_s < 0.0, self._last_setpoint_clock_s,
                            self._setpoints_streaming(),
                            rejected_unsigned=self._rejected_unsigned,
                            rejected_bad_signature=self._rejected_bad_signature,
                            behaviour_reported_clock_s=self._behaviour_reported_clock_s)

    # -- the operator and the faults ----------------------------------------------------------

    def pilot_set_mode(self, behaviour: Behaviour) -> None:
        """The pilot flips the mode switch (an RC override): it always wins."""
        with self._lock:
            self._set_behaviour(behaviour, by_pilot=True)

    def pilot_arm(self, arm: bool = True) -> None:
        """The pilot arms or disarms with the sticks."""
        with self._lock:
            if arm:
                self._arm()
            else:
                self._armed = False

    def set_battery_percent(self, percent: float) -> None:
        """Drain (or charge) the battery to a level."""
        with self._lock:
            self._battery_used_s = self.config.battery_flight_s * (1.0 - percent / 100.0)

    def gps_glitch(self, offset_ned_m: tuple[float, float, float], duration_s: float) -> None:
        """The reported position jumps by offset for duration (the vehicle does not move)."""
        with self._lock:
            self._glitch = (np.array(offset_ned_m, dtype=np.float64), self._t_s + duration_s)

    def reboot(self, downtime_s: float = 2.0) -> None:
        """Go silent for downtime_s, then boot again: new boot time, disarmed, on the ground."""
        with self._lock:
            self._reboot_until_s = self.clock.now_s() + downtime_s

    # -- the loop -----------------------------------------------------------------------------

    def _loop(self) -> None:
        while not self._stopping.is_set():
            now = self.clock.now_s()
            with self._lock:
                if now < self._reboot_until_s:
                    self.link.receive(now)  # the wire is dead: everything is lost
                    rebooting = True
                else:
                    rebooting = False
                    if self._reboot_until_s > 0.0:
                        self._reboot_until_s = -1.0
                        boot = self._boot + 1
                        self._reset(now)
                        self._boot = boot
            if rebooting:
                self._stopping.wait(0.005)
                continue
            packets = self.link.receive(now, wait_wall_s=0.002)
            with self._lock:
                for data, _ in packets:
                    for msg in self._rx.parse_buffer(data) or []:
                        if self._signature_ok(msg):
                            self._handle(msg)
                self._simulate(now - self._boot_wall_s)
                self._send_due()

    def _simulate(self, t_s: float) -> None:
        dt = self.config.physics_dt_s
        while self._t_s + dt <= t_s:
            self._t_s += dt
            self._mode_logic()
            target = self._target()
            self._vehicle = step(self._vehicle, target, dt, self.config.limits, self._armed)
            if self._armed and not self._vehicle.on_ground:
                self._battery_used_s += dt
            sigma = self.config.gps_drift_m_per_sqrt_s
            if sigma > 0.0:
                self._drift += self._rng.normal(0.0, sigma * math.sqrt(dt), 3) * [1, 1, 0.5]

    # -- modes --------------------------------------------------------------------------------

    def _set_behaviour(self, behaviour: Behaviour, by_pilot: bool = False) -> None:
        if behaviour is self._behaviour:
            return
        previous = self._behaviour
        self._behaviour = behaviour
        self._behaviour_reported_clock_s = None
        self._mode_target = None
        self._rtl_phase = 0
        if behaviour is not Behaviour.OFFBOARD:
            self._guided_takeoff_alt = None
        hold_here = Target(position_ned=self._vehicle.position_ned.copy(),
                           yaw_rad=self._vehicle.yaw_rad)
        if behaviour in (Behaviour.HOLD, Behaviour.BRAKE, Behaviour.POSITION, Behaviour.ALTITUDE,
                         Behaviour.MANUAL, Behaviour.READY, Behaviour.MISSION):
            self._mode_target = hold_here
        if by_pilot:
            self._statustext(f"pilot: mode {previous.value} -> {behaviour.value}")

    def _mode_logic(self) -> None:
        v = self._vehicle
        t = self._t_s
        if self._armed and v.on_ground:
            if self._behaviour is Behaviour.LAND or (
                self._behaviour is Behaviour.RTL and self._rtl_phase >= 2
            ):
                if self._landed_at_s == 0.0:
                    self._landed_at_s = t
                elif t - self._landed_at_s > LANDED_DISARM_S:
                    self._armed = False
                    self._statustext("landed: disarmed")
            elif t - self._armed_at_s > PREFLIGHT_DISARM_S and self._behaviour not in (
                Behaviour.TAKEOFF, Behaviour.OFFBOARD,
            ):
                self._armed = False
                self._statustext("preflight: disarmed, no takeoff")
        else:
            self._landed_at_s = 0.0
        if self._behaviour is Behaviour.TAKEOFF and self._mode_target is not None:
            assert self._mode_target.position_ned is not None
            if abs(v.position_ned[2] - self._mode_target.position_ned[2]) < REACHED_M:
                self._set_behaviour(Behaviour.HOLD)
        if self._behaviour is Behaviour.OFFBOARD and self.config.flavour is Flavour.PX4:
            last = self._setpoint.t_s if self._setpoint is not None else -math.inf
            if self._armed and t - last > self._params["COM_OF_LOSS_T"]:
                action = list(Failsafe)[int(self._params["COM_OBL_RC_ACT"])]
                self._statustext(f"failsafe: offboard setpoints lost, {action.value}")
                self._set_behaviour(
                    {Failsafe.HOLD: Behaviour.HOLD, Failsafe.LAND: Behaviour.LAND,
                     Failsafe.RTL: Behaviour.RTL}[action]
                )
        if (self._armed and not self._battery_failsafe_done
                and self._battery_percent() < self.config.battery_low_percent):
            self._battery_failsafe_done = True
            self._statustext("failsafe: low battery, returning")
            self._set_behaviour(Behaviour.RTL)

    def _target(self) -> Target | None:
        v = self._vehicle
        b = self._behaviour
        if b is Behaviour.TAKEOFF:
            if self._mode_target is None:
                alt = self._params["MIS_TAKEOFF_ALT"]
                self._mode_target = Target(
                    position_ned=np.array([v.position_ned[0], v.position_ned[1], -alt]),
                    yaw_rad=v.yaw_rad,
                )
            return self._mode_target
        if b is Behaviour.LAND:
            return Target(velocity_ned=np.array([0.0, 0.0, LAND_SPEED_M_S]))
        if b is Behaviour.RTL:
            return self._rtl_target()
        if b is Behaviour.OFFBOARD:
            if self._guided_takeoff_alt is not None and self._setpoint is None:
                return Target(position_ned=np.array(
                    [v.position_ned[0], v.position_ned[1], -self._guided_takeoff_alt]))
            if self._setpoint is not None:
                return self._setpoint.target
            return Target(position_ned=v.position_ned.copy())
        return self._mode_target

    def _rtl_target(self) -> Target:
        v = self._vehicle
        alt = max(self._params["RTL_RETURN_ALT"], -float(v.position_ned[2]))
        above_home = np.array([self._home[0], self._home[1], -alt])
        if self._rtl_phase == 0:  # climb
            if -v.position_ned[2] >= alt - REACHED_M:
                self._rtl_phase = 1
            return Target(position_ned=np.array([v.position_ned[0], v.position_ned[1], -alt]))
        if self._rtl_phase == 1:  # fly home
            if float(np.hypot(*(v.position_ned[:2] - self._home[:2]))) < REACHED_M:
                self._rtl_phase = 2
            return Target(position_ned=above_home)
        return Target(velocity_ned=np.array([0.0, 0.0, LAND_SPEED_M_S]))  # land

    # -- arming -------------------------------------------------------------------------------

    def _arm_refusal(self) -> str | None:
        if self._t_s < self.config.armable_after_s:
            return "estimator not ready"
        armable = PX4_ARMABLE if self.config.flavour is Flavour.PX4 else COPTER_ARMABLE
        if self._behaviour not in armable:
            return f"cannot arm in {self._behaviour.value}"
        if self._battery_percent() < self.config.battery_low_percent:
            return "battery low"
        return None

    def _arm(self) -> bool:
        if self._armed:
            return True
        refusal = self._arm_refusal()
        if refusal is not None:
            self._statustext(f"arming denied: {refusal}")
            return False
        self._armed = True
        self._armed_at_s = self._t_s
        self._battery_failsafe_done = False
        return True

    def _battery_percent(self) -> float:
        used = self._battery_used_s / self.config.battery_flight_s
        return float(np.clip(100.0 * (1.0 - used), 0.0, 100.0))

    # -- incoming messages --------------------------------------------------------------------

    def _signature_ok(self, msg: mavlink.MAVLink_message) -> bool:
        """Signing off, a valid signature, or an allow-listed message; else counted and False."""
        if self.config.signing_key is None or isinstance(msg, mavlink.MAVLink_bad_data):
            return True  # bad data matches nothing in _handle
        verdict = check_signature(self._mav, msg.get_msgbuf())
        if verdict is Signature.VALID:
            return True
        if msg.get_msgId() in UNSIGNED_ACCEPTED[self.config.flavour]:
            return True  # as the C library's accept_unsigned callback: unsigned or invalid
        if verdict is Signature.UNSIGNED:
            self._rejected_unsigned += 1
        else:
            self._rejected_bad_signature += 1
        return False

    def _handle(self, msg: mavlink.MAVLink_message) -> None:
        kind = msg.get_type()
        if kind in ("COMMAND_LONG", "COMMAND_INT"):
            if msg.target_system in (0, self.config.system_id) and msg.target_component in (
                0, self.config.component_id
            ):
                self._command(msg)
        elif kind == "SET_POSITION_TARGET_LOCAL_NED":
            self._setpoint_local(msg)
        elif kind == "SET_POSITION_TARGET_GLOBAL_INT":
            self._setpoint_global(msg)
        elif kind == "SET_MODE":
            self._mode_request(msg.base_mode, msg.custom_mode, raw_custom=True)
        elif kind == "PARAM_REQUEST_READ":
            self._param_read(msg)
        elif kind == "PARAM_REQUEST_LIST":
            for index, name in enumerate(self._params):
                self._param_value(name, index)
        elif kind == "PARAM_SET":
            name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else msg.param_id
            if name in self._params:
                self._params[name] = float(msg.param_value)
            self._param_value(name, list(self._params).index(name) if name in self._params else -1)
        elif kind == "REQUEST_DATA_STREAM":
            self._data_stream(msg)
        elif kind == "TIMESYNC":
            if msg.tc1 == 0:
                now_ns = int(self._t_s * 1e9)
                self._send(self._mav.timesync_encode(now_ns, msg.ts1))
        elif kind == "STATUSTEXT":  # a real autopilot routes it on to the ground station
            text = msg.text if isinstance(msg.text, str) else msg.text.decode(errors="replace")
            self.texts_received.append((msg.get_srcComponent(), msg.severity, text.rstrip("\x00")))
        elif kind in ("MISSION_REQUEST_LIST", "MISSION_COUNT", "MISSION_CLEAR_ALL"):
            self._send(self._mav.mission_ack_encode(
                msg.get_srcSystem(), msg.get_srcComponent(), mavlink.MAV_MISSION_UNSUPPORTED))

    def _ack(self, msg: mavlink.MAVLink_message, result: int) -> None:
        self._send(self._mav.command_ack_encode(
            msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))

    def _command(self, msg: mavlink.MAVLink_message) -> None:
        cmd = msg.command
        p = [msg.param1, msg.param2, msg.param3, msg.param4]
        accepted, denied = mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED
        if cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            if p[0] >= 0.5:
                self._ack(msg, accepted if self._arm() else denied)
            elif self._vehicle.on_ground or abs(p[1] - FORCE_MAGIC) < 0.5:
                self._armed = False
                self._ack(msg, accepted)
            else:
                self._ack(msg, denied)
        elif cmd == mavlink.MAV_CMD_NAV_TAKEOFF:
            self._takeoff(msg)
        elif cmd == mavlink.MAV_CMD_NAV_LAND:
            self._set_behaviour(Behaviour.LAND)
            self._ack(msg, accepted)
        elif cmd == mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            self._set_behaviour(Behaviour.RTL)
            self._ack(msg, accepted)
        elif cmd == mavlink.MAV_CMD_DO_SET_MODE:
            self._ack(msg, self._mode_request(int(p[0]), int(p[1]), int(p[2])))
        elif cmd == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            msg_id, interval_us = int(p[0]), p[1]
            if interval_us < 0:
                self._intervals.pop(msg_id, None)
            elif interval_us == 0:
                rate = PX4_RATES_HZ.get(msg_id)
                if rate is not None:
                    self._intervals[msg_id] = 1.0 / rate
            else:
                self._intervals[msg_id] = interval_us / 1e6
            self._next_due.pop(msg_id, None)
            self._ack(msg, accepted)
        elif cmd == mavlink.MAV_CMD_REQUEST_MESSAGE:
            known = int(p[0]) in SENDABLE
            self._ack(msg, accepted if known else mavlink.MAV_RESULT_UNSUPPORTED)
            if known:  # the ack first, then the message, as PX4 does
                self._send_message(int(p[0]))
        elif cmd == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self._ack(msg, accepted)
            self._send_message(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        elif cmd == mavlink.MAV_CMD_GET_HOME_POSITION:
            self._ack(msg, accepted)
            self._send_message(mavlink.MAVLINK_MSG_ID_HOME_POSITION)
        elif cmd == mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN and int(p[0]) == 1:
            if self._armed:
                self._ack(msg, denied)
            else:
                self._ack(msg, accepted)
                self._reboot_until_s = self.clock.now_s() + 2.0
        else:
            self._ack(msg, mavlink.MAV_RESULT_UNSUPPORTED)

    def _takeoff(self, msg: mavlink.MAVLink_message) -> None:
        if not self._armed:
            self._ack(msg, mavlink.MAV_RESULT_DENIED)
            return
        if self.config.flavour is Flavour.PX4:
            alt = msg.param7  # AMSL when given; MAVSDK leaves it NaN: MIS_TAKEOFF_ALT
            if math.isfinite(alt):
                home_alt = float(self.geo.ned_to_geodetic(*self._home)[2])
                self._params["MIS_TAKEOFF_ALT"] = max(alt - home_alt, 0.5)
            self._set_behaviour(Behaviour.TAKEOFF)
            self._ack(msg, mavlink.MAV_RESULT_ACCEPTED)
            return
        # A Copter takes off in GUIDED, to param7 metres above home.
        if self._behaviour is not Behaviour.OFFBOARD or not math.isfinite(msg.param7):
            self._ack(msg, mavlink.MAV_RESULT_FAILED)
            return
        self._guided_takeoff_alt = float(msg.param7)
        self._setpoint = None
        self._ack(msg, mavlink.MAV_RESULT_ACCEPTED)

    def _mode_request(
        self, base_mode: int, custom_main: int, custom_sub: int = 0, raw_custom: bool = False
    ) -> int:
        if not base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return int(mavlink.MAV_RESULT_UNSUPPORTED)
        if raw_custom and self.config.flavour is Flavour.PX4:
            custom_main, custom_sub = (custom_main >> 16) & 0xFF, (custom_main >> 24) & 0xFF
        behaviour = decode(self.config.flavour, custom_main, custom_sub)
        if behaviour is None or behaviour is Behaviour.MISSION:
            return int(mavlink.MAV_RESULT_DENIED)  # no such mode here, or no mission loaded
        px4_offboard = behaviour is Behaviour.OFFBOARD and self.config.flavour is Flavour.PX4
        if px4_offboard and not self._setpoints_streaming():
            self._statustext("offboard denied: no setpoint stream")
            return int(mavlink.MAV_RESULT_DENIED)
        if behaviour is Behaviour.TAKEOFF and not self._armed:
            return int(mavlink.MAV_RESULT_DENIED)
        self._set_behaviour(behaviour)
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def _setpoints_streaming(self) -> bool:
        t = self._t_s
        recent = [s for s in self._setpoint_times if t - s <= STREAMING_WINDOW_S]
        return len(recent) >= 2 and t - recent[-1] <= STREAMING_FRESH_S

    def _accept_setpoint(self, target: Target) -> None:
        self._last_setpoint_clock_s = self._boot_wall_s + self._t_s
        self._setpoint = _Setpoint(target, self._t_s)
        self._setpoint_times.append(self._t_s)
        if self.config.flavour is Flavour.ARDUPILOT and self._behaviour is Behaviour.OFFBOARD:
            self._guided_takeoff_alt = None  # setpoints override a GUIDED take-off

    def _setpoint_local(self, msg: mavlink.MAVLink_message) -> None:
        mask = msg.type_mask
        frame = msg.coordinate_frame
        yaw = None if mask & TYPEMASK_YAW else float(msg.yaw)
        origin = self._local_origin
        if frame in (mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED,
                     mavlink.MAV_FRAME_LOCAL_OFFSET_NED):
            origin = self._vehicle.position_ned
        if not mask & TYPEMASK_POSITION:
            position = origin + np.array([msg.x, msg.y, msg.z], dtype=np.float64)
            self._accept_setpoint(Target(position_ned=position, yaw_rad=yaw))
        elif not mask & TYPEMASK_VELOCITY:
            velocity = np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64)
            self._accept_setpoint(Target(velocity_ned=velocity, yaw_rad=yaw))

    def _setpoint_global(self, msg: mavlink.MAVLink_message) -> None:
        mask = msg.type_mask
        yaw = None if mask & TYPEMASK_YAW else float(msg.yaw)
        if not mask & TYPEMASK_POSITION:
            lat, lon = msg.lat_int / 1e7, msg.lon_int / 1e7
            home_alt = float(self.geo.ned_to_geodetic(*self._home)[2])
            alt = msg.alt + (home_alt if msg.coordinate_frame in (
                mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
            ) else 0.0)
            north, east, down = self.geo.geodetic_to_ned(lat, lon, alt)
            position = np.array([float(north), float(east), float(down)])
            self._accept_setpoint(Target(position_ned=position, yaw_rad=yaw))
        elif not mask & TYPEMASK_VELOCITY:
            velocity = np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64)
            self._accept_setpoint(Target(velocity_ned=velocity, yaw_rad=yaw))

    def _param_read(self, msg: mavlink.MAVLink_message) -> None:
        name = msg.param_id
        names = list(self._params)
        if msg.param_index >= 0 and msg.param_index < len(names) and not name:
            name = names[msg.param_index]
        if name in self._params:
            self._param_value(name, names.index(name))

    def _param_value(self, name: str, index: int) -> None:
        if index < 0:
            return
        value = self._params[name]
        self._send(self._mav.param_value_encode(
            name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32, len(self._params), index))

    def _data_stream(self, msg: mavlink.MAVLink_message) -> None:
        streams = list(DATA_STREAMS) if msg.req_stream_id == 0 else [msg.req_stream_id]
        for stream in streams:
            for msg_id in DATA_STREAMS.get(stream, ()):
                if msg.start_stop and msg.req_message_rate > 0:
                    self._intervals[msg_id] = 1.0 / msg.req_message_rate
                else:
                    self._intervals.pop(msg_id, None)

    # -- outgoing messages --------------------------------------------------------------------

    def _send(self, msg: mavlink.MAVLink_message) -> None:
        self.link.send(msg.pack(self._mav), self.clock.now_s())

    def _statustext(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> None:
        self.statustexts.append(text)
        self._send(self._mav.statustext_encode(severity, text.encode()[:50]))

    def _send_due(self) -> None:
        t = self._t_s
        if t >= self._next_heartbeat:
            # 1 Hz, drifting with the loop: locked in step with the other streams, each second's
            # burst of messages met the same control tick of the service at 4x.
            self._next_heartbeat = t + 1.0
            self._send_heartbeat()
        for msg_id, interval in list(self._intervals.items()):
            due = self._next_due.get(msg_id, 0.0)
            if t >= due:
                self._next_due[msg_id] = max(due + interval, t)
                self._send_message(msg_id)

    def _send_heartbeat(self) -> None:
        """The heartbeat, which carries the mode; notes when a new mode is first reported."""
        if self._behaviour_reported_clock_s is None:
            self._behaviour_reported_clock_s = self._boot_wall_s + self._t_s
        self._send(self._heartbeat())

    def _heartbeat(self) -> mavlink.MAVLink_message:
        cfg = self.config
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self._armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        if self._behaviour in (Behaviour.OFFBOARD, Behaviour.HOLD, Behaviour.TAKEOFF,
                               Behaviour.LAND, Behaviour.RTL, Behaviour.MISSION):
            base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED | mavlink.MAV_MODE_FLAG_AUTO_ENABLED
        base |= mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED | mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        autopilot = (mavlink.MAV_AUTOPILOT_PX4 if cfg.flavour is Flavour.PX4
                     else mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
        state = mavlink.MAV_STATE_ACTIVE if self._armed else mavlink.MAV_STATE_STANDBY
        return self._mav.heartbeat_encode(
            mavlink.MAV_TYPE_QUADROTOR, autopilot, base, encode(cfg.flavour, self._behaviour),
            state)

    def _reported_ned(self) -> FloatArray:
        """The position the estimator reports (world NED): truth, drift, noise, glitch."""
        pos = self._vehicle.position_ned + self._drift
        if self.config.position_noise_m > 0.0:
            pos = pos + self._rng.normal(0.0, self.config.position_noise_m, 3) * [1, 1, 0.5]
        offset, until = self._glitch
        if self._t_s < until:
            pos = pos + offset
        return pos

    def _send_message(self, msg_id: int) -> bool:
        """Send one message of the given id; False when this autopilot has no such message."""
        t_ms = int(self._t_s * 1000) & 0xFFFFFFFF
        v = self._vehicle
        m = self._mav
        if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            self._send_heartbeat()
        elif msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            self._send(m.autopilot_version_encode(
                CAPABILITIES, 0x010E0000, 0, 0, 0, b"\x00" * 8, b"\x00" * 8, b"\x00" * 8, 0, 0,
                0x5157_0000 + self.config.system_id))
        elif msg_id == mavlink.MAVLINK_MSG_ID_SYS_STATUS:
            health = SENSORS | (mavlink.MAV_SYS_STATUS_PREARM_CHECK
                                if self._arm_refusal() is None or self._armed else 0)
            pct = self._battery_percent()
            self._send(m.sys_status_encode(
                SENSORS | mavlink.MAV_SYS_STATUS_PREARM_CHECK,
                SENSORS | mavlink.MAV_SYS_STATUS_PREARM_CHECK, health, 250,
                int(14800 + 2000 * pct / 100), 1200 if self._armed else 50, int(pct),
                0, 0, 0, 0, 0, 0))
        elif msg_id in (mavlink.MAVLINK_MSG_ID_ATTITUDE,
                        mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION):
            roll, pitch = v.roll_pitch_rad()
            if msg_id == mavlink.MAVLINK_MSG_ID_ATTITUDE:
                self._send(m.attitude_encode(t_ms, roll, pitch, v.yaw_rad, 0.0, 0.0, 0.0))
            else:
                w, x, y, z = v.quaternion_wxyz()
                self._send(m.attitude_quaternion_encode(t_ms, w, x, y, z, 0.0, 0.0, 0.0))
        elif msg_id == mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            pos = self._reported_ned()
            lat, lon, alt = (float(a) for a in self.geo.ned_to_geodetic(*pos))
            home_alt = float(self.geo.ned_to_geodetic(*self._home)[2])
            heading = int(math.degrees(v.yaw_rad) % 360 * 100)
            self._send(m.global_position_int_encode(
                t_ms, int(lat * 1e7), int(lon * 1e7), int(alt * 1000),
                int((alt - home_alt) * 1000), *(int(c * 100) for c in v.velocity_ned), heading))
        elif msg_id == mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            pos = self._reported_ned() - self._local_origin
            self._send(m.local_position_ned_encode(t_ms, *pos, *v.velocity_ned))
        elif msg_id == mavlink.MAVLINK_MSG_ID_HOME_POSITION:
            lat, lon, alt = (float(a) for a in self.geo.ned_to_geodetic(*self._home))
            local = self._home - self._local_origin
            self._send(m.home_position_encode(
                int(lat * 1e7), int(lon * 1e7), int(alt * 1000), *local, [1.0, 0.0, 0.0, 0.0],
                0.0, 0.0, 0.0, int(self._t_s * 1e6)))
        elif msg_id == mavlink.MAVLINK_MSG_ID_GPS_RAW_INT:
            pos = self._reported_ned()
            lat, lon, alt = (float(a) for a in self.geo.ned_to_geodetic(*pos))
            speed = float(np.hypot(*v.velocity_ned[:2]))
            cog = int(math.degrees(math.atan2(v.velocity_ned[1], v.velocity_ned[0])) % 360 * 100)
            self._send(m.gps_raw_int_encode(
                int(self._t_s * 1e6), mavlink.GPS_FIX_TYPE_3D_FIX, int(lat * 1e7),
                int(lon * 1e7), int(alt * 1000), 80, 120, int(speed * 100), cog, 14))
        elif msg_id == mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            if v.on_ground:
                landed = mavlink.MAV_LANDED_STATE_ON_GROUND
            elif self._behaviour is Behaviour.LAND:
                landed = mavlink.MAV_LANDED_STATE_LANDING
            elif self._behaviour is Behaviour.TAKEOFF:
                landed = mavlink.MAV_LANDED_STATE_TAKEOFF
            else:
                landed = mavlink.MAV_LANDED_STATE_IN_AIR
            self._send(m.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_UNDEFINED, landed))
        elif msg_id == mavlink.MAVLINK_MSG_ID_BATTERY_STATUS:
            pct = self._battery_percent()
            cells = [int(3700 + 500 * pct / 100)] * 4 + [65535] * 6
            self._send(m.battery_status_encode(
                0, mavlink.MAV_BATTERY_FUNCTION_ALL, mavlink.MAV_BATTERY_TYPE_LIPO, 2500, cells,
                1200 if self._armed else 50, -1, -1, int(pct)))
        elif msg_id == mavlink.MAVLINK_MSG_ID_VFR_HUD:
            alt = float(self.geo.ned_to_geodetic(*self._vehicle.position_ned)[2])
            speed = float(np.hypot(*v.velocity_ned[:2]))
            self._send(m.vfr_hud_encode(speed, speed, int(math.degrees(v.yaw_rad) % 360),
                                        50 if self._armed else 0, alt, -float(v.velocity_ned[2])))
        else:
            return False
        return True
