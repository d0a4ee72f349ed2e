"""Scenario files by name: the ones a package ships, and a command-line argument resolved."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from companion.errors import ConfigError


def shipped_scenarios(package: str = "companion") -> dict[str, Path]:
    """The scenario files that ship with a package (companion's or sitl's), by name."""
    folder = Path(str(resources.files(package) / "scenarios"))
    return {p.stem: p for p in sorted(folder.glob("*.toml"))}


def resolve_scenario(arg: str) -> Path:
    """A scenario path from a file path or the name of a shipped scenario."""
    path = Path(arg)
    if path.exists():
        return path
    shipped = shipped_scenarios()
    if arg in shipped:
        return shipped[arg]
    names = ", ".join(shipped) or "none"
    raise ConfigError(arg, f"no such scenario file, and no shipped scenario of that name ({names})")
