"""A mock PX4 or ArduPilot Copter autopilot that speaks MAVLink 2 over UDP on loopback.

It is what the real MAVSDK library connects to in the tests: heartbeats with the flavour's mode
encoding, AUTOPILOT_VERSION with the capability bits MAVSDK checks, command acks, the parameter
protocol for the parameters MAVSDK reads, telemetry at realistic rates with boot-time stamps,
and PX4's offboard rules: OFFBOARD is refused unless setpoints already stream, and a setpoint
stream that stops for COM_OF_LOSS_T falls back from OFFBOARD to the configured failsafe mode,
which returns to OFFBOARD when the stream comes back unless the mode was changed or the vehicle
disarmed meanwhile (PX4 v1.15's mode fallback, measured on SIH). The ArduPilot
flavour uses Copter's mode numbers, GUIDED for offboard, streams nothing until asked, reports
local NED about its EKF origin, and refuses to arm in modes that forbid it.

It starts and reports as the real firmware was measured to (ArduPilot master 2023-07 SITL, PX4
v1.15 SIH; `FLAVOUR_DEFAULTS`): an estimator warm-up before arming and a GPS fix before which
the position reads lat = lon = 0; PX4's "velocity unstable" arm refusals right after it reports
healthy, given as EVENT messages (sitl.events), never STATUSTEXT; ArduPilot's motor spool-up
before a GUIDED take-off leaves the ground, and its relative altitude reading above the true
height. What it reports can differ from the truth by slowly varying estimate errors
(`GaussMarkov`), with the uncertainty stated as the firmware states it (GPS_RAW_INT h_acc and
v_acc; PX4's ESTIMATOR_STATUS and ODOMETRY covariances). The vehicle flies on its estimate: a
setpoint is reached where the estimate says, and the truth is off by the estimate's error.

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
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum

import numpy as np
from numpy.typing import NDArray
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.geo import LocalNed
from companion.rotation import quaternion_from_euler
from companion.vehicle.signing import Signature, check_signature, new_signer
from sitl import events
from sitl.clock import SimClock
from sitl.link import UdpLink
from sitl.modes import COPTER_ARMABLE, PX4_ARMABLE, Behaviour, Flavour, decode, encode
from sitl.vehicle import (
    Target,
    VehicleLimits,
    VehicleState,
    step,
    wrap_rad,
)
from sitl.workers import Workers

FloatArray = NDArray[np.float64]

FORCE_MAGIC = 21196.0  # param2 of ARM_DISARM that forces it (PX4 and ArduPilot)
PREFLIGHT_DISARM_S = 10.0  # PX4 COM_DISARM_PRFLT: armed on the ground without taking off
LANDED_DISARM_S = 2.0  # PX4 COM_DISARM_LAND
LAND_SPEED_M_S = 0.7
REACHED_M = 0.3
TAKEOFF_DONE_M = 0.8  # PX4 NAV_MC_ALT_RAD: AUTO.TAKEOFF hands over to Hold this close
STREAMING_WINDOW_S = 1.0  # offboard needs setpoints above 2 Hz: two within this window...
STREAMING_FRESH_S = 0.5  # ...and the last one this recent
IN_AIR_HEIGHT_M = 0.2  # the landed state says "in air" once this high above the ground
MANUAL_CONTROL_FRESH_S = 1.0  # PX4: POSCTL and ALTCTL need MANUAL_CONTROL this recent
ACCURACY_FLOOR_M = 0.02  # the smallest position uncertainty reported
ACCURACY_FLOOR_DEG = 0.1  # the smallest attitude uncertainty reported
NO_FIX_ACCURACY_M = 1000.0  # ESTIMATOR_STATUS pos_horiz_accuracy before the GPS fix
RANGEFINDER_MIN_M = 0.1  # DISTANCE_SENSOR min_distance
RANGEFINDER_NOISE_M = 0.01  # white noise of a rangefinder reading
UINT16_UNKNOWN = 0xFFFF  # GPS_RAW_INT eph, epv, cog: not known


class Failsafe(Enum):
    """What the autopilot does when the offboard setpoints stop (COM_OBL_RC_ACT)."""

    POSITION = "position"
    HOLD = "hold"
    LAND = "land"
    RTL = "rtl"


# PX4's COM_OBL_RC_ACT values of the modelled actions. The others (1 Altitude, 2 Manual,
# 6 Terminate, 7 Disarm) are not modelled: set over MAVLink, they fly Position, PX4's default.
COM_OBL_RC_ACT: dict[Failsafe, int] = {
    Failsafe.POSITION: 0, Failsafe.RTL: 3, Failsafe.LAND: 4, Failsafe.HOLD: 5,
}
FAILSAFE_BEHAVIOUR: dict[Failsafe, Behaviour] = {
    Failsafe.POSITION: Behaviour.POSITION, Failsafe.HOLD: Behaviour.HOLD,
    Failsafe.LAND: Behaviour.LAND, Failsafe.RTL: Behaviour.RTL,
}


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
    mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS: 1.0,  # PX4 v1.15's onboard mode
    mavlink.MAVLINK_MSG_ID_ODOMETRY: 30.0,
}
PX4_DISTANCE_SENSOR_HZ = 10.0  # with a rangefinder
PX4_ONLY = frozenset({mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS, mavlink.MAVLINK_MSG_ID_ODOMETRY})
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
    mavlink.MAV_DATA_STREAM_EXTRA3: (mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR,),
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
    mavlink.MAVLINK_MSG_ID_VFR_HUD, mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR, *PX4_RATES_HZ,
})  # what _send_message can send (some only by one flavour, or with a rangefinder)
ESTIMATOR_FLAGS_FIX = (
    mavlink.ESTIMATOR_ATTITUDE | mavlink.ESTIMATOR_VELOCITY_HORIZ
    | mavlink.ESTIMATOR_VELOCITY_VERT | mavlink.ESTIMATOR_POS_HORIZ_REL
    | mavlink.ESTIMATOR_POS_HORIZ_ABS | mavlink.ESTIMATOR_POS_VERT_ABS
    | mavlink.ESTIMATOR_PRED_POS_HORIZ_REL | mavlink.ESTIMATOR_PRED_POS_HORIZ_ABS
)  # ESTIMATOR_STATUS.flags with a GPS fix...
ESTIMATOR_FLAGS_NO_FIX = (
    mavlink.ESTIMATOR_ATTITUDE | mavlink.ESTIMATOR_VELOCITY_VERT
    | mavlink.ESTIMATOR_POS_VERT_ABS | mavlink.ESTIMATOR_CONST_POS_MODE
)  # ...and before it
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
# Why arming is refused: PX4's EVENT id and ArduPilot's STATUSTEXT.
REFUSALS: dict[str, tuple[int, str]] = {
    "no_fix": (events.EVENT_NO_GPS_FIX, "PreArm: GPS 1: Bad fix"),
    "not_ready": (events.EVENT_ESTIMATOR_NOT_READY, "PreArm: Need Position Estimate"),
    "mode": (events.EVENT_MODE_NOT_ARMABLE, "Arm: Mode not armable"),
    "battery": (events.EVENT_BATTERY_LOW, "PreArm: Battery 1 below minimum arming capacity"),
    "horizontal_unstable": (events.EVENT_HORIZONTAL_VELOCITY_UNSTABLE,
                            "PreArm: horizontal velocity unstable"),
    "vertical_unstable": (events.EVENT_VERTICAL_VELOCITY_UNSTABLE,
                          "PreArm: vertical velocity unstable"),
}


@dataclass(frozen=True, slots=True)
class Firmware:
    """How one firmware starts up and reports its height: the config's values in force."""

    armable_after_s: float  # estimator warm-up: arming refused before
    gps_fix_after_s: float  # no position (lat = lon = 0, no local position) before
    arm_unstable_s: float  # after armable_after_s: ARM TEMPORARILY_REJECTED, velocity unstable
    takeoff_spoolup_s: float  # from NAV_TAKEOFF to leaving the ground
    rel_alt_bias_m: float  # reported height minus true height


# The measured defaults of each flavour (ArduPilot master 2023-07 SITL, PX4 v1.15 SIH). PX4's
# warm-up is kept at 2 s for the tests' time budgets; the real one is healthy after 33-37 s.
FLAVOUR_DEFAULTS: dict[Flavour, Firmware] = {
    Flavour.PX4: Firmware(armable_after_s=2.0, gps_fix_after_s=0.0, arm_unstable_s=3.0,
                          takeoff_spoolup_s=0.0, rel_alt_bias_m=0.0),
    Flavour.ARDUPILOT: Firmware(armable_after_s=40.0, gps_fix_after_s=25.0, arm_unstable_s=0.0,
                                takeoff_spoolup_s=1.75, rel_alt_bias_m=0.25),
}


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
    offboard_failsafe: Failsafe = Failsafe.POSITION  # COM_OBL_RC_ACT (PX4's default: 0)
    # None: the flavour's measured value (FLAVOUR_DEFAULTS; see `firmware`).
    armable_after_s: float | None = None  # estimator settling after boot
    gps_fix_after_s: float | None = None  # GPS fix after boot (never after armable_after_s)
    arm_unstable_s: float | None = None  # velocity-unstable arm refusals after armable_after_s
    takeoff_spoolup_s: float | None = None  # motor spool-up from NAV_TAKEOFF to lift-off
    rel_alt_bias_m: float | None = None  # reported height minus true height
    position_noise_m: float = 0.0  # white noise on the reported position, per axis
    gps_drift_m_per_sqrt_s: float = 0.0  # random walk of the reported position
    # Estimate errors: 1-sigma of first-order Gauss-Markov processes (0: the true pose).
    heading_error_deg: float = 0.0  # measured: PX4 SIH 1-12 degrees, ArduPilot within 0.6
    attitude_error_deg: float = 0.0  # roll and pitch; measured: PX4 1-2 degrees
    position_error_m: float = 0.0  # north and east; measured: PX4 0.13-0.25 m, ArduPilot 0.02
    height_error_m: float = 0.0  # measured: PX4 up to 1.8 m
    error_time_constant_s: float = 30.0  # correlation time of those errors
    rangefinder: bool = False  # a downward DISTANCE_SENSOR
    rangefinder_max_m: float = 40.0
    battery_flight_s: float = 1800.0  # flight time on a full battery
    battery_low_percent: float = 20.0  # below: the battery failsafe returns home
    limits: VehicleLimits = field(default_factory=VehicleLimits)
    physics_dt_s: float = 0.02
    seed: int = 0
    signing_key: bytes | None = None  # 32 bytes: sign everything, reject unsigned frames

    def firmware(self) -> Firmware:
        """The start-up values in force: each one given, else the flavour's measured one.

        The flavour's GPS fix comes no later than a given armable_after_s, and its velocity-
        unstable refusals follow only its own warm-up: a warm-up given by hand ends cleanly.
        """
        d = FLAVOUR_DEFAULTS[self.flavour]
        armable_s = d.armable_after_s if self.armable_after_s is None else self.armable_after_s
        fix_s = (min(d.gps_fix_after_s, armable_s) if self.gps_fix_after_s is None
                 else self.gps_fix_after_s)
        unstable_s = self.arm_unstable_s
        if unstable_s is None:
            unstable_s = d.arm_unstable_s if self.armable_after_s is None else 0.0
        return Firmware(
            armable_after_s=armable_s,
            gps_fix_after_s=fix_s,
            arm_unstable_s=unstable_s,
            takeoff_spoolup_s=(d.takeoff_spoolup_s if self.takeoff_spoolup_s is None
                               else self.takeoff_spoolup_s),
            rel_alt_bias_m=d.rel_alt_bias_m if self.rel_alt_bias_m is None else self.rel_alt_bias_m,
        )


class GaussMarkov:
    """Seeded first-order Gauss-Markov processes: stationary N(0, sigma^2), correlation time tau.

    Each `step(dt_s)` maps x to a x + sqrt(1 - a^2) sigma w with a = exp(-dt_s / tau) and w
    standard normal; the start is a draw of the stationary distribution.
    """

    def __init__(self, sigmas: FloatArray, tau_s: float, rng: np.random.Generator) -> None:
        self.sigmas = np.asarray(sigmas, dtype=np.float64)
        self.tau_s = tau_s
        self._rng = rng
        self._on = bool(np.any(self.sigmas > 0.0))
        self.value = self.sigmas * rng.standard_normal(self.sigmas.shape) if self._on else (
            np.zeros(self.sigmas.shape))

    def step(self, dt_s: float) -> FloatArray:
        """Advance by dt_s; the new value."""
        if self._on:
            a = math.exp(-dt_s / self.tau_s)
            noise = self._rng.standard_normal(self.sigmas.shape)
            self.value = a * self.value + math.sqrt(1.0 - a * a) * self.sigmas * noise
        return self.value


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
    # Estimate minus truth the vehicle flies on: north, east, down (m), roll, pitch, yaw (rad).
    estimate_error: tuple[float, ...] = (0.0,) * 6


@dataclass
class _Setpoint:
    target: Target
    t_s: float


class MockAutopilot:
    """The simulated autopilot, its vehicle and its link; `start()` runs it in a thread.

    `on_setpoint` (constructor argument or attribute, default None), if set, is called with the
    SITL clock time of every setpoint the autopilot accepts, on its thread and under its lock:
    an observer for measurements (benchmarks/soak.py), which must return at once.
    """

    def __init__(
        self, config: AutopilotConfig, link: UdpLink, clock: SimClock, geo: LocalNed,
        on_setpoint: Callable[[float], None] | None = None,
    ) -> None:
        self.config = config
        self.on_setpoint = on_setpoint
        self.link = link
        self.clock = clock
        self.geo = geo
        self.firmware = config.firmware()
        self._rng = np.random.default_rng(config.seed)
        # Own streams, so that the estimate errors and the extra messages leave the noise and
        # drift of the position reports as they were.
        seeds = np.random.SeedSequence([config.seed, 1]).spawn(3)
        self._error_rng = np.random.default_rng(seeds[0])
        self._odometry_rng = np.random.default_rng(seeds[1])
        self._rangefinder_rng = np.random.default_rng(seeds[2])
        self._lock = threading.RLock()
        self._workers = Workers()
        self._stopping = self._workers.stopping
        self._boot = 0
        self._reboot_until_s = -1.0
        self._glitch: tuple[FloatArray, float] = (np.zeros(3), -1.0)
        self.statustexts: list[str] = []  # sent as STATUSTEXT
        self.events_sent: list[int] = []  # EVENT ids sent (PX4)
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
        self._offboard_fallback = False  # in the offboard-loss failsafe, OFFBOARD still intended
        self._mode_target: Target | None = None
        self._rtl_phase = 0
        self._guided_takeoff_alt: float | None = None
        self._takeoff_at_s: float | None = None  # NAV_TAKEOFF accepted: spool-up from then
        self._airborne = False  # left the ground (IN_AIR_HEIGHT_M) since it last touched it
        self._last_manual_control_s = -math.inf
        self._event_sequence = 0
        self._setpoint: _Setpoint | None = None
        self._setpoint_times: deque[float] = deque(maxlen=16)
        self._battery_used_s = 0.0
        self._battery_failsafe_done = False
        self._drift = np.zeros(3)
        deg = math.radians
        self._error = GaussMarkov(
            np.array([cfg.position_error_m, cfg.position_error_m, cfg.height_error_m,
                      deg(cfg.attitude_error_deg), deg(cfg.attitude_error_deg),
                      deg(cfg.heading_error_deg)]),
            cfg.error_time_constant_s, self._error_rng)
        self._params: dict[str, float] = {
            "MIS_TAKEOFF_ALT": cfg.takeoff_alt_m,
            "RTL_RETURN_ALT": cfg.rtl_alt_m,
            "COM_OF_LOSS_T": cfg.offboard_loss_timeout_s,
            "COM_OBL_RC_ACT": float(COM_OBL_RC_ACT[cfg.offboard_failsafe]),
        }
        if cfg.flavour is Flavour.PX4:
            self._intervals = {k: 1.0 / v for k, v in PX4_RATES_HZ.items()}
            if cfg.rangefinder:
                self._intervals[mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR] = (
                    1.0 / PX4_DISTANCE_SENSOR_HZ)
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
        self._workers.start(("sitl-autopilot", self._loop))

    def stop(self) -> None:
        """Stop the loop and close the link."""
        self._workers.stop()
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
                            behaviour_reported_clock_s=self._behaviour_reported_clock_s,
                            estimate_error=(*(float(c) for c in self._offset_ned()),
                                            *(float(c) for c in self._error.value[3:])))

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
                self._disarm()

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
            if self._vehicle.on_ground:
                self._airborne = False
            elif -self._vehicle.position_ned[2] >= IN_AIR_HEIGHT_M:
                self._airborne = True
            sigma = self.config.gps_drift_m_per_sqrt_s
            if sigma > 0.0:
                self._drift += self._rng.normal(0.0, sigma * math.sqrt(dt), 3) * [1, 1, 0.5]
            self._error.step(dt)

    # -- modes --------------------------------------------------------------------------------

    def _set_behaviour(self, behaviour: Behaviour, by_pilot: bool = False) -> None:
        """Switch to a mode; any switch, or a request for the mode it is in, ends a fallback."""
        self._offboard_fallback = False
        if behaviour is self._behaviour:
            return
        previous = self._behaviour
        self._behaviour = behaviour
        self._behaviour_reported_clock_s = None
        self._mode_target = None
        self._rtl_phase = 0
        if behaviour is not Behaviour.OFFBOARD:
            self._guided_takeoff_alt = None
        self._takeoff_at_s = self._t_s if behaviour is Behaviour.TAKEOFF else None
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
                    self._disarm()
                    self._statustext("landed: disarmed")
            elif t - self._armed_at_s > PREFLIGHT_DISARM_S and self._behaviour not in (
                Behaviour.TAKEOFF, Behaviour.OFFBOARD,
            ):
                self._disarm()
                self._statustext("preflight: disarmed, no takeoff")
        else:
            self._landed_at_s = 0.0
        if self._behaviour is Behaviour.TAKEOFF and self._mode_target is not None:
            assert self._mode_target.position_ned is not None
            if abs(v.position_ned[2] - self._mode_target.position_ned[2]) < TAKEOFF_DONE_M:
                self._set_behaviour(Behaviour.HOLD)
        if self._behaviour is Behaviour.OFFBOARD and self.config.flavour is Flavour.PX4:
            last = self._setpoint.t_s if self._setpoint is not None else -math.inf
            if self._armed and t - last > self._params["COM_OF_LOSS_T"]:
                action = self._offboard_loss_action()
                self._statustext(f"failsafe: offboard setpoints lost, {action.value}")
                self._set_behaviour(FAILSAFE_BEHAVIOUR[action])
                self._offboard_fallback = True
        elif self._offboard_fallback and self._armed and self._setpoints_streaming():
            self._statustext("failsafe: offboard setpoints back, offboard")
            self._set_behaviour(Behaviour.OFFBOARD)
        if (self._armed and not self._battery_failsafe_done
                and self._battery_percent() < self.config.battery_low_percent):
            self._battery_failsafe_done = True
            self._statustext("failsafe: low battery, returning")
            self._set_behaviour(Behaviour.RTL)

    def _offboard_loss_action(self) -> Failsafe:
        """The failsafe COM_OBL_RC_ACT names; Position for a value not modelled."""
        value = self._params["COM_OBL_RC_ACT"]
        return next((f for f, v in COM_OBL_RC_ACT.items() if v == value), Failsafe.POSITION)

    def _spooling_up(self) -> bool:
        """On the ground after NAV_TAKEOFF, the motors not yet at take-off speed."""
        return (self._takeoff_at_s is not None and self._vehicle.on_ground
                and self._t_s - self._takeoff_at_s < self.firmware.takeoff_spoolup_s)

    def _target(self) -> Target | None:
        v = self._vehicle
        b = self._behaviour
        if b is Behaviour.TAKEOFF:
            if self._spooling_up():
                return None
            if self._mode_target is None:
                alt = self._params["MIS_TAKEOFF_ALT"]
                self._mode_target = Target(
                    position_ned=np.array([v.position_ned[0], v.position_ned[1],
                                           self._true_down(-alt)]),
                    yaw_rad=v.yaw_rad,
                )
            return self._mode_target
        if b is Behaviour.LAND:
            return Target(velocity_ned=np.array([0.0, 0.0, LAND_SPEED_M_S]))
        if b is Behaviour.RTL:
            return self._rtl_target()
        if b is Behaviour.OFFBOARD:
            if self._guided_takeoff_alt is not None and self._setpoint is None:
                if self._spooling_up():
                    return None
                return Target(position_ned=np.array(
                    [v.position_ned[0], v.position_ned[1],
                     self._true_down(-self._guided_takeoff_alt)]))
            if self._setpoint is not None:
                return self._setpoint.target
            return Target(position_ned=v.position_ned.copy())
        return self._mode_target

    def _rtl_target(self) -> Target:
        """Climb, fly home and land, where the estimate says those are."""
        v = self._vehicle
        offset = self._offset_ned()
        alt = max(self._params["RTL_RETURN_ALT"], -float(v.position_ned[2] + offset[2]))
        down = self._true_down(-alt)
        above_home = np.array([*(self._home[:2] - offset[:2]), down])
        if self._rtl_phase == 0:  # climb
            if v.position_ned[2] <= down + REACHED_M:
                self._rtl_phase = 1
            return Target(position_ned=np.array([v.position_ned[0], v.position_ned[1], down]))
        if self._rtl_phase == 1:  # fly home
            if float(np.hypot(*(v.position_ned[:2] - above_home[:2]))) < REACHED_M:
                self._rtl_phase = 2
            return Target(position_ned=above_home)
        return Target(velocity_ned=np.array([0.0, 0.0, LAND_SPEED_M_S]))  # land

    # -- the estimate -------------------------------------------------------------------------

    def _offset_ned(self) -> FloatArray:
        """Estimate minus truth that the vehicle flies on: the estimate error and the bias."""
        offset: FloatArray = self._error.value[:3].copy()
        offset[2] -= self.firmware.rel_alt_bias_m
        return offset

    def _true_down(self, reported_down_m: float) -> float:
        """The true down of a height the estimate reports."""
        return reported_down_m - float(self._offset_ned()[2])

    def _has_fix(self) -> bool:
        return self._t_s >= self.firmware.gps_fix_after_s

    def _reported_attitude(self) -> tuple[float, float, float]:
        """Roll, pitch and yaw as the estimator reports them (radians)."""
        roll, pitch = self._vehicle.roll_pitch_rad()
        e = self._error.value
        return (float(roll + e[3]), float(pitch + e[4]),
                wrap_rad(float(self._vehicle.yaw_rad + e[5])))

    def _accuracy(self) -> tuple[float, float, float, float]:
        """1-sigma uncertainty as reported: horizontal (per axis) and vertical position
        (metres), roll and pitch, and heading (radians); never below the floors."""
        cfg = self.config
        horizontal_m = max(math.hypot(cfg.position_error_m, cfg.position_noise_m),
                           ACCURACY_FLOOR_M)
        vertical_m = max(math.hypot(cfg.height_error_m, 0.5 * cfg.position_noise_m),
                         ACCURACY_FLOOR_M)
        return (horizontal_m, vertical_m,
                math.radians(max(cfg.attitude_error_deg, ACCURACY_FLOOR_DEG)),
                math.radians(max(cfg.heading_error_deg, ACCURACY_FLOOR_DEG)))

    # -- arming -------------------------------------------------------------------------------

    def _arm_refusal(self) -> str | None:
        """Why the pre-arm checks fail now (a key of REFUSALS), or None: healthy."""
        if not self._has_fix():
            return "no_fix"
        if self._t_s < self.firmware.armable_after_s:
            return "not_ready"
        armable = PX4_ARMABLE if self.config.flavour is Flavour.PX4 else COPTER_ARMABLE
        if self._behaviour not in armable:
            return "mode"
        if self._battery_percent() < self.config.battery_low_percent:
            return "battery"
        return None

    def _unstable(self) -> str | None:
        """In the velocity-unstable span after becoming healthy: which check fails, else None.

        The horizontal velocity check fails in the first half of the span, the vertical one in
        the second: both refusals PX4 gave.
        """
        since_s = self._t_s - self.firmware.armable_after_s
        span_s = self.firmware.arm_unstable_s
        if not 0.0 <= since_s < span_s:
            return None
        return "horizontal_unstable" if since_s < span_s / 2.0 else "vertical_unstable"

    def _arm(self) -> int:
        """Arm if the checks pass; the MAV_RESULT (a refusal is reported as the flavour does)."""
        if self._armed:
            return int(mavlink.MAV_RESULT_ACCEPTED)
        refusal = self._arm_refusal()
        result = mavlink.MAV_RESULT_DENIED
        if refusal is None:
            refusal = self._unstable()
            result = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        if refusal is not None:
            event_id, text = REFUSALS[refusal]
            self._refuse(event_id, text)
            return int(result)
        self._armed = True
        self._armed_at_s = self._t_s
        self._battery_failsafe_done = False
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def _disarm(self) -> None:
        """Disarm; it also ends an offboard-loss fallback."""
        self._armed = False
        self._offboard_fallback = False

    def _refuse(self, event_id: int, ardupilot_text: str) -> None:
        """Say why a command was refused: PX4 with an EVENT, ArduPilot with a STATUSTEXT."""
        if self.config.flavour is Flavour.PX4:
            self._event(event_id)
        else:
            self._statustext(ardupilot_text, mavlink.MAV_SEVERITY_CRITICAL)

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
        elif kind == "MANUAL_CONTROL":  # sticks, from anyone: PX4 may fly POSCTL and ALTCTL
            self._last_manual_control_s = self._t_s
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
                self._ack(msg, self._arm())
            elif self._vehicle.on_ground or abs(p[1] - FORCE_MAGIC) < 0.5:
                self._disarm()
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
                rate = (PX4_DISTANCE_SENSOR_HZ if msg_id == mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR
                        else PX4_RATES_HZ.get(msg_id))
                if rate is not None:
                    self._intervals[msg_id] = 1.0 / rate
            else:
                self._intervals[msg_id] = interval_us / 1e6
            self._next_due.pop(msg_id, None)
            self._ack(msg, accepted)
        elif cmd == mavlink.MAV_CMD_REQUEST_MESSAGE:
            known = self._available(int(p[0]))
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
        self._takeoff_at_s = self._t_s
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
        px4 = self.config.flavour is Flavour.PX4
        if px4 and behaviour is Behaviour.OFFBOARD and not self._setpoints_streaming():
            self._event(events.EVENT_OFFBOARD_NOT_AVAILABLE)
            return int(mavlink.MAV_RESULT_DENIED)
        if (px4 and behaviour in (Behaviour.POSITION, Behaviour.ALTITUDE)
                and self._t_s - self._last_manual_control_s > MANUAL_CONTROL_FRESH_S):
            self._event(events.EVENT_POSITION_NOT_AVAILABLE if behaviour is Behaviour.POSITION
                        else events.EVENT_ALTITUDE_NOT_AVAILABLE)
            return int(mavlink.MAV_RESULT_TEMPORARILY_REJECTED)  # no sticks to fly it with
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
        if self.on_setpoint is not None:
            self.on_setpoint(self._last_setpoint_clock_s)

    def _setpoint_local(self, msg: mavlink.MAVLink_message) -> None:
        mask = msg.type_mask
        frame = msg.coordinate_frame
        yaw = self._true_yaw(None if mask & TYPEMASK_YAW else float(msg.yaw))
        origin = self._local_origin - self._offset_ned()  # the estimate's origin, in truth
        if frame in (mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED,
                     mavlink.MAV_FRAME_LOCAL_OFFSET_NED):
            origin = self._vehicle.position_ned
        if not mask & TYPEMASK_POSITION:
            position = origin + np.array([msg.x, msg.y, msg.z], dtype=np.float64)
            self._accept_setpoint(Target(position_ned=position, yaw_rad=yaw))
        elif not mask & TYPEMASK_VELOCITY:
            velocity = np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64)
            self._accept_setpoint(Target(velocity_ned=velocity, yaw_rad=yaw))

    def _true_yaw(self, reported_yaw_rad: float | None) -> float | None:
        """The true heading of one the estimate reports (None stays None)."""
        if reported_yaw_rad is None:
            return None
        return wrap_rad(reported_yaw_rad - float(self._error.value[5]))

    def _setpoint_global(self, msg: mavlink.MAVLink_message) -> None:
        mask = msg.type_mask
        yaw = self._true_yaw(None if mask & TYPEMASK_YAW else float(msg.yaw))
        if not mask & TYPEMASK_POSITION:
            lat, lon = msg.lat_int / 1e7, msg.lon_int / 1e7
            home_alt = float(self.geo.ned_to_geodetic(*self._home)[2])
            alt = msg.alt + (home_alt if msg.coordinate_frame in (
                mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
            ) else 0.0)
            north, east, down = self.geo.geodetic_to_ned(lat, lon, alt)
            position = np.array([float(north), float(east), float(down)]) - self._offset_ned()
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

    def _event(self, event_id: int) -> None:
        """Send an EVENT (PX4's way of reporting; its text is in events.PX4_EVENT_TEXTS)."""
        self.events_sent.append(event_id)
        self._send(events.event_message(event_id, int(self._t_s * 1000), self._event_sequence))
        self._event_sequence = (self._event_sequence + 1) & 0xFFFF

    def _available(self, msg_id: int) -> bool:
        """Whether this autopilot has the message at all (flavour, rangefinder)."""
        if msg_id in PX4_ONLY:
            return self.config.flavour is Flavour.PX4
        if msg_id == mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR:
            return self.config.rangefinder
        return msg_id in SENDABLE

    def _send_due(self) -> None:
        """Send what is due, in the order it fell due (a late loop keeps the order)."""
        t = self._t_s
        due: list[tuple[float, int | None]] = []
        if t >= self._next_heartbeat:
            # 1 Hz, drifting with the loop: locked in step with the other streams, each second's
            # burst of messages met the same control tick of the service at 4x.
            due.append((self._next_heartbeat, None))
            self._next_heartbeat = t + 1.0
        for msg_id, interval in list(self._intervals.items()):
            at_s = self._next_due.get(msg_id, 0.0)
            if t >= at_s:
                self._next_due[msg_id] = max(at_s + interval, t)
                due.append((at_s, msg_id))
        for _, stream in sorted(due, key=lambda d: (d[0], d[1] is not None)):
            if stream is None:
                self._send_heartbeat()
            else:
                self._send_message(stream)

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

    def _reported_ned(self, with_bias: bool = True, rng: np.random.Generator | None = None
                      ) -> FloatArray:
        """The position the estimator reports (world NED): truth, estimate error, resting-
        height bias (without_bias: GPS_RAW_INT's raw fix), drift, noise, glitch."""
        pos = self._vehicle.position_ned + self._error.value[:3] + self._drift
        if with_bias:
            pos = pos - np.array([0.0, 0.0, self.firmware.rel_alt_bias_m])
        if self.config.position_noise_m > 0.0:
            noise = (rng or self._rng).normal(0.0, self.config.position_noise_m, 3)
            pos = pos + noise * [1, 1, 0.5]
        offset, until = self._glitch
        if self._t_s < until:
            pos = pos + offset
        return pos

    def _send_message(self, msg_id: int) -> bool:
        """Send one message of the given id; False when this autopilot has no such message."""
        if not self._available(msg_id):
            return False
        if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            self._send_heartbeat()
        elif msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            self._send(self._mav.autopilot_version_encode(
                CAPABILITIES, 0x010E0000, 0, 0, 0, b"\x00" * 8, b"\x00" * 8, b"\x00" * 8, 0, 0,
                0x5157_0000 + self.config.system_id))
        elif msg_id in (mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
                        mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
                        mavlink.MAVLINK_MSG_ID_GPS_RAW_INT, mavlink.MAVLINK_MSG_ID_ODOMETRY,
                        mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS):
            self._send_position(msg_id)
        else:
            self._send_status(msg_id)
        return True

    def _send_position(self, msg_id: int) -> None:
        """The estimate's messages: before the GPS fix, no position (lat = lon = 0, no NED)."""
        t_ms = int(self._t_s * 1000) & 0xFFFFFFFF
        t_us = int(self._t_s * 1e6)
        v = self._vehicle
        m = self._mav
        fix = self._has_fix()
        h_sigma_m, v_sigma_m, att_sigma_rad, hdg_sigma_rad = self._accuracy()
        if msg_id == mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            heading = int(math.degrees(self._reported_attitude()[2]) % 360 * 100)
            if not fix:
                self._send(m.global_position_int_encode(t_ms, 0, 0, 0, 0, 0, 0, 0, heading))
                return
            lat, lon, alt = (float(a) for a in self.geo.ned_to_geodetic(*self._reported_ned()))
            home_alt = float(self.geo.ned_to_geodetic(*self._home)[2])
            self._send(m.global_position_int_encode(
                t_ms, int(lat * 1e7), int(lon * 1e7), int(alt * 1000),
                int((alt - home_alt) * 1000), *(int(c * 100) for c in v.velocity_ned), heading))
        elif msg_id == mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            if fix:
                pos = self._reported_ned() - self._local_origin
                self._send(m.local_position_ned_encode(t_ms, *pos, *v.velocity_ned))
        elif msg_id == mavlink.MAVLINK_MSG_ID_GPS_RAW_INT:
            if not fix:
                self._send(m.gps_raw_int_encode(
                    t_us, mavlink.GPS_FIX_TYPE_NO_FIX, 0, 0, 0, UINT16_UNKNOWN, UINT16_UNKNOWN,
                    0, UINT16_UNKNOWN, 0))
                return
            pos = self._reported_ned(with_bias=False)
            lat, lon, alt = (float(a) for a in self.geo.ned_to_geodetic(*pos))
            speed = float(np.hypot(*v.velocity_ned[:2]))
            cog = int(math.degrees(math.atan2(v.velocity_ned[1], v.velocity_ned[0])) % 360 * 100)
            self._send(m.gps_raw_int_encode(
                t_us, mavlink.GPS_FIX_TYPE_3D_FIX, int(lat * 1e7), int(lon * 1e7),
                int(alt * 1000), 80, 120, int(speed * 100), cog, 14,
                h_acc=round(h_sigma_m * 1000), v_acc=round(v_sigma_m * 1000)))
        elif msg_id == mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS:
            flags = ESTIMATOR_FLAGS_FIX if fix else ESTIMATOR_FLAGS_NO_FIX
            if self.config.rangefinder:
                flags |= mavlink.ESTIMATOR_POS_VERT_AGL
            self._send(m.estimator_status_encode(
                t_us, flags, 0.1, 0.1 if fix else 0.0, 0.1, 0.05,
                0.1 if self.config.rangefinder else 0.0, 0.0,
                h_sigma_m if fix else NO_FIX_ACCURACY_M, v_sigma_m))
        elif msg_id == mavlink.MAVLINK_MSG_ID_ODOMETRY and fix:
            pos = self._reported_ned(rng=self._odometry_rng) - self._local_origin
            roll, pitch, yaw = self._reported_attitude()
            q = quaternion_from_euler(roll, pitch, yaw)
            pose_cov = [0.0] * 21  # upper-right triangle of x, y, z, roll, pitch, yaw
            for index, sigma in zip(
                    (0, 6, 11, 15, 18, 20),
                    (h_sigma_m, h_sigma_m, v_sigma_m, att_sigma_rad, att_sigma_rad,
                     hdg_sigma_rad), strict=True):
                pose_cov[index] = sigma * sigma
            velocity_cov = [math.nan] + [0.0] * 20  # NaN first: not known
            velocity_body = _body_from_ned(q, v.velocity_ned)  # in the child frame, FRD
            self._send(m.odometry_encode(
                t_us, mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_FRD, *pos, q,
                *velocity_body, 0.0, 0.0, 0.0, pose_cov, velocity_cov, 0,
                mavlink.MAV_ESTIMATOR_TYPE_GPS_INS, 0))

    def _send_status(self, msg_id: int) -> None:
        """The messages that are not the position estimate."""
        t_ms = int(self._t_s * 1000) & 0xFFFFFFFF
        v = self._vehicle
        m = self._mav
        if msg_id == mavlink.MAVLINK_MSG_ID_SYS_STATUS:
            present = SENSORS | mavlink.MAV_SYS_STATUS_PREARM_CHECK
            health = SENSORS if self._has_fix() else SENSORS & ~mavlink.MAV_SYS_STATUS_SENSOR_GPS
            if self._arm_refusal() is None or self._armed:
                health |= mavlink.MAV_SYS_STATUS_PREARM_CHECK
            pct = self._battery_percent()
            self._send(m.sys_status_encode(
                present, present, health, 250, int(14800 + 2000 * pct / 100),
                1200 if self._armed else 50, int(pct), 0, 0, 0, 0, 0, 0))
        elif msg_id in (mavlink.MAVLINK_MSG_ID_ATTITUDE,
                        mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION):
            roll, pitch, yaw = self._reported_attitude()
            if msg_id == mavlink.MAVLINK_MSG_ID_ATTITUDE:
                self._send(m.attitude_encode(t_ms, roll, pitch, yaw, 0.0, 0.0, 0.0))
            else:
                w, x, y, z = quaternion_from_euler(roll, pitch, yaw)
                self._send(m.attitude_quaternion_encode(t_ms, w, x, y, z, 0.0, 0.0, 0.0))
        elif msg_id == mavlink.MAVLINK_MSG_ID_HOME_POSITION:
            lat, lon, alt = (float(a) for a in self.geo.ned_to_geodetic(*self._home))
            local = self._home - self._local_origin
            self._send(m.home_position_encode(
                int(lat * 1e7), int(lon * 1e7), int(alt * 1000), *local, [1.0, 0.0, 0.0, 0.0],
                0.0, 0.0, 0.0, int(self._t_s * 1e6)))
        elif msg_id == mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            self._send(m.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_UNDEFINED,
                                                   self._landed_state()))
        elif msg_id == mavlink.MAVLINK_MSG_ID_BATTERY_STATUS:
            pct = self._battery_percent()
            cells = [int(3700 + 500 * pct / 100)] * 4 + [65535] * 6
            self._send(m.battery_status_encode(
                0, mavlink.MAV_BATTERY_FUNCTION_ALL, mavlink.MAV_BATTERY_TYPE_LIPO, 2500, cells,
                1200 if self._armed else 50, -1, -1, int(pct)))
        elif msg_id == mavlink.MAVLINK_MSG_ID_VFR_HUD:
            alt = float(self.geo.ned_to_geodetic(*self._reported_ned())[2])
            speed = float(np.hypot(*v.velocity_ned[:2]))
            heading = int(math.degrees(self._reported_attitude()[2]) % 360)
            self._send(m.vfr_hud_encode(speed, speed, heading, 50 if self._armed else 0, alt,
                                        -float(v.velocity_ned[2])))
        elif msg_id == mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR:
            self._send_distance(t_ms)

    def _landed_state(self) -> int:
        """EXTENDED_SYS_STATE.landed_state: in the air once IN_AIR_HEIGHT_M up; PX4 says
        TAKEOFF from the take-off command on, even while still on the ground."""
        if self._behaviour is Behaviour.TAKEOFF and self._armed:
            return int(mavlink.MAV_LANDED_STATE_TAKEOFF)
        if not self._airborne:
            return int(mavlink.MAV_LANDED_STATE_ON_GROUND)
        if self._behaviour is Behaviour.LAND:
            return int(mavlink.MAV_LANDED_STATE_LANDING)
        return int(mavlink.MAV_LANDED_STATE_IN_AIR)

    def _send_distance(self, t_ms: int) -> None:
        """DISTANCE_SENSOR of the downward rangefinder: the slant range to the flat ground
        (z = 0) along the body's down axis, with noise; beyond its range, max + 1 cm."""
        v = self._vehicle
        roll, pitch = v.roll_pitch_rad()
        height_m = max(-float(v.position_ned[2]), 0.0)
        range_m = height_m / max(math.cos(roll) * math.cos(pitch), 1e-3)
        range_m += float(self._rangefinder_rng.normal(0.0, RANGEFINDER_NOISE_M))
        max_cm = round(self.config.rangefinder_max_m * 100)
        in_range = range_m <= self.config.rangefinder_max_m
        current_cm = min(max(round(range_m * 100), 0), max_cm) if in_range else max_cm + 1
        self._send(self._mav.distance_sensor_encode(
            t_ms, round(RANGEFINDER_MIN_M * 100), max_cm, current_cm,
            mavlink.MAV_DISTANCE_SENSOR_LASER, 0, mavlink.MAV_SENSOR_ROTATION_PITCH_270,
            round((RANGEFINDER_NOISE_M * 100) ** 2), signal_quality=100 if in_range else 1))


def _body_from_ned(q_wxyz: tuple[float, float, float, float], vector_ned: FloatArray
                   ) -> tuple[float, float, float]:
    """A NED vector in the body frame FRD of the attitude q (body to NED, scalar first)."""
    w, x, y, z = q_wxyz
    rotation = np.array([  # body to NED
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])
    body = rotation.T @ np.asarray(vector_ned, dtype=np.float64)
    return float(body[0]), float(body[1]), float(body[2])
