"""The operator's page under load: five browsers watch a whole field mission (SITL, real time).

The view may cost the service under 5 % of a core (its CPU time: making the messages in worker
threads, keeping the trails and sending on the event loop) and keep the setpoints on schedule
as sent (tests/setpoint_schedule.py, the rule of every flight test). A page that stops reading
is dropped, not buffered for.
The browsers (tests/view_pages.py) run in a process of their own on one core at the lowest CPU
priority: an operator's browser runs on a phone or a laptop, not on the companion computer,
whose two cores the test shares with them.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import pytest

from benchmarks.soak import gap_stats
from companion.sim.scenario import load_scenario
from sitl.cli import sitl_scenarios
from sitl.demo import fly
from sitl.figures import record_figure
from tests.setpoint_schedule import assert_on_schedule

pytestmark = [pytest.mark.sitl, pytest.mark.browser]

SPEEDUP = 1.0  # real time, as a vehicle flies
PERIOD_S = 0.1  # mission.setpoint_rate_hz = 10
PAGES = 5
MAX_CORE_SHARE = 0.05
ROOT = Path(__file__).resolve().parents[1]


def test_five_browsers_cost_little_and_a_stalled_one_is_dropped(tmp_path: Path) -> None:
    browsers: list[subprocess.Popen[str]] = []

    def announce(text: str) -> None:
        if text.startswith("view: serving the operator's page at "):
            browsers.append(subprocess.Popen(
                [sys.executable, "-m", "tests.view_pages", text.rsplit(" ", 1)[1], str(PAGES)],
                cwd=ROOT, stdout=subprocess.PIPE, text=True))

    s = load_scenario(sitl_scenarios()["field-5-tags"])
    scenario = dataclasses.replace(s, vehicle=dataclasses.replace(s.vehicle, flavour="px4"))
    cpu_before = resource.getrusage(resource.RUSAGE_SELF)
    started = time.monotonic()
    try:
        result = asyncio.run(fly(scenario, speedup=SPEEDUP, out_dir=tmp_path,
                                 announce=announce, view={"port": 0}))
        wall_s = time.monotonic() - started
        cpu_after = resource.getrusage(resource.RUSAGE_SELF)
        assert len(browsers) == 1
        out, _ = browsers[0].communicate(timeout=120)
    finally:
        for proc in browsers:
            proc.kill()
            proc.wait()
    watched = json.loads(out)
    counters = result.run.counters
    process_share = ((cpu_after.ru_utime + cpu_after.ru_stime - cpu_before.ru_utime
                      - cpu_before.ru_stime) / wall_s)
    view_share = counters["view_cpu_ms"] / 1e3 / wall_s
    print(f"\nview: {PAGES} pages for {wall_s:.0f} s: {100 * view_share:.2f} % of a core "
          f"({counters['view_cpu_ms']} ms; the whole test process {100 * process_share:.0f} %), "
          f"{counters['view_messages_sent']} messages sent, "
          f"{counters['view_pages_dropped_slow']} stalled page dropped")
    assert result.run.mission_state in ("done", "landing"), result.run.mission_state
    assert view_share < MAX_CORE_SHARE
    assert counters["view_pages"] >= PAGES + 1
    assert counters["view_pages_dropped_slow"] == 1  # the stalled client, not a browser
    steps = counters["steps"]
    assert counters["view_messages_sent"] >= 0.8 * PAGES * steps
    assert all(seq >= 0.9 * steps for seq in watched["last_seq"]), (watched, steps)
    assert all(watched["stale_at_end"])
    events = [json.loads(line) for line in
              (result.run.out_dir / "events.jsonl").read_text().splitlines()]
    sent = [e["t_s"] for e in events if e["event"] == "setpoint" and e["mode"] == "searching"]
    assert len(sent) > 200
    gaps = gap_stats(sent, PERIOD_S)
    print(f"setpoints while searching: {len(sent)}, longest gap {1e3 * gaps.max_s:.0f} ms, "
          f"{gaps.over_limit} over {1e3 * gaps.limit_s:.0f} ms")
    record_figure("view-load", pages=PAGES, flight_wall_s=round(wall_s, 1),
                  view_cpu_percent_of_a_core=round(100 * view_share, 2),
                  max_setpoint_gap_ms=round(1e3 * gaps.max_s, 1),
                  setpoint_gaps_over_1_5_periods=gaps.over_limit,
                  stalled_page_dropped=counters["view_pages_dropped_slow"])
    assert_on_schedule(gaps, PERIOD_S)
