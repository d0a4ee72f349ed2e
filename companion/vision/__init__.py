"""Vision: the camera model, tag detection and projection of detections to the ground."""
