"""Figures the reliability tests and the soak measure, kept for `benchmarks/reliability_report.py`.

`record_figure(name, **figures)` writes out/reliability/NAME.json (the checkout's out/ folder,
which git ignores); the report turns the latest of them into docs/reliability.md.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

FIGURES_DIR = Path(__file__).resolve().parent.parent / "out" / "reliability"


def record_figure(name: str, **figures: Any) -> None:
    """Keep one test's measured figures under name (replacing the previous ones)."""
    FIGURES_DIR.mkdir(parents=True, exist_ok=True)
    (FIGURES_DIR / f"{name}.json").write_text(json.dumps(figures, indent=1, default=float))
