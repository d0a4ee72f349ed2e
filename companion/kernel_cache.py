"""Compiled kernels whose disk cache follows every module of their package, not only their own."""

from __future__ import annotations

import hashlib
import inspect
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from numba import njit
from numba.core.dispatcher import Dispatcher

F = TypeVar("F", bound=Callable[..., Any])

_STAMP = "package-sources.sha256"
"""Beside the cached kernels: the digest of the package's sources they were compiled from."""

_checked: set[Path] = set()
"""Packages whose cache this process has checked (once each, before any of their kernels runs)."""


def kernel(func: F) -> Dispatcher[F]:
    """func compiled by numba (nopython, nogil), cached on disk until any module of its package
    changes.

    numba checks a cached kernel against its own file only, yet the kernel holds the compiled
    code of the kernels it calls from other modules: after a change to fov.py alone (a `git
    pull`, or an upgrade that leaves the cache beside the package), filter._update_kernel would
    go on running the old fov.disk_kernel. So the first kernel of a package that a process
    defines compares the digest of all the package's sources with the one stamped beside the
    cache and, when they differ, clears the cache before any kernel loads from it.
    """
    dispatcher = njit(cache=True, nogil=True)(func)
    package = Path(inspect.getfile(func)).parent
    if package not in _checked:
        _checked.add(package)
        cache_dir = getattr(getattr(dispatcher, "_cache", None), "_cache_path", None)
        if cache_dir is not None:
            clear_if_stale(package, Path(cache_dir))
    return dispatcher


def clear_if_stale(package: Path, cache_dir: Path) -> bool:
    """Remove the cached kernels (*.nbi, *.nbc) in cache_dir unless they were compiled from the
    package's present sources, and stamp them with those; whether it removed them. A cache
    directory that cannot be written is left as it is."""
    digest = hashlib.sha256()
    for path in sorted(package.glob("*.py")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    stamp = cache_dir / _STAMP
    try:
        if stamp.is_file() and stamp.read_text() == digest.hexdigest():
            return False
        for cached in (*cache_dir.glob("*.nbi"), *cache_dir.glob("*.nbc")):
            cached.unlink(missing_ok=True)
        cache_dir.mkdir(parents=True, exist_ok=True)
        stamp.write_text(digest.hexdigest())
    except OSError:
        return False
    return True
