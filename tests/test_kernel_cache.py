"""The kernel cache across modules: a change to a called kernel's module reaches its callers."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from companion.kernel_cache import clear_if_stale

_CALLER = """from companion.kernel_cache import kernel
from kernels.callee import value


@kernel
def doubled():
    return 2 * value()
"""

_CALLEE = """from companion.kernel_cache import kernel


@kernel
def value():
    return {value}
"""


def _doubled(root: Path) -> int:
    """kernels.caller.doubled() in a new interpreter (numba's cache on disk, in the package)."""
    env = {**os.environ, "PYTHONPATH": str(root)}
    env.pop("NUMBA_CACHE_DIR", None)
    done = subprocess.run(
        [sys.executable, "-c", "from kernels.caller import doubled; print(doubled())"],
        env=env, capture_output=True, text=True, check=True, timeout=120,
    )
    return int(done.stdout)


def test_a_change_to_a_called_kernels_module_reaches_the_callers_cache(tmp_path: Path) -> None:
    package = tmp_path / "kernels"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "caller.py").write_text(_CALLER)
    (package / "callee.py").write_text(_CALLEE.format(value=1))
    assert _doubled(tmp_path) == 2
    cached = sorted(p.name for p in (package / "__pycache__").glob("*.nb[ic]"))
    assert any(name.startswith("caller.doubled-") for name in cached)
    assert _doubled(tmp_path) == 2  # loaded from the cache, not cleared
    assert sorted(p.name for p in (package / "__pycache__").glob("*.nb[ic]")) == cached
    # The callee's module alone changes (a `git pull`): numba alone would run the caller's
    # cached code, which holds the old callee, and print 2.
    (package / "callee.py").write_text(_CALLEE.format(value=5))
    assert _doubled(tmp_path) == 10


def test_a_stale_cache_is_cleared_and_stamped_a_fresh_one_kept_an_unwritable_one_left(
    tmp_path: Path,
) -> None:
    package, cache = tmp_path / "package", tmp_path / "cache"
    package.mkdir()
    (package / "a.py").write_text("x = 1\n")
    assert clear_if_stale(package, cache)  # no stamp yet
    for name in ("a.f-3.py311.nbi", "a.f-3.py311.1.nbc", "a.cpython-311.pyc"):
        (cache / name).write_bytes(b"")
    assert not clear_if_stale(package, cache)
    assert len(list(cache.iterdir())) == 4
    (package / "b.py").write_text("y = 2\n")  # a new module counts as a change
    assert clear_if_stale(package, cache)
    assert sorted(p.name for p in cache.iterdir()) == ["a.cpython-311.pyc",
                                                        "package-sources.sha256"]
    (package / "b.py").write_text("y = 3\n")
    blocked = tmp_path / "blocked"
    blocked.write_text("")  # where the cache directory should be: nothing can be written
    assert not clear_if_stale(package, blocked)
