"""The view's data model: pure functions from the estimator's state to the page's JSON messages.

A page first reads a `scene` (what does not change in a flight: the search area, the geofence,
the local grid and its UTM zone), then one `step` message per estimator step: the vehicle, its
path and camera footprint, the detections and blind steps of the last scans, the PHD intensity
as a heat map, the mixture's components and the tracks with 2-sigma ellipses, recent history,
latitude / longitude and whether they are seen or coasting, with the mission's state and
counters. Positions are metres on the search frame's grid (x east, y north from the search
area's south-west corner), rounded to a centimetre.

`Trails` keeps what a step message shows of the past (the path, each track's history, the last
scans' detections and blind steps); `Trails.after` gives the trails one step later, the live
service and the replay view alike.
"""

from __future__ import annotations

import base64
import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.pipeline import SearchFrame
from companion.report import confirmed_tracks
from companion.sat.filter import SatState
from companion.sat.tracks import TrackParams, grown_covs

__all__ = ["MAX_MESSAGE_BYTES", "Status", "Trails", "Vehicle", "encode", "heat_map",
           "scene_message", "step_message", "utm_zone_name", "yaw_deg"]

FloatArray = NDArray[np.float64]
PATH_POINTS = 600  # the vehicle's path: this many recent points
HISTORY_POINTS = 30  # each track's recent positions
SCANS_KEPT = 5  # detections of this many recent scans
BLIND_KEPT = 5  # the most recent blind steps and why
MAX_COMPONENTS = 64  # the heaviest components are drawn
MAX_TRACKS = 200
HEAT_CELLS = 64  # heat map cells along the longer side of the area's box
MAX_MESSAGE_BYTES = 512_000  # a step message larger than this loses its heat map and components
SIGMA = 2.0  # ellipses are drawn at 2 sigma


def _r(value: float, digits: int = 2) -> float:
    return round(float(value), digits)


def _points(xy: FloatArray | None) -> list[list[float]] | None:
    if xy is None:
        return None
    return [[_r(x), _r(y)] for x, y in np.asarray(xy, dtype=np.float64).reshape(-1, 2)]


def utm_zone_name(epsg: int) -> str:
    """'32N' for EPSG:32632, '33S' for EPSG:32733."""
    zone = epsg % 100
    return f"{zone}{'N' if epsg // 100 == 326 else 'S'}"


def yaw_deg(q_wxyz: tuple[float, ...] | list[float]) -> float:
    """The heading (degrees clockwise from north, 0..360) of a body-to-NED quaternion."""
    w, x, y, z = (float(v) for v in q_wxyz)
    return math.degrees(math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))) % 360.0


@dataclass(frozen=True)
class Vehicle:
    """Where the vehicle is on the grid, its heading and height above home."""

    xy_m: tuple[float, float]
    heading_deg: float | None = None
    alt_m: float | None = None


@dataclass(frozen=True)
class Status:
    """The service's side of a step: mission state, link and camera health, counters, home."""

    mission: str | None = None
    link_ok: bool | None = None
    camera_ok: bool | None = None
    counters: dict[str, int] = field(default_factory=dict)
    home_xy_m: tuple[float, float] | None = None


@dataclass(frozen=True)
class Trails:
    """What step messages show of the past, oldest first, each bounded."""

    path: tuple[tuple[float, float], ...] = ()
    history: dict[int, tuple[tuple[float, float], ...]] = field(default_factory=dict)
    scans: tuple[tuple[float, tuple[tuple[float, float], ...]], ...] = ()  # (t_s, detections)
    blind: tuple[tuple[float, str], ...] = ()  # (t_s, reason)

    def after(self, t_s: float, vehicle_xy: tuple[float, float] | None,
              detections_xy: FloatArray, blind: str | None, state: SatState | None) -> Trails:
        """The trails with one more step: its vehicle position, detections, blind reason and
        the tracks' positions (tracks that ended leave their history)."""
        path = self.path
        if vehicle_xy is not None:
            here = (_r(vehicle_xy[0]), _r(vehicle_xy[1]))
            if not path or path[-1] != here:
                path = (*path, here)[-PATH_POINTS:]
        history: dict[int, tuple[tuple[float, float], ...]] = {}
        if state is not None:
            tracks = state.tracks
            for i in range(min(tracks.size, MAX_TRACKS)):
                track_id = int(tracks.ids[i])
                here = (_r(tracks.means[i, 0]), _r(tracks.means[i, 1]))
                before = self.history.get(track_id, ())
                history[track_id] = before if before and before[-1] == here else (
                    (*before, here)[-HISTORY_POINTS:])
        detections = tuple((_r(x), _r(y)) for x, y in
                           np.asarray(detections_xy, dtype=np.float64).reshape(-1, 2))
        scans = self.scans if blind is not None else (
            (*self.scans, (_r(t_s, 3), detections))[-SCANS_KEPT:])
        blinds = self.blind if blind is None else ((*self.blind, (_r(t_s, 3), blind))[-BLIND_KEPT:])
        return Trails(path, history, scans, blinds)


def heat_map(state: SatState | None, width_m: float, height_m: float,
             cells: int = HEAT_CELLS) -> dict[str, Any] | None:
    """The PHD intensity (expected targets per m²) at the centres of a grid over the box
    [0, width] x [0, height]: its size, the peak and the cells as bytes 0..255 of the peak
    (rows from the south, base64), or None when there is nothing to show."""
    if state is None or state.mixture.size == 0 or width_m <= 0 or height_m <= 0:
        return None
    cell_m = max(width_m, height_m) / cells
    nx, ny = max(1, math.ceil(width_m / cell_m)), max(1, math.ceil(height_m / cell_m))
    xs = (np.arange(nx) + 0.5) * cell_m
    ys = (np.arange(ny) + 0.5) * cell_m
    grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)  # rows from the south
    m = state.mixture
    means, covs = m.means[:, :2], m.covs[:, :2, :2]
    det = covs[:, 0, 0] * covs[:, 1, 1] - covs[:, 0, 1] * covs[:, 1, 0]
    ok = det > 0
    if not np.any(ok):
        return None
    means, covs, det, weights = means[ok], covs[ok], det[ok], m.weights[ok]
    inv = np.stack([np.stack([covs[:, 1, 1], -covs[:, 0, 1]], -1),
                    np.stack([-covs[:, 1, 0], covs[:, 0, 0]], -1)], -2) / det[:, None, None]
    d = grid[None, :, :] - means[:, None, :]
    mahal = np.einsum("kgi,kij,kgj->kg", d, inv, d)
    density = (weights / (2.0 * math.pi * np.sqrt(det)))[:, None] * np.exp(-0.5 * mahal)
    values = density.sum(axis=0)
    peak = float(values.max())
    if not peak > 0:
        return None
    cells_u8 = np.clip(np.round(255.0 * values / peak), 0, 255).astype(np.uint8)
    return {"nx": nx, "ny": ny, "cell_m": _r(cell_m, 4), "peak": float(f"{peak:.4g}"),
            "cells": base64.b64encode(cells_u8.tobytes()).decode("ascii")}


def _cov(c: FloatArray) -> list[float]:
    """A 2x2 covariance as [xx, xy, yy] (m²)."""
    return [_r(c[0, 0], 4), _r(c[0, 1], 4), _r(c[1, 1], 4)]


def _components(state: SatState | None) -> list[list[float]]:
    """The heaviest components as [x, y, xx, xy, yy, weight]."""
    if state is None or state.mixture.size == 0:
        return []
    m = state.mixture
    order = np.argsort(-m.weights, kind="stable")[:MAX_COMPONENTS]
    return [[_r(m.means[i, 0]), _r(m.means[i, 1]), *_cov(m.covs[i, :2, :2]),
             _r(m.weights[i], 4)] for i in order]


def _tracks(state: SatState | None, frame: SearchFrame, params: TrackParams,
            trails: Trails) -> list[dict[str, Any]]:
    """Every track (confirmed ones with the report's lat/lon and covariance, as tracks.csv has
    them; tentative ones too), confirmed first, by id."""
    if state is None or state.tracks.size == 0:
        return []
    tracks, t_s = state.tracks, state.t_s
    reported = {r.id: r for r in confirmed_tracks(tracks, frame.origin_utm_m, frame.utm.epsg,
                                                  frame.to_latlon, t_s, params)}
    covs = grown_covs(tracks, t_s, params.motion)
    coasting = tracks.coasting(t_s, params.coast_after_s)
    out = []
    for i in range(tracks.size):
        track_id = int(tracks.ids[i])
        r = reported.get(track_id)
        x, y = (float(v) for v in tracks.means[i, :2])
        if r is not None:
            lat, lon = r.lat_deg, r.lon_deg
            cov = [_r(r.cov_ee_m2, 4), _r(r.cov_en_m2, 4), _r(r.cov_nn_m2, 4)]
        else:
            lat, lon = (float(v) for v in frame.to_latlon(tracks.means[i, :2][None])[0])
            cov = _cov(covs[i, :2, :2])
        out.append({"id": track_id, "x": _r(x), "y": _r(y), "cov": cov,
                    "lat": round(lat, 7), "lon": round(lon, 7),
                    "confirmed": bool(tracks.confirmed[i]), "coasting": bool(coasting[i]),
                    "seen_s": _r(tracks.seen_t_s[i], 3), "born_s": _r(tracks.born_t_s[i], 3),
                    "history": [list(p) for p in trails.history.get(track_id, ())]})
    out.sort(key=lambda t: (not t["confirmed"], t["id"]))
    return out[:MAX_TRACKS]


def scene_message(frame: SearchFrame, geofence_latlon: FloatArray | None, *, mode: str,
                  rate_hz: float, expected_targets: int | None, name: str = "",
                  notes: list[str] | None = None,
                  orthophoto: dict[str, Any] | None = None) -> dict[str, Any]:
    """What a page reads once: the grid (its UTM zone and origin), the area, the fence and
    the orthophoto's address and bounds (Orthophoto.scene(), or None)."""
    fence = None
    if geofence_latlon is not None and len(geofence_latlon):
        fence_latlon = np.asarray(geofence_latlon, dtype=np.float64)
        e, n = frame.utm.geodetic_to_utm(fence_latlon[:, 0], fence_latlon[:, 1])
        fence = _points(frame.from_utm(np.column_stack([e, n])))
    return {"type": "scene", "mode": mode, "name": name, "utm_epsg": frame.utm.epsg,
            "utm_zone": utm_zone_name(frame.utm.epsg),
            "origin_utm": [_r(v, 3) for v in frame.origin_utm_m],
            "size_m": [_r(frame.world.width_m), _r(frame.world.height_m)],
            "area": _points(frame.area_xy_m), "geofence": fence, "rate_hz": rate_hz,
            "expected_targets": expected_targets, "notes": notes or [],
            "orthophoto": orthophoto}


def step_message(seq: int, frame: SearchFrame, state: SatState | None, record: dict[str, Any],
                 trails: Trails, params: TrackParams, vehicle: Vehicle | None = None,
                 status: Status | None = None, *, heat: bool = True) -> dict[str, Any]:
    """One step's message from the estimator's state after it, its step record (as in
    steps.jsonl), the trails including it and the service's status; `vehicle` None: the
    step's own sensor position."""
    status = status or Status()
    if vehicle is None and record.get("vehicle_utm"):
        xy = frame.from_utm(np.asarray(record["vehicle_utm"][0], dtype=np.float64))
        pose = (record.get("input") or {}).get("pose")
        vehicle = Vehicle((float(xy[0]), float(xy[1])),
                          yaw_deg(pose[4:8]) if pose and len(pose) >= 8 else None,
                          None)
    region = record.get("region_utm")
    footprint = None if not region else _points(
        frame.from_utm(np.asarray(region, dtype=np.float64)))
    w, h = frame.world.width_m, frame.world.height_m
    message = {
        "type": "step", "seq": seq, "t_s": _r(record.get("t_s", 0.0), 3),
        "blind": record.get("blind"), "mission": status.mission, "link_ok": status.link_ok,
        "camera_ok": status.camera_ok, "counters": status.counters,
        "home": None if status.home_xy_m is None else [_r(v) for v in status.home_xy_m],
        "vehicle": None if vehicle is None else {
            "x": _r(vehicle.xy_m[0]), "y": _r(vehicle.xy_m[1]),
            "heading_deg": None if vehicle.heading_deg is None else _r(vehicle.heading_deg, 1),
            "alt_m": None if vehicle.alt_m is None else _r(vehicle.alt_m)},
        "path": [list(p) for p in trails.path], "footprint": footprint,
        "scans": [{"t_s": t, "xy": [list(p) for p in xy]} for t, xy in trails.scans],
        "blind_steps": [{"t_s": t, "reason": why} for t, why in trails.blind],
        "expected_targets": _r(record.get("weight_sum", 0.0) if state is None
                               else state.mixture.total_weight, 3),
        "components": _components(state),
        "heat": heat_map(state, w, h) if heat else None,
        "tracks": _tracks(state, frame, params, trails),
    }
    if state is None and record.get("confirmed_ids") is not None:
        message["confirmed_ids"] = record["confirmed_ids"]
    return message


def _finite(value: Any) -> Any:
    """value with every non-finite float (NaN, inf) made None, which JSON can carry."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


def encode(message: dict[str, Any]) -> str:
    """The message as compact JSON (non-finite numbers as null), kept under MAX_MESSAGE_BYTES
    by leaving out first the heat map and components, then the oldest path and history."""
    try:
        text = json.dumps(message, separators=(",", ":"), allow_nan=False)
    except ValueError:
        message = _finite(message)
        text = json.dumps(message, separators=(",", ":"), allow_nan=False)
    if len(text) <= MAX_MESSAGE_BYTES:
        return text
    slim = {**message, "heat": None, "components": [], "truncated": True}
    text = json.dumps(slim, separators=(",", ":"), allow_nan=False)
    if len(text) <= MAX_MESSAGE_BYTES:
        return text
    slim["path"] = slim.get("path", [])[-50:]
    slim["tracks"] = [{**t, "history": t["history"][-3:]} for t in slim.get("tracks", [])][:50]
    return json.dumps(slim, separators=(",", ":"), allow_nan=False)
