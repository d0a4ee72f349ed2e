"""Soak study: a long SITL mission with moving targets and clutter, watched for leaks and jitter.

The companion service flies the `soak-30-targets` scenario (sitl/scenarios/) in this process with
the mock autopilot and the rendered camera, searching by lawn mower (or the --planner given) for
--minutes simulated minutes, then landing. It prints: the simulated and wall durations and the
speed-up achieved; the process's RSS (peak, and the slope of a least-squares line through the
samples after the first 20 %, in MB per simulated hour); the filter's component count against its
cap; the setpoint stream's intervals in simulated time as the service sent them (events.jsonl) and
as the autopilot received them (median, p99, max gap, and the gaps over 1.5 periods) and how late
the event loop woke; the size of the estimator's checkpoint; the blind estimator
steps; how the mission went; the confirmed tracks against the truth at the end.

    python benchmarks/soak.py [--minutes 30] [--speedup 4] [--targets 30] [--clutter 0.2]
                              [--out DIR] [--rss-every 10] [--seed N] [--pilot-resumes]
                              [--planner lawnmower|search-track]

The SITL's clock is the wall clock times the speed-up, whether or not the process gets the CPU,
so on a busy machine a stall of 0.8 s / speed-up of wall time already looks like a lost link to
the service, which then stops searching and waits for a pilot. --pilot-resumes adds that pilot
(it selects OFFBOARD again after a few seconds of hold) so that the search goes on; the report
counts how often it had to.

A study, not a test: the exit status is 0 whatever the figures (tests/test_soak.py asserts on
a short run of the same code, imported as `benchmarks.soak`). The headline figures also go to
soak-MINUTESmin.json in the figures folder (sitl/figures.py: $COMPANION_FIGURES_DIR, else
out/reliability) for docs/reliability.md. The machine is shared: the timing figures are noisy.

How it works: `soak(SoakOptions(...))` flies `sitl.demo.fly` (the mock autopilot, the rendered
camera and the real service over MAVSDK on loopback, all in this process) on the scenario with
`targets` walking targets and `clutter_per_frame` false tags per frame, searching until
`mission.time_limit_s` = `search_s`, then landing. While it flies it samples:

- the resident set size of this whole process (VmRSS of /proc/self/status, Linux), every
  `rss_every_s` simulated seconds, from a thread;
- every setpoint the mock autopilot accepts, at its simulated receive time;
- how late the event loop, which the service's tasks share, wakes from 5 ms sleeps (wall).

Afterwards it reads the run's steps.jsonl (components, blind steps) and events.jsonl (setpoints
sent, when the stream was started and stopped) and returns a `SoakReport`; `report_lines`
formats it.

Clutter: the SITL draws distractor tags (`sensor.clutter_prob` + `clutter_rate` per scenario
step, spread over the step's frames) with ids above the targets', each in one frame only, at a
random place in the footprint; the service's allow-list is empty (all ids), so they reach the
filter as false detections. `clutter_per_frame` X sets the per-step mean to X * frames per step,
so that each frame, and so each estimator step (one frame), has X false tags on average; the
service's `estimator.clutter_per_scan` is set to X as well.

With `pilot_resumes`, a pilot (a thread watching the autopilot) selects OFFBOARD again a few
seconds after the vehicle was left holding mid-air, as the service, after a lost link, waits for
a pilot to do; the report lists when.

Each soak writes into a new folder under `out_dir`: the service's output.dir, and rss.csv (the
RSS samples). The service resumes from a checkpoint younger than ten minutes that it finds in
its output.dir, and a resumed service takes no automatic step, so a soak after another in the
same folder would never take off. A mission not over `stop_margin_s` simulated seconds after
its time limit is stopped.

Instrumentation, through documented hooks only: `fly(on_sitl=...)` hands over the Sitl it
builds, before it starts; the soak starts the RSS sampler on the SITL clock there and sets the
autopilot's `on_setpoint` observer, which records the time of every setpoint accepted. Nothing
else of the run changes.
"""


from __future__ import annotations

import argparse
import array
import asyncio
import contextlib
import math
import pickle
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.keys import load_toml
from companion.plan.planners import lawnmower_path
from companion.plan.world import World
from companion.run_folder import read_events, read_steps
from companion.sim.scenario import Scenario, parse_scenario
from companion.vehicle.mavsdk_link import route_mavsdk_log
from sitl import demo
from sitl.autopilot import MockAutopilot
from sitl.cli import sitl_scenarios
from sitl.clock import SimClock
from sitl.figures import record_figure
from sitl.modes import Behaviour
from sitl.runner import Sitl

__all__ = ["GapStats", "RssSampler", "SoakOptions", "SoakReport", "gap_stats", "main",
           "read_rss_mb", "report_lines", "rss_slope_mb_per_h", "soak", "soak_figures",
           "soak_scenario", "stream_pauses"]

FloatArray = NDArray[np.float64]
SCENARIO = "soak-30-targets"
WARMUP_FRACTION = 0.2  # RSS samples before this share of the run are the warm-up
GAP_LIMIT_PERIODS = 1.5  # a setpoint gap longer than this many periods is counted
LAG_PROBE_WALL_S = 0.005  # wall seconds between the event loop's lag probes
LONG_LAG_MS = 100.0  # event-loop lags longer than this are listed with their time
PILOT_POLL_S = 0.25  # simulated seconds between the soak pilot's looks at the autopilot
PILOT_REACTION_S = 3.0  # simulated seconds of hold before the soak pilot selects OFFBOARD
_PROC_STATUS = Path("/proc/self/status")
_BYTES_PER_KB = 1024.0  # /proc reports kB = KiB


# ---------------------------------------------------------------------------------------------
# Measurements
# ---------------------------------------------------------------------------------------------

def read_rss_mb(field_name: str = "VmRSS") -> float:
    """This process's resident set size (or another /proc/self/status field in kB), in MB."""
    for line in _PROC_STATUS.read_text().splitlines():
        if line.startswith(f"{field_name}:"):
            return float(line.split()[1]) * _BYTES_PER_KB / 1e6
    raise RuntimeError(f"{_PROC_STATUS} has no {field_name} line")


class RssSampler:
    """Samples read_rss_mb() every every_s seconds of `clock` (simulated time), in a thread.

    start() takes the first sample at once; stop() takes a last one and joins. The samples are
    (t_s on the clock, rss_mb) pairs, in time order.
    """

    def __init__(self, clock: Callable[[], float], every_s: float,
                 wall_per_clock_s: float) -> None:
        if not every_s > 0.0 or not wall_per_clock_s > 0.0:
            raise ValueError(f"every_s and wall_per_clock_s must be > 0, got {every_s!r}, "
                             f"{wall_per_clock_s!r}")
        self._clock = clock
        self._wait_wall_s = every_s * wall_per_clock_s
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._samples: list[tuple[float, float]] = []
        self._thread = threading.Thread(target=self._run, name="soak-rss", daemon=True)

    def start(self) -> RssSampler:
        """Take the first sample and start the thread; returns self."""
        self._sample()
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and take a last sample. Idempotent."""
        if self._stop.is_set():
            return
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        self._sample()

    @property
    def samples(self) -> list[tuple[float, float]]:
        """(t_s, rss_mb) so far."""
        with self._lock:
            return list(self._samples)

    def _sample(self) -> None:
        sample = (self._clock(), read_rss_mb())
        with self._lock:
            self._samples.append(sample)

    def _run(self) -> None:
        while not self._stop.wait(self._wait_wall_s):
            self._sample()


def rss_slope_mb_per_h(t_s: Sequence[float] | FloatArray, rss_mb: Sequence[float] | FloatArray,
                       skip_fraction: float = WARMUP_FRACTION) -> float:
    """Slope of the least-squares line through the samples after the first skip_fraction of the
    sampled time span, in MB per hour of t_s; NaN with fewer than 3 such samples."""
    t = np.asarray(t_s, dtype=np.float64)
    rss = np.asarray(rss_mb, dtype=np.float64)
    if len(t) == 0:
        return math.nan
    keep = t >= t[0] + skip_fraction * (t[-1] - t[0])
    if keep.sum() < 3 or np.ptp(t[keep]) <= 0.0:
        return math.nan
    slope_per_s = float(np.polyfit(t[keep], rss[keep], 1)[0])
    return slope_per_s * 3600.0


@dataclass(frozen=True)
class GapStats:
    """Intervals between consecutive setpoints of a stream, in simulated seconds."""

    count: int  # setpoints
    median_s: float
    p99_s: float
    max_s: float
    over_limit: int  # gaps longer than limit_s
    limit_s: float
    worst_at_s: tuple[float, ...]  # start times of the longest gaps over the limit (up to 5)


def gap_stats(times_s: Sequence[float], period_s: float, pauses: Sequence[tuple[float, float]] = (),
              limit_periods: float = GAP_LIMIT_PERIODS) -> GapStats:
    """Setpoint intervals of a stream, leaving out those that span a pause (stream stopped at
    the pause's start and started again at its end, on purpose). Gaps over limit_periods
    periods are counted."""
    t = np.sort(np.asarray(times_s, dtype=np.float64))
    limit_s = limit_periods * period_s
    gaps = np.diff(t)
    starts = t[:-1]
    if len(pauses):
        stopped = np.zeros(len(gaps), dtype=bool)
        for stop_s, _ in pauses:
            stopped |= (starts <= stop_s) & (t[1:] >= stop_s)
        gaps, starts = gaps[~stopped], starts[~stopped]
    if len(gaps) == 0:
        return GapStats(len(t), math.nan, math.nan, math.nan, 0, limit_s, ())
    over = gaps > limit_s
    worst = np.argsort(gaps)[::-1][:min(int(over.sum()), 5)]
    return GapStats(len(t), float(np.median(gaps)), float(np.percentile(gaps, 99)),
                    float(gaps.max()), int(over.sum()), limit_s,
                    tuple(round(float(starts[i]), 2) for i in worst))


def stream_pauses(events: Sequence[dict[str, Any]]) -> list[tuple[float, float]]:
    """(stop_s, restart_s) of every deliberate stop of the setpoint stream in events.jsonl
    (restart_s = inf when it was not started again)."""
    pauses: list[tuple[float, float]] = []
    stopped_at: float | None = None
    for e in events:
        if e.get("event") != "command":
            continue
        if e.get("kind") == "stop_setpoints" and stopped_at is None:
            stopped_at = float(e["t_s"])
        elif e.get("kind") == "start_setpoints" and stopped_at is not None:
            pauses.append((stopped_at, float(e["t_s"])))
            stopped_at = None
    if stopped_at is not None:
        pauses.append((stopped_at, math.inf))
    return pauses


# ---------------------------------------------------------------------------------------------
# The run
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class SoakOptions:
    """One soak: what to fly, how fast, how often to sample, where to write."""

    search_s: float = 1800.0  # mission.time_limit_s: the search, without take-off and landing
    speedup: float = 4.0  # simulated seconds per wall second
    targets: int = 30
    clutter_per_frame: float = 0.2  # mean false tags per frame (= per estimator step)
    out_dir: Path = Path("out/soak")
    rss_every_s: float = 10.0  # simulated seconds between RSS samples
    seed: int | None = None  # None: the scenario's
    stop_margin_s: float = 120.0  # a mission not over this long after the time limit is stopped
    pilot_resumes: bool = False  # a pilot selects OFFBOARD again when the search has stopped
    planner: str = "lawnmower"  # search.planner: lawnmower or search-track


def soak_scenario(targets: int, clutter_per_frame: float, seed: int | None = None) -> Scenario:
    """The soak-30-targets scenario with `targets` targets and clutter_per_frame false tags per
    frame on average (clutter_prob + clutter_rate = clutter_per_frame * frames per step)."""
    data = load_toml(sitl_scenarios()[SCENARIO], "scenario")
    camera, sensor = data["camera"], data["sensor"]
    per_step = clutter_per_frame * max(float(camera["rate_hz"]) * float(data["dt"]), 1.0)
    sensor["clutter_prob"] = min(per_step, 1.0)
    sensor["clutter_rate"] = per_step - sensor["clutter_prob"]
    data["targets"]["count"] = targets
    if seed is not None:
        data["seed"] = seed
    return parse_scenario(data, name=SCENARIO)


def _sweeps_needed(scenario: Scenario, search_s: float) -> int:
    """Lawn-mower passes that last longer than search_s, so the search never runs out of path."""
    world = World(*scenario.world.size_m)
    one = lawnmower_path(world, np.array(scenario.robot.start_xy), scenario.robot.lane_spacing_m, 1)
    legs = np.vstack([np.array(scenario.robot.start_xy)[None], one])
    length_m = float(np.linalg.norm(np.diff(legs, axis=0), axis=1).sum())
    return max(scenario.robot.sweeps, math.ceil(search_s * scenario.robot.speed_m_s / length_m) + 1)


class _Pilot:
    """A pilot who selects OFFBOARD again when the service stopped searching mid-air.

    Once the vehicle has been in OFFBOARD, whenever it is armed, in the air and holding or in
    Position (the autopilot's offboard failsafe, after the service stopped its stream; PX4's
    Position fallback usually returns to OFFBOARD by itself first) for PILOT_REACTION_S
    while setpoints stream again (the service, in READY, streams "hold here"), the pilot flips
    the mode switch to OFFBOARD: the service then searches on (it never does so by itself after
    a link loss). Polls every PILOT_POLL_S simulated seconds, in a thread.
    """

    def __init__(self, autopilot: MockAutopilot, clock: SimClock) -> None:
        self.resumes_at_s: list[float] = []
        self._autopilot = autopilot
        self._clock = clock
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="soak-pilot", daemon=True)

    def start(self) -> _Pilot:
        """Start watching; returns self."""
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop watching and join."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()

    def _run(self) -> None:
        searched = False
        holding_since_s: float | None = None
        while not self._stop.wait(self._clock.wall_s(PILOT_POLL_S)):
            snap = self._autopilot.snapshot()
            searched |= snap.behaviour is Behaviour.OFFBOARD
            holding = (searched and snap.online and snap.armed and not snap.vehicle.on_ground
                       and snap.behaviour in (Behaviour.HOLD, Behaviour.POSITION)
                       and snap.setpoints_streaming)
            if not holding:
                holding_since_s = None
                continue
            if holding_since_s is None:
                holding_since_s = snap.clock_s
            elif snap.clock_s - holding_since_s >= PILOT_REACTION_S:
                self._autopilot.pilot_set_mode(Behaviour.OFFBOARD)
                self.resumes_at_s.append(round(snap.clock_s, 1))
                holding_since_s = None


class _Probes:
    """What the soak attaches to the SITL that fly() builds."""

    def __init__(self, rss_every_s: float, pilot_resumes: bool) -> None:
        self.rss_every_s = rss_every_s
        self.pilot_resumes = pilot_resumes
        self.sitl: Sitl | None = None
        self.rss: RssSampler | None = None
        self.pilot: _Pilot | None = None
        # array, not list: 8 / 4 bytes a sample, so the probes themselves hardly grow the RSS
        self.setpoints_received_s = array.array("d")
        self.loop_lags_ms = array.array("f")
        self.long_lags: list[tuple[float, float]] = []  # (simulated t_s at the end, wall ms)

    def attach(self, sitl: Sitl) -> None:
        """Start the RSS sampler on the SITL's clock, record every setpoint accepted and, if
        asked, start the pilot."""
        self.sitl = sitl
        clock: SimClock = sitl.clock
        self.rss = RssSampler(clock.now_s, self.rss_every_s, clock.wall_s(1.0)).start()
        autopilot = sitl.autopilot
        if self.pilot_resumes:
            self.pilot = _Pilot(autopilot, clock).start()
        # runs on the autopilot's thread, under its lock: an append, nothing more
        autopilot.on_setpoint = self.setpoints_received_s.append


@dataclass(frozen=True)
class SoakReport:
    """What a soak measured (times are simulated seconds unless named wall)."""

    options: SoakOptions
    scenario: Scenario
    out_dir: Path  # the service's run folder (its parent, the soak's folder, has rss.csv)
    sim_s: float
    wall_s: float
    steps: int
    steps_due: int  # estimator.rate_hz times the time from the first step to the last
    blind_steps: dict[str, int]  # reason -> count
    frames_published: int
    frames_late: int
    rss_t_s: FloatArray
    rss_mb: FloatArray
    rss_hwm_mb: float  # VmHWM at the end: the process's peak, warm-up included
    rss_slope_mb_per_h: float
    rss_growth_after_warmup_mb: float  # highest sample after the warm-up minus the first one
    checkpoint_mb: float  # size of the service's last estimator checkpoint (NaN: none)
    track_log_rows: int | None  # rows of the filter's track history log in it, if it has one
    components_max: int
    components_median: float
    components_cap: int
    setpoint_period_s: float
    loop_lag_ms: tuple[float, float, float]  # median, p99, max wall ms the event loop woke late
    long_lags: list[tuple[float, float]]  # (simulated t_s, wall ms) of lags over LONG_LAG_MS
    sent: GapStats  # setpoint events of the service (events.jsonl)
    received: GapStats  # setpoints the autopilot accepted
    mission_state: str
    landed: bool
    mission_texts: list[str]  # the mission's status texts, in order
    pilot_resumes_at_s: list[float]  # when the soak's pilot selected OFFBOARD again
    threads_left: list[str]  # Python threads started by the run and still alive after it
    fds_left: int  # file descriptors open after the run that were not before it
    errors: list[str]  # "error" events and failed commands
    confirmed: int
    targets_found: int
    targets_missed: int
    false_tracks: int
    truth_count: int
    counters: dict[str, int] = field(default_factory=dict)


def _checkpoint_figures(run_dir: Path) -> tuple[float, int | None]:
    """(MB, rows of the tracks' history log or None) of the run's last estimator checkpoint.

    The checkpoint is the service's own pickle of its filter state (written in this run), and
    its size follows whatever the state keeps; the history log is read only if it is there.
    """
    path = run_dir / "checkpoint.pkl"
    if not path.is_file():
        return math.nan, None
    with path.open("rb") as fh:
        data = pickle.load(fh)  # our own run's file
    rows = getattr(getattr(getattr(data.get("state"), "tracks", None), "log", None),
                   "length", None)
    return path.stat().st_size / 1e6, rows if isinstance(rows, int) else None


def _open_fds() -> int:
    """File descriptors this process has open (Linux)."""
    return len(list(Path("/proc/self/fd").iterdir()))


def _overrides(scenario: Scenario, options: SoakOptions) -> dict[str, dict[str, Any]]:
    """The service configuration tables the soak changes (on top of sitl/service.toml)."""
    return {
        "search": {"sweeps": _sweeps_needed(scenario, options.search_s),
                   "planner": options.planner},
        "mission": {"end": "time", "time_limit_s": options.search_s, "end_action": "land"},
        "estimator": {"clutter_per_scan": options.clutter_per_frame},
        "output": {"plots": False},
    }


async def _watch_loop(probes: _Probes) -> None:
    """Until cancelled: how late this event loop wakes from a LAG_PROBE_WALL_S sleep (wall ms),
    and the simulated time of each lag over LONG_LAG_MS.

    The service's tasks share the loop, so a late wake-up is time the loop was busy elsewhere
    (or waited for the GIL, or for a CPU).
    """
    while True:
        before = time.perf_counter()
        await asyncio.sleep(LAG_PROBE_WALL_S)
        lag_ms = 1e3 * max(time.perf_counter() - before - LAG_PROBE_WALL_S, 0.0)
        probes.loop_lags_ms.append(lag_ms)
        if lag_ms > LONG_LAG_MS and probes.sitl is not None:
            probes.long_lags.append((probes.sitl.clock.now_s(), lag_ms))


async def _fly(scenario: Scenario, options: SoakOptions, out_dir: Path,
               probes: _Probes) -> demo.DemoResult:
    watch = asyncio.get_running_loop().create_task(_watch_loop(probes))
    try:
        tables = _overrides(scenario, options)
        return await demo.fly(scenario, speedup=options.speedup, out_dir=out_dir,
                              stop_after_s=options.search_s + options.stop_margin_s,
                              on_sitl=probes.attach,
                              search=tables["search"], mission=tables["mission"],
                              estimator=tables["estimator"], output=tables["output"])
    finally:
        watch.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await watch


def _fresh_dir(root: Path) -> Path:
    """A new, empty folder under root for one soak (its own output.dir)."""
    stamp = datetime.now(UTC).strftime("soak-%Y%m%dT%H%M%SZ")
    path, n = root / stamp, 1
    while path.exists():
        n += 1
        path = root / f"{stamp}-{n}"
    path.mkdir(parents=True)
    return path


def soak(options: SoakOptions) -> SoakReport:
    """Fly one soak mission (blocking, its own event loop) and measure it."""
    scenario = soak_scenario(options.targets, options.clutter_per_frame, options.seed)
    probes = _Probes(options.rss_every_s, options.pilot_resumes)
    out_dir = _fresh_dir(options.out_dir)
    threads_before = set(threading.enumerate())
    fds_before = _open_fds()
    wall_start_s = time.monotonic()
    try:
        result = asyncio.run(_fly(scenario, options, out_dir, probes))
    finally:
        if probes.rss is not None:
            probes.rss.stop()
        if probes.pilot is not None:
            probes.pilot.stop()
    wall_s = time.monotonic() - wall_start_s
    threads_left = sorted(t.name for t in threading.enumerate()
                          if t not in threads_before and t.is_alive())
    fds_left = _open_fds() - fds_before
    assert probes.sitl is not None and probes.rss is not None  # fly() built its Sitl
    sitl = probes.sitl
    run_dir = result.run.out_dir
    steps, events = read_steps(run_dir), read_events(run_dir)
    config = demo.service_config(scenario, sitl, out_dir, **_overrides(scenario, options))
    period_s = 1.0 / config.mission.setpoint_rate_hz
    cap = config.filter.max_components
    rate_hz = config.estimator.rate_hz

    components = np.array([s["components"] for s in steps], dtype=np.int64)
    blind: dict[str, int] = {}
    for record in steps:
        if record["blind"] is not None:
            blind[record["blind"]] = blind.get(record["blind"], 0) + 1
    step_t = [float(s["t_s"]) for s in steps]
    steps_due = 1 + round((step_t[-1] - step_t[0]) * rate_hz) if step_t else 0

    samples = np.array(probes.rss.samples, dtype=np.float64).reshape(-1, 2)
    rss_t, rss = samples[:, 0], samples[:, 1]
    np.savetxt(out_dir / "rss.csv", samples, fmt="%.3f", delimiter=",", header="t_s,rss_mb",
               comments="")
    after = rss_t >= rss_t[0] + WARMUP_FRACTION * (rss_t[-1] - rss_t[0])
    growth = float(rss[after].max() - rss[after][0]) if after.any() else math.nan

    checkpoint_mb, log_rows = _checkpoint_figures(run_dir)
    pauses = stream_pauses(events)
    sent_s = [float(e["t_s"]) for e in events if e["event"] == "setpoint"]
    sc = result.score
    final = result.autopilot
    armed_s = next((e["t_s"] for e in events if e["event"] == "mode" and e["armed"]), math.inf)
    errors = [f"{e['event']}: {e.get('error') or e.get('kind')}" for e in events
              if e["event"] == "error" or (e["event"] == "command_failed" and not (
                  e["kind"] == "arm" and e["t_s"] < armed_s))]  # PX4's transient refusals
    return SoakReport(
        options=options, scenario=scenario, out_dir=run_dir,
        sim_s=final.clock_s, wall_s=wall_s, steps=len(steps), steps_due=steps_due,
        blind_steps=blind, frames_published=sitl.frames.published, frames_late=sitl.frames.late,
        rss_t_s=rss_t, rss_mb=rss, rss_hwm_mb=read_rss_mb("VmHWM"),
        rss_slope_mb_per_h=rss_slope_mb_per_h(rss_t, rss), rss_growth_after_warmup_mb=growth,
        checkpoint_mb=checkpoint_mb, track_log_rows=log_rows,
        components_max=int(components.max(initial=0)),
        components_median=float(np.median(components)) if len(components) else math.nan,
        components_cap=cap, setpoint_period_s=period_s,
        loop_lag_ms=_median_p99_max(probes.loop_lags_ms), long_lags=list(probes.long_lags),
        sent=gap_stats(sent_s, period_s, pauses),
        received=gap_stats(probes.setpoints_received_s, period_s, pauses),
        mission_state=result.run.mission_state,
        mission_texts=[str(e["text"]) for e in events
                       if e["event"] == "command" and e.get("kind") == "statustext"],
        threads_left=threads_left, fds_left=fds_left,
        pilot_resumes_at_s=[] if probes.pilot is None else list(probes.pilot.resumes_at_s),
        landed=not final.armed and final.vehicle.on_ground,
        errors=errors, confirmed=len(result.run.tracks),
        targets_found=len(sc.errors_m) - sc.missed, targets_missed=sc.missed,
        false_tracks=sc.false_tracks, truth_count=len(sc.errors_m),
        counters=dict(result.run.counters))


def _median_p99_max(values: Sequence[float]) -> tuple[float, float, float]:
    if not values:
        return math.nan, math.nan, math.nan
    a = np.asarray(values, dtype=np.float64)
    return float(np.median(a)), float(np.percentile(a, 99)), float(a.max())


def _gap_line(name: str, g: GapStats) -> str:
    worst = f" (at t = {', '.join(f'{t:g}' for t in g.worst_at_s)} s)" if g.worst_at_s else ""
    return (f"  {name}: {g.count} setpoints, period median {g.median_s:.3f} s, "
            f"p99 {g.p99_s:.3f} s, max gap {g.max_s:.3f} s; {g.over_limit} gaps > "
            f"{g.limit_s:.3f} s{worst}")


def _worst_lags(lags: Sequence[tuple[float, float]], n: int = 5) -> str:
    worst = sorted(lags, key=lambda lag: -lag[1])[:n]
    if not worst:
        return ""
    return " (" + ", ".join(f"{ms:.0f} ms at t = {t:.1f} s" for t, ms in worst) + ")"


def _times_line(times_s: Sequence[float], n: int = 10) -> str:
    if not times_s:
        return ""
    more = ", ..." if len(times_s) > n else ""
    return f" (at t = {', '.join(f'{t:g}' for t in times_s[:n])}{more} s)"


def _texts_line(texts: Sequence[str]) -> str:
    """The distinct texts in first-seen order, with a count when one came more than once."""
    counts: dict[str, int] = {}
    for text in texts:
        counts[text] = counts.get(text, 0) + 1
    return " | ".join(text if n == 1 else f"{text} (x{n})" for text, n in counts.items())


def report_lines(r: SoakReport) -> list[str]:
    """The figures the soak command prints."""
    o, sc = r.options, r.scenario
    blind = ", ".join(f"{k}: {v}" for k, v in sorted(r.blind_steps.items())) or "none"
    cap_ok = "never above the cap" if r.components_max <= r.components_cap else "ABOVE THE CAP"
    return [
        f"soak: {sc.name}, {sc.targets.count} moving targets, {o.clutter_per_frame:g} false "
        f"tags per frame, search {o.search_s:g} s, speed-up {o.speedup:g}x",
        f"simulated {r.sim_s:.1f} s ({r.sim_s / 60:.1f} min) in {r.wall_s:.1f} s wall: "
        f"{r.sim_s / r.wall_s:.2f}x achieved",
        f"  estimator steps {r.steps} of {r.steps_due} due "
        f"({100 * r.steps / max(r.steps_due, 1):.0f} %); camera frames rendered "
        f"{r.frames_published}, late (skipped) {r.frames_late}",
        f"RSS: first {r.rss_mb[0]:.1f} MB, peak sampled {r.rss_mb.max():.1f} MB (VmHWM "
        f"{r.rss_hwm_mb:.1f} MB), last {r.rss_mb[-1]:.1f} MB; {len(r.rss_mb)} samples",
        f"  after the first {100 * WARMUP_FRACTION:.0f} %: slope {r.rss_slope_mb_per_h:+.1f} MB "
        f"per simulated hour, growth {r.rss_growth_after_warmup_mb:+.1f} MB",
        f"  estimator checkpoint at the end: {r.checkpoint_mb:.1f} MB"
        + ("" if r.track_log_rows is None else
           f", of which a track history of {r.track_log_rows} rows"),
        f"components: max {r.components_max}, median {r.components_median:.0f}, cap "
        f"{r.components_cap} ({cap_ok})",
        f"setpoint stream (period {r.setpoint_period_s:.3f} s, simulated time):",
        _gap_line("sent (events.jsonl)", r.sent),
        _gap_line("received (autopilot)", r.received),
        f"  event loop woke late by (wall): median {r.loop_lag_ms[0]:.1f} ms, p99 "
        f"{r.loop_lag_ms[1]:.1f} ms, max {r.loop_lag_ms[2]:.1f} ms (x {o.speedup:g} in "
        f"simulated time); {len(r.long_lags)} over {LONG_LAG_MS:g} ms{_worst_lags(r.long_lags)}",
        f"steps blind: {sum(r.blind_steps.values())} of {r.steps} ({blind})",
        f"confirmed at the end: {r.confirmed} tracks; {r.targets_found} of {r.truth_count} "
        f"targets within 3 m, {r.targets_missed} missed, {r.false_tracks} false",
        f"service: state {r.mission_state}, {'landed and disarmed' if r.landed else 'NOT landed'}"
        f", errors: {'; '.join(r.errors) or 'none'}; threads left {len(r.threads_left)}, "
        f"file descriptors left {r.fds_left}",
        f"  mission: {_texts_line(r.mission_texts)}",
        ("  the soak's pilot selected OFFBOARD again "
         f"{len(r.pilot_resumes_at_s)} times{_times_line(r.pilot_resumes_at_s)}"
         if o.pilot_resumes else "  (no pilot: a search the service stopped stays stopped)"),
        f"run folder: {r.out_dir}",
    ]


def soak_figures(r: SoakReport) -> dict[str, float | int | str]:
    """The soak's headline figures, for docs/reliability.md (sitl/figures.py)."""
    return {"simulated_min": round(r.sim_s / 60.0, 1), "speedup": round(r.sim_s / r.wall_s, 2),
            "targets": r.scenario.targets.count, "rss_peak_mb": round(r.rss_hwm_mb, 1),
            "rss_slope_mb_per_h": round(r.rss_slope_mb_per_h, 1),
            "components_max": r.components_max, "components_cap": r.components_cap,
            "setpoint_period_median_s": round(r.received.median_s, 3),
            "setpoint_max_gap_sent_s": round(r.sent.max_s, 3),
            "setpoint_max_gap_received_s": round(r.received.max_s, 3),
            "setpoint_gaps_over_1.5_periods_sent": r.sent.over_limit,
            "setpoint_gaps_over_1.5_periods_received": r.received.over_limit,
            "steps": f"{r.steps} of {r.steps_due}", "mission": r.mission_state}


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
    parser.add_argument("--planner", choices=("lawnmower", "search-track"), default="lawnmower",
                        help="the search planner (search.planner)")
    parser.add_argument("--pilot-resumes", action="store_true",
                        help="a pilot selects OFFBOARD again whenever the search stopped mid-air")
    args = parser.parse_args()
    route_mavsdk_log(lambda line: print(f"  {line}", file=sys.stderr, flush=True))
    options = SoakOptions(search_s=60.0 * args.minutes, speedup=args.speedup,
                          targets=args.targets, clutter_per_frame=args.clutter,
                          out_dir=args.out, rss_every_s=args.rss_every, seed=args.seed,
                          pilot_resumes=args.pilot_resumes, planner=args.planner)
    print(f"soak: {args.minutes:g} simulated minutes of search at {args.speedup:g}x, "
          f"about {(60.0 * args.minutes + 45.0) / args.speedup / 60.0:.1f} min wall", flush=True)
    report = soak(options)
    for line in report_lines(report):
        print(line, flush=True)
    suffix = "" if args.planner == "lawnmower" else f"-{args.planner}"
    record_figure(f"soak-{args.minutes:g}min{suffix}", **soak_figures(report))


if __name__ == "__main__":
    main()
