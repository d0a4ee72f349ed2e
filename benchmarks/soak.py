"""Soak study: a long SITL mission with moving targets and clutter, watched for leaks and jitter.

The companion service flies the `soak-30-targets` scenario (sitl/scenarios/) in this process
with the mock autopilot and the rendered camera, searching by lawn mower for --minutes simulated
minutes, then landing. It prints: the simulated and wall durations and the speed-up achieved;
the process's RSS (peak, and the slope of a least-squares line through the samples after the
first 20 %, in MB per simulated hour); the filter's component count against its cap; the
setpoint stream's intervals in simulated time as the service sent them (events.jsonl) and as
the autopilot received them (median, p99, max gap, and the gaps over 1.5 periods: the target is
none) and how late the event loop woke; the size of the estimator's checkpoint; the blind
estimator steps; how the mission went; the confirmed tracks against the truth at the end.

    python benchmarks/soak.py [--minutes 30] [--speedup 4] [--targets 30] [--clutter 0.2]
                              [--out DIR] [--rss-every 10] [--seed N] [--pilot-resumes]

The SITL's clock is the wall clock times the speed-up, whether or not the process gets the CPU,
so on a busy machine a stall of 0.8 s / speed-up of wall time already looks like a lost link to
the service, which then stops searching and waits for a pilot. --pilot-resumes adds that pilot
(it selects OFFBOARD again after a few seconds of hold) so that the search goes on; the report
counts how often it had to.

A study, not a test: the exit status is 0 whatever the figures (tests/test_soak.py asserts on
a short run of the same code, sitl/soak.py). The headline figures also go to
out/reliability/soak-MINUTESmin.json for docs/reliability.md. The machine is shared: the timing
figures are noisy.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from companion.vehicle.mavsdk_link import route_mavsdk_log
from sitl.figures import record_figure
from sitl.soak import SoakOptions, report_lines, soak, soak_figures


def main() -> None:
    """Run one soak and print its figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=30.0,
                        help="simulated minutes of search (take-off and landing come on top)")
    parser.add_argument("--speedup", type=float, default=4.0,
                        help="simulated seconds per wall second")
    parser.add_argument("--targets", type=int, default=30, help="moving targets (tags 0..N-1)")
    parser.add_argument("--clutter", type=float, default=0.2,
                        help="mean false tags per frame, i.e. per estimator step")
    parser.add_argument("--out", type=Path, default=Path("out/soak"), help="report folder")
    parser.add_argument("--rss-every", type=float, default=10.0,
                        help="simulated seconds between RSS samples")
    parser.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    parser.add_argument("--pilot-resumes", action="store_true",
                        help="a pilot selects OFFBOARD again whenever the search stopped mid-air")
    args = parser.parse_args()
    route_mavsdk_log(lambda line: print(f"  {line}", file=sys.stderr, flush=True))
    options = SoakOptions(search_s=60.0 * args.minutes, speedup=args.speedup,
                          targets=args.targets, clutter_per_frame=args.clutter,
                          out_dir=args.out, rss_every_s=args.rss_every, seed=args.seed,
                          pilot_resumes=args.pilot_resumes)
    print(f"soak: {args.minutes:g} simulated minutes of search at {args.speedup:g}x, "
          f"about {(60.0 * args.minutes + 45.0) / args.speedup / 60.0:.1f} min wall", flush=True)
    report = soak(options)
    for line in report_lines(report):
        print(line, flush=True)
    record_figure(f"soak-{args.minutes:g}min", **soak_figures(report))


if __name__ == "__main__":
    main()
