"""The main demonstration: the companion service flies a SITL mission and is scored against truth.

`companion-demo [SCENARIO] [--speedup X] [--faults PLAN] [--flavour px4|ardupilot]` starts the
mock autopilot and the rendered camera of a scenario. It then runs the real service on them with
`sitl/service.toml`, whose search area, altitude, lanes, camera and filter come from the
scenario. The service arms, takes off, searches, tracks and lands. The command prints the
confirmed targets against the truth and the paths of the report files.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.command import run_command
from companion.config import ServiceConfig, parse_config
from companion.errors import ConfigError
from companion.keys import load_toml
from companion.pipeline import SearchFrame
from companion.report import Score, score
from companion.service import RunResult, Service
from companion.sim.scenario import Scenario, load_scenario, scenario_to_dict
from companion.vehicle.mavsdk_link import route_mavsdk_log
from sitl.autopilot import Snapshot
from sitl.cli import resolve_mission
from sitl.faults import parse_faults
from sitl.link import free_udp_port
from sitl.runner import Sitl

__all__ = ["DemoResult", "fly", "main", "service_config"]

FloatArray = NDArray[np.float64]
FENCE_MARGIN_M = 5.0


def _latlon(scenario: Scenario, xy_m: FloatArray) -> list[list[float]]:
    """World points (x east, y north) -> [lat, lon]."""
    lat, lon, _ = scenario.geo.local_ned().ned_to_geodetic(xy_m[:, 1], xy_m[:, 0],
                                                              np.zeros(len(xy_m)))
    return [[float(a), float(b)] for a, b in zip(lat, lon, strict=True)]


def service_config(scenario: Scenario, sitl: Sitl, out_dir: Path,
                   **overrides: dict[str, Any]) -> ServiceConfig:
    """sitl/service.toml with the scenario's area, flight, filter and this SITL's addresses."""
    base = Path(str(resources.files("sitl") / "service.toml"))
    data: dict[str, Any] = load_toml(base, "configuration")
    w, h = scenario.world.size_m
    box = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
    m = FENCE_MARGIN_M
    fence = box + np.array([[-m, -m], [m, -m], [m, m], [-m, m]])
    r, v = scenario.robot, scenario.vehicle
    data["vehicle"]["connection"] = sitl.mavlink_url
    data["camera"] = {"source": sitl.camera_url, "kind": "mjpeg"}
    data["search"].update(area=_latlon(scenario, box), altitude_m=v.altitude_m,
                          speed_m_s=r.speed_m_s, lane_spacing_m=r.lane_spacing_m,
                          sweeps=r.sweeps, planner=r.planner, heading_deg=v.heading_deg,
                          stop_when_left=r.stop_when_left)
    if r.planner == "search-track" and scenario.belief.kind == "empty" and r.unseen_targets >= 1:
        # what the planner searches for: the targets a user expects before any is seen (with
        # no initial belief, as the service has none)
        data["search"]["expected_targets"] = round(r.unseen_targets)
    data["safety"].update(geofence=_latlon(scenario, fence),
                          max_alt_m=max(data["safety"]["max_alt_m"], v.altitude_m + 5.0))
    data["filter"] = scenario_to_dict(scenario)["filter"]
    # The vehicle's calibration, as a user measures it once: the relative altitude minus the
    # camera's true height (ArduPilot: +0.25 m).
    data["pose"]["camera_rest_height_m"] = -sitl.autopilot.firmware.rel_alt_bias_m
    data["output"]["dir"] = str(out_dir.resolve())
    for table, values in overrides.items():
        data.setdefault(table, {}).update(values)
    return parse_config(data, base=base.parent)


@dataclass(frozen=True)
class DemoResult:
    """The service's run and its score against the truth."""

    run: RunResult
    score: Score
    truth_xy_m: FloatArray  # search frame
    tracks_xy_m: FloatArray
    autopilot: Snapshot  # the mock autopilot's state at the end
    frame: SearchFrame  # the run's search frame (truth and tracks are in it)


async def fly(scenario: Scenario, *, speedup: float, out_dir: Path, faults: str = "",
              announce: Any = None, stop_after_s: float | None = None,
              signing_key: bytes | None = None, mavlink_port: int | None = None,
              on_sitl: Callable[[Sitl], None] | None = None,
              **overrides: dict[str, Any]) -> DemoResult:
    """One whole SITL mission flown by the service (stopped at stop_after_s simulated s); with
    signing_key the autopilot accepts only signed MAVLink (configure the key file to match);
    mavlink_port is where the service's MAVSDK listens (default: a free one); on_sitl, if given,
    is called with the Sitl once it is built and before it starts (to attach probes)."""
    sitl = Sitl(scenario, speedup=speedup, faults=parse_faults(faults),
                mavlink_port=mavlink_port or free_udp_port(), signing_key=signing_key)
    if on_sitl is not None:
        on_sitl(sitl)
    with sitl:
        config = service_config(scenario, sitl, out_dir, **overrides)
        service = Service(config, camera=scenario.camera, clock=sitl.clock.now_s,
                          time_scale=speedup, announce=announce or (lambda _: None))
        stop = asyncio.Event()
        if stop_after_s is not None:
            asyncio.get_running_loop().call_later(
                max(stop_after_s - sitl.clock.now_s(), 0.0) / speedup, stop.set)
        run = await service.run(stop)
        end_s = sitl.clock.now_s()
        final = sitl.autopilot.snapshot()
    frame, state = service.pipeline.frame, service.pipeline.state
    # The tracks are the estimate at the last step, so they are scored against where the
    # targets were then; by end_s (after the service's shutdown) movers have walked on.
    tags = sitl.world.tags(end_s if state is None else state.t_s)
    truth = []
    for tag in tags:
        lat, lon, _ = scenario.geo.local_ned().ned_to_geodetic(tag.north_m, tag.east_m, 0.0)
        e, n = frame.utm.geodetic_to_utm(lat, lon)
        truth.append(frame.from_utm(np.array([float(e), float(n)])))
    truth_xy = np.array(truth).reshape(-1, 2)
    tracks_xy = np.array([[t.easting_m, t.northing_m] for t in run.tracks]).reshape(-1, 2)
    tracks_xy = frame.from_utm(tracks_xy)
    return DemoResult(run, score(tracks_xy, truth_xy), truth_xy, tracks_xy, final, frame)


def report(result: DemoResult) -> str:
    """The table the command prints."""
    s = result.score
    lines = [f"{'target':>6} {'x m':>7} {'y m':>7} {'error m':>8}"]
    for i, (xy, err) in enumerate(zip(result.truth_xy_m, s.errors_m, strict=True)):
        shown = f"{err:8.2f}" if np.isfinite(err) else "  missed"
        lines.append(f"{i:>6} {xy[0]:7.2f} {xy[1]:7.2f} {shown}")
    found = len(s.errors_m) - s.missed
    lines.append(f"confirmed {len(result.run.tracks)} tracks: {found} of {len(s.errors_m)} "
                 f"targets found, {s.missed} missed, {s.false_tracks} false")
    out = result.run.out_dir
    lines.append(f"reports: {out / 'tracks.geojson'}, {out / 'tracks.csv'}, "
                 f"{out / 'steps.jsonl'}, {out / 'events.jsonl'}")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    """The command's arguments."""
    parser = argparse.ArgumentParser(prog="companion-demo", description=__doc__.splitlines()[0])
    parser.add_argument("scenario", nargs="?", default="field-5-tags",
                        help="a SITL scenario (default: field-5-tags, the paper's field test)")
    parser.add_argument("--speedup", type=float, default=4.0,
                        help="simulated seconds per wall second (default 4)")
    parser.add_argument("--faults", default="", help="fault plan (see companion-sitl --help)")
    parser.add_argument("--flavour", choices=("px4", "ardupilot"), default=None,
                        help="override the scenario's autopilot")
    parser.add_argument("--out", type=Path, default=Path("out/sitl"), help="report folder")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of `companion-demo`."""
    args = build_parser().parse_args(argv)

    def body() -> int:
        if not args.speedup > 0:
            raise ConfigError("--speedup", f"must be > 0, got {args.speedup}")
        scenario = load_scenario(resolve_mission(args.scenario))
        if args.flavour:
            scenario = dataclasses.replace(
                scenario, vehicle=dataclasses.replace(scenario.vehicle, flavour=args.flavour))
        route_mavsdk_log(lambda line: print(f"  {line}", file=sys.stderr, flush=True))
        print(f"companion-demo: {scenario.name} ({scenario.vehicle.flavour}), speed-up "
              f"{args.speedup:g}x", flush=True)
        result = asyncio.run(fly(scenario, speedup=args.speedup, out_dir=args.out,
                                 faults=args.faults,
                                 announce=lambda text: print(f"  {text}", flush=True)))
        print(report(result))
        return 0 if result.score.missed == 0 and result.score.false_tracks == 0 else 1

    return run_command("companion-demo", body)


if __name__ == "__main__":
    sys.exit(main())
