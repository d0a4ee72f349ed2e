"""The camera frames a run processed, as image files in the run folder, within a disk budget.

`FrameRecorder.write` encodes one grayscale or BGR uint8 frame with OpenCV (JPEG, or lossless
PNG so that a replay re-detects exactly what the service saw) and stores it as
`<frames_dir>/<index:06d>.<format>`, numbered from 0. Each file is written whole to
`<name>.tmp`, flushed and renamed into place: a crash never leaves a half image under its final
name. One line per kept frame is appended to `<frames_dir>/index.csv` (`index,capture_t_s,file`,
`file` relative to frames_dir), flushed per line, so the frames replay without the steps log.

Frames are a luxury: the service keeps flying and recording detections without them. So frames
stop being kept, for the rest of the run, with one line to `log` and never an exception, when
 - the encoded images (index.csv not counted) would exceed `budget_bytes`;
 - the free space of frames_dir's parent minus the frame would fall below `min_free_bytes`
   (`disk_free` is asked on the first write and every 20th; in between, the free space is
   estimated as the last answer minus the bytes written since);
 - writing fails with an OSError (disk full, permissions) or OpenCV cannot encode the frame.
From then on `write` returns None, and `stopped_reason` says why.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import TextIO

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.errors import ConfigError, InputError

__all__ = ["FORMATS", "FREE_CHECK_EVERY", "INDEX_NAME", "FrameRecorder"]

FORMATS = ("jpg", "png")
INDEX_NAME = "index.csv"
FREE_CHECK_EVERY = 20  # writes between two calls of disk_free
_MB = 1e6


def _disk_free_bytes(path: Path) -> int:
    """Free bytes on the filesystem holding path, for an unprivileged user."""
    return shutil.disk_usage(path).free


def _mb(n_bytes: float) -> str:
    """Bytes as megabytes (10^6 bytes) with one decimal."""
    return f"{n_bytes / _MB:.1f} MB"


class FrameRecorder:
    """Writes camera frames into a run folder, within a byte budget, above a free-space floor."""

    def __init__(self, frames_dir: Path, *, budget_bytes: int, min_free_bytes: int,
                 image_format: str = "jpg", jpeg_quality: int = 90,
                 log: Callable[[str], None] = lambda _: None,
                 disk_free: Callable[[Path], int] = _disk_free_bytes) -> None:
        if not budget_bytes > 0:
            raise ConfigError("output.frames_budget_mb",
                              f"must be > 0 (leave frames off instead), got {budget_bytes!r} bytes")
        if not min_free_bytes >= 0:
            raise ConfigError("output.min_free_mb", f"must be >= 0, got {min_free_bytes!r} bytes")
        if image_format not in FORMATS:
            raise ConfigError("output.frames",
                              f'must be "jpg" or "png" here ("off" makes no recorder), '
                              f"got {image_format!r}")
        if not 1 <= jpeg_quality <= 100:
            raise ConfigError("output.jpeg_quality",
                              f"must be an integer in [1, 100], got {jpeg_quality!r}")
        self.frames_dir = frames_dir
        self.budget_bytes = budget_bytes
        self.min_free_bytes = min_free_bytes
        self.image_format = image_format
        self._params = ([cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)]
                        if image_format == "jpg" else [])
        self._log = log
        self._disk_free = disk_free
        self._index: TextIO | None = None
        self._kept = 0
        self._bytes_written = 0
        self._free_bytes = 0  # the last answer of disk_free, less what was written since
        self._stopped_reason: str | None = None
        self._closed = False

    @property
    def kept(self) -> int:
        """Frames written."""
        return self._kept

    @property
    def bytes_written(self) -> int:
        """Bytes of the image files written (index.csv not counted)."""
        return self._bytes_written

    @property
    def stopped_reason(self) -> str | None:
        """Why frames stopped being kept, or None while they are kept."""
        return self._stopped_reason

    def write(self, image: NDArray[np.uint8], capture_t_s: float) -> str | None:
        """Store one frame; its name relative to the run folder ('frames/000017.png') or None."""
        if self._stopped_reason is not None or self._closed:
            return None
        if image.dtype != np.uint8 or not (
                image.ndim == 2 or (image.ndim == 3 and image.shape[2] in (1, 3))):
            raise InputError(f"a frame must be a grayscale or BGR uint8 image, got "
                             f"{image.dtype} of shape {image.shape}")
        try:
            ok, buffer = cv2.imencode("." + self.image_format, np.ascontiguousarray(image),
                                      self._params)
        except cv2.error as exc:  # its text is several lines; the last one says what went wrong
            ok, buffer, problem = False, None, (str(exc).strip().splitlines() or [""])[-1]
        else:
            problem = "cv2.imencode returned no image"
        if not ok or buffer is None:
            self._stop(f"OpenCV cannot encode a {image.shape} frame as {self.image_format} "
                       f"({problem})")
            return None
        data = buffer.tobytes()
        if self._bytes_written + len(data) > self.budget_bytes:
            self._stop(f"the budget of {_mb(self.budget_bytes)} is reached")
            return None
        if self._kept % FREE_CHECK_EVERY == 0:
            try:
                self._free_bytes = int(self._disk_free(self.frames_dir.parent))
            except OSError as exc:
                self._stop(f"the free space cannot be read ({exc})")
                return None
        if self._free_bytes - len(data) < self.min_free_bytes:
            self._stop(f"the free space ({_mb(self._free_bytes)}) would fall below the floor "
                       f"of {_mb(self.min_free_bytes)}")
            return None
        name = f"{self._kept:06d}.{self.image_format}"
        try:
            index = self._open_index()
            self._store(name, data)
            index.write(f"{self._kept},{float(capture_t_s)!r},{name}\n")
            index.flush()
        except OSError as exc:
            self._stop(f"writing failed ({exc})")
            return None
        self._kept += 1
        self._bytes_written += len(data)
        self._free_bytes -= len(data)
        return f"{self.frames_dir.name}/{name}"

    def close(self) -> None:
        """Close index.csv; later writes return None. Safe to call twice."""
        self._closed = True
        if self._index is not None:
            try:
                self._index.close()
            except OSError as exc:
                self._log(f"frames: closing {INDEX_NAME} failed: {exc}")
            self._index = None

    def _store(self, name: str, data: bytes) -> None:
        """Write data whole under frames_dir/name via name.tmp and a rename."""
        final = self.frames_dir / name
        tmp = final.with_name(name + ".tmp")
        try:
            with tmp.open("wb") as fh:
                fh.write(data)
                fh.flush()
            os.replace(tmp, final)
        except OSError:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
            raise

    def _open_index(self) -> TextIO:
        """index.csv, created (with frames_dir) with its header on the first frame."""
        if self._index is None:
            self.frames_dir.mkdir(parents=True, exist_ok=True)
            self._index = (self.frames_dir / INDEX_NAME).open("w", encoding="utf-8")
            self._index.write("index,capture_t_s,file\n")
        return self._index

    def _stop(self, why: str) -> None:
        """Stop keeping frames, saying so once."""
        self._stopped_reason = why
        self._log(f"frames: no longer kept: {why} after {self._kept} frames "
                  f"(detections are still recorded)")
