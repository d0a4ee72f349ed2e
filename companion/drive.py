"""What feeds the pipeline: timestamped observations, and the one loop that steps it over them.

An `Observation` is what the estimator gets at one step, at its time on the autopilot's boot
clock: a frame with the pose at its capture time, or the detected tag centres (pixels) with that
pose (what a replay of recorded detections has), or a reason there is nothing to see (blind).
The live service, the replays and the benchmarks all make observations; `observe` steps the
pipeline on one, and `drive` steps it over many, writing each step's record to a run folder.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from companion.errors import InputError
from companion.pipeline import Pipeline, StepRecord
from companion.vision.projection import GeoPose, PoseUncertainty

__all__ = ["Observation", "StepSink", "drive", "observe"]

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
