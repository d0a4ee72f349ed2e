"""AprilTag detection with pupil-apriltags, centres in OpenCV's pixel convention.

`TagDetector` is pupil_apriltags.Detector with its C objects freed in the order the C library
needs: pupil-apriltags 1.0.4 destroys the tag families before the detector, whose destructor
then writes into the freed family (pupil-labs/apriltags#34), which corrupts the heap and aborts
the process later, far from the cause.
"""

from __future__ import annotations

from collections.abc import Collection

import numpy as np
import pupil_apriltags
from numpy.typing import NDArray

__all__ = ["PUPIL_OFFSET_PX", "TagDetector", "detect_centres"]

PUPIL_OFFSET_PX = 0.5  # pupil-apriltags puts pixel centres at +0.5 (OpenCV: at integers)


class TagDetector(pupil_apriltags.Detector):  # type: ignore[misc]
    """A pupil_apriltags.Detector that frees the detector before its tag families."""

    def __del__(self) -> None:
        detector_ptr = getattr(self, "tag_detector_ptr", None)
        if detector_ptr is None:
            return
        self.tag_detector_ptr = None
        self.libc.apriltag_detector_destroy.restype = None
        self.libc.apriltag_detector_destroy(detector_ptr)  # it still reads its families
        for family, family_ptr in self.tag_families.items():
            destroy = getattr(self.libc, f"{family}_destroy")
            destroy.restype = None
            destroy(family_ptr)


def detect_centres(detector: pupil_apriltags.Detector, image: NDArray[np.uint8],
                   min_decision_margin: float = 0.0, allowed_ids: Collection[int] = ()
                   ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Tag ids (n,) and centres (n, 2) [u, v] in OpenCV pixels of the tags in a grey image.

    Detections below min_decision_margin, or with an id outside allowed_ids when it is not
    empty, are left out.
    """
    found = [d for d in detector.detect(np.ascontiguousarray(image))
             if d.decision_margin >= min_decision_margin
             and (not allowed_ids or d.tag_id in allowed_ids)]
    ids = np.array([d.tag_id for d in found], dtype=np.int64)
    centres = np.array([d.center for d in found], dtype=np.float64).reshape(-1, 2)
    return ids, centres - PUPIL_OFFSET_PX
