"""Run independent tasks in parallel: local worker processes, or a dask.distributed cluster.

`run_tasks(fn, tasks, jobs, scheduler)` calls `fn(*task)` for every task and returns the results
in task order. Without a scheduler the tasks run on a local process pool of `jobs` workers (in
this process when jobs = 1); with `scheduler = "tcp://HOST:PORT"` they are submitted to that
dask scheduler. `fn` must be a module-level (picklable) pure function of its arguments, so that
both engines give the same results for the same tasks. dask.distributed is imported only when
a scheduler is given (the optional `cluster` extra).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any, TypeVar
from urllib.parse import urlsplit

from companion.errors import ConfigError

__all__ = ["CONNECT_TIMEOUT_S", "Progress", "check_scheduler_address", "run_tasks"]

R = TypeVar("R")
Progress = Callable[[int, int], None]

CONNECT_TIMEOUT_S = 10.0
_SCHEMES = ("tcp", "tls")
_OPTION = "--scheduler"


def check_scheduler_address(address: str) -> str:
    """The address itself when it reads SCHEME://HOST:PORT (tcp or tls); ConfigError otherwise."""
    expected = f"expected tcp://HOST:PORT, got {address!r}"
    try:
        parts = urlsplit(address)
        port = parts.port
    except ValueError as exc:
        raise ConfigError(_OPTION, f"{expected} ({exc})") from exc
    if parts.scheme not in _SCHEMES or not parts.hostname or port is None or port == 0:
        raise ConfigError(_OPTION, expected)
    if parts.path not in ("", "/") or parts.query or parts.fragment:
        raise ConfigError(_OPTION, expected)
    return address


def run_tasks(
    fn: Callable[..., R],
    tasks: Sequence[tuple[Any, ...]],
    jobs: int,
    scheduler: str | None = None,
    progress: Progress | None = None,
) -> list[R]:
    """fn(*task) for every task, in task order; on `jobs` local processes or on `scheduler`.

    `progress(done, total)` is called after each finished task (in completion order). A task's
    exception is raised here. ConfigError (naming --scheduler) when the address is malformed,
    dask.distributed is not installed, or no scheduler answers within CONNECT_TIMEOUT_S.
    """
    if jobs < 1:
        raise ConfigError("--jobs", f"must be >= 1, got {jobs}")
    report: Progress = progress if progress is not None else _no_progress
    if scheduler is not None:
        return _run_on_cluster(fn, tasks, check_scheduler_address(scheduler), report)
    if jobs == 1:
        return _run_here(fn, tasks, report)
    return _run_on_pool(fn, tasks, jobs, report)


def _no_progress(done: int, total: int) -> None:
    """Progress that nobody watches."""


def _run_here(fn: Callable[..., R], tasks: Sequence[tuple[Any, ...]], report: Progress) -> list[R]:
    """Every task in this process, one after the other."""
    results = []
    for done, task in enumerate(tasks, start=1):
        results.append(fn(*task))
        report(done, len(tasks))
    return results


def _run_on_pool(
    fn: Callable[..., R], tasks: Sequence[tuple[Any, ...]], jobs: int, report: Progress
) -> list[R]:
    """Every task on a local pool of `jobs` worker processes."""
    results: dict[int, R] = {}
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        futures = {pool.submit(fn, *task): i for i, task in enumerate(tasks)}
        for done, future in enumerate(as_completed(futures), start=1):
            results[futures[future]] = future.result()
            report(done, len(tasks))
    return [results[i] for i in range(len(tasks))]


def _run_on_cluster(
    fn: Callable[..., R], tasks: Sequence[tuple[Any, ...]], address: str, report: Progress
) -> list[R]:
    """Every task on the dask scheduler at `address`; the client is closed afterwards."""
    try:  # optional (the `cluster` extra), and only partly typed: used as a plain module
        distributed: Any = importlib.import_module("distributed")
    except ImportError as exc:
        raise ConfigError(
            _OPTION, "needs dask.distributed, which is not installed (pip install "
                     "'companion[cluster]')") from exc
    try:
        client = distributed.Client(address, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise ConfigError(
            _OPTION, f"no dask scheduler answered at {address} within "
                     f"{CONNECT_TIMEOUT_S:g} s ({type(exc).__name__})") from exc
    try:
        futures = [client.submit(fn, *task, pure=False) for task in tasks]
        index = {future.key: i for i, future in enumerate(futures)}
        results: dict[int, R] = {}
        for done, future in enumerate(distributed.as_completed(futures, loop=client.loop), start=1):
            results[index[future.key]] = future.result()
            report(done, len(tasks))
        return [results[i] for i in range(len(tasks))]
    finally:
        client.close()
