"""The flown paths of several runs side by side: one map panel per run, written as a PNG file.

`flown_path` keeps what the figure needs of a run (small, picklable: workers send it back);
`plot_paths` draws each one's path over the world with the true targets and the confirmed
tracks at the end. Like `companion.sim.plots`, the figure is built on matplotlib's object API
with the Agg canvas (no pyplot), and matplotlib is imported only when a figure is drawn.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from companion.errors import InputError
from companion.run_plots import new_figure, require_matplotlib, save_png

if TYPE_CHECKING:
    from companion.sim.run import SimResult

__all__ = ["FlownPath", "flown_path", "plot_paths"]

FloatArray = NDArray[np.float64]

PANEL_SIZE_IN = (4.6, 5.0)


@dataclass(frozen=True)
class FlownPath:
    """One run on the map: the world (m), the robot's path, the truth and the confirmed tracks
    at the end (x, y in metres), and a label for its panel."""

    label: str
    world_m: tuple[float, float]
    robot_xy: FloatArray  # (K + 1, 2), the start included
    truth_xy: FloatArray  # (n, 2) true targets at the last step
    tracks_xy: FloatArray  # (m, 2) confirmed track means at the last step

    def __post_init__(self) -> None:
        for name in ("robot_xy", "truth_xy", "tracks_xy"):
            shape = np.shape(getattr(self, name))
            if len(shape) != 2 or shape[1] != 2:
                raise InputError(f"FlownPath {self.label!r}: {name} must be (n, 2), got {shape}")


def flown_path(result: SimResult, label: str) -> FlownPath:
    """The flown path, final truth and final confirmed tracks of one simulated run."""
    tracks = result.final_state.tracks
    confirmed = np.asarray(tracks.confirmed, dtype=bool)
    size_x, size_y = (float(v) for v in result.scenario.world.size_m)
    return FlownPath(
        label=label,
        world_m=(size_x, size_y),
        robot_xy=np.asarray(result.robot_xy, dtype=np.float32),
        truth_xy=np.asarray(result.final_truth_xy, dtype=np.float64).reshape(-1, 2),
        tracks_xy=np.asarray(tracks.means, dtype=np.float64)[confirmed, :2].reshape(-1, 2),
    )


def plot_paths(paths: Sequence[FlownPath], title: str, out_path: Path) -> Path:
    """One map panel per path (same axes limits), path, truth and tracks on each; -> out_path."""
    require_matplotlib()
    from matplotlib.patches import Rectangle  # noqa: PLC0415  # optional extra

    if len(paths) == 0:
        raise InputError(f"plot_paths {title!r}: no paths to plot")
    size_x = max(p.world_m[0] for p in paths)
    size_y = max(p.world_m[1] for p in paths)
    margin_m = 0.05 * max(size_x, size_y)
    fig = new_figure((PANEL_SIZE_IN[0] * len(paths), PANEL_SIZE_IN[1]))
    axes = fig.subplots(1, len(paths), squeeze=False, sharex=True, sharey=True)[0]
    for ax, p in zip(axes, paths, strict=True):
        robot = np.asarray(p.robot_xy, dtype=np.float64)
        ax.add_patch(Rectangle((0.0, 0.0), p.world_m[0], p.world_m[1], fill=False,
                               edgecolor="k", linewidth=1.0))
        ax.plot(robot[:, 0], robot[:, 1], color="C0", linewidth=0.7, alpha=0.8,
                label="flown path")
        if robot.shape[0]:
            ax.plot(robot[0, 0], robot[0, 1], marker="s", color="C0", markersize=6,
                    linestyle="none", label="start")
            ax.plot(robot[-1, 0], robot[-1, 1], marker="^", color="C0", markersize=7,
                    linestyle="none", label="end")
        ax.plot(p.truth_xy[:, 0], p.truth_xy[:, 1], marker="x", color="k", markersize=8,
                markeredgewidth=1.8, linestyle="none",
                label=f"true targets ({p.truth_xy.shape[0]})")
        ax.plot(p.tracks_xy[:, 0], p.tracks_xy[:, 1], marker="o", markersize=9,
                markerfacecolor="none", markeredgecolor="C3", markeredgewidth=1.4,
                linestyle="none", label=f"confirmed tracks ({p.tracks_xy.shape[0]})")
        ax.set_xlim(-margin_m, size_x + margin_m)
        ax.set_ylim(-margin_m, size_y + margin_m)
        ax.set_aspect("equal")
        ax.set_title(p.label, fontsize="medium")
        ax.set_xlabel("x, east (m)")
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=2, fontsize="small")
    axes[0].set_ylabel("y, north (m)")
    fig.suptitle(title)
    return save_png(fig, Path(out_path))
