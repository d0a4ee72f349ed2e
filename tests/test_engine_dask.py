"""The battery on a real dask.distributed cluster (a scheduler and two workers on loopback) gives
the local engine's results.csv, timing columns aside; an unreachable scheduler is a named error.

Everything that talks to the cluster runs in child processes, so that no dask thread is left in
the test process (which forks worker pools elsewhere).
"""

from __future__ import annotations

import csv
import json
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

import companion
from companion.sim.battery import TIMING_COLUMNS

pytest.importorskip("distributed")

ROOT = Path(companion.__file__).resolve().parent.parent
DASK = Path(sys.executable).with_name("dask")
START_TIMEOUT_S = 45.0
TINY = ["battery", "--families", "close-pairs,moving-walk", "--seeds", "2", "--steps", "50",
        "--variants", "defaults,round-1"]

# The workers register once they are up; a child asks the scheduler until both are there.
WAIT_FOR_WORKERS = """
import sys
from distributed import Client
with Client(scheduler_file=sys.argv[1], timeout=20) as client:
    client.wait_for_workers(2, timeout=float(sys.argv[2]))
"""


def _env() -> dict[str, str]:
    """The environment of every child: this checkout's companion first on the path."""
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    return {**os.environ, "PYTHONPATH": path}


def _stop(processes: list[subprocess.Popen[bytes]]) -> None:
    """Terminate every process, the last started first; wait for it, kill it if it hangs."""
    for p in reversed(processes):
        if p.poll() is None:
            p.terminate()
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=10)


def _wait_for_file(path: Path, process: subprocess.Popen[bytes], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not (path.exists() and path.stat().st_size > 0):
        if process.poll() is not None:
            raise RuntimeError(f"the scheduler exited with {process.returncode}")
        if time.monotonic() > deadline:
            raise TimeoutError(f"no scheduler file {path} after {timeout_s} s")
        time.sleep(0.05)


@pytest.fixture(scope="module")
def scheduler_address(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A dask scheduler and two one-thread workers on 127.0.0.1; its address. Stopped after."""
    folder = tmp_path_factory.mktemp("dask")
    scheduler_file = folder / "scheduler.json"
    processes: list[subprocess.Popen[bytes]] = []
    logs = []
    try:
        log = (folder / "scheduler.log").open("wb")
        logs.append(log)
        processes.append(subprocess.Popen(
            [str(DASK), "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
             "--scheduler-file", str(scheduler_file)],
            cwd=folder, env=_env(), stdout=log, stderr=subprocess.STDOUT))
        _wait_for_file(scheduler_file, processes[0], START_TIMEOUT_S)
        for i in range(2):
            log = (folder / f"worker{i}.log").open("wb")
            logs.append(log)
            processes.append(subprocess.Popen(
                [str(DASK), "worker", "--scheduler-file", str(scheduler_file), "--host",
                 "127.0.0.1", "--nthreads", "1", "--nworkers", "1", "--no-dashboard",
                 "--local-directory", str(folder / f"worker{i}")],
                cwd=folder, env=_env(), stdout=log, stderr=subprocess.STDOUT))
        subprocess.run([sys.executable, "-c", WAIT_FOR_WORKERS, str(scheduler_file),
                        str(START_TIMEOUT_S)], env=_env(), check=True,
                       timeout=START_TIMEOUT_S + 30, capture_output=True)
        address = json.loads(scheduler_file.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:")
        yield address
    finally:
        _stop(processes)
        for log in logs:
            log.close()


def _companion(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "companion", *args], cwd=cwd, env=_env(),
                          capture_output=True, text=True, timeout=300, check=False)


def _rows_without_timing(path: Path) -> list[dict[str, str]]:
    with path.open() as fh:
        return [{k: v for k, v in row.items() if k not in TIMING_COLUMNS}
                for row in csv.DictReader(fh)]


def test_the_cluster_gives_the_local_results(scheduler_address: str, tmp_path: Path) -> None:
    local = _companion([*TINY, "--jobs", "2", "--out", str(tmp_path / "local")], tmp_path)
    assert local.returncode == 0, local.stderr
    cluster = _companion([*TINY, "--scheduler", scheduler_address, "--out",
                          str(tmp_path / "cluster")], tmp_path)
    assert cluster.returncode == 0, cluster.stderr
    expected = _rows_without_timing(tmp_path / "local" / "results.csv")
    assert len(expected) == 8
    assert _rows_without_timing(tmp_path / "cluster" / "results.csv") == expected
    with (tmp_path / "cluster" / "results.csv").open() as fh:
        assert set(TIMING_COLUMNS) <= set(next(csv.reader(fh)))
    # The tables carry no timing row that could differ but the filter time.
    assert cluster.stdout.count("### ") == 2


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def test_an_unreachable_scheduler_is_a_named_error(tmp_path: Path) -> None:
    address = f"tcp://127.0.0.1:{_free_port()}"
    started = time.monotonic()
    done = _companion(["battery", "--families", "clutter-0", "--seeds", "1", "--scheduler",
                       address, "--out", str(tmp_path / "out")], tmp_path)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines()[-1].startswith(
        f"companion: --scheduler: no dask scheduler answered at {address}")
    assert "Traceback" not in done.stderr
    assert time.monotonic() - started < 40.0
    assert not (tmp_path / "out").exists()
