"""Figures like the paper's, written as PNG files: one run's time series and map, study bands.

Every function is a pure function of its inputs and the output path: same inputs, same bytes.
Figures are built on matplotlib's object API with the Agg canvas, never through pyplot, so no
window opens, no backend is switched and no figure is registered anywhere (nothing to leak over
hundreds of calls). matplotlib is imported lazily: it is the optional `plots` extra.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from companion.errors import InputError
from companion.run_plots import (
    DPI,
    MAP_FIGSIZE_IN,
    SERIES_FIGSIZE_IN,
    plot_flight,
    plot_mahalanobis,
)
from companion.run_plots import gaps as _gaps
from companion.run_plots import new_figure as _figure
from companion.run_plots import require_matplotlib as _require_matplotlib
from companion.run_plots import save_png as _save
from companion.run_plots import time_axis as _time_axis

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from companion.sim.run import SimResult

__all__ = [
    "DPI",
    "MAP_FIGSIZE_IN",
    "SERIES_FIGSIZE_IN",
    "SeriesBand",
    "aggregate",
    "plot_bands",
    "plot_flight",
    "plot_mahalanobis",
    "plot_run",
]

FloatArray = NDArray[np.float64]

_SIGMAS = 2.0  # covariance ellipses drawn at Mahalanobis distance 2 (2-sigma)
_PNG = "png"
_SAFE_NAME = re.compile(r"[^A-Za-z0-9._-]+")


# ---------------------------------------------------------------------------------------------
# Study bands
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SeriesBand:
    """One experiment's time series aggregated over seeds: a mean line and a lo..hi band."""

    label: str
    t_s: FloatArray  # (K,)
    mean: FloatArray  # (K,)
    lo: FloatArray  # (K,) e.g. mean - std or a percentile
    hi: FloatArray  # (K,)

    def __post_init__(self) -> None:
        shapes = {name: np.shape(getattr(self, name)) for name in ("t_s", "mean", "lo", "hi")}
        k = shapes["t_s"]
        if len(k) != 1 or any(s != k for s in shapes.values()):
            raise InputError(
                f"SeriesBand {self.label!r}: t_s, mean, lo and hi must be 1-D of one length, "
                f"got shapes {shapes}"
            )


def aggregate(label: str, t_s: FloatArray, runs: Sequence[FloatArray]) -> SeriesBand:
    """Mean and population std (ddof=0) over runs per time step; band = mean -/+ std.

    NaN is a missing value and is skipped (np.nanmean semantics); a column with no value stays
    NaN. An infinite value makes its column's mean, lo and hi that infinity (NaN when both signs
    occur), as a mean over it would be. No RuntimeWarning is raised in any case.
    """
    t = np.asarray(t_s, dtype=np.float64)
    if t.ndim != 1:
        raise InputError(f"aggregate {label!r}: t_s must be 1-D, got shape {t.shape}")
    if len(runs) == 0:
        raise InputError(f"aggregate {label!r}: no runs to aggregate")
    for i, run in enumerate(runs):
        if np.shape(run) != t.shape:
            raise InputError(
                f"aggregate {label!r}: run {i} has shape {np.shape(run)}, t_s has {t.shape}"
            )
    values = np.array([np.asarray(r, dtype=np.float64) for r in runs])  # (R, K), a copy
    finite = np.isfinite(values)
    n = finite.sum(axis=0)
    some = n > 0
    total = np.where(finite, values, 0.0).sum(axis=0)
    mean = np.divide(total, n, out=np.full(t.shape, np.nan), where=some)
    dev = np.subtract(values, mean, out=np.zeros_like(values), where=finite)
    var = np.divide((dev**2).sum(axis=0), n, out=np.full(t.shape, np.nan), where=some)
    std = np.sqrt(var)
    lo, hi = mean - std, mean + std
    pos_inf = np.any(values == np.inf, axis=0)
    neg_inf = np.any(values == -np.inf, axis=0)
    for arr in (mean, lo, hi):
        arr[pos_inf] = np.inf
        arr[neg_inf] = -np.inf
        arr[pos_inf & neg_inf] = np.nan
    return SeriesBand(label, t.copy(), mean, lo, hi)


def plot_bands(  # the study code's agreed signature
    bands: Sequence[SeriesBand],
    title: str,
    ylabel: str,
    out_path: Path,
    hline: float | None = None,
    logy: bool = False,
) -> Path:
    """One line per band over a shaded lo..hi region, an optional dashed reference; -> out_path.

    Non-finite values are gaps. With logy, values <= 0 are gaps and a band's lo is clipped to
    the smallest positive value plotted; the axis stays linear when nothing is positive.
    """
    _require_matplotlib()
    if len(bands) == 0:
        raise InputError(f"plot_bands {title!r}: no bands to plot")
    if hline is not None and not math.isfinite(hline):
        raise InputError(f"plot_bands {title!r}: hline must be finite, got {hline!r}")
    series = [
        (b, _gaps(b.t_s), _gaps(b.mean, logy), _gaps(b.lo), _gaps(b.hi, logy)) for b in bands
    ]
    positive = [
        v[(v > 0) & np.isfinite(v)] for _, _, mean, _, hi in series for v in (mean, hi)
    ]
    floor = min((float(v.min()) for v in positive if v.size), default=math.nan)
    if not math.isfinite(floor) and hline is not None and hline > 0:
        floor = hline  # nothing positive to plot but the reference line
    use_log = logy and math.isfinite(floor)

    fig = _figure(SERIES_FIGSIZE_IN)
    ax = fig.add_subplot()
    for i, (band, t, mean, lo, hi) in enumerate(series):
        color = f"C{i % 10}"
        # On a log axis a band reaching down to <= 0 is drawn to the smallest positive value.
        low = np.where(np.isnan(lo), np.nan, np.maximum(lo, floor)) if use_log else lo
        ax.fill_between(t, low, hi, color=color, alpha=0.2, linewidth=0)
        ax.plot(t, mean, color=color, linewidth=1.5, label=band.label)
    if hline is not None:
        ax.axhline(hline, color="0.3", linestyle="--", linewidth=1.0, label=f"reference {hline:g}")
    if use_log:
        ax.set_yscale("log")
    ax.set_title(title)
    _time_axis(ax, np.concatenate([t for _, t, _, _, _ in series]))
    ax.set_ylabel(ylabel)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    return _save(fig, Path(out_path))


# ---------------------------------------------------------------------------------------------
# One run
# ---------------------------------------------------------------------------------------------


def plot_run(result: SimResult, out_dir: Path) -> list[Path]:
    """The four figures of one run (count, mahalanobis, ospa, trajectory) in out_dir; their paths.

    Files are named `<scenario>-s<seed>-<figure>.png` (the scenario name with characters other
    than letters, digits, '.', '_' and '-' replaced by '_'). out_dir is created if missing.
    """
    _require_matplotlib()
    _check_run(result)
    s = result.scenario
    stem = _SAFE_NAME.sub("_", f"{s.name}-s{result.seed}")
    where = f"{s.name}, seed {result.seed}"
    out = Path(out_dir)
    return [
        _save(_count_figure(result, where), out / f"{stem}-count.{_PNG}"),
        _save(_mahalanobis_figure(result, where), out / f"{stem}-mahalanobis.{_PNG}"),
        _save(_ospa_figure(result, where), out / f"{stem}-ospa.{_PNG}"),
        _save(_trajectory_figure(result, where), out / f"{stem}-trajectory.{_PNG}"),
    ]


def _check_run(r: SimResult) -> None:
    """InputError naming the first SimResult field whose shape does not fit the others."""
    if np.ndim(r.t_s) != 1:
        raise InputError(f"SimResult.t_s: expected a 1-D array, got shape {np.shape(r.t_s)}")
    k = int(np.shape(r.t_s)[0])
    for name in (
        "true_count", "tracks_confirmed", "weight_sum", "components", "ospa",
        "mahal_closest_mean", "mahal_second_mean",
    ):
        if np.shape(getattr(r, name)) != (k,):
            got = np.shape(getattr(r, name))
            raise InputError(f"SimResult.{name}: expected shape ({k},) like t_s, got {got}")
    if np.shape(r.robot_xy) != (k + 1, 2):
        got = np.shape(r.robot_xy)
        raise InputError(f"SimResult.robot_xy: expected shape ({k + 1}, 2), got {got}")
    m_shape = np.shape(r.measurements)
    if len(m_shape) != 2 or m_shape[1] != 3:
        raise InputError(f"SimResult.measurements: expected shape (M, 3), got {m_shape}")
    if np.shape(r.is_clutter) != (m_shape[0],):
        got = np.shape(r.is_clutter)
        raise InputError(f"SimResult.is_clutter: expected shape ({m_shape[0]},), got {got}")


def _count_figure(r: SimResult, where: str) -> Figure:
    """Estimated number of targets over time (the paper's Fig. est_num) for one run."""
    fig = _figure(SERIES_FIGSIZE_IN)
    ax = fig.add_subplot()
    t = _gaps(r.t_s)
    ax.plot(t, _gaps(r.components), color="C1", linewidth=1.0, drawstyle="steps-post",
            label="components")
    ax.plot(t, _gaps(r.weight_sum), color="C2", linewidth=1.0, label="sum of weights")
    ax.plot(t, _gaps(r.tracks_confirmed), color="C0", linewidth=1.5, drawstyle="steps-post",
            label="confirmed tracks")
    ax.plot(t, _gaps(r.true_count), color="k", linestyle="--", linewidth=1.0,
            drawstyle="steps-post", label="true count")
    ax.set_ylim(bottom=0.0)
    ax.set_title(f"Estimated number of targets: {where}")
    _time_axis(ax, t)
    ax.set_ylabel("number of targets")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    return fig


def _mahalanobis_figure(r: SimResult, where: str) -> Figure:
    """Mean Mahalanobis distance of the true targets to their closest / second confirmed track."""
    fig = _figure(SERIES_FIGSIZE_IN)
    ax = fig.add_subplot()
    t = _gaps(r.t_s)
    closest, second = _gaps(r.mahal_closest_mean), _gaps(r.mahal_second_mean)
    ax.plot(t, closest, color="C0", linewidth=1.2, label="closest confirmed track")
    ax.plot(t, second, color="C3", linewidth=1.2, label="second-closest confirmed track")
    both = np.concatenate([closest, second])
    positive = both[both > 0]  # NaN compares False: finite values only
    # A log axis only when the values span more than a decade: second-closest distances are
    # often ten times the closest ones, and a linear axis would flatten the closest curve.
    if positive.size and float(positive.max()) > 10.0 * float(positive.min()):
        ax.set_yscale("log")
    elif positive.size == 0:
        ax.set_ylim(0.0, 1.0)
    if not np.isfinite(both).any():
        ax.text(0.5, 0.5, "no confirmed track at any step", transform=ax.transAxes,
                ha="center", va="center", color="0.4")
    ax.set_title(f"Mean Mahalanobis distance, true targets to tracks: {where}")
    _time_axis(ax, t)
    ax.set_ylabel("Mahalanobis distance (dimensionless)")
    ax.grid(True, alpha=0.3, which="both")
    ax.legend(loc="best", fontsize="small", title="gaps: no such track for some target")
    return fig


def _ospa_figure(r: SimResult, where: str) -> Figure:
    """OSPA over time, with the cut-off c dashed."""
    c_m = float(r.scenario.metrics.ospa_c)
    p = float(r.scenario.metrics.ospa_p)
    fig = _figure(SERIES_FIGSIZE_IN)
    ax = fig.add_subplot()
    t = _gaps(r.t_s)
    ax.plot(t, _gaps(r.ospa), color="C0", linewidth=1.2, zorder=3, label=f"OSPA (p = {p:g})")
    ax.axhline(c_m, color="0.3", linestyle="--", linewidth=1.0, label=f"cut-off c = {c_m:g} m")
    ax.set_ylim(0.0, 1.05 * c_m)
    ax.set_title(f"OSPA, confirmed tracks vs true targets: {where}")
    _time_axis(ax, t)
    ax.set_ylabel("OSPA (m)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    return fig


def _trajectory_figure(r: SimResult, where: str) -> Figure:
    """The map at the last step (the paper's Fig. trajectory_lawn_and_largest)."""
    from matplotlib.collections import EllipseCollection  # noqa: PLC0415  # optional extra
    from matplotlib.lines import Line2D  # noqa: PLC0415
    from matplotlib.patches import Circle, Polygon, Rectangle  # noqa: PLC0415

    s = r.scenario
    size_x, size_y = (float(v) for v in s.world.size_m)
    robot = np.asarray(r.robot_xy, dtype=np.float64)
    last = robot[-1]
    fig = _figure(MAP_FIGSIZE_IN)
    ax = fig.add_subplot()
    handles: list[Any] = []

    ax.add_patch(Rectangle((0.0, 0.0), size_x, size_y, fill=False, edgecolor="k", linewidth=1.2))
    handles.append(Line2D([], [], color="k", linewidth=1.2, label="world"))

    if s.sensor.fov != "disk":
        corners = np.asarray(s.sensor.fov_polygon_xy, dtype=np.float64)
        reach_m = float(np.hypot(corners[:, 0], corners[:, 1]).max())
        fov_patch: Any = Polygon(corners + last, closed=True)
    else:
        reach_m = float(s.sensor.fov_radius_m)
        fov_patch = Circle((float(last[0]), float(last[1])), reach_m)
    fov_patch.set(facecolor="C0", alpha=0.12, edgecolor="C0", linewidth=1.0, label="FOV (last)")
    ax.add_patch(fov_patch)
    handles.append(fov_patch)

    (path_line,) = ax.plot(robot[:, 0], robot[:, 1], color="0.45", linewidth=0.8,
                           label="robot path")
    (robot_dot,) = ax.plot(last[0], last[1], marker="^", color="C0", markersize=8,
                           linestyle="none", label="robot (last)")
    handles += [path_line, robot_dot]

    meas = np.asarray(r.measurements, dtype=np.float64)
    clutter = np.asarray(r.is_clutter, dtype=bool)
    for mask, color, label in ((~clutter, "C2", "measurements"), (clutter, "C3", "clutter")):
        (dots,) = ax.plot(meas[mask, 1], meas[mask, 2], marker=".", markersize=2.0,
                          linestyle="none", color=color, alpha=0.35, label=label)
        handles.append(dots)

    mix = r.final_state.mixture
    comp_means = np.asarray(mix.means, dtype=np.float64)[:, :2]
    comp_covs = np.asarray(mix.covs, dtype=np.float64)[:, :2, :2]
    ok = np.isfinite(comp_means).all(axis=1) & np.isfinite(comp_covs).all(axis=(1, 2))
    widths, heights, angles = _ellipse_axes(comp_covs[ok])
    ax.add_collection(EllipseCollection(
        widths, heights, angles, units="xy", offsets=comp_means[ok],
        offset_transform=ax.transData, facecolors="none", edgecolors="C4", alpha=0.35,
        linewidths=0.8,
    ))
    handles.append(Line2D([], [], color="C4", alpha=0.35, linewidth=0.8,
                          label=f"components ({int(ok.sum())}, {_SIGMAS:g}-sigma)"))

    tracks = r.final_state.tracks
    confirmed = np.flatnonzero(np.asarray(tracks.confirmed, dtype=bool))
    for row in confirmed:
        track_id = int(tracks.ids[row])
        color = f"C{track_id % 10}"
        _, hist_means, _ = tracks.log.history(track_id)
        hist = np.asarray(hist_means, dtype=np.float64)[:, :2]
        ax.plot(hist[:, 0], hist[:, 1], color=color, linewidth=1.2)
        mean_xy = np.asarray(tracks.means[row], dtype=np.float64)[:2]
        cov_xy = np.asarray(tracks.covs[row], dtype=np.float64)[:2, :2]
        ax.plot(mean_xy[0], mean_xy[1], marker="o", color=color, markersize=4)
        if np.isfinite(cov_xy).all() and np.isfinite(mean_xy).all():
            w, h, a = _ellipse_axes(cov_xy[None])
            ax.add_collection(EllipseCollection(
                w, h, a, units="xy", offsets=mean_xy[None], offset_transform=ax.transData,
                facecolors="none", edgecolors=color, linewidths=1.2,
            ))
        ax.annotate(str(track_id), (float(mean_xy[0]), float(mean_xy[1])),
                    xytext=(4, 4), textcoords="offset points", fontsize=8, color=color)
    handles.append(Line2D([], [], color="C0", marker="o", markersize=4, linewidth=1.2,
                          label=f"confirmed tracks ({confirmed.size}):\n"
                                f"history, {_SIGMAS:g}-sigma, id"))

    truth = np.asarray(r.final_truth_xy, dtype=np.float64).reshape(-1, 2)
    (truth_marks,) = ax.plot(truth[:, 0], truth[:, 1], marker="x", color="k", markersize=8,
                             markeredgewidth=1.8, linestyle="none",
                             label=f"true targets ({truth.shape[0]})")
    handles.append(truth_marks)

    margin_m = max(0.05 * max(size_x, size_y), reach_m)
    ax.set_xlim(-margin_m, size_x + margin_m)
    ax.set_ylim(-margin_m, size_y + margin_m)
    ax.set_aspect("equal")
    t_end = float(r.t_s[-1]) if np.size(r.t_s) else 0.0
    ax.set_title(f"Trajectory and tracks at t = {t_end:g} s (step {np.size(r.t_s)}): {where}")
    ax.set_xlabel("x, east (m)")
    ax.set_ylabel("y, north (m)")
    fig.legend(handles=handles, loc="outside right upper", fontsize="small")
    return fig


# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------


def _ellipse_axes(covs_xy: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Full widths, heights (m) and angles (deg) of the _SIGMAS ellipses of (n, 2, 2) covs."""
    sym = 0.5 * (covs_xy + np.swapaxes(covs_xy, 1, 2))
    eigval, eigvec = np.linalg.eigh(sym)  # ascending; columns are eigenvectors
    eigval = np.clip(eigval, 0.0, None)  # rounding can leave a tiny negative eigenvalue
    widths = 2.0 * _SIGMAS * np.sqrt(eigval[:, 1])  # x^T P^-1 x = k^2: semi-axis k sqrt(lambda)
    heights = 2.0 * _SIGMAS * np.sqrt(eigval[:, 0])
    angles = np.degrees(np.arctan2(eigvec[:, 1, 1], eigvec[:, 0, 1]))
    return widths, heights, angles
