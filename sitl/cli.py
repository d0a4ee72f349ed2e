"""The `companion-sitl` command (also `python -m sitl`): run one SITL mission until stopped.

It prints where to connect (the MAVLink UDP port a client listens on, as for PX4 SITL, and the
camera's MJPEG URL) on standard output, a status line every few simulated seconds on standard
error, and stops cleanly on Ctrl-C or SIGTERM (or after --duration simulated seconds).
With --external-autopilot URL no mock autopilot runs: the camera renders the scenario from the
pose of a real autopilot SITL read at URL (`sitl.external`).
Exit status: 0 when stopped, 2 for a bad scenario, fault plan or arguments, 1 for anything else.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path

from companion.command import run_command
from companion.errors import ConfigError
from companion.scenario_lookup import shipped_scenarios
from companion.sim.scenario import load_scenario
from sitl.external import URL_KEY, run_external
from sitl.faults import parse_faults
from sitl.runner import PX4_OFFBOARD_PORT, Sitl

EXIT_OK = 0


def sitl_scenarios() -> dict[str, Path]:
    """The SITL missions that ship with the package, by name."""
    return shipped_scenarios("sitl")


def resolve_mission(arg: str) -> Path:
    """A scenario path from a file path or the name of a shipped SITL or filter scenario."""
    path = Path(arg)
    if path.exists():
        return path
    known = {**shipped_scenarios(), **sitl_scenarios()}
    if arg in known:
        return known[arg]
    raise ConfigError(arg, "no such scenario file, and no shipped scenario of that name "
                           f"({', '.join(sitl_scenarios())}, or any of `companion simulate`'s)")


def _port(text: str) -> int:
    value = int(text)
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"must be a port in [0, 65535], got {value}")
    return value


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0.0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The command's arguments."""
    parser = argparse.ArgumentParser(
        prog="companion-sitl",
        description="Software-in-the-loop drone: a mock PX4/ArduPilot autopilot on MAVLink "
                    "(UDP, loopback) and a rendered downward camera (MJPEG over HTTP).",
        epilog="Fault plan (--faults): comma-separated items, e.g. "
               "'loss=5,latency=0.05,cut@60+10,freeze@30+5,gps@120+20:5/0,battery@300:15,"
               "pilot@200:posctl,reboot@400+3'; times are simulated seconds since start. "
               "See sitl/faults.py for every item.",
    )
    parser.add_argument("scenario", help="a scenario TOML file, or a shipped scenario's name")
    parser.add_argument("--speedup", type=_positive, default=None,
                        help="simulated seconds per wall second (default 1)")
    parser.add_argument("--faults", default="", help="fault plan (see below)")
    parser.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    parser.add_argument("--host", default="127.0.0.1", help="address to serve on")
    parser.add_argument("--mavlink-port", type=_port, default=None,
                        help="UDP port the MAVLink client listens on (MAVSDK: "
                             "udpin://HOST:PORT; default 14540 as PX4 SITL)")
    parser.add_argument("--gcs-port", type=_port, default=None,
                        help="also send MAVLink to this port (QGroundControl: 14550)")
    parser.add_argument("--camera-port", type=_port, default=0,
                        help="HTTP port of the camera stream (default: a free port)")
    parser.add_argument("--duration", type=_positive, default=None,
                        help="stop after this many simulated seconds")
    parser.add_argument("--status-every", type=float, default=10.0,
                        help="simulated seconds between status lines (0: none)")
    parser.add_argument(URL_KEY, metavar="URL", default=None,
                        help="no mock autopilot: render from the pose of an ArduPilot or PX4 "
                             "SITL read over MAVLink at URL (loopback, e.g. "
                             "udpin:127.0.0.1:14560); --duration and --status-every are then "
                             "wall seconds")
    return parser


def _status(sitl: Sitl) -> str:
    snap = sitl.autopilot.snapshot()
    north, east, down = snap.vehicle.position_ned
    armed = "armed" if snap.armed else "disarmed"
    return (f"t {sitl.clock.now_s():7.1f} s  {snap.behaviour.value:<8} {armed:<8} "
            f"N {north:7.1f} E {east:7.1f} alt {0.0 - down:5.1f} m  "
            f"battery {snap.battery_percent:3.0f} %  frames {sitl.frames.published}")


def run(args: argparse.Namespace, stop: threading.Event) -> int:
    """Run the mission the arguments describe until `stop` is set or the duration is over."""
    scenario = load_scenario(resolve_mission(args.scenario), seed=args.seed)
    faults = parse_faults(args.faults)
    if args.external_autopilot is not None:
        for flag, value in (("--speedup", args.speedup), ("--mavlink-port", args.mavlink_port),
                            ("--gcs-port", args.gcs_port)):
            if value is not None:
                raise ConfigError(flag, f"not with {URL_KEY}: there is no mock autopilot, and "
                                        "the camera runs on the external autopilot's clock")
        return run_external(scenario, args.external_autopilot, stop, faults=faults,
                            host=args.host, camera_port=args.camera_port,
                            duration_s=args.duration, status_every_s=args.status_every)
    speedup = 1.0 if args.speedup is None else args.speedup
    mavlink_port = PX4_OFFBOARD_PORT if args.mavlink_port is None else args.mavlink_port
    sitl = Sitl(scenario, speedup=speedup, faults=faults, host=args.host,
                mavlink_port=mavlink_port, gcs_port=args.gcs_port,
                camera_port=args.camera_port)
    with sitl:
        print(f"scenario {scenario.name} ({scenario.vehicle.flavour}), speed-up {speedup:g}x")
        print(f"mavlink {sitl.mavlink_url}")
        if args.gcs_port is not None:
            print(f"gcs udpin://{args.host}:{args.gcs_port}")
        print(f"camera {sitl.camera_url}", flush=True)
        next_status_s = 0.0
        while not stop.is_set():
            now_s = sitl.clock.now_s()
            if args.duration is not None and now_s >= args.duration:
                break
            if args.status_every > 0.0 and now_s >= next_status_s:
                print(_status(sitl), file=sys.stderr, flush=True)
                next_status_s = now_s + args.status_every
            stop.wait(0.05)
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of `companion-sitl`."""
    args = build_parser().parse_args(argv)
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda *_: stop.set())

    def body() -> int:
        try:
            return run(args, stop)
        except KeyboardInterrupt:  # Ctrl-C is how it is meant to stop
            return EXIT_OK

    return run_command("companion-sitl", body)


if __name__ == "__main__":
    sys.exit(main())
