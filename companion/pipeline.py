"""One pipeline for the live service, the SITL and replay: frame + pose -> tags -> UTM -> SAT step.

`Pipeline.step(image, pose)` runs one estimator step on a frame: detect tags, project them to
the ground in UTM, take the footprint this frame covered as the sensing region, and step the
GM-PHD. A blank frame (lens cap, black picture), a frozen frame (the same picture as the step
before, bit for bit: a real sensor's noise never repeats) or a camera too near the ground makes
the step blind. `Pipeline.blind(t_s)` steps with no frame (camera down, no pose): it predicts
but does not apply a no-detection update, because not seeing is not seeing nothing. It is
synchronous and reads no clock: time comes with the pose.

The estimator works in a search frame: UTM metres shifted so that the search area's bounding box
starts at (0, 0). That frame is UTM up to a constant, and the planners' World is that box.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.config import CameraConfig, SearchConfig, ServiceConfig
from companion.geo import Utm
from companion.plan.world import World
from companion.sat.filter import SatParams, SatState, Scan, initial_state, step
from companion.sat.fov import ConvexPolygon, Disk, Region
from companion.sat.gp import GpPredictor
from companion.sat.mixture import Mixture
from companion.sat.params import sat_params
from companion.sat.predict import LinearModel
from companion.sat.tracks import TrackLog, same_layout
from companion.vision.calibration import load_calibration
from companion.vision.camera import CameraModel
from companion.vision.projection import (
    GeoPose,
    PoseUncertainty,
    footprint_utm,
    project_detections,
    vehicle_utm,
)
from companion.vision.tags import TagDetector, detect_centres

__all__ = ["Pipeline", "SearchFrame", "StepRecord", "camera_model"]

FloatArray = NDArray[np.float64]
REBOOT_JUMP_S = 1.0  # the autopilot's boot time went back by more: it rebooted
BLANK_FRAME_STD = 2.0  # grey levels: below this a frame shows nothing (lens cap, black frame)
MIN_HEIGHT_M = 1.0  # lower than this the camera sees too little of the ground to count
WARM_UP_STEPS = 12  # enough for a track to be confirmed and predicted by its GP


def camera_model(config: CameraConfig) -> CameraModel:
    """The camera: from its calibration file, or an ideal pinhole of the configured view."""
    if config.calibration is not None:
        return load_calibration(config.calibration, config.mount_rpy_deg, config.mount_offset_m)
    return CameraModel.from_hfov(config.hfov_deg, config.width_px, config.height_px,
                                 mount_rpy_deg=config.mount_rpy_deg,
                                 mount_offset_m=config.mount_offset_m)


@dataclass(frozen=True)
class SearchFrame:
    """UTM in one zone, shifted so that the search area's bounding box starts at (0, 0)."""

    utm: Utm
    origin_utm_m: FloatArray  # (2,) easting, northing of the box's south-west corner
    world: World
    area_xy_m: FloatArray  # (k, 2) the area polygon in this frame

    @staticmethod
    def from_config(search: SearchConfig) -> SearchFrame:
        """The frame of a configured search area."""
        utm = Utm(search.utm_epsg)
        easting, northing = utm.geodetic_to_utm(search.area_latlon[:, 0], search.area_latlon[:, 1])
        corners = np.column_stack([easting, northing])
        origin = corners.min(axis=0)
        size = corners.max(axis=0) - origin
        return SearchFrame(utm, origin, World(float(size[0]), float(size[1])), corners - origin)

    def to_utm(self, xy_m: FloatArray) -> FloatArray:
        """(..., 2) search-frame points -> easting, northing."""
        return np.asarray(xy_m, dtype=np.float64) + self.origin_utm_m

    def from_utm(self, en_m: FloatArray) -> FloatArray:
        """(..., 2) easting, northing -> search-frame points."""
        return np.asarray(en_m, dtype=np.float64) - self.origin_utm_m

    def to_latlon(self, xy_m: FloatArray) -> FloatArray:
        """(n, 2) search-frame points -> (n, 2) [lat, lon]."""
        en = self.to_utm(np.atleast_2d(xy_m))
        lat, lon = self.utm.utm_to_geodetic(en[:, 0], en[:, 1])
        return np.column_stack([lat, lon])


@dataclass(frozen=True)
class StepRecord:
    """What one step saw and did: the JSON-lines log record and the pipeline's counters."""

    t_s: float  # on the estimator's time base (the autopilot's boot time, across reboots)
    blind: str | None  # why no frame was used ("no frame", "no pose", ...) or None
    detections: int  # tags the detector kept
    measurements_xy_m: FloatArray  # (m, 2) search frame
    region_xy_m: FloatArray | None  # (k, 2) the sensing region's outline, or None when blind
    vehicle_xy_m: FloatArray | None
    r_cov_m2: FloatArray
    components: int
    weight_sum: float
    confirmed: int
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self, frame: SearchFrame) -> dict[str, Any]:
        """The record as plain JSON data (UTM coordinates)."""
        def en(xy: FloatArray | None) -> list[list[float]] | None:
            if xy is None:
                return None
            return [[round(float(e), 3), round(float(n), 3)] for e, n in frame.to_utm(xy)]

        return {"t_s": round(self.t_s, 6), "blind": self.blind, "detections": self.detections,
                "measurements_utm": en(self.measurements_xy_m),
                "region_utm": en(self.region_xy_m),
                "vehicle_utm": en(None if self.vehicle_xy_m is None else self.vehicle_xy_m[None]),
                "r_cov_m2": np.round(self.r_cov_m2, 4).tolist(), "components": self.components,
                "weight_sum": round(self.weight_sum, 4), "confirmed": self.confirmed,
                **self.extra}


def _shrunk(polygon_xy: FloatArray, margin_m: float) -> FloatArray:
    """A convex polygon moved towards its centroid so that its edges come in by about margin_m."""
    centre = polygon_xy.mean(axis=0)
    edges = np.roll(polygon_xy, -1, axis=0) - polygon_xy
    normals = np.column_stack([edges[:, 1], -edges[:, 0]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    inradius = float(np.min(np.abs(np.sum((polygon_xy - centre) * normals, axis=1))))
    if margin_m <= 0.0 or inradius <= 0.0:
        return polygon_xy
    scale = max(1.0 - margin_m / inradius, 0.05)
    shrunk: FloatArray = centre + (polygon_xy - centre) * scale
    return shrunk


class Pipeline:
    """Frames and poses in, estimator state out; one instance per flight."""

    def __init__(self, config: ServiceConfig, camera: CameraModel,
                 detector: TagDetector | None = None) -> None:
        self.config = config
        self.camera = camera
        self.frame = SearchFrame.from_config(config.search)
        est = config.estimator
        self.params: SatParams = sat_params(config.filter, est.p_detect, est.clutter_per_scan,
                                            1.0 / est.rate_hz, self.frame.area_xy_m)
        self.gp = GpPredictor(self.params.gp)
        self.state: SatState | None = None
        self.detector = detector or TagDetector(
            families=config.detector.family, nthreads=config.detector.threads,
            quad_decimate=config.detector.decimate)
        p = config.pose
        self.pose_sigma = PoseUncertainty(p.horizontal_std_m, p.vertical_std_m,
                                          p.attitude_std_deg, p.heading_std_deg)
        self._last_boot_s: float | None = None
        self._time_offset_s = 0.0
        self._last_image_digest = b""

    # -- time --------------------------------------------------------------------------------

    def _filter_time(self, boot_t_s: float) -> float:
        """The estimator's time for an autopilot boot time: continuous across reboots."""
        last = self._last_boot_s
        if last is not None and boot_t_s < last - REBOOT_JUMP_S:
            self._time_offset_s += last - boot_t_s  # a reboot: carry on from where we were
            last = None
        self._last_boot_s = boot_t_s if last is None else max(last, boot_t_s)
        t_s = boot_t_s + self._time_offset_s
        if self.state is not None:
            t_s = max(t_s, self.state.t_s)
        return t_s

    def _state_at(self, t_s: float) -> SatState:
        if self.state is None:
            self.state = self._initial_state(t_s)
        return self.state

    def _initial_state(self, t_s: float) -> SatState:
        dim = 4 if self.params.linear_model is LinearModel.CONSTANT_VELOCITY else 2
        return initial_state(Mixture.empty(dim), t_s, self.params)

    def warm_up(self) -> None:
        """Step a throwaway estimator on made-up scans of one target in the middle of the
        area, so that numba compiles (or loads from its cache) the estimator's kernels now and
        not in the flight's first step. This pipeline's state is left alone."""
        centre_xy = self.frame.area_xy_m.mean(axis=0)
        half_m = 10.0

        def frame(xy: FloatArray) -> Region:
            if self.config.estimator.fov == "disk":
                return Disk(xy, half_m)
            return ConvexPolygon(xy + half_m * np.array(
                [[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]))

        r_cov = np.eye(2) * 0.1
        state = self._initial_state(0.0)
        period_s = 1.0 / self.config.estimator.rate_hz
        for k in range(WARM_UP_STEPS):
            z = (centre_xy + np.array([0.1 * k, 0.0]))[None, :]
            state, _ = step(state, Scan(k * period_s, frame(centre_xy), z, r_cov, centre_xy),
                            self.params, self.gp)
        # Then frames whose edge crosses the target, unseen (Eq. edge_shift's p(F)).
        edge_xy = centre_xy + np.array([0.1 * (WARM_UP_STEPS - 1) + half_m, 0.0])
        for k in range(WARM_UP_STEPS, WARM_UP_STEPS + 2):
            state, _ = step(state, Scan(k * period_s, frame(edge_xy), np.zeros((0, 2)), r_cov,
                                        edge_xy), self.params, self.gp)

    # -- checkpoints -------------------------------------------------------------------------

    def checkpoint(self) -> dict[str, Any]:
        """What `restore` needs to carry on: the estimator's state, its clock, the area."""
        return {"state": self.state, "last_boot_s": self._last_boot_s,
                "time_offset_s": self._time_offset_s,
                "area_latlon": np.asarray(self.config.search.area_latlon).tolist()}

    def restore(self, saved: dict[str, Any]) -> str | None:
        """Carry on from a checkpoint of the same search area: None, or why not (and nothing
        changed): another area, not a checkpoint of this pipeline, or one whose estimator state
        another version wrote."""
        state = saved.get("state")
        if not np.array_equal(np.asarray(saved.get("area_latlon"), dtype=np.float64),
                              np.asarray(self.config.search.area_latlon)):
            return "is of another search area"
        if not isinstance(state, SatState):
            return "holds no estimator state"
        if not same_layout(state.tracks, self._initial_state(0.0).tracks):
            return "was written by another version of the estimator"
        self.state = state
        self._last_boot_s = saved.get("last_boot_s")
        self._time_offset_s = float(saved.get("time_offset_s", 0.0))
        return None

    # -- steps -------------------------------------------------------------------------------

    def step(self, image: NDArray[np.uint8], pose: GeoPose,
             sigma: PoseUncertainty | None = None) -> StepRecord:
        """One estimator step on a frame taken at pose.t_s (the autopilot's boot time), the
        pose uncertain by sigma (default: the configured floors)."""
        if pose.height_agl_m < MIN_HEIGHT_M:
            return self.blind(pose.t_s, "on the ground")
        if float(np.std(image[::4, ::4])) < BLANK_FRAME_STD:
            return self.blind(pose.t_s, "blank frame")
        digest = hashlib.blake2b(np.ascontiguousarray(image).data, digest_size=16).digest()
        frozen, self._last_image_digest = digest == self._last_image_digest, digest
        if frozen:
            return self.blind(pose.t_s, "frozen frame")
        det = self.config.detector
        _, pixels = detect_centres(self.detector, image, det.min_decision_margin,
                                   det.allowed_ids)
        return self.step_detections(pixels, pose, sigma)

    def step_detections(self, pixels: FloatArray, pose: GeoPose,
                        sigma: PoseUncertainty | None = None) -> StepRecord:
        """One step on a frame's detected tag centres (OpenCV pixels): what replay re-runs."""
        sigma = sigma or self.pose_sigma
        det = self.config.detector
        est = self.config.estimator
        centre = np.array([[self.camera.cx_px, self.camera.cy_px]])
        ground = project_detections(self.camera, pose, np.vstack([centre, pixels]),
                                    self.frame.utm, det.pixel_std_px, sigma,
                                    est.max_range_m)
        valid = ground.valid[1:]
        z = self.frame.from_utm(ground.xy_utm_m[1:][valid])
        covs = ground.cov_utm_m2[1:][valid]
        r_cov = covs.mean(axis=0) if len(covs) else ground.cov_utm_m2[0]
        if not np.all(np.isfinite(r_cov)):  # the centre ray misses the ground (camera level?)
            return self.blind(pose.t_s, "the camera does not see the ground")
        vehicle = self.frame.from_utm(vehicle_utm(pose, self.frame.utm))
        region: Region
        if est.fov == "disk":
            region = Disk(vehicle, est.fov_radius_m)
            outline = vehicle + est.fov_radius_m * np.column_stack(
                [np.cos(np.linspace(0, 2 * math.pi, 24, endpoint=False)),
                 np.sin(np.linspace(0, 2 * math.pi, 24, endpoint=False))])
        else:
            footprint = footprint_utm(self.camera, pose, self.frame.utm, est.max_range_m)
            outline = _shrunk(self.frame.from_utm(footprint.vertices_xy), est.footprint_margin_m)
            region = ConvexPolygon(outline)
        record = self._advance(pose.t_s, Scan(0.0, region, z, r_cov, vehicle), None,
                               len(pixels), outline)
        record.extra["input"] = {
            "boot_t_s": pose.t_s,
            "pose": [pose.lat_deg, pose.lon_deg, pose.alt_amsl_m, pose.height_agl_m,
                     *pose.q_wxyz],
            "pixels": np.asarray(pixels, dtype=np.float64).tolist(),
            "pose_sigma": [sigma.horizontal_m, sigma.vertical_m, sigma.attitude_deg,
                           sigma.heading_deg]}
        return record

    def blind(self, boot_t_s: float, reason: str) -> StepRecord:
        """A step without a usable frame: predict only, nobody is erased for being unseen."""
        r_cov = np.eye(2) * self.params.gp.sigma_n_m ** 2
        record = self._advance(boot_t_s, Scan(0.0, None, np.zeros((0, 2)), r_cov, np.zeros(2)),
                               reason, 0, None)
        record.extra["input"] = {"boot_t_s": boot_t_s}
        return record

    def _advance(self, boot_t_s: float, scan: Scan, blind: str | None, detections: int,
                 outline: FloatArray | None) -> StepRecord:
        t_s = self._filter_time(boot_t_s)
        state = self._state_at(t_s)
        scan = Scan(t_s, scan.region, scan.measurements_xy, scan.r_cov, scan.sensor_xy)
        self.state, _ = step(state, scan, self.params, self.gp)
        if self.state.tracks.log.length:  # the per-step track history is for the study's
            # plots; a flight of hours would keep every row (and pickle it in checkpoints)
            self.state = self.state._replace(tracks=self.state.tracks._replace(
                log=TrackLog.empty(self.state.tracks.means.shape[1])))
        tracks = self.state.tracks
        return StepRecord(
            t_s=t_s, blind=blind, detections=detections,
            measurements_xy_m=np.asarray(scan.measurements_xy), region_xy_m=outline,
            vehicle_xy_m=None if blind else np.asarray(scan.sensor_xy),
            r_cov_m2=np.asarray(scan.r_cov), components=self.state.mixture.size,
            weight_sum=float(self.state.mixture.total_weight),
            confirmed=int(tracks.confirmed.sum()),
            extra={"confirmed_ids": tracks.ids[tracks.confirmed].tolist(),
                   "coasting_ids": tracks.ids[tracks.confirmed & tracks.coasting(
                       t_s, self.params.tracks.coast_after_s)].tolist()})
