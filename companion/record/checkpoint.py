"""The estimator's state saved as it goes, so that a restarted service carries on the search.

`save_checkpoint(run_dir, data)` writes `checkpoint.pkl` in a run folder whole or not at all
(a temporary file renamed over it). `latest_checkpoint(root, ...)` finds the newest one among
the run folders under root that is younger than max_age_s; a checkpoint that cannot be read is
skipped with a reason, never raised. The data is whatever `Pipeline.checkpoint()` returns; it is
pickled, so only a run folder the service wrote itself should be trusted with it.
"""

from __future__ import annotations

import os
import pickle
from collections.abc import Callable
from pathlib import Path
from typing import Any

from companion.record.rotation import run_folders

__all__ = ["CHECKPOINT_NAME", "latest_checkpoint", "save_checkpoint"]

CHECKPOINT_NAME = "checkpoint.pkl"
_VERSION = 1


def save_checkpoint(run_dir: Path, data: dict[str, Any]) -> None:
    """Replace the run's checkpoint with data, atomically."""
    tmp = run_dir / (CHECKPOINT_NAME + ".tmp")
    with tmp.open("wb") as fh:
        pickle.dump({"version": _VERSION, **data}, fh, protocol=pickle.HIGHEST_PROTOCOL)
    os.replace(tmp, run_dir / CHECKPOINT_NAME)


def latest_checkpoint(root: Path, *, exclude: Path, max_age_s: float, now_wall_s: float,
                      log: Callable[[str], None] = lambda _: None
                      ) -> tuple[Path, dict[str, Any]] | None:
    """The newest readable checkpoint under root younger than max_age_s (by its file time)."""
    for run in reversed(run_folders(root)):
        path = run / CHECKPOINT_NAME
        if run.resolve() == exclude.resolve() or not path.is_file():
            continue
        if now_wall_s - path.stat().st_mtime > max_age_s:
            return None  # the newest is too old, and so are the ones before it
        try:
            with path.open("rb") as fh:
                data = pickle.load(fh)
            if not isinstance(data, dict) or data.get("version") != _VERSION:
                raise ValueError("not a checkpoint of this version")
        except Exception as exc:  # a torn or foreign file: say so, go on
            log(f"checkpoint: {path} is unreadable ({type(exc).__name__}: {exc}): skipped")
            continue
        return path, data
    return None
