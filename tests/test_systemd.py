"""Deployment: the unit file verifies, and the service talks systemd's notify protocol."""

from __future__ import annotations

import asyncio
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from companion.notify import Notifier
from companion.service import Service
from companion.sim.scenario import load_scenario
from sitl.cli import sitl_scenarios
from sitl.demo import service_config
from sitl.figures import record_figure
from sitl.link import free_udp_port
from sitl.runner import Sitl

pytestmark = pytest.mark.sitl

ROOT = Path(__file__).resolve().parent.parent
UNIT = ROOT / "systemd" / "companion.service"
INSTALLED_BINARY = "/opt/companion/venv/bin/companion"  # where the README installs it
SPEEDUP = 4.0


def test_the_unit_file_verifies(tmp_path: Path) -> None:
    text = UNIT.read_text()
    for line in ("Type=notify", "NotifyAccess=main", "Restart=on-failure", "User=companion",
                 "NoNewPrivileges=yes", "ProtectSystem=strict", "ProtectHome=yes",
                 "PrivateTmp=yes", "DevicePolicy=closed", "After=network-online.target",
                 "Nice=-5", "CPUWeight=400", "RestrictRealtime=yes"):
        assert f"\n{line}\n" in text, line
    assert "WatchdogSec=" in text and "DeviceAllow=char-video4linux rw" in text
    # systemd-analyze checks that ExecStart's program exists: point it at this installation.
    unit = tmp_path / "companion.service"
    unit.write_text(text.replace(INSTALLED_BINARY, str(Path(sys.prefix) / "bin" / "companion")))
    analyze = shutil.which("systemd-analyze")
    assert analyze, "systemd-analyze is needed (Debian package systemd; make test installs it)"
    done = subprocess.run([analyze, "verify", str(unit)], capture_output=True, text=True,
                          timeout=60, check=False)
    assert done.returncode == 0 and not done.stderr.strip(), done.stderr


def test_the_unit_is_hardened_to_an_exposure_of_2_1_at_most(tmp_path: Path) -> None:
    """`systemd-analyze security` scores the unit's sandboxing: 0 (locked down) to 10; the
    operator's page (a TCP listener, no capability) must not raise it above 2.1."""
    analyze = shutil.which("systemd-analyze")
    assert analyze, "systemd-analyze is needed (Debian package systemd; make test installs it)"
    unit = tmp_path / "companion.service"
    unit.write_text(UNIT.read_text())
    done = subprocess.run([analyze, "security", "--offline=yes", "--no-pager", str(unit)],
                          capture_output=True, text=True, timeout=60, check=False)
    found = re.search(r"Overall exposure level for companion\.service: (\d+\.\d+)", done.stdout)
    assert found, done.stdout[-500:] + done.stderr
    exposure = float(found.group(1))
    assert exposure <= 2.1
    record_figure("systemd-security", exposure=exposure)


class StalledDetector:
    """Stands in for pupil-apriltags' detector and hangs until released: a stalled pipeline."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.entered = threading.Event()

    def detect(self, image: object) -> list[object]:
        self.entered.set()
        self.release.wait()
        return []


def test_ready_then_watchdog_which_stops_when_the_pipeline_stalls(tmp_path: Path) -> None:
    address = tmp_path / "notify"
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    listener.bind(str(address))
    listener.setblocking(False)
    received: list[tuple[float, str]] = []
    scenario = load_scenario(sitl_scenarios()["field-5-tags"])

    async def session() -> None:
        loop = asyncio.get_running_loop()

        async def listen() -> None:
            while True:
                data = await loop.sock_recv(listener, 4096)
                received.append((time.monotonic(), data.decode()))

        async def until(condition: object, timeout_s: float) -> None:
            deadline = time.monotonic() + timeout_s
            while not condition():  # type: ignore[operator]
                assert time.monotonic() < deadline, received[-5:]
                await asyncio.sleep(0.05)

        with Sitl(scenario, speedup=SPEEDUP, mavlink_port=free_udp_port()) as sitl:
            service = Service(service_config(scenario, sitl, tmp_path), camera=scenario.camera,
                              clock=sitl.clock.now_s, time_scale=SPEEDUP,
                              notifier=Notifier(str(address), watchdog_usec=1_000_000))
            stop = asyncio.Event()
            listening = asyncio.create_task(listen())
            running = asyncio.create_task(service.run(stop))
            await until(lambda: any(m.startswith("READY=1") for _, m in received), 30.0)
            await until(lambda: sum(m == "WATCHDOG=1" for _, m in received) >= 6, 10.0)
            stalled = StalledDetector()
            service.pipeline.detector = stalled  # type: ignore[assignment]
            await until(stalled.entered.is_set, 10.0)
            stalled_at = time.monotonic()
            await asyncio.sleep(4.0)  # longer than the 2 s of silence that count as a stall
            stalled.release.set()
            stop.set()
            await running
            listening.cancel()

        watchdogs = np.array([t for t, m in received if m == "WATCHDOG=1"])
        before = watchdogs[watchdogs < stalled_at]
        gaps = np.diff(before[-5:])
        assert np.all((gaps > 0.45) & (gaps < 0.8)), gaps  # every half of WatchdogSec
        assert not np.any(watchdogs > stalled_at + 2.6)  # silent once the pipeline is stuck

    asyncio.run(session())
    while True:  # what arrived after the listener stopped
        try:
            received.append((time.monotonic(), listener.recv(4096).decode()))
        except BlockingIOError:
            break
    listener.close()
    statuses = [m for _, m in received if m.startswith("STATUS=")]
    assert any("searching" in m or "ready" in m for m in statuses), statuses
    assert received[-1][1] == "STOPPING=1"
