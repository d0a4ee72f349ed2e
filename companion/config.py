"""The service's configuration file (TOML), validated in full before anything starts.

Every key is declared once in `SECTIONS` (kind and range, default, one-line doc), as the scenario
keys are. `load_config` returns a frozen `ServiceConfig` or raises `ConfigError` naming the bad
key and the reason (`AggregateConfigError`, one line per key, when several are bad).
`companion check-config FILE` and `companion run` use it, and `docs/configuration.md` is
generated from the declarations (`python -m companion.config --markdown`).
"""

from __future__ import annotations

import argparse
import copy
import ipaddress
import json
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from companion.errors import ConfigError, ErrorCollector, InputError
from companion.geo import LocalNed, Utm, utm_zone_for
from companion.keys import (
    REQUIRED,
    Bool,
    Choice,
    Derived,
    Float,
    Floats,
    Int,
    Ints,
    Key,
    PathText,
    Points,
    Text,
    load_toml,
    markdown_rows,
    read_table,
    section_table,
    unknown_key,
)
from companion.plan.gate import GateLimits
from companion.plan.keep_in import clearance_m as clearance_m_at
from companion.plan.planners import PlannerKind
from companion.sat.params import FILTER_KEYS, FilterSpec, FovKind

__all__ = ["ServiceConfig", "load_config", "parse_config", "schema_markdown"]

FloatArray = NDArray[np.float64]
FAMILIES = ("tag36h11", "tag25h9", "tag16h5", "tagCircle21h7", "tagCircle49h12",
            "tagStandard41h12", "tagStandard52h13", "tagCustom48h12")
_ANGLE = Float(ge=-180.0, le=180.0)
_OFFSET = Float(ge=-10.0, le=10.0)
_LAT_LON = "array of [lat, lon] (WGS84 degrees)"


@dataclass(frozen=True, slots=True)
class VehicleConfig:
    """How to reach the autopilot."""

    connection: str
    connect_timeout_s: float
    telemetry_rate_hz: float
    signing_key_file: str | None


@dataclass(frozen=True, slots=True)
class CameraConfig:
    """The camera: where frames come from, its intrinsics and how it is mounted."""

    source: str
    kind: Literal["auto", "opencv", "mjpeg"]
    calibration: str | None
    width_px: int
    height_px: int
    hfov_deg: float
    mount_rpy_deg: tuple[float, float, float]
    mount_offset_m: tuple[float, float, float]
    latency_s: float


@dataclass(frozen=True, slots=True)
class DetectorConfig:
    """pupil-apriltags' settings and which detections to keep."""

    family: str
    decimate: float
    threads: int
    min_decision_margin: float
    allowed_ids: tuple[int, ...]
    pixel_std_px: float


@dataclass(frozen=True, slots=True)
class PoseConfig:
    """How much to trust the autopilot's pose (propagated into each measurement's covariance)."""

    horizontal_std_m: float
    vertical_std_m: float
    attitude_std_deg: float
    heading_std_deg: float
    camera_rest_height_m: float
    max_gap_s: float
    glitch_gate_m: float
    glitch_accept_after_s: float


@dataclass(frozen=True, slots=True)
class EstimatorConfig:
    """When and how the GM-PHD steps."""

    rate_hz: float
    p_detect: float
    clutter_per_scan: float
    fov: FovKind  # CAMERA or DISK
    fov_radius_m: float
    footprint_margin_m: float
    max_range_m: float


@dataclass(frozen=True, slots=True)
class SearchConfig:
    """Where to search and how to fly over it."""

    area_latlon: FloatArray  # (k, 2) [lat, lon] polygon
    utm_epsg: int
    altitude_m: float  # above home
    speed_m_s: float
    planner: PlannerKind
    lane_spacing_m: float
    sweeps: int
    heading_deg: float
    expected_targets: int | None
    stop_when_left: float  # search-track: the search ends below this many targets left to find


@dataclass(frozen=True, slots=True)
class SafetyConfig:
    """The gate every setpoint passes."""

    geofence_latlon: FloatArray  # (k, 2) [lat, lon] polygon
    min_alt_m: float
    max_alt_m: float
    max_speed_h_m_s: float
    max_speed_v_m_s: float
    fence_clearance_m: float = 3.0


@dataclass(frozen=True, slots=True)
class MissionConfig:
    """What the service may do by itself, and when the mission ends."""

    auto_arm_takeoff: bool
    auto_offboard: bool
    arm_retry_s: float
    offboard_retry_s: float
    resume_on_pilot_offboard: bool
    end: Literal["covered", "targets", "time"]
    time_limit_s: float
    end_action: Literal["hold", "land", "rtl"]
    setpoint_rate_hz: float


@dataclass(frozen=True, slots=True)
class OutputConfig:
    """Where the run's reports go, and how much disk they may take."""

    dir: str
    plots: bool
    frames: Literal["off", "jpg", "png"]
    frames_budget_mb: float
    jpeg_quality: int
    max_runs_mb: float
    min_free_mb: float


@dataclass(frozen=True, slots=True)
class ViewConfig:
    """The operator's read-only web page: where it listens and who may read it."""

    enabled: bool
    bind: str
    port: int
    token_file: str | None
    max_clients: int
    orthophoto: str | None


@dataclass(frozen=True, slots=True)
class ServiceConfig:
    """The whole configuration."""

    vehicle: VehicleConfig
    camera: CameraConfig
    detector: DetectorConfig
    pose: PoseConfig
    estimator: EstimatorConfig
    filter: FilterSpec
    search: SearchConfig
    safety: SafetyConfig
    mission: MissionConfig
    output: OutputConfig
    view: ViewConfig
    data: Mapping[str, Any] = field(default_factory=dict, compare=False, repr=False)  # as read


SECTIONS: dict[str, tuple[Key, ...]] = {
    "vehicle": (
        Key("connection", Text(), "udpin://127.0.0.1:14540",
            "MAVSDK connection URL: udpin://HOST:PORT, tcpout://HOST:PORT, "
            "serial:///dev/ttyAMA0:921600"),
        Key("connect_timeout_s", Float(gt=0), 30.0,
            "seconds to wait for the autopilot's heartbeat"),
        Key("telemetry_rate_hz", Float(gt=0, le=200), 20.0,
            "rate asked for position and attitude (an ArduPilot sends nothing unasked)"),
        Key("signing_key_file", Text(), Derived("none: unsigned MAVLink"),
            "MAVLink 2 signing key (64 hex digits, mode 0600): the link to the autopilot goes "
            "through a signing relay (docs/signing.md)"),
    ),
    "camera": (
        Key("source", Text(), REQUIRED,
            "what cv2.VideoCapture opens (device index, /dev/videoN, GStreamer pipeline, "
            "rtsp:// or http:// URL, video file) or the SITL's MJPEG URL"),
        Key("kind", Choice("auto", "opencv", "mjpeg"), "auto",
            "how to read the source; auto: mjpeg for .../stream.mjpg URLs, else OpenCV"),
        Key("calibration", Text(), Derived("none: width_px, height_px, hfov_deg"),
            "OpenCV calibration file (YAML/XML: image_width, image_height, camera_matrix, "
            "distortion_coefficients); relative to this file"),
        Key("width_px", Int(ge=16), 640, "image width without a calibration file"),
        Key("height_px", Int(ge=16), 480, "image height without a calibration file"),
        Key("hfov_deg", Float(ge=1, le=170), 90.0,
            "horizontal field of view without a calibration file (no distortion)"),
        Key("mount_rpy_deg", Floats("[roll, pitch, yaw]", _ANGLE, _ANGLE, _ANGLE),
            [0.0, 0.0, 0.0], "mounting relative to straight down, top of the image forward"),
        Key("mount_offset_m",
            Floats("[forward, right, down]", _OFFSET, _OFFSET, _OFFSET), [0.0, 0.0, 0.0],
            "camera centre in the body frame, metres"),
        Key("latency_s", Float(ge=0, le=5), 0.0,
            "exposure-to-receipt delay of a source without capture times"),
    ),
    "detector": (
        Key("family", Choice(*FAMILIES), "tag36h11", "AprilTag family"),
        Key("decimate", Float(ge=1, le=8), 1.0,
            "quad_decimate: faster, but small tags are lost (see docs/sitl.md)"),
        Key("threads", Int(ge=1), 2, "detector threads"),
        Key("min_decision_margin", Float(ge=0), 20.0,
            "detections with a lower decision margin are dropped"),
        Key("allowed_ids", Ints(ge=0), [],
            "keep only these tag ids (empty: all); ids never reach the estimator"),
        Key("pixel_std_px", Float(gt=0, le=50), 1.0,
            "standard deviation of a detected tag centre, pixels"),
    ),
    "pose": (
        Key("horizontal_std_m", Float(ge=0, le=100), 0.5,
            "least standard deviation of the horizontal position: the autopilot's own figure "
            "(ODOMETRY, ESTIMATOR_STATUS or GPS_RAW_INT) is used when larger"),
        Key("vertical_std_m", Float(ge=0, le=100), 0.3,
            "least standard deviation of the height above the ground (same sources)"),
        Key("attitude_std_deg", Float(ge=0, le=30), 1.0,
            "least standard deviation of roll and pitch (ODOMETRY's, when larger)"),
        Key("heading_std_deg", Float(ge=0, le=90), 2.0,
            "least standard deviation of the heading (ODOMETRY's, when larger)"),
        Key("camera_rest_height_m", Float(ge=-5, le=5), 0.0,
            "the camera's height above ground with the vehicle at rest, added to the relative "
            "altitude (zero at rest) when no rangefinder or terrain height is known"),
        Key("max_gap_s", Float(gt=0, le=10), 0.5,
            "a frame whose capture time falls in a longer gap of telemetry has no pose"),
        Key("glitch_gate_m", Float(gt=0, le=1000), 8.0,
            "a position further than this from where the velocity puts it is a GPS glitch: "
            "refused, and frames taken then are blind"),
        Key("glitch_accept_after_s", Float(gt=0, le=600), 10.0,
            "a jump that lasts this long is believed (the estimate was reset)"),
    ),
    "estimator": (
        Key("rate_hz", Float(gt=0, le=30), 2.0,
            "estimator steps per second, each on the newest frame (the others are dropped)"),
        Key("p_detect", Float(ge=0, le=1), 0.95, "p(D | in the footprint)"),
        Key("clutter_per_scan", Float(ge=0), 0.1,
            "expected false detections per step"),
        Key("fov", Choice(FovKind.CAMERA, FovKind.DISK), "camera",
            "sensing region: the camera footprint this frame covered, or the paper's disk"),
        Key("fov_radius_m", Float(gt=0), 6.0, "disk radius for fov = \"disk\""),
        Key("footprint_margin_m", Float(ge=0, le=10), 0.5,
            "the footprint shrunk by this much: a tag cut by the image edge is not detected "
            "(a 0.5 m tag printed with its quiet zone reaches 0.44 m from its centre)"),
        Key("max_range_m", Float(gt=0), 100.0,
            "ground points farther than this from the vehicle are out of the footprint"),
    ),
    "filter": FILTER_KEYS,
    "search": (
        Key("area", Points(_LAT_LON), REQUIRED,
            "the search area polygon; the lawn mower covers its bounding box, within the geofence "
            "(safety.fence_clearance_m)", field="area_latlon"),
        Key("utm_epsg", Int(ge=0), Derived("the UTM zone of the area's centre"),
            "EPSG code of the UTM zone for the whole flight (326xx north, 327xx south)"),
        Key("altitude_m", Float(gt=0, le=500), 8.0, "search altitude above home"),
        Key("speed_m_s", Float(gt=0, le=30), 1.0, "search speed"),
        Key("planner", Choice(*PlannerKind),
            "lawnmower", "path planner"),
        Key("lane_spacing_m", Float(gt=0), 8.0, "lawn-mower lane spacing"),
        Key("sweeps", Int(ge=1), 1, "lawn-mower passes over the area"),
        Key("heading_deg", _ANGLE, 0.0, "yaw held while searching"),
        Key("expected_targets", Int(ge=1), Derived("unknown"),
            "targets to confirm before mission.end = \"targets\" ends the mission"),
        Key("stop_when_left", Float(ge=0), 0.05,
            "search-track planner: its search ends (mission.end = \"covered\") once fewer "
            "targets than this are expected left to find; it expects expected_targets (or 1) "
            "spread over the area at the start"),
    ),
    "safety": (
        Key("geofence", Points(_LAT_LON), Derived("the search area"),
            "no setpoint leaves this polygon", field="geofence_latlon"),
        Key("min_alt_m", Float(gt=0), 2.0, "lowest setpoint above home"),
        Key("max_alt_m", Float(gt=0), 30.0, "highest setpoint above home"),
        Key("max_speed_h_m_s", Float(gt=0, le=30), 3.0,
            "setpoints move at most this fast horizontally"),
        Key("max_speed_v_m_s", Float(gt=0, le=10), 1.0,
            "setpoints move at most this fast vertically"),
        Key("fence_clearance_m", Float(ge=0, le=100), 3.0,
            "the planner keeps its path this far inside the geofence (a vehicle overshoots a "
            "lane's end; its position wanders), so that the gate need not move a setpoint"),
    ),
    "mission": (
        Key("auto_arm_takeoff", Bool(), False,
            "arm and take off by itself (default: the pilot does)"),
        Key("auto_offboard", Bool(), False,
            "enter OFFBOARD by itself once, when ready (default: the pilot selects it)"),
        Key("arm_retry_s", Float(gt=0, le=600), 20.0,
            "an arm the autopilot refuses is asked again every 2 s for this long"),
        Key("offboard_retry_s", Float(gt=0, le=600), 20.0,
            "an OFFBOARD request the autopilot refuses or never answers is asked again every "
            "2 s for this long, unless the mode changes meanwhile"),
        Key("resume_on_pilot_offboard", Bool(), True,
            "after a pilot takeover, resume when the pilot selects OFFBOARD again"),
        Key("end", Choice("covered", "targets", "time"), "covered",
            "the mission ends when the lawn mower is done, expected targets are confirmed, or "
            "at the time limit (the time limit always applies)"),
        Key("time_limit_s", Float(gt=0), 900.0, "longest search"),
        Key("end_action", Choice("hold", "land", "rtl"), "land",
            "what to ask the autopilot at the end"),
        Key("setpoint_rate_hz", Float(gt=2, le=50), 10.0,
            "setpoint stream rate (PX4 needs more than 2 Hz)"),
    ),
    "output": (
        Key("dir", Text(), "runs", "folder for the run's reports; relative to this file"),
        Key("plots", Bool(), True, "write the study's plots at the end"),
        Key("frames", Choice("off", "jpg", "png"), "off",
            "keep each processed frame as an image (png: lossless, replay re-detects exactly)"),
        Key("frames_budget_mb", Float(gt=0), 500.0,
            "disk for one run's frames; past it only detections are kept, with a log line"),
        Key("jpeg_quality", Int(ge=1, le=100), 90, "JPEG quality of kept frames"),
        Key("max_runs_mb", Float(gt=0), 5000.0,
            "all run folders together; the oldest are removed at start to stay under it"),
        Key("min_free_mb", Float(ge=0), 500.0,
            "free disk to leave: old runs are removed at start, frames stop below it"),
    ),
    "view": (
        Key("enabled", Bool(), True,
            "serve the operator's read-only web page (map, estimate, targets) while flying"),
        Key("bind", Text(), "127.0.0.1",
            "address the page listens on; any other than a loopback one needs view.token_file"),
        Key("port", Int(ge=0, le=65535), 8090, "TCP port of the page (0: any free port)"),
        Key("token_file", Text(), Derived("none: no token (loopback only)"),
            "file holding the access token the page and its stream require (mode 600)"),
        Key("max_clients", Int(ge=1, le=64), 8,
            "browsers connected at once; more are refused"),
        Key("orthophoto", PathText(), Derived("none: no background image"),
            "the operator's orthophoto under the map, a GeoTIFF (.tif, .tiff) or MBTiles "
            "(.mbtiles) file; relative to this file; empty: none (docs/view.md)"),
    ),
}


def _latlon_polygon(key: str, points: FloatArray) -> FloatArray:
    if points.shape[0] < 3:
        raise ConfigError(key, f"must have at least 3 [lat, lon] vertices, got {points.shape[0]}")
    if not (np.all(np.abs(points[:, 0]) <= 90.0) and np.all(np.abs(points[:, 1]) <= 180.0)):
        raise ConfigError(key, "latitudes must be in [-90, 90] and longitudes in [-180, 180]; "
                               "write [lat, lon] pairs")
    return points


def _geofence_shape(fence_latlon: FloatArray, clearance_m: float) -> None:
    """ConfigError naming safety.geofence unless the safety gate accepts its shape (simple,
    with an area), and naming safety.fence_clearance_m unless some point of the fence keeps it;
    checked in the local plane at its first vertex."""
    lat0, lon0 = (float(v) for v in fence_latlon[0])
    north, east, _ = LocalNed(lat0, lon0, 0.0).geodetic_to_ned(
        fence_latlon[:, 0], fence_latlon[:, 1], 0.0)
    fence_ne = np.column_stack([north, east])
    try:
        GateLimits(fence_ne, 1.0, 2.0, 1.0, 1.0)
    except InputError as exc:
        raise ConfigError("safety.geofence", exc.reason) from exc
    # The most clearance on a 60 x 60 grid, give or take half the grid's diagonal.
    low, high = fence_ne.min(axis=0), fence_ne.max(axis=0)
    axes = [np.linspace(a, b, 60) for a, b in zip(low, high, strict=True)]
    grid = np.stack(np.meshgrid(*axes), axis=-1).reshape(-1, 2)
    slack_m = float(np.hypot(*(high - low))) / 59.0 / 2.0
    widest_m = float(clearance_m_at(grid, fence_ne).max())
    if widest_m + slack_m < clearance_m:
        raise ConfigError("safety.fence_clearance_m",
                          f"{clearance_m:g} m: no point of safety.geofence is that far inside it "
                          f"(at most about {widest_m:.1f} m); the plan would have nowhere to fly")


def _relative(base: Path | None, path: str) -> str:
    p = Path(path)
    return str(p if p.is_absolute() or base is None else base / p)


def _utm_epsg(key: str, epsg: int) -> int:
    """epsg after checking that it is a WGS84 / UTM zone; the core's reason under our key."""
    try:
        Utm(epsg)
    except InputError as exc:
        raise ConfigError(key, exc.reason) from exc
    return epsg


def _search(search: dict[str, Any]) -> dict[str, Any]:
    """[search] with its area checked and its UTM zone derived (when not given) and checked."""
    area = _latlon_polygon("search.area", search["area_latlon"])
    if search["utm_epsg"] is None:
        lat, lon = area.mean(axis=0)
        search["utm_epsg"] = utm_zone_for(float(lat), float(lon))
    _utm_epsg("search.utm_epsg", search["utm_epsg"])
    return search


def _safety(safety: dict[str, Any], area: FloatArray | None) -> dict[str, Any]:
    """[safety] with its geofence (the search area by default) and altitude band checked."""
    if safety["geofence_latlon"] is None:
        if area is None:  # the search area is wrong: reported as such
            return safety
        safety["geofence_latlon"] = area
    _geofence_shape(_latlon_polygon("safety.geofence", safety["geofence_latlon"]),
                    safety["fence_clearance_m"])
    low_m, high_m = safety["min_alt_m"], safety["max_alt_m"]
    if low_m >= high_m:
        raise ConfigError("safety.max_alt_m",
                          f"must be above safety.min_alt_m ({low_m!r}), got {high_m!r}")
    return safety


def _cross_sections(t: dict[str, dict[str, Any]], errors: ErrorCollector) -> None:
    """The rules across sections, each checked when the sections it reads are sound."""
    search, safety, mission = t.get("search"), t.get("safety"), t.get("mission")
    if search is not None and safety is not None:
        low_m, high_m = safety["min_alt_m"], safety["max_alt_m"]
        if not low_m <= search["altitude_m"] <= high_m:
            errors.add(ConfigError("search.altitude_m", f"must lie in the safety band [{low_m!r}, "
                                   f"{high_m!r}], got {search['altitude_m']!r}"))
    view = t.get("view")
    if view is not None and view["enabled"] and view["token_file"] is None:
        try:
            loopback = ipaddress.ip_address(view["bind"]).is_loopback
        except ValueError:
            loopback = view["bind"] == "localhost"
        if not loopback:
            errors.add(ConfigError("view.token_file", "is required when view.bind "
                                   f"({view['bind']!r}) is not a loopback address"))
    if (search is not None and mission is not None and mission["end"] == "targets"
            and search["expected_targets"] is None):
        errors.add(ConfigError("search.expected_targets",
                               "is required when mission.end = \"targets\""))


def _relative_paths(t: dict[str, dict[str, Any]], base: Path | None) -> None:
    """The file names of the configuration made relative to its folder."""
    if "view" in t and t["view"]["orthophoto"] == "":
        t["view"]["orthophoto"] = None  # empty: no orthophoto
    for section, leaf in (("camera", "calibration"), ("output", "dir"),
                          ("vehicle", "signing_key_file"), ("view", "token_file"),
                          ("view", "orthophoto")):
        if section in t and t[section][leaf] is not None:
            t[section][leaf] = _relative(base, t[section][leaf])


def parse_config(data: Mapping[str, Any], base: Path | None = None) -> ServiceConfig:
    """The ServiceConfig of TOML data (relative paths against base); ConfigError names a bad key,
    AggregateConfigError lists every bad key when there are several."""
    if not isinstance(data, Mapping):
        raise ConfigError("config", "must be a table of sections")
    errors = ErrorCollector()
    for section in data:
        if section not in SECTIONS:
            errors.add(unknown_key(str(section), str(section), list(SECTIONS)))
    tables: dict[str, dict[str, Any]] = {}
    for section, keys in SECTIONS.items():
        read = errors.attempt(partial(_read_section, data, section, keys))
        if read is not None:
            tables[section] = read
    if "search" in tables and errors.attempt(partial(_search, tables["search"])) is None:
        del tables["search"]
    area = tables["search"]["area_latlon"] if "search" in tables else None
    if "safety" in tables and errors.attempt(partial(_safety, tables["safety"], area)) is None:
        del tables["safety"]
    _cross_sections(tables, errors)
    errors.raise_any()
    _relative_paths(tables, base)
    return ServiceConfig(
        vehicle=VehicleConfig(**tables["vehicle"]),
        camera=CameraConfig(**tables["camera"]),
        detector=DetectorConfig(**tables["detector"]),
        pose=PoseConfig(**tables["pose"]),
        estimator=EstimatorConfig(**tables["estimator"]),
        filter=FilterSpec(**tables["filter"]),
        search=SearchConfig(**tables["search"]),
        safety=SafetyConfig(**tables["safety"]),
        mission=MissionConfig(**tables["mission"]),
        output=OutputConfig(**tables["output"]),
        view=ViewConfig(**tables["view"]),
        data=copy.deepcopy(dict(data)),
    )


def _read_section(data: Mapping[str, Any], section: str, keys: Sequence[Key]) -> dict[str, Any]:
    """One section's checked values (field name -> value)."""
    return read_table(section_table(data, section), section, keys)


def load_config(path: str | Path) -> ServiceConfig:
    """The configuration in a TOML file, or the same tables as JSON (a run folder's
    config.json); ConfigError names the file or the bad key."""
    p = Path(path)
    if p.suffix.lower() != ".json":
        return parse_config(load_toml(p, "configuration"), base=p.parent)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        raise ConfigError(str(p), "no such configuration file") from exc
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(str(p), f"not a JSON configuration: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(str(p), "not a JSON configuration: not an object of tables")
    return parse_config(data, base=p.parent)


def schema_markdown() -> str:
    """The configuration reference (docs/configuration.md), generated from the declarations."""
    lines = [
        "# Service configuration keys",
        "",
        "<!-- Generated by `python -m companion.config --markdown > docs/configuration.md`;",
        "     edit the declarations in companion/config.py, not this file. -->",
        "",
        "One TOML file configures `companion run` (`companion check-config FILE` checks it).",
        "Every key is optional unless its default says required; an unknown key, a wrong type or",
        "an out-of-range value stops the start with a message naming the key (exit status 2);",
        "every such error of the file is listed at once, one `key: reason` line each.",
        "Examples: `systemd/companion.toml` (a real vehicle), `sitl/service.toml` (the SITL).",
        "The `[filter]` table has the same keys as a scenario's (`docs/scenario.md`).",
    ]
    for section, keys in SECTIONS.items():
        if section == "filter":
            continue
        lines += ["", f"## `[{section}]`", "", *markdown_rows(section, keys)]
    lines += ["", "Cross-key rules: `safety.min_alt_m` < `safety.max_alt_m`; `search.altitude_m` "
              "inside that band; `mission.end = \"targets\"` needs `search.expected_targets`; "
              "`view.bind` other than a loopback address needs `view.token_file`; "
              "polygons need at least 3 [lat, lon] vertices.", ""]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m companion.config --markdown` prints the key reference."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--markdown", action="store_true", help="print the key reference")
    args = parser.parse_args(argv)
    if args.markdown:
        sys.stdout.write(schema_markdown())
    return 0


if __name__ == "__main__":
    sys.exit(main())

