"""Debian's headless Chromium driven by Playwright, for the view's tests (no browser download)."""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from playwright.sync_api import BrowserContext, Page, sync_playwright

CHROMIUM = Path("/usr/bin/chromium")
# The network is closed: without these Chromium stalls on connections it tries to make.
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync"]
DOCS = Path(__file__).resolve().parents[1] / "docs"


@contextlib.contextmanager
def chromium(width: int = 1280, height: int = 800) -> Iterator[BrowserContext]:
    """A headless Chromium with a new, empty profile, closed at the end."""
    assert CHROMIUM.is_file(), f"{CHROMIUM} is missing: apt-get install chromium (make test does)"
    with sync_playwright() as pw, tempfile.TemporaryDirectory(prefix="chromium-") as profile:
        context = pw.chromium.launch_persistent_context(
            profile, executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS,
            viewport={"width": width, "height": height})
        try:
            yield context
        finally:
            context.close()


class InThread:
    """Runs a function in a thread (the browser's side of a test while the service flies in
    the main thread's event loop) and gives back its result or raises its error."""

    def __init__(self, target: Callable[[], Any]) -> None:
        self._target = target
        self._result: Any = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        try:
            self._result = self._target()
        except BaseException as exc:
            self._error = exc

    def start(self) -> InThread:
        """Start the thread."""
        self._thread.start()
        return self

    def result(self, timeout_s: float) -> Any:
        """Wait for the function; its result, or its error raised here."""
        self._thread.join(timeout_s)
        assert not self._thread.is_alive(), f"the browser's side took over {timeout_s} s"
        if self._error is not None:
            raise self._error
        return self._result


@contextlib.contextmanager
def serving(run_dir: Path, *extra: str) -> Iterator[str]:
    """`companion view RUN --port 0 ...` as a user starts it; the page's address."""
    err = run_dir.with_name(run_dir.name + "-view-stderr.txt")
    with err.open("w") as err_file:
        proc = subprocess.Popen([sys.executable, "-m", "companion", "view", str(run_dir),
                                 "--port", "0", *extra], stdout=subprocess.PIPE,
                                stderr=err_file, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line, err.read_text()
        yield str(json.loads(line)["url"])
    finally:
        proc.terminate()
        proc.wait(10)


def set_slider(page: Page, index: int) -> None:
    """Move the replay page's time slider to step `index` and wait until the page shows it."""
    page.eval_on_selector("#slider", """(el, k) => { el.value = String(k);
                                       el.dispatchEvent(new Event("input")); }""", index)
    page.wait_for_selector(f"body[data-seq='{index + 1}']", timeout=30_000)
