"""Scenario files (TOML) read into frozen, validated specs; the contract is scenario-format.md.

Every key is declared once in companion.sim.scenario_keys (TOML name, value kind with its range,
default, one-line doc; the dataclass field is the name unless declared), and parsing here,
`scenario_to_dict` and the key reference `docs/scenario.md` (`python -m companion.sim.scenario
--markdown`, written by companion.sim.scenario_doc) are all driven by those declarations. The
specs are in companion.sim.specs, footprint geometry in companion.sim.footprint. Rules that tie
several keys together live in the section builders below (`_targets`, `_sensor`, ...) and are
listed in `CROSS_KEY_RULES` for the reference. Every error of a file is reported at once.

Defaults reproduce the paper's set-up: ten stationary targets in a 150 m x 150 m world, a 25 m disk
FOV, 10 % clutter, three lawn-mower sweeps at 0.5 m/s, an exact initial belief. Coordinates are
metres in a local frame whose origin is the world's lower-left corner, x east, y north.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from companion.errors import ConfigError, ErrorCollector, InputError
from companion.geo import Utm, utm_zone_for
from companion.keys import (
    Int,
    Text,
    describe,
    dump_table,
    frozen_rows,
    load_toml,
    read_table,
    section_table,
    toml_text,
    unknown_key,
)
from companion.sat.params import FilterSpec
from companion.sim.footprint import camera_footprint_xy, convex_ccw
from companion.sim.scenario_doc import schema_markdown
from companion.sim.scenario_keys import COMPONENT_KEYS, DEFAULT_TARGET_COUNT, SECTION_KEYS, TOP_KEYS
from companion.sim.specs import (
    BeliefComponent,
    BeliefSpec,
    GeoSpec,
    MetricsSpec,
    RobotSpec,
    Scenario,
    SensorSpec,
    TargetsSpec,
    VehicleSpec,
    WorldSpec,
)
from companion.vision.camera import CameraModel

__all__ = [
    "BeliefComponent",
    "BeliefSpec",
    "GeoSpec",
    "MetricsSpec",
    "RobotSpec",
    "Scenario",
    "SensorSpec",
    "TargetsSpec",
    "VehicleSpec",
    "WorldSpec",
    "camera_footprint_xy",
    "load_scenario",
    "parse_scenario",
    "scenario_to_dict",
    "schema_markdown",
]

FloatArray = NDArray[np.float64]
T = TypeVar("T")




def _check_inside(key: str, x: float, y: float, world: WorldSpec, what: str = "") -> None:
    sx, sy = world.size_m
    if not (0.0 <= x <= sx and 0.0 <= y <= sy):
        raise ConfigError(
            key,
            f"{what}must be inside the world, 0 <= x <= {sx!r} and 0 <= y <= {sy!r}, "
            f"got {toml_text([x, y])}",
        )


def _targets(v: dict[str, Any], world: WorldSpec) -> TargetsSpec:
    positions: FloatArray = v["positions_xy"]
    n_given = positions.shape[0]
    if v["count"] is None:
        v["count"] = n_given if n_given else DEFAULT_TARGET_COUNT
    elif n_given and v["count"] != n_given:
        raise ConfigError(
            "targets.count",
            f"must equal the number of targets.positions ({n_given}) or be omitted, "
            f"got {v['count']}",
        )
    for i, (x, y) in enumerate(positions):
        _check_inside(f"targets.positions[{i}]", float(x), float(y), world)
    for i, (_, x, y) in enumerate(v["appear"]):
        _check_inside(f"targets.appear[{i}]", x, y, world, what="[x, y] ")
    n_initial, n_total = v["count"], v["count"] + len(v["appear"])
    gone: dict[int, int] = {}
    for i, (step, index) in enumerate(v["disappear"]):
        if index >= n_total:
            raise ConfigError(
                f"targets.disappear[{i}][1]",
                f"must be a target index < {n_total} ({n_initial} initial + "
                f"{n_total - n_initial} appearing), got {index}",
            )
        if index in gone:
            raise ConfigError(
                f"targets.disappear[{i}][1]",
                f"target {index} already disappears in targets.disappear[{gone[index]}]",
            )
        gone[index] = i
        if index >= n_initial:
            appears = v["appear"][index - n_initial][0]
            if step < appears:
                raise ConfigError(
                    f"targets.disappear[{i}][0]",
                    f"must be >= {appears}, the step at which target {index} appears, got {step}",
                )
    return TargetsSpec(**v)


def _sensor(v: dict[str, Any], camera: CameraModel, vehicle: VehicleSpec) -> SensorSpec:
    polygon: FloatArray = v["fov_polygon_xy"]
    if v["fov"] == "camera":
        if polygon.shape[0]:
            raise ConfigError("sensor.fov_polygon",
                              'is only allowed when sensor.fov = "polygon", got fov "camera"')
        v["fov_polygon_xy"] = camera_footprint_xy(camera, vehicle.altitude_m, vehicle.heading_deg)
    elif v["fov"] == "polygon":
        if polygon.shape[0] == 0:
            raise ConfigError("sensor.fov_polygon", 'is required when sensor.fov = "polygon"')
        v["fov_polygon_xy"] = convex_ccw("sensor.fov_polygon", polygon)
    elif polygon.shape[0]:
        raise ConfigError(
            "sensor.fov_polygon",
            f'is only allowed when sensor.fov = "polygon", got fov {toml_text(v["fov"])}',
        )
    return SensorSpec(**v)


def _geo(v: dict[str, Any], world: WorldSpec) -> GeoSpec:
    if v["utm_epsg"] is None:
        lat, lon, _ = GeoSpec(v["origin"], 0).local_ned().ned_to_geodetic(
            world.size_m[1] / 2.0, world.size_m[0] / 2.0, 0.0)
        try:
            v["utm_epsg"] = utm_zone_for(float(lat), float(lon))
        except InputError as exc:  # the world's centre is off the Earth's coordinates
            raise ConfigError("geo.origin", f"the world's centre: {exc.reason}") from exc
    try:
        Utm(v["utm_epsg"])
    except InputError as exc:
        raise ConfigError("geo.utm_epsg", exc.reason) from exc
    return GeoSpec(**v)


def _camera(v: dict[str, Any]) -> CameraModel:
    hfov_deg = v.pop("hfov_deg")
    if hfov_deg is not None:
        if v["fx_px"] is not None or v["fy_px"] is not None:
            raise ConfigError("camera.hfov_deg", "give either hfov_deg or fx_px (and fy_px)")
        v["fx_px"] = 0.5 * v["width_px"] / math.tan(math.radians(0.5 * hfov_deg))
    if v["fy_px"] is None:
        v["fy_px"] = v["fx_px"]
    # Left at NaN, CameraModel derives them: a 90 degree FOV, the principal point at the centre.
    given: dict[str, Any] = {k: (math.nan if x is None else x) for k, x in v.items()}
    return CameraModel(**given)


def _robot(v: dict[str, Any], world: WorldSpec) -> RobotSpec:
    x, y = v["start_xy"]
    _check_inside("robot.start", x, y, world)
    return RobotSpec(**v)


def _belief(v: dict[str, Any], n_targets: int) -> BeliefSpec:
    if v["count"] is None:
        v["count"] = n_targets
    count = v["count"]
    rules = {"exact": ("equal", count == n_targets), "under": ("be <", count < n_targets),
             "over": ("be >", count > n_targets)}
    if v["kind"] in rules and not rules[v["kind"]][1]:
        raise ConfigError(
            "belief.count",
            f"must {rules[v['kind']][0]} the number of initial targets ({n_targets}) for "
            f"belief.kind = {toml_text(v['kind'])}, got {count}",
        )
    tables: tuple[Mapping[Any, Any], ...] = v["components"]
    if v["kind"] == "explicit" and not tables:
        raise ConfigError("belief.components", 'is required when belief.kind = "explicit"')
    if v["kind"] != "explicit" and tables:
        raise ConfigError(
            "belief.components",
            f'is only allowed when belief.kind = "explicit", got kind {toml_text(v["kind"])}',
        )
    components = []
    for i, table in enumerate(tables):
        c = read_table(table, f"belief.components[{i}]", COMPONENT_KEYS)
        if c["cov"] is None:
            c["cov"] = frozen_rows((np.eye(2) * v["variance_m2"]).tolist(), 2)
        components.append(BeliefComponent(**c))
    v["components"] = tuple(components)
    return BeliefSpec(**v)


def parse_scenario(data: Mapping[str, Any], name: str = "scenario") -> Scenario:
    """The Scenario described by TOML data (`name` when it has no name key); ConfigError if bad,
    AggregateConfigError listing every bad key when there are several."""
    if not isinstance(data, Mapping):
        raise ConfigError(name, f"must be a table of scenario keys, got {describe(data)}")
    errors = ErrorCollector()
    top_known = [k.leaf for k in TOP_KEYS] + list(SECTION_KEYS)
    for key in data:
        if key not in top_known:
            errors.add(unknown_key(str(key), str(key), top_known))

    def top_table() -> dict[str, Any]:
        top = read_table({k: data[k] for k in data if k in top_known and k not in SECTION_KEYS},
                         "", TOP_KEYS)
        if top["name"] is None:
            top["name"] = Text().parse("name", name)
        return top

    def read(section: str) -> dict[str, Any] | None:
        keys = SECTION_KEYS[section]
        return errors.attempt(lambda: read_table(section_table(data, section), section, keys))

    def build(make: Callable[..., T], values: dict[str, Any] | None, *needs: object) -> T | None:
        if values is None or any(n is None for n in needs):
            return None
        return errors.attempt(lambda: make(values, *needs))

    top = errors.attempt(top_table)
    world_v = read("world")
    world = None if world_v is None else WorldSpec(**world_v)
    targets = build(_targets, read("targets"), world)
    camera = build(_camera, read("camera"))
    vehicle_v = read("vehicle")
    vehicle = None if vehicle_v is None else VehicleSpec(**vehicle_v)
    sensor = build(_sensor, read("sensor"), camera, vehicle)
    robot = build(_robot, read("robot"), world)
    belief = build(_belief, read("belief"), None if targets is None else targets.count)
    filter_v, metrics_v = read("filter"), read("metrics")
    geo = build(_geo, read("geo"), world)
    errors.raise_any()
    assert top is not None and filter_v is not None and metrics_v is not None  # else raised
    return Scenario(
        **top,
        world=_sound(world),
        targets=_sound(targets),
        sensor=_sound(sensor),
        robot=_sound(robot),
        belief=_sound(belief),
        filter=FilterSpec(**filter_v),
        metrics=MetricsSpec(**metrics_v),
        geo=_sound(geo),
        camera=_sound(camera),
        vehicle=_sound(vehicle),
    )


def _sound(value: T | None) -> T:
    """A part that was read without error (every error has been raised before)."""
    assert value is not None
    return value


def load_scenario(path: str | Path, seed: int | None = None) -> Scenario:
    """The Scenario in a TOML file, `seed` (when given) replacing the file's; ConfigError if bad."""
    p = Path(path)
    data = load_toml(p, "scenario")
    scenario = parse_scenario(data, name=p.stem)
    if seed is not None:
        scenario = dataclasses.replace(scenario, seed=Int(ge=0).parse("seed", seed))
    return scenario


def scenario_to_dict(s: Scenario) -> dict[str, Any]:
    """The scenario as plain TOML data with every key spelled out (but the [vehicle] flavour
    defaults left to the flavour); parse_scenario reads it back."""
    out = dump_table(s, TOP_KEYS)
    for section, keys in SECTION_KEYS.items():
        out[section] = dump_table(getattr(s, section), keys)
    if s.sensor.fov == "camera":  # the footprint is derived from [camera] and [vehicle]
        del out["sensor"]["fov_polygon"]
    return out



def main(argv: Sequence[str] | None = None) -> int:
    """Print the key reference (--markdown) or check a scenario file; 2 on a bad file or usage."""
    parser = argparse.ArgumentParser(
        prog="python -m companion.sim.scenario", description="Scenario file keys and checks."
    )
    parser.add_argument("--markdown", action="store_true", help="print the key reference")
    parser.add_argument("file", nargs="?", help="a scenario file to check")
    args = parser.parse_args(argv)
    if args.markdown:
        sys.stdout.write(schema_markdown())
        return 0
    if args.file is None:
        parser.print_usage(sys.stderr)
        return 2
    try:
        scenario = load_scenario(args.file)
    except ConfigError as exc:
        print(exc, file=sys.stderr)
        return 2
    print(f"{args.file}: ok ({scenario.name})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
