"""What feeds the pipeline: timestamped observations, and the one loop that steps it over them.

An `Observation` is what the estimator gets at one step, at its time on the autopilot's boot
clock: a frame with the pose at its capture time, or the detected tag centres (pixels) with that
pose (what a replay of recorded detections has), or a reason there is nothing to see (blind).
The live service, the replays and the benchmarks all make observations; `observe` steps the
pipeline on one, and `drive` steps it over many, writing each step's record to a run folder.
`frame_observation` gives a frame the pose a `VehicleView` has for its capture time, live and in
the replay of a flight log alike.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from companion.config import PoseConfig
from companion.errors import InputError
from companion.pipeline import Pipeline, StepRecord
from companion.plan.setpoints import tilt_cos
from companion.vehicle.view import Accuracy, VehicleView
from companion.vision.projection import GeoPose, PoseUncertainty

__all__ = ["Observation", "StepSink", "drive", "frame_observation", "observe", "pose_sigma"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Observation:
    """One step's input at boot time t_s: image or pixels with a pose, or a blind reason."""

    t_s: float
    pose: GeoPose | None = None
    image: NDArray[np.uint8] | None = None
    pixels: FloatArray | None = None  # (n, 2) tag centres, OpenCV pixels
    sigma: PoseUncertainty | None = None  # None: the configured floors
    blind: str | None = None  # why there is nothing to see (no frame, no pose, ...)
    extra: dict[str, Any] = field(default_factory=dict)  # added to the step's record

    @staticmethod
    def nothing(t_s: float, reason: str) -> Observation:
        """A blind step: nothing to see at t_s, for the reason given."""
        return Observation(t_s, blind=reason)


def pose_sigma(floors: PoseConfig, reported: Accuracy) -> PoseUncertainty:
    """The pose uncertainty a measurement carries: the autopilot's own figures where it gives
    them, never below the configured floors."""
    def at_least(floor: float, value: float) -> float:
        return floor if math.isnan(value) else max(floor, value)

    return PoseUncertainty(at_least(floors.horizontal_std_m, reported.horizontal_std_m),
                           at_least(floors.vertical_std_m, reported.vertical_std_m),
                           at_least(floors.attitude_std_deg, reported.attitude_std_deg),
                           at_least(floors.heading_std_deg, reported.heading_std_deg))


def frame_observation(view: VehicleView, capture_s: float, image: NDArray[np.uint8],
                      pose: PoseConfig) -> Observation:
    """A frame taken at capture_s with the view's pose then (the height from its best source,
    the autopilot's accuracy), or blind when the view has no plausible pose for that time or
    the vehicle has landed."""
    if view.landed():  # the camera at rest near the ground: its misses say nothing of the field
        return Observation.nothing(capture_s, "on the ground")
    sample = view.poses.at(capture_s)
    if sample is None:
        glitch = view.gate.refused_around(capture_s)
        return Observation.nothing(capture_s, "implausible position (GPS glitch?)" if glitch
                                   else "no pose at the capture time")
    height_m, height_source = view.height_at(capture_s, sample.alt_rel_m,
                                             tilt_cos(sample.q_wxyz), pose.camera_rest_height_m)
    geo = GeoPose(capture_s, sample.lat_deg, sample.lon_deg, sample.alt_amsl_m, height_m,
                  sample.q_wxyz)
    return Observation(capture_s, geo, image, sigma=pose_sigma(pose, view.accuracy()),
                       extra={"height_source": height_source})


class StepSink(Protocol):
    """Where step records go (a run folder)."""

    def write_step(self, record: dict[str, Any]) -> None: ...


def observe(pipeline: Pipeline, obs: Observation) -> StepRecord:
    """One pipeline step on one observation; its extra fields go into the record."""
    if obs.pose is None or obs.blind is not None:
        record = pipeline.blind(obs.t_s, obs.blind or "blind")
    elif obs.image is not None:
        record = pipeline.step(obs.image, obs.pose, obs.sigma)
    elif obs.pixels is not None:
        record = pipeline.step_detections(obs.pixels, obs.pose, obs.sigma)
    else:
        raise InputError(f"observation at {obs.t_s} s: a pose with neither image nor pixels")
    record.extra.update(obs.extra)
    return record


def drive(pipeline: Pipeline, observations: Iterable[Observation], sink: StepSink | None,
          on_step: Callable[[StepRecord], None] | None = None) -> int:
    """Step the pipeline over the observations in order, each record (after on_step, which may
    add to it) written to sink; the number of steps."""
    steps = 0
    for obs in observations:
        record = observe(pipeline, obs)
        if on_step is not None:
            on_step(record)
        if sink is not None:
            sink.write_step(record.to_json(pipeline.frame))
        steps += 1
    return steps
