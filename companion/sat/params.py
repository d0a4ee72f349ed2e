"""The GM-PHD filter's parameters as configured: the [filter] keys, their spec and SatParams.

The scenario files and the service configuration share the [filter] table (`FILTER_KEYS`, read
into a `FilterSpec`); `sat_params` turns it, with p(D|F), clutter and the step, into the
filter's `SatParams`. `MotionModel` and `FovKind` name the configured motion model and sensing
region kind (str-valued: they compare equal to, and print as, their TOML text).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import ConvexHull

from companion.keys import Bool, Choice, Derived, Float, Int, Key, Pair
from companion.sat.birth import BirthWeight
from companion.sat.filter import FilterKind, SatParams
from companion.sat.fov import ConvexPolygon
from companion.sat.gp import GpParams
from companion.sat.motion import TargetMotion
from companion.sat.predict import LinearModel
from companion.sat.tracks import TrackParams
from companion.sat.update import PushMode, PushRule

__all__ = ["FILTER_KEYS", "FilterSpec", "FovKind", "MotionModel", "sat_params"]

FloatArray = NDArray[np.float64]


class MotionModel(StrEnum):
    """How confirmed tracks are predicted: a GP over their recent positions, or the linear model."""

    GP = "gp"
    LINEAR = "linear"


class FovKind(StrEnum):
    """The sensing region: the paper's disk, a fixed polygon, or the camera's ground footprint."""

    DISK = "disk"
    POLYGON = "polygon"
    CAMERA = "camera"


@dataclass(frozen=True, slots=True)
class FilterSpec:
    """Parameters of the search-and-track filter."""

    kind: FilterKind
    p_survive: float
    push_rule: bool
    push_band: tuple[float, float]
    push_mode: Literal["moment", "paper"]
    extract_weight: float
    confirm_length: int
    prune_weight: float
    merge_distance: float  # squared Mahalanobis distance (Vo & Ma's U); also the track gate
    max_components: int
    motion: MotionModel
    process_noise: float  # m^2 per step per axis
    birth_weight: float
    birth: Literal["adaptive", "constant"]
    linear_model: Literal["cp", "cv"]
    velocity_variance: float  # m^2/s^2
    gp_sigma_f: float  # m
    gp_lengthscale: float  # s
    gp_sigma_n: float | None  # m; None: the measurement noise std
    gp_window: int  # points
    track_timeout: float  # s
    target_speed: float  # m/s
    manoeuvre_time: float  # s
    confirm_existence: float
    drop_existence: float
    coast_after: float  # s


_GP = GpParams()
_MOTION = TargetMotion()
_TRACKS = TrackParams()

FILTER_KEYS: tuple[Key, ...] = (
    Key("kind", Choice(*FilterKind), "gmphd",
        "the estimator: \"gmphd\" (the paper's GM-PHD) or \"lmb\" (the labeled "
        "multi-Bernoulli filter, one existence probability and track id per target)"),
    Key("p_survive", Float(ge=0, le=1), 1.0, "survival probability p_S"),
    Key("push_rule", Bool(), True, "the paper's limited-FOV update rule"),
    Key("push_band", Pair(Float(ge=0, le=1), ordered=True), [0.4, 0.6],
        "p_D band [lo, hi] in which the push rule acts"),
    Key("push_mode", Choice("moment", "paper"), "moment",
        "how the push rule moves a missed component: \"paper\" = Eq. push inside the band; "
        "\"moment\" = the mean and covariance of its exact no-detection posterior (any p_D)",
        project=True),
    Key("extract_weight", Float(gt=0), 0.5, "state extraction weight"),
    Key("confirm_length", Int(ge=1), 3,
        "steps supported by a detection before a track is confirmed (l_threshold)"),
    Key("prune_weight", Float(ge=0), 0.001, "pruning weight"),
    Key("merge_distance", Float(ge=0), 10.0,
        "threshold on the SQUARED Mahalanobis distance (Vo & Ma's U); also the track gate"),
    Key("max_components", Int(ge=1), 100, "components kept after merging"),
    Key("motion", Choice(MotionModel.GP, MotionModel.LINEAR), "gp",
        "motion model of confirmed tracks"),
    Key("process_noise", Float(ge=0), 0.01,
        "variance per step per axis of the linear model, m^2 (for \"cv\": acceleration "
        "spectral density times the step)"),
    Key("birth_weight", Float(gt=0), 1.0,
        "weight of a measurement-driven new component (the paper uses 1)"),
    Key("birth", Choice("adaptive", "constant"), "adaptive",
        "adaptive: the share of a measurement that clutter and the existing components do "
        "not explain (Ristic et al. 2012); constant: birth_weight (the paper)",
        project=True),
    Key("linear_model", Choice("cp", "cv"), "cp",
        "linear motion: constant position (random walk) or constant velocity", project=True),
    Key("velocity_variance", Float(gt=0), 1.0,
        "velocity prior of a new component for linear_model = \"cv\", m^2/s^2", project=True),
    Key("gp_sigma_f", Float(gt=0), _GP.sigma_f_m,
        "GP signal std, metres", project=True),
    Key("gp_lengthscale", Float(gt=0), _GP.lengthscale_s,
        "GP kernel length scale, seconds", project=True),
    Key("gp_sigma_n", Float(gt=0),
        Derived(f"the measurement noise: `sensor.noise_std` in a scenario, {_GP.sigma_n_m:g} in "
                "the service"),
        "GP observation noise std, metres: the noise of the positions a track's GP regresses on",
        project=True),
    Key("gp_window", Int(ge=2), _GP.window,
        "a track's most recent detected positions the GP regresses on", project=True),
    Key("track_timeout", Float(gt=0), 30.0,
        "seconds without support before a confirmed track ends", project=True),
    Key("target_speed", Float(ge=0, le=100), _MOTION.speed_m_s,
        "typical ground speed of the targets, m/s (0: stationary): how fast an unseen "
        "track's uncertainty grows, and the prior on its GP's trend", project=True),
    Key("manoeuvre_time", Float(gt=0), _MOTION.manoeuvre_s,
        "typical time between the targets' changes of heading, seconds", project=True),
    Key("confirm_existence", Float(gt=0, le=0.9999), _TRACKS.confirm_existence,
        "existence probability a track needs, besides confirm_length detections, to be "
        "confirmed (its score: detections for, misses in view against)", project=True),
    Key("drop_existence", Float(gt=0, le=0.9999), _TRACKS.drop_existence,
        "existence probability below which a track ends", project=True),
    Key("coast_after", Float(gt=0), _TRACKS.coast_after_s,
        "seconds without a detection after which a confirmed track is reported as coasting "
        "(on prediction alone) rather than seen", project=True),
)


def sat_params(f: FilterSpec, p_detect: float, clutter_per_scan: float, dt_s: float,
               area_xy: FloatArray | None = None,
               noise_std_m: float = _GP.sigma_n_m) -> SatParams:
    """The filter's parameters from a [filter] table, p(D|F), clutter, the step length, the
    search area's (k, 2) polygon (None: targets anywhere) and the measurement noise std.

    The GP's observation noise is the measurement noise unless [filter] sets it: learned
    values match it (learn-gp gives 0.9965 m on the paper's 1 m sensor), and a smaller one
    makes a track's GP follow the noise of its detections, its mean off a standing target by
    more than its covariance says.

    The GP's trend has the motion class's velocity as its prior (slope_sd_m_s = speed / sqrt 2
    per axis, 0 for stationary targets): a walker's track is where its detections lead, not
    behind them.

    The linear model's noise per step is at least the targets' motion class's displacement
    variance over one step, so that a component that no GP predicts can follow a mover. A track
    coasting alone exists only as far as it lies in the area's convex hull (its polygon, if
    convex), so that the simulator and the service end tracks that walk out alike.
    """
    motion = TargetMotion(f.target_speed, f.manoeuvre_time)
    step_var_m2 = max(f.process_noise, motion.displacement_var_m2(dt_s))
    return SatParams(
        kind=FilterKind(f.kind),
        p_survive=f.p_survive,
        p_detect=p_detect,
        clutter_per_scan=clutter_per_scan,
        push=PushRule(*f.push_band, PushMode(f.push_mode)) if f.push_rule else None,
        extract_weight=f.extract_weight,
        prune_weight=f.prune_weight,
        merge_distance_sq=f.merge_distance,
        max_components=f.max_components,
        use_gp=f.motion == MotionModel.GP,
        linear_model=LinearModel(f.linear_model),
        q_m2_per_s=step_var_m2 / dt_s,
        birth=BirthWeight(f.birth),
        birth_weight=f.birth_weight,
        velocity_var_m2_s2=f.velocity_variance,
        gp=GpParams(f.gp_sigma_f, f.gp_lengthscale,
                    noise_std_m if f.gp_sigma_n is None else f.gp_sigma_n, f.gp_window,
                    slope_sd_m_s=math.sqrt(motion.velocity_var_m2_s2)),
        tracks=TrackParams(f.merge_distance, f.confirm_length, f.track_timeout, f.gp_window,
                           motion, f.confirm_existence, f.drop_existence,
                           coast_after_s=f.coast_after,
                           area=None if area_xy is None else ConvexPolygon(
                               area_xy[ConvexHull(area_xy).vertices])),
    )
