"""The confirmed tracks as a ground station or GIS reads them, and scored against the truth.

`confirmed_tracks` turns the estimator's tracks into plain records (id, lat/lon, UTM,
covariance, first/last seen, last detected, coasting). `write_geojson` and `write_csv` write
them. `score` matches them to true positions and gives each target's error, the missed
targets and the false tracks.
"""

from __future__ import annotations

import csv
import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from companion.sat.tracks import TrackParams, Tracks, grown_covs

__all__ = ["Score", "TrackRecord", "confirmed_tracks", "score", "write_csv", "write_geojson"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class TrackRecord:
    """One confirmed target as reported."""

    id: int
    lat_deg: float
    lon_deg: float
    easting_m: float
    northing_m: float
    utm_epsg: int
    cov_ee_m2: float
    cov_en_m2: float
    cov_nn_m2: float
    first_seen_s: float
    last_seen_s: float  # last step that supported the track
    last_detected_s: float  # last detection of its target
    coasting: bool  # not detected for more than filter.coast_after: on prediction alone


def confirmed_tracks(tracks: Tracks, origin_utm_m: FloatArray, utm_epsg: int,
                     to_latlon: Any, t_s: float, params: TrackParams) -> list[TrackRecord]:
    """The confirmed tracks at t_s with their honest covariances (tracks.grown_covs); means are
    in the search frame (UTM minus origin_utm_m)."""
    covs = grown_covs(tracks, t_s, params.motion)
    coasting = tracks.coasting(t_s, params.coast_after_s)
    out = []
    for i in np.flatnonzero(tracks.confirmed):
        e, n = (tracks.means[i, :2] + origin_utm_m).tolist()
        lat, lon = to_latlon(tracks.means[i, :2][None])[0].tolist()
        c = covs[i, :2, :2]
        out.append(TrackRecord(int(tracks.ids[i]), lat, lon, e, n, utm_epsg, float(c[0, 0]),
                               float(c[0, 1]), float(c[1, 1]), float(tracks.born_t_s[i]),
                               float(tracks.last_t_s[i]), float(tracks.seen_t_s[i]),
                               bool(coasting[i])))
    return out


def write_geojson(path: Path, records: list[TrackRecord]) -> None:
    """A FeatureCollection of points (lon, lat) with every record field as a property."""
    features = [{"type": "Feature",
                 "geometry": {"type": "Point", "coordinates": [r.lon_deg, r.lat_deg]},
                 "properties": asdict(r)} for r in records]
    path.write_text(json.dumps({"type": "FeatureCollection", "features": features}, indent=1))


def write_csv(path: Path, records: list[TrackRecord]) -> None:
    """One row per record, a header of the field names."""
    fields = list(TrackRecord.__slots__)
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fields)
        writer.writeheader()
        for r in records:
            writer.writerow(asdict(r))


@dataclass(frozen=True)
class Score:
    """Tracks against the truth: per target the error (inf when missed), and the false tracks."""

    errors_m: FloatArray  # (n_true,) distance to the matched track; inf if none within gate
    false_tracks: int  # confirmed tracks matched to no target

    @property
    def missed(self) -> int:
        """Targets with no track within the gate."""
        return int(np.sum(~np.isfinite(self.errors_m)))


def score(tracks_xy: FloatArray, truth_xy: FloatArray, gate_m: float = 3.0) -> Score:
    """Optimal one-to-one matching of tracks to targets, pairs farther than gate_m refused."""
    tracks_xy = np.asarray(tracks_xy, dtype=np.float64).reshape(-1, 2)
    truth_xy = np.asarray(truth_xy, dtype=np.float64).reshape(-1, 2)
    errors = np.full(len(truth_xy), np.inf)
    matched = 0
    if len(tracks_xy) and len(truth_xy):
        d = np.linalg.norm(truth_xy[:, None] - tracks_xy[None], axis=2)
        rows, cols = linear_sum_assignment(np.where(d <= gate_m, d, 1e9))
        ok = d[rows, cols] <= gate_m
        errors[rows[ok]] = d[rows[ok], cols[ok]]
        matched = int(ok.sum())
    return Score(errors, len(tracks_xy) - matched)
