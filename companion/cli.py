"""The `companion` command: the onboard service, its configuration check, and the paper's study.

Exit status: 0 on success, 2 for a bad scenario file or arguments (one line on standard error
that names the key), 1 for anything else. Standard output carries only results; progress and
messages go to standard error. Set COMPANION_DEBUG=1 to see tracebacks.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from companion.command import EXIT_OK, run_command
from companion.errors import ConfigError
from companion.progress import progress_bar
from companion.scenario_lookup import resolve_scenario

if TYPE_CHECKING:
    from companion.config import ServiceConfig
    from companion.vision.camera import CameraModel


def _simulate(args: argparse.Namespace) -> int:
    from companion.sim.run import simulate
    from companion.sim.scenario import load_scenario

    scenario = load_scenario(resolve_scenario(args.scenario), seed=args.seed)
    if args.kind is not None:
        scenario = dataclasses.replace(
            scenario, filter=dataclasses.replace(scenario.filter, kind=args.kind))
    with progress_bar(scenario.name, unit="step") as bar:
        result = simulate(scenario, progress=bar.update_to)
    summary = result.summary()
    if args.out is not None:
        from companion.sim.plots import plot_run

        args.out.mkdir(parents=True, exist_ok=True)
        for path in plot_run(result, args.out):
            print(f"wrote {path}", file=sys.stderr)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        width = max(map(len, summary))
        for key, value in summary.items():
            shown = f"{value:.4g}" if isinstance(value, float) else str(value)
            print(f"{key:<{width}}  {shown}")
    return EXIT_OK


def _study(args: argparse.Namespace) -> int:
    from companion.sim.engine import check_scheduler_address
    from companion.sim.planner_study import parse_planners
    from companion.sim.study import run_study

    if args.scheduler is not None:
        check_scheduler_address(args.scheduler)
    planners = [] if args.planners is None else parse_planners(args.planners)
    run_study(seeds=args.seeds, out_dir=args.out, jobs=args.jobs, only=args.only, steps=args.steps,
              scheduler=args.scheduler, kinds=_kinds(args.kinds), planners=planners)
    return EXIT_OK


def _kinds(text: str) -> list[str]:
    """The estimator kinds of a comma-separated --kinds value; ConfigError names a bad one."""
    from companion.sat.filter import FilterKind

    kinds = [k.strip() for k in text.split(",") if k.strip()]
    known = [k.value for k in FilterKind]
    bad = [k for k in kinds if k not in known]
    if bad or not kinds:
        raise ConfigError("--kinds", f"expected names from {', '.join(known)}, got {text!r}")
    return list(dict.fromkeys(kinds))


def _battery(args: argparse.Namespace) -> int:
    from companion.sim.battery import (
        FAMILIES,
        VARIANTS,
        format_family_list,
        parse_names,
        run_battery,
    )

    if args.list:
        sys.stdout.write(format_family_list())
        return EXIT_OK
    run_battery(families=parse_names(args.families, list(FAMILIES), "--families"),
                seeds=args.seeds, out_dir=args.out,
                variants=parse_names(args.variants, list(VARIANTS), "--variants"),
                jobs=args.jobs, scheduler=args.scheduler, steps=args.steps)
    return EXIT_OK


def _learn_gp(args: argparse.Namespace) -> int:
    from companion.sim.scenario import load_scenario
    from companion.sim.training import learn_for_scenario, learn_motion_for_scenario

    scenario = load_scenario(resolve_scenario(args.scenario))
    params = learn_for_scenario(scenario, args.targets, args.steps, args.seed)
    motion = (learn_motion_for_scenario(scenario, args.targets, args.steps, args.seed)
              if scenario.targets.speed_m_s > 0.0 else None)
    print(f"# learned by: companion learn-gp {args.scenario} --targets {args.targets} "
          f"--steps {args.steps} --seed {args.seed}")
    print(f"gp_sigma_f = {params.sigma_f_m:.4g}")
    print(f"gp_lengthscale = {params.lengthscale_s:.4g}")
    print(f"gp_sigma_n = {params.sigma_n_m:.4g}")
    if motion is not None:
        print(f"target_speed = {motion.speed_m_s:.4g}")
        print(f"manoeuvre_time = {motion.manoeuvre_s:.4g}")
    return EXIT_OK


def _check_signing_key(config: ServiceConfig) -> None:
    """A signing key file that is missing, malformed or readable by others stops the start."""
    if config.vehicle.signing_key_file is not None:
        from companion.vehicle.signing import load_signing_key

        load_signing_key(Path(config.vehicle.signing_key_file))


def _check_view_token(config: ServiceConfig) -> None:
    """A view token file that is missing, too short or readable by others stops the start."""
    if config.view.enabled and config.view.token_file is not None:
        from companion.view.server import load_token

        load_token(Path(config.view.token_file))


def _check_orthophoto(config: ServiceConfig) -> str:
    """A view orthophoto that cannot be read stops check-config (`run` flies on without it:
    docs/view.md); what it makes, for the report line."""
    if not (config.view.enabled and config.view.orthophoto is not None):
        return ""
    from companion.pipeline import SearchFrame
    from companion.view.orthophoto import load_orthophoto

    ortho = load_orthophoto(Path(config.view.orthophoto), SearchFrame.from_config(config.search),
                            config.safety.geofence_latlon)
    w, h = ortho.size_px
    return f", orthophoto {ortho.name} of {w} x {h} px at {ortho.resolution_m:.2f} m"


def _check_config(args: argparse.Namespace) -> int:
    from companion.config import load_config

    config = load_config(args.config)
    _check_signing_key(config)
    _check_view_token(config)
    ortho = _check_orthophoto(config)
    s = config.search
    print(f"{args.config}: ok (vehicle {config.vehicle.connection}, camera "
          f"{config.camera.source}, search area of {s.area_latlon.shape[0]} vertices in "
          f"EPSG:{s.utm_epsg} at {s.altitude_m:g} m, reports to {config.output.dir}{ortho})")
    return EXIT_OK


def _run(args: argparse.Namespace) -> int:
    import asyncio
    import signal

    from companion.config import load_config
    from companion.service import Service
    from companion.vehicle.mavsdk_link import route_mavsdk_log

    config = load_config(args.config)
    _check_signing_key(config)
    _check_view_token(config)
    route_mavsdk_log(lambda line: print(line, file=sys.stderr, flush=True))

    async def fly() -> int:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        service = Service(config, announce=lambda text: print(text, file=sys.stderr, flush=True))
        result = await service.run(stop)
        print(json.dumps({"out_dir": str(result.out_dir), "state": result.mission_state,
                          "confirmed": len(result.tracks), **result.counters}))
        return EXIT_OK

    return asyncio.run(fly())


def _replay(args: argparse.Namespace) -> int:
    from companion.config import load_config
    from companion.replay import FrameTimes, load_truth, replay_log, replay_run

    config = load_config(args.config) if args.config else None
    truth = load_truth(args.truth) if args.truth else None
    source: Path = args.run_or_log
    if args.kind is not None:
        from companion.run_folder import read_config

        if config is None and not source.is_dir():
            raise ConfigError("--config", "a flight log replays with its configuration")
        base = config if config is not None else read_config(source)
        config = dataclasses.replace(
            base, filter=dataclasses.replace(base.filter, kind=args.kind))
    times = FrameTimes(args.frame_times, args.frame_offset_s, args.frame_rate_hz)
    with progress_bar(f"replay {source.name}", unit="step") as bar:
        if source.is_dir():
            if args.frames or times != FrameTimes():
                raise ConfigError("--frames", "a run folder replays its own frames; "
                                  "--frames and the frame times are for flight logs")
            result = replay_run(source, args.out or source / "replay", config,
                                progress=bar.update_to, truth_latlon=truth,
                                redetect=not args.recorded_detections)
        else:
            if args.frames is None or config is None:
                raise ConfigError("--frames" if args.frames is None else "--config",
                                  f"a flight log ({source.name}) replays with the video or "
                                  "image folder of its flight and the configuration "
                                  "(search area, camera, estimator)")
            result = replay_log(source, args.frames,
                                args.out or source.with_name(f"{source.stem}-replay"), config,
                                times, progress=bar.update_to, truth_latlon=truth)
    for warning in result.warnings:
        print(f"companion: warning: {warning}", file=sys.stderr)
    factor = result.flight_s / result.wall_s if result.wall_s > 0 else float("inf")
    print(f"replayed {result.steps} steps ({result.flight_s:.0f} s of flight) in "
          f"{result.wall_s:.1f} s, {factor:.0f}x real time: {len(result.tracks)} confirmed "
          f"tracks -> {result.out_dir}")
    if result.score is not None and truth is not None:
        print(f"{'target':>6} {'lat':>11} {'lon':>11} {'error m':>8}")
        for i, ((lat, lon), err) in enumerate(zip(truth, result.score.errors_m, strict=True)):
            shown = f"{err:8.2f}" if math.isfinite(err) else "  missed"
            print(f"{i:>6} {lat:11.6f} {lon:11.6f} {shown}")
        print(f"{result.score.missed} missed, {result.score.false_tracks} false tracks")
    if args.view:
        if source.is_dir():  # the same estimate again, over the run's recorded detections
            return _serve_view(source, args, config)
        from companion.pipeline import camera_model

        assert config is not None  # a log replays only with a configuration
        return _serve_view(result.out_dir, args, config, camera_model(config.camera))
    return EXIT_OK


def _serve_view(run_dir: Path, args: argparse.Namespace, config: ServiceConfig | None,
                camera: CameraModel | None = None) -> int:
    """Serve the view of a run folder until Ctrl-C or SIGTERM."""
    import asyncio
    import ipaddress
    import signal

    from companion.view.recorded import recorded_view
    from companion.view.server import ViewServer, load_token

    try:
        loopback = ipaddress.ip_address(args.bind).is_loopback
    except ValueError:
        loopback = args.bind == "localhost"
    if not loopback and args.token_file is None:
        raise ConfigError("--token-file", f"is required when --bind ({args.bind}) is not a "
                          "loopback address")
    token = None if args.token_file is None else load_token(args.token_file)
    view = recorded_view(run_dir, config, camera, args.orthophoto)
    for warning in view.warnings:
        print(f"companion: warning: {warning}", file=sys.stderr)

    async def serve() -> int:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        server = ViewServer(view.scene, bind=args.bind, port=args.port, token=token,
                            steps=view.steps, address_keys=("--bind", "--port"),
                            orthophoto_png=None if view.orthophoto is None
                            else view.orthophoto.png)
        await server.start()
        print(f"view of {run_dir.name} ({len(view.steps)} steps) at {server.url}"
              f"{'' if token is None else ' (add ?token=... from the token file)'}; "
              "Ctrl-C stops", file=sys.stderr, flush=True)
        print(json.dumps({"url": server.url, "steps": len(view.steps)}), flush=True)
        await stop.wait()
        await server.close()
        return EXIT_OK

    return asyncio.run(serve())


def _view(args: argparse.Namespace) -> int:
    from companion.config import load_config

    config = load_config(args.config) if args.config else None
    return _serve_view(args.run_dir, args, config)


def _add_view_arguments(parser: argparse.ArgumentParser, flag: str = "") -> None:
    parser.add_argument("--bind", default="127.0.0.1",
                        help=f"{flag}address the page listens on (default 127.0.0.1; any other "
                             "needs --token-file)")
    parser.add_argument("--port", type=int, default=8090,
                        help=f"{flag}TCP port of the page (default 8090; 0: any free port)")
    parser.add_argument("--token-file", type=Path, default=None,
                        help=f"{flag}file holding the access token the page requires (mode 600)")
    parser.add_argument("--orthophoto", type=Path, default=None,
                        help=f"{flag}GeoTIFF or MBTiles file under the map, instead of the one "
                             "of the run's configuration")


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


KINDS = ("gmphd", "lmb")
"""The estimator kinds, by their filter.kind names (companion.sat.filter.FilterKind)."""


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand."""
    parser = argparse.ArgumentParser(prog="companion", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    sim = sub.add_parser("simulate", help="run one scenario (filter only, synthetic measurements)")
    sim.add_argument("scenario", help="a scenario TOML file, or the name of a shipped scenario")
    sim.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    sim.add_argument("--json", action="store_true", help="print the result as one JSON object")
    sim.add_argument("--out", type=Path, default=None, help="write plots to this directory")
    sim.add_argument("--kind", choices=KINDS, default=None,
                     help="the estimator, overriding the scenario's filter.kind")
    sim.set_defaults(run=_simulate)

    study = sub.add_parser("study", help="the paper's whole simulation study, Monte Carlo")
    study.add_argument("--seeds", type=_positive_int, default=10, help="seeds per experiment")
    study.add_argument("--out", type=Path, default=Path("out/study"), help="output directory")
    study.add_argument("--jobs", type=_positive_int, default=os.cpu_count() or 1,
                       help="worker processes (default: one per core)")
    study.add_argument("--only", default=None,
                       help="run only the experiments whose scenario name contains this text")
    study.add_argument("--steps", type=_positive_int, default=None,
                       help="cut every run to this many steps (a quick look, not the figures)")
    study.add_argument("--kinds", default="gmphd,lmb", metavar="KIND,...",
                       help="estimators to run side by side (gmphd, lmb; default both)")
    study.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                       help="run on this dask.distributed scheduler instead of local processes")
    study.add_argument("--planners", default=None, metavar="PLANNER,...",
                       help="also fly the lawn-mower experiments with these planners, the same "
                            "seeds, into planners.md and figures (lawnmower, nearest-gaussian, "
                            "largest-gaussian, search-track; e.g. lawnmower,search-track; "
                            "default: none, the paper's study only)")
    study.set_defaults(run=_study)

    battery = sub.add_parser(
        "battery", help="families of generated scenarios over seeds, estimator variants side by "
                        "side")
    battery.add_argument("--families", default=None, metavar="NAME,...",
                         help="the families to run (default: all; see --list)")
    battery.add_argument("--seeds", type=int, default=20, help="seeds per family and variant")
    battery.add_argument("--out", type=Path, default=Path("out/battery"), help="output directory")
    battery.add_argument("--variants", default="defaults", metavar="NAME,...",
                         help="[filter] variants to compare; search-track flies the "
                              "search-and-track planner (default: defaults)")
    battery.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                         help="local worker processes (default: one per core)")
    battery.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                         help="run on this dask.distributed scheduler instead of local processes")
    battery.add_argument("--steps", type=int, default=None,
                         help="cut every run to this many steps (a quick look)")
    battery.add_argument("--list", action="store_true",
                         help="print the families with a line each and exit")
    battery.set_defaults(run=_battery)

    learn = sub.add_parser(
        "learn-gp",
        help="learn the GP hyperparameters from noisy observations of a scenario's target motion",
    )
    learn.add_argument("scenario", help="a scenario TOML file, or the name of a shipped scenario")
    learn.add_argument("--targets", type=_positive_int, default=20, help="training trajectories")
    learn.add_argument("--steps", type=_positive_int, default=1200, help="steps per trajectory")
    learn.add_argument("--seed", type=int, default=1000, help="seed of the training set")
    learn.set_defaults(run=_learn_gp)

    run = sub.add_parser("run", help="the onboard service: search, track and fly (Ctrl-C stops)")
    run.add_argument("--config", type=Path, required=True, help="the service's TOML configuration")
    run.set_defaults(run=_run)

    replay = sub.add_parser("replay", help="re-run a flight through the pipeline offline: a run "
                                           "folder, or a flight log with its video")
    replay.add_argument("run_or_log", metavar="RUN_OR_LOG", type=Path,
                        help="a run folder written by `companion run`, or a flight log: "
                             "MAVLink .tlog, ArduPilot .bin or PX4 .ulg")
    replay.add_argument("--frames", type=Path, default=None,
                        help="with a log: the flight's video file or image folder")
    replay.add_argument("--frame-times", type=Path, default=None,
                        help="with a log: each frame's time on the log's clock (s), one per "
                             "line or a t_s column")
    replay.add_argument("--frame-offset-s", type=float, default=None,
                        help="with a log: the log time of the first frame (instead of "
                             "--frame-times)")
    replay.add_argument("--frame-rate-hz", type=float, default=None,
                        help="with --frame-offset-s: frames per second (default: the video's)")
    replay.add_argument("--config", type=Path, default=None,
                        help="the configuration: another one to tune a run with (default: the "
                             "run's own); required with a log")
    replay.add_argument("--kind", choices=KINDS, default=None,
                        help="the estimator, overriding the configuration's filter.kind")
    replay.add_argument("--recorded-detections", action="store_true",
                        help="use a run's recorded detections even where its frames were kept")
    replay.add_argument("--out", type=Path, default=None,
                        help="output folder (default: RUN/replay, or LOG-replay beside a log)")
    replay.add_argument("--truth", type=Path, default=None,
                        help="true target positions (CSV with lat, lon columns, or GeoJSON "
                             "points): prints each target's error")
    replay.add_argument("--view", action="store_true",
                        help="then serve the replay's view: a time slider over its steps")
    _add_view_arguments(replay, "with --view: ")
    replay.set_defaults(run=_replay)

    view = sub.add_parser("view", help="serve the operator's page over a recorded run folder: "
                                       "its map and targets at any time of the flight")
    view.add_argument("run_dir", metavar="RUN", type=Path,
                      help="a run folder written by `companion run` (or by `replay`)")
    view.add_argument("--config", type=Path, default=None,
                      help="re-estimate with this configuration instead of the run's own")
    _add_view_arguments(view)
    view.set_defaults(run=_view)

    check = sub.add_parser("check-config", help="validate a service configuration file and exit")
    check.add_argument("config", type=Path, help="the service's TOML configuration")
    check.set_defaults(run=_check_config)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `companion` command."""
    args = build_parser().parse_args(argv)
    return run_command("companion", lambda: int(args.run(args)))


if __name__ == "__main__":
    sys.exit(main())
