"""A progress bar on standard error for the long commands (simulate, study, replay)."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator

from tqdm import tqdm


class ProgressBar:
    """A tqdm bar on standard error with a `update_to(done, total)` callback."""

    def __init__(self, bar: tqdm) -> None:
        self._bar = bar

    def update_to(self, done: int, total: int) -> None:
        """Set the bar to done out of total."""
        if self._bar.total != total:
            self._bar.total = total
        self._bar.update(done - self._bar.n)


@contextlib.contextmanager
def progress_bar(description: str, unit: str) -> Iterator[ProgressBar]:
    """A progress bar on standard error (quiet when standard error is not a terminal)."""
    with tqdm(desc=description, unit=unit, file=sys.stderr, mininterval=0.5, leave=False,
              disable=None) as bar:
        yield ProgressBar(bar)
