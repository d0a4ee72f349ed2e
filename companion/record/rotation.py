"""Old run folders make way for new ones: the runs never fill the disk.

`make_room` deletes whole run folders under a root, oldest first, until the run folders total at
most `max_total_bytes` and the disk has at least `min_free_bytes` free. A run folder is a direct
child of the root that is a real directory (not a symlink) named `run-*`, as the service makes
them: `run-20261122T101500Z`, then `run-20261122T101500Z-2` for a second run in that second.
Oldest is the smallest name (the names are UTC timestamps), ties broken by the numeric suffix
(none counts as 1); the name, not mtime, so that the order is deterministic. Nothing else under
the root is ever deleted, no symlink is followed, and the folders in `keep` (the current run)
stay even when they are the oldest. A folder's size is the sum of its files' sizes (lstat).

It never raises for want of room: when removing every removable run is not enough, it logs a
warning and returns. Apart from the filesystem it is pure: `disk_free` and `log` are injected.
"""

from __future__ import annotations

import os
import re
import shutil
from collections.abc import Callable, Collection
from dataclasses import dataclass
from pathlib import Path

from companion.errors import ConfigError

__all__ = ["RUN_PREFIX", "Removed", "make_room", "run_folders", "tree_bytes"]

RUN_PREFIX = "run-"
_MB = 1e6
_SUFFIX = re.compile(r"^(?P<stem>.+)-(?P<n>[0-9]+)$")


@dataclass(frozen=True)
class Removed:
    """A run folder make_room deleted, and the bytes its files took."""

    path: Path
    bytes: int


def _disk_free_bytes(path: Path) -> int:
    """Free bytes on the filesystem holding path, for an unprivileged user."""
    return shutil.disk_usage(path).free


def _mb(n_bytes: float, *, whole: bool = True) -> str:
    """Bytes as megabytes (10^6 bytes) with one decimal, or none when whole and whole is set."""
    mb = n_bytes / _MB
    return f"{mb:.0f} MB" if whole and mb == round(mb) else f"{mb:.1f} MB"


def _age_key(name: str) -> tuple[str, int, str]:
    """Sort key, oldest first: the timestamp part, then the suffix (none is run 1)."""
    match = _SUFFIX.match(name)
    if match is None:
        return name, 1, name
    return match["stem"], int(match["n"]), name


def run_folders(root: Path) -> list[Path]:
    """The run folders directly under root, oldest first; [] when root is missing."""
    try:
        entries = list(os.scandir(root))
    except (FileNotFoundError, NotADirectoryError):
        return []
    runs = [Path(e.path) for e in entries
            if e.name.startswith(RUN_PREFIX) and e.is_dir(follow_symlinks=False)]
    return sorted(runs, key=lambda p: _age_key(p.name))


def tree_bytes(path: Path) -> int:
    """Sum of the sizes of the files under path, symlinks not followed (a link counts itself)."""
    total, folders = 0, [path]
    while folders:
        try:
            entries = list(os.scandir(folders.pop()))
        except OSError:  # gone meanwhile, or unreadable: nothing we can count
            continue
        for entry in entries:
            try:
                if entry.is_dir(follow_symlinks=False):
                    folders.append(Path(entry.path))
                else:
                    total += entry.stat(follow_symlinks=False).st_size
            except OSError:
                continue
    return total


def make_room(root: Path, *, max_total_bytes: int, min_free_bytes: int,
              keep: Collection[Path] = (),
              disk_free: Callable[[Path], int] = _disk_free_bytes,
              log: Callable[[str], None] = lambda _: None) -> list[Removed]:
    """Delete the oldest run folders under root, never those in keep, until the runs fit."""
    if not max_total_bytes >= 0:
        raise ConfigError("output.max_runs_mb", f"must be >= 0, got {max_total_bytes!r}")
    if not min_free_bytes >= 0:
        raise ConfigError("output.min_free_mb", f"must be >= 0, got {min_free_bytes!r}")
    if not root.is_dir():
        return []
    runs = run_folders(root)
    kept = {_identity(p) for p in keep}
    sizes = {run: tree_bytes(run) for run in runs}
    total = sum(sizes.values())
    free = disk_free(root)
    goal = f"to keep the runs under {_mb(max_total_bytes)} and {_mb(min_free_bytes)} free"
    removed: list[Removed] = []
    for run in runs:
        if total <= max_total_bytes and free >= min_free_bytes:
            break
        if _identity(run) in kept:
            continue
        try:
            shutil.rmtree(run)
        except OSError as exc:  # part of it may be gone: count what is left
            left = tree_bytes(run)
            total -= sizes[run] - left
            free = disk_free(root)
            log(f"runs: could not remove {run.name} ({exc}); {_mb(left, whole=False)} left")
            continue
        removed.append(Removed(run, sizes[run]))
        total -= sizes[run]
        free = disk_free(root)
        log(f"runs: removed {run.name} ({_mb(sizes[run], whole=False)}) {goal}")
    if free < min_free_bytes:
        log(f"runs: warning: only {_mb(free, whole=False)} free, below the floor of "
            f"{_mb(min_free_bytes)}, and no run folder is left to remove")
    if total > max_total_bytes:
        log(f"runs: warning: the runs kept total {_mb(total, whole=False)}, over "
            f"{_mb(max_total_bytes)}, and no run folder is left to remove")
    return removed


def _identity(path: Path) -> Path:
    """The path, absolute and with symlinks resolved, to compare with keep."""
    return Path(os.path.realpath(path))
