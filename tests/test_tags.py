"""Tag detection: the detector frees its C objects safely and reports OpenCV-convention centres."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pupil_apriltags

from companion.vision.camera import BodyPose, CameraModel, project_points
from companion.vision.tags import TagDetector, detect_centres
from sitl.camera import Renderer, Tag


class _CallLog:
    """Stands in for the C library: records the names of the functions called, calls nothing."""

    def __init__(self) -> None:
        self.calls: list[str] = []

    def __getattr__(self, name: str) -> Callable[..., None]:
        def record(*args: object) -> None:
            self.calls.append(name)

        record.restype = None  # type: ignore[attr-defined]
        return record


def _destroy_order(detector: pupil_apriltags.Detector) -> list[str]:
    detector.detect(np.zeros((480, 640), np.uint8))
    log = _CallLog()
    detector.libc = log  # the C objects are leaked, not freed in the wrong order
    detector.__del__()
    detector.tag_detector_ptr = None
    return log.calls


def test_the_detector_is_freed_before_its_tag_family() -> None:
    # pupil-labs/apriltags#34: apriltag_detector_destroy writes into its families, so they must
    # outlive it; upstream frees them first (the heap corruption this class works around).
    assert _destroy_order(pupil_apriltags.Detector(families="tag36h11")) == [
        "tag36h11_destroy", "apriltag_detector_destroy"]
    ours = TagDetector(families="tag36h11")
    assert _destroy_order(ours) == ["apriltag_detector_destroy", "tag36h11_destroy"]
    ours.__del__()  # a second call frees nothing


def test_centres_are_in_opencv_pixels() -> None:
    camera = CameraModel()
    pose = BodyPose.from_euler(0.0, 0.0, 0.0, -8.0)
    tags = [Tag(7, 1.0, -2.0, 0.8, 0.3), Tag(3, -2.0, 3.0, 0.8, 1.1)]  # 32 px across
    image = Renderer(camera, texture_seed=2).render(pose, tags, np.random.default_rng(0))
    ids, centres = detect_centres(TagDetector(families="tag36h11"), image)
    assert sorted(ids.tolist()) == [3, 7]
    for tag_id, centre in zip(ids, centres, strict=True):
        tag = next(t for t in tags if t.tag_id == tag_id)
        expected, _ = project_points(camera, pose, np.array([[tag.north_m, tag.east_m, 0.0]]))
        assert np.linalg.norm(centre - expected[0]) < 0.5
    empty_ids, empty_centres = detect_centres(TagDetector(), np.zeros((48, 64), np.uint8))
    assert empty_ids.shape == (0,) and empty_centres.shape == (0, 2)
