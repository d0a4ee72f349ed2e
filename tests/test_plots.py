"""Figures: every file written is a PNG of the expected size, nothing is left open, edge cases
(polygon FOV, no tracks and no measurements, gaps, log axes) plot, aggregation is nan-aware."""

from __future__ import annotations

import dataclasses
import sys
import warnings
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # test process only: pyplot is imported to check no figure is registered

import matplotlib.image as mpimg
import matplotlib.pyplot as plt
import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from companion.errors import CompanionError, InputError
from companion.sim.plots import (
    DPI,
    MAP_FIGSIZE_IN,
    SERIES_FIGSIZE_IN,
    SeriesBand,
    aggregate,
    plot_bands,
    plot_run,
)
from companion.sim.run import SimResult, simulate
from companion.sim.scenario import Scenario, parse_scenario

FloatArray = npt.NDArray[np.float64]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
FIGURES = ("count", "mahalanobis", "ospa", "trajectory")
STEPS = 300



def _pixels(size_in: tuple[float, float]) -> tuple[int, int]:
    """(rows, columns) of a PNG written at DPI."""
    return round(size_in[1] * DPI), round(size_in[0] * DPI)


def _assert_png(path: Path, size_in: tuple[float, float]) -> None:
    assert path.is_file()
    assert path.read_bytes()[:8] == PNG_MAGIC
    image = mpimg.imread(path)
    assert image.shape[:2] == _pixels(size_in)
    assert image.shape[2] in (3, 4)
    assert float(image[..., :3].std()) > 0.01  # something was drawn, not a blank canvas


def _scenario(fov: str = "disk", empty: bool = False) -> Scenario:
    sensor: dict[str, Any] = {"fov": fov, "fov_radius": 8.0, "clutter_prob": 0.1}
    if fov == "polygon":
        sensor["fov_polygon"] = [[-7.0, -5.0], [7.0, -5.0], [9.0, 4.0], [-9.0, 4.0]]
    if empty:  # nothing to detect and no clutter: no measurement, no component, no track
        sensor.update(p_detect=0.0, clutter_prob=0.0)
    data: dict[str, Any] = {
        "name": f"tiny-{fov}" + ("-empty" if empty else ""),
        "seed": 4,
        "steps": STEPS,
        "world": {"size": [40.0, 40.0]},
        "targets": {"positions": [[8.0, 9.0], [30.0, 12.0], [21.0, 31.0]]},
        "sensor": sensor,
        "robot": {"start": [0.0, 0.0], "speed": 1.0, "lane_spacing": 10.0, "sweeps": 1},
        "belief": {"kind": "empty"} if empty else {"kind": "exact", "offset": 3.0},
        "metrics": {"ospa_c": 20.0},
    }
    return parse_scenario(data)


def _result(fov: str = "disk", empty: bool = False) -> Any:
    s = _scenario(fov, empty)
    return simulate(s)


@pytest.fixture(scope="module")
def disk_run() -> Any:
    return _result("disk")


def _arrays(result: Any) -> dict[str, FloatArray]:
    return {f.name: np.copy(getattr(result, f.name)) for f in dataclasses.fields(result)
            if isinstance(getattr(result, f.name), np.ndarray)}


# --------------------------------------------------------------------------- plot_run


def test_runs_come_from_the_real_simulation(disk_run: Any) -> None:
    assert isinstance(disk_run, SimResult)
    assert disk_run.t_s.size == STEPS


def test_plot_run_writes_four_valid_pngs_and_leaves_nothing_open(
    disk_run: Any, tmp_path: Path
) -> None:
    r = disk_run
    assert r.measurements.shape[0] > 0 and r.is_clutter.any()  # the map shows both kinds
    assert r.final_state.tracks.confirmed.any()  # and at least one confirmed track
    before = _arrays(r)
    paths = plot_run(r, tmp_path / "figs")
    assert [p.name for p in paths] == [f"tiny-disk-s4-{name}.png" for name in FIGURES]
    assert all(p.parent == tmp_path / "figs" for p in paths)
    for p in paths[:3]:
        _assert_png(p, SERIES_FIGSIZE_IN)
    _assert_png(paths[3], MAP_FIGSIZE_IN)
    assert plt.get_fignums() == []
    after = _arrays(r)
    for name, value in before.items():  # the caller's arrays are untouched
        np.testing.assert_array_equal(after[name], value, err_msg=name)
    again = plot_run(r, tmp_path / "again")  # deterministic: the same bytes
    for p, q in zip(paths, again, strict=True):
        assert p.read_bytes() == q.read_bytes(), p.name


def test_plot_run_polygon_fov(tmp_path: Path) -> None:
    r = _result("polygon")
    assert r.scenario.sensor.fov == "polygon"
    paths = plot_run(r, tmp_path)
    assert [p.name for p in paths] == [f"tiny-polygon-s4-{name}.png" for name in FIGURES]
    _assert_png(paths[3], MAP_FIGSIZE_IN)
    assert plt.get_fignums() == []


def test_plot_run_without_tracks_or_measurements(tmp_path: Path) -> None:
    r = _result("disk", empty=True)
    assert r.measurements.shape == (0, 3)
    assert not r.final_state.tracks.confirmed.any()
    assert r.final_state.mixture.weights.size == 0
    assert not np.isfinite(r.mahal_closest_mean).any()  # the Mahalanobis figure is all gaps
    # A scenario name is not trusted as a path: the files stay in out_dir.
    r = dataclasses.replace(r, scenario=dataclasses.replace(r.scenario, name="../up/and away"))
    paths = plot_run(r, tmp_path / "out")
    assert [p.name for p in paths] == [f".._up_and_away-s4-{name}.png" for name in FIGURES]
    assert all(p.parent == tmp_path / "out" for p in paths)
    for p in paths[:3]:
        _assert_png(p, SERIES_FIGSIZE_IN)
    _assert_png(paths[3], MAP_FIGSIZE_IN)
    assert plt.get_fignums() == []


def test_plot_run_rejects_series_of_the_wrong_length(disk_run: Any, tmp_path: Path) -> None:
    short = dataclasses.replace(disk_run, ospa=disk_run.ospa[:-1])
    with pytest.raises(InputError, match=r"SimResult\.ospa"):
        plot_run(short, tmp_path)
    bad_robot = dataclasses.replace(disk_run, robot_xy=disk_run.robot_xy[1:])
    with pytest.raises(InputError, match=r"SimResult\.robot_xy"):
        plot_run(bad_robot, tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_missing_matplotlib_names_the_extra(
    disk_run: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.setitem(sys.modules, name, None)  # `import matplotlib...` now fails
    with pytest.raises(CompanionError, match=r"pip install 'companion\[plots\]'"):
        plot_run(disk_run, tmp_path)
    band = SeriesBand("a", np.arange(3.0), np.ones(3), np.zeros(3), np.full(3, 2.0))
    with pytest.raises(CompanionError, match="plots need matplotlib"):
        plot_bands([band], "t", "y", tmp_path / "x.png")


# --------------------------------------------------------------------------- aggregate


def test_aggregate_hand_computed_with_nan_and_inf() -> None:
    t = np.array([1.0, 2.0, 3.0, 4.0])
    runs = [
        np.array([1.0, np.nan, np.nan, 1.0]),
        np.array([3.0, 5.0, np.nan, np.inf]),
        np.array([5.0, np.nan, np.nan, 2.0]),
    ]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        band = aggregate("exp", t, runs)
    assert band.label == "exp"
    np.testing.assert_array_equal(band.t_s, t)
    # column 0: mean 3, population std sqrt(8/3); column 1: one value, std 0; column 2: none.
    std0 = np.sqrt(8.0 / 3.0)
    np.testing.assert_allclose(band.mean[:2], [3.0, 5.0], atol=1e-12)
    np.testing.assert_allclose(band.lo[:2], [3.0 - std0, 5.0], atol=1e-12)
    np.testing.assert_allclose(band.hi[:2], [3.0 + std0, 5.0], atol=1e-12)
    assert np.isnan([band.mean[2], band.lo[2], band.hi[2]]).all()
    assert band.mean[3] == band.lo[3] == band.hi[3] == np.inf
    assert runs[1][3] == np.inf and np.isnan(runs[0][1])  # inputs untouched


def test_aggregate_both_infinities_give_nan() -> None:
    band = aggregate("x", np.arange(2.0), [np.array([np.inf, 1.0]), np.array([-np.inf, 3.0])])
    assert np.isnan(band.mean[0]) and np.isnan(band.lo[0]) and np.isnan(band.hi[0])
    assert band.mean[1] == 2.0 and band.lo[1] == 1.0 and band.hi[1] == 3.0


@settings(deadline=None, max_examples=40)
@given(
    hnp.arrays(
        np.float64,
        st.tuples(st.integers(1, 6), st.integers(1, 8)),
        elements=st.floats(-1e6, 1e6, allow_nan=False),
    )
)
def test_aggregate_matches_numpy_on_finite_runs(values: FloatArray) -> None:
    band = aggregate("p", np.arange(values.shape[1], dtype=np.float64), list(values))
    mean, std = values.mean(axis=0), values.std(axis=0)
    np.testing.assert_allclose(band.mean, mean, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(band.hi - band.mean, std, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(band.mean - band.lo, std, rtol=1e-6, atol=1e-6)


def test_aggregate_rejects_bad_runs() -> None:
    t = np.arange(3.0)
    with pytest.raises(InputError, match="no runs"):
        aggregate("x", t, [])
    with pytest.raises(InputError, match="run 1 has shape"):
        aggregate("x", t, [np.zeros(3), np.zeros(4)])
    with pytest.raises(InputError, match="t_s must be 1-D"):
        aggregate("x", np.zeros((2, 2)), [np.zeros((2, 2))])


# --------------------------------------------------------------------------- plot_bands


def _bands() -> list[SeriesBand]:
    rng = np.random.default_rng(3)
    t = np.arange(1.0, 201.0)
    out = []
    for i, label in enumerate(("with push rule", "without push rule")):
        runs = [20.0 * np.exp(-t / (50.0 * (i + 1))) + rng.normal(0, 1.0, t.size) for _ in range(5)]
        runs[0][50:60] = np.nan
        out.append(aggregate(label, t, runs))
    return out


def test_plot_bands_writes_a_png(tmp_path: Path) -> None:
    out = plot_bands(_bands(), "OSPA with and without the limited-FOV rule", "OSPA (m)",
                     tmp_path / "study" / "ospa.png", hline=3.0)
    assert out == tmp_path / "study" / "ospa.png"
    _assert_png(out, SERIES_FIGSIZE_IN)
    assert plt.get_fignums() == []


def test_plot_bands_logy_with_nonpositive_and_empty_values(tmp_path: Path) -> None:
    t = np.arange(5.0)
    nothing = SeriesBand("all nan", t, np.full(5, np.nan), np.full(5, np.nan), np.full(5, np.nan))
    dips = SeriesBand("dips below 0", t, np.array([1.0, 0.0, 2.0, np.inf, 5.0]),
                      np.array([-1.0, -2.0, 1.0, np.nan, 4.0]), np.array([3.0, 2.0, 3.0, 9, 6.0]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        a = plot_bands([nothing, dips], "largest track variance", "variance (m²)",
                       tmp_path / "a.png", hline=10.0, logy=True)
        b = plot_bands([nothing], "nothing at all", "variance (m²)", tmp_path / "b.png", logy=True)
    _assert_png(a, SERIES_FIGSIZE_IN)
    assert b.read_bytes()[:8] == PNG_MAGIC
    assert plt.get_fignums() == []


def test_plot_bands_is_deterministic(tmp_path: Path) -> None:
    bands = _bands()
    a = plot_bands(bands, "n", "number of targets", tmp_path / "a.png", hline=10.0)
    b = plot_bands(bands, "n", "number of targets", tmp_path / "b.png", hline=10.0)
    assert a.read_bytes() == b.read_bytes()


def test_plot_bands_rejects_bad_input(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no bands"):
        plot_bands([], "t", "y", tmp_path / "x.png")
    with pytest.raises(InputError, match="SeriesBand 'b'"):
        SeriesBand("b", np.arange(3.0), np.zeros(3), np.zeros(2), np.zeros(3))
    band = SeriesBand("a", np.arange(3.0), np.ones(3), np.zeros(3), np.full(3, 2.0))
    with pytest.raises(InputError, match="hline"):
        plot_bands([band], "t", "y", tmp_path / "x.png", hline=float("nan"))
    assert not (tmp_path / "x.png").exists()
