"""Figures the reliability tests and the soak measure, kept for `benchmarks/reliability_report.py`.

`record_figure(name, **figures)` writes NAME.json into `figures_dir()`: the folder named by the
environment variable COMPANION_FIGURES_DIR, else out/reliability under the current directory
(never beside the installed package). tests/conftest.py points it at the checkout's
out/reliability (which git ignores); the report turns the latest files there into
docs/reliability.md.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

__all__ = ["FIGURES_DIR_ENV", "figures_dir", "record_figure"]

FIGURES_DIR_ENV = "COMPANION_FIGURES_DIR"


def figures_dir() -> Path:
    """Where figures go: $COMPANION_FIGURES_DIR, else ./out/reliability (read at each call)."""
    return Path(os.environ.get(FIGURES_DIR_ENV) or Path("out") / "reliability")


def record_figure(name: str, **figures: Any) -> None:
    """Keep one test's measured figures under name in figures_dir() (replacing the previous)."""
    folder = figures_dir()
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{name}.json").write_text(json.dumps(figures, indent=1, default=float))
