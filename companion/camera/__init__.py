"""Camera: frame sources (OpenCV devices, pipelines, URLs and files; MJPEG with capture times)."""
