"""The figures of a flight's run folder, written as PNG files: the map and counts of the
steps, and with true positions each target's Mahalanobis distance to its closest track.

Pure functions of their inputs and the output path: same inputs, same bytes. Figures are built
on matplotlib's object API with the Agg canvas, never through pyplot, so no window opens and no
figure is registered anywhere. matplotlib is imported lazily: it is the optional `plots` extra.
The study's figures (companion.sim.plots) share the sizes and helpers defined here.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from companion.errors import CompanionError

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = [
    "DPI",
    "MAP_FIGSIZE_IN",
    "SERIES_FIGSIZE_IN",
    "gaps",
    "new_figure",
    "plot_flight",
    "plot_mahalanobis",
    "require_matplotlib",
    "save_png",
    "time_axis",
]

FloatArray = NDArray[np.float64]

DPI = 100
"""Dots per inch of every PNG: with the sizes below, images of 800 x 450 and 900 x 700 pixels."""
SERIES_FIGSIZE_IN = (8.0, 4.5)
"""Width, height (inches) of a time-series figure: wide, as time runs over thousands of steps."""
MAP_FIGSIZE_IN = (9.0, 7.0)
"""Width, height (inches) of the trajectory map: a square map plus the legend on its right."""

_PNG = "png"
_INSTALL_HINT = "plots need matplotlib: pip install 'companion[plots]'"


def plot_flight(steps: Sequence[dict[str, Any]], tracks_en_m: FloatArray, out_dir: Path,
                area_en_m: FloatArray | None = None) -> list[Path]:
    """A service run's map (area, path, footprints, detections, confirmed tracks, UTM) and counts.

    `steps` are the records of a run's steps.jsonl; tracks_en_m (n, 2) the confirmed tracks'
    easting and northing; area_en_m (k, 2) the search area's outline. Writes flight-map.png and
    flight-count.png in out_dir.
    """
    require_matplotlib()
    seen = [s for s in steps if s.get("vehicle_utm")]
    path = np.array([s["vehicle_utm"][0] for s in seen]).reshape(-1, 2)
    meas = [m for s in steps for m in (s.get("measurements_utm") or [])]
    z = np.array(meas, dtype=np.float64).reshape(-1, 2)
    tracks = np.asarray(tracks_en_m, dtype=np.float64).reshape(-1, 2)
    every = max(len(seen) // 40, 1)

    fig = new_figure(MAP_FIGSIZE_IN)
    ax = fig.add_subplot()
    if area_en_m is not None:
        area = np.vstack([area_en_m, area_en_m[:1]])
        ax.plot(area[:, 0], area[:, 1], color="tab:green", linewidth=1.2, label="search area")
    for s in seen[::every]:
        outline = np.array(s["region_utm"] + s["region_utm"][:1])
        ax.plot(outline[:, 0], outline[:, 1], color="0.8", linewidth=0.6)
    ax.plot(path[:, 0], path[:, 1], color="tab:blue", linewidth=1.0, label="vehicle")
    ax.scatter(z[:, 0], z[:, 1], s=4, color="tab:orange", label="detections")
    ax.scatter(tracks[:, 0], tracks[:, 1], s=60, marker="x", color="tab:red",
               label="confirmed tracks")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("easting (m)")
    ax.set_ylabel("northing (m)")
    ax.ticklabel_format(useOffset=True, style="plain")
    ax.legend(loc="best", fontsize="small")
    written = [save_png(fig, out_dir / "flight-map.png")]

    t = np.array([s["t_s"] for s in steps], dtype=np.float64)
    fig = new_figure(SERIES_FIGSIZE_IN)
    ax = fig.add_subplot()
    ax.step(t, [s["confirmed"] for s in steps], where="post", label="confirmed tracks")
    ax.plot(t, [s["detections"] for s in steps], ".", markersize=2, label="detections per step")
    blind = np.array([s["blind"] is not None for s in steps])
    if blind.any():
        ax.plot(t[blind], np.zeros(int(blind.sum())), "|", color="tab:gray", label="blind steps")
    ax.set_xlabel("autopilot time (s)")
    ax.set_ylabel("count")
    ax.legend(loc="best", fontsize="small")
    written.append(save_png(fig, out_dir / "flight-count.png"))
    return written


def plot_mahalanobis(t_s: FloatArray, closest: FloatArray, out_dir: Path) -> Path:
    """Each true target's Mahalanobis distance to its closest confirmed track over time.

    closest (steps, targets); +inf where no track is confirmed. Writes flight-mahalanobis.png.
    """
    require_matplotlib()
    fig = new_figure(SERIES_FIGSIZE_IN)
    ax = fig.add_subplot()
    t = gaps(t_s)
    values = np.asarray(closest, dtype=np.float64).reshape(t.size, -1)
    for j in range(values.shape[1]):
        ax.plot(t, gaps(values[:, j]), linewidth=1.0, label=f"target {j}")
    finite = values[np.isfinite(values) & (values > 0)]
    if finite.size and float(finite.max()) > 10.0 * float(finite.min()):
        ax.set_yscale("log")
    ax.set_title("Mahalanobis distance, each true target to its closest confirmed track")
    time_axis(ax, t)
    ax.set_xlabel("autopilot time (s)")
    ax.set_ylabel("Mahalanobis distance")
    ax.grid(True, alpha=0.3, which="both")
    if 0 < values.shape[1] <= 12:
        ax.legend(loc="best", fontsize="small", title="gaps: no confirmed track yet")
    return save_png(fig, out_dir / "flight-mahalanobis.png")


def require_matplotlib() -> None:
    """CompanionError with the install hint when matplotlib cannot be imported."""
    try:
        import matplotlib  # noqa: PLC0415  # lazily: matplotlib is the optional `plots` extra
        import matplotlib.backends.backend_agg  # noqa: PLC0415
        import matplotlib.figure  # noqa: PLC0415, F401
    except ImportError as exc:
        raise CompanionError(_INSTALL_HINT) from exc


def new_figure(size_in: tuple[float, float]) -> Figure:
    """A new figure on its own Agg canvas (no pyplot: nothing global to close or leak)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: PLC0415
    from matplotlib.figure import Figure  # noqa: PLC0415

    fig = Figure(figsize=size_in, dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def save_png(fig: Figure, path: Path) -> Path:
    """Write fig as PNG at path (parents created), release its artists; -> path."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, format=_PNG, dpi=DPI)
    finally:
        fig.clear()
    return path


def time_axis(ax: Axes, t_s: FloatArray) -> None:
    """x axis over the whole run, even where the series start or end with gaps."""
    finite = t_s[np.isfinite(t_s)]
    if finite.size and float(finite.max()) > float(finite.min()):
        ax.set_xlim(float(finite.min()), float(finite.max()))
    ax.set_xlabel("time (s)")


def gaps(values: object, positive_only: bool = False) -> FloatArray:
    """A float copy with non-finite values (and values <= 0 when positive_only) set to NaN."""
    out = np.array(values, dtype=np.float64, copy=True).reshape(-1)
    bad = ~np.isfinite(out)
    if positive_only:
        bad |= ~(out > 0)
    out[bad] = np.nan
    return out
