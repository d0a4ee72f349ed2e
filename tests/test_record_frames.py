"""Frames: written whole, indexed, decodable; stopped once, quietly, by budget, floor or error."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from companion.errors import ConfigError, InputError
from companion.record.frames import FrameRecorder

_HUGE_FREE = 10**15


def _noise(seed: int, shape: tuple[int, ...]) -> NDArray[np.uint8]:
    """Incompressible pixels: every PNG of this shape has about the same size."""
    return np.random.default_rng(seed).integers(0, 256, size=shape, dtype=np.uint8)


def _smooth(shape: tuple[int, ...]) -> NDArray[np.uint8]:
    """A gradient JPEG keeps close to the original."""
    rows, cols = shape[:2]
    ramp = (np.add.outer(np.arange(rows), np.arange(cols)) * 255 // (rows + cols)).astype(np.uint8)
    return ramp if len(shape) == 2 else np.repeat(ramp[:, :, None], shape[2], axis=2)


def _recorder(frames_dir: Path, lines: list[str] | None = None, *, budget_bytes: int = 10**9,
              min_free_bytes: int = 0, image_format: str = "png",
              disk_free: Callable[[Path], int] = lambda _: _HUGE_FREE) -> FrameRecorder:
    return FrameRecorder(frames_dir, budget_bytes=budget_bytes, min_free_bytes=min_free_bytes,
                         image_format=image_format,
                         log=(lines.append if lines is not None else lambda _: None),
                         disk_free=disk_free)


def _png_bytes(image: NDArray[np.uint8]) -> int:
    ok, buffer = cv2.imencode(".png", image)
    assert ok
    return len(buffer)


def _imread(path: Path) -> NDArray[np.uint8]:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image is not None, path
    return np.asarray(image, dtype=np.uint8)


def _tmp_files(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.name.endswith(".tmp")]


@pytest.mark.parametrize("shape", [(48, 64), (48, 64, 3)])
def test_png_frames_come_back_identical(tmp_path: Path, shape: tuple[int, ...]) -> None:
    frames_dir = tmp_path / "frames"
    recorder = _recorder(frames_dir)
    assert not frames_dir.exists()  # made on the first write
    images = [_noise(seed, shape) for seed in range(3)]
    names = [recorder.write(image, 10.0 + k) for k, image in enumerate(images)]
    recorder.close()
    assert names == ["frames/000000.png", "frames/000001.png", "frames/000002.png"]
    assert recorder.kept == 3 and recorder.stopped_reason is None
    files = sorted(frames_dir.glob("*.png"))
    assert recorder.bytes_written == sum(f.stat().st_size for f in files)
    for name, image in zip(names, images, strict=True):
        assert name is not None
        back = _imread(tmp_path / name)
        assert back.shape == image.shape and np.array_equal(back, image)
    assert _tmp_files(tmp_path) == []


@pytest.mark.parametrize("shape", [(60, 80), (60, 80, 3)])
def test_jpeg_frames_decode_to_the_same_shape(tmp_path: Path, shape: tuple[int, ...]) -> None:
    recorder = _recorder(tmp_path / "frames", image_format="jpg")
    image = _smooth(shape)
    name = recorder.write(image, 1.5)
    recorder.close()
    assert name == "frames/000000.jpg"
    back = _imread(tmp_path / name)
    assert back.shape == image.shape
    assert np.mean(np.abs(back.astype(float) - image)) < 3.0  # quality 90 on a gradient


def test_index_lists_each_kept_frame(tmp_path: Path) -> None:
    frames_dir = tmp_path / "frames"
    recorder = _recorder(frames_dir)
    times_s = [0.1, 1700000000.123456, 2.0]
    for k, t_s in enumerate(times_s):
        recorder.write(_noise(k, (8, 8)), t_s)
    # flushed per line: readable before close
    lines = (frames_dir / "index.csv").read_text(encoding="utf-8").splitlines()
    assert lines == ["index,capture_t_s,file", "0,0.1,000000.png",
                     "1,1700000000.123456,000001.png", "2,2.0,000002.png"]
    for line in lines[1:]:
        assert (frames_dir / line.split(",")[2]).is_file()
    recorder.close()


def test_the_budget_stops_frames_with_one_log_line(tmp_path: Path) -> None:
    frames_dir = tmp_path / "frames"
    images = [_noise(seed, (32, 32)) for seed in range(10)]
    size = _png_bytes(images[0])
    budget_bytes = int(3.5 * size)
    lines: list[str] = []
    recorder = _recorder(frames_dir, lines, budget_bytes=budget_bytes)
    names = [recorder.write(image, float(k)) for k, image in enumerate(images)]
    recorder.close()
    assert all(names[:3]) and names[3:] == [None] * 7
    assert recorder.kept == 3 and recorder.bytes_written <= budget_bytes
    assert len(lines) == 1
    assert lines[0].startswith("frames: no longer kept: the budget of ")
    assert "after 3 frames" in lines[0] and "detections are still recorded" in lines[0]
    assert recorder.stopped_reason is not None and "budget" in recorder.stopped_reason
    assert len(list(frames_dir.glob("*.png"))) == 3
    assert len((frames_dir / "index.csv").read_text(encoding="utf-8").splitlines()) == 4


def test_the_budget_line_is_in_megabytes(tmp_path: Path) -> None:
    lines: list[str] = []
    recorder = _recorder(tmp_path / "frames", lines, budget_bytes=500_000)
    assert recorder.write(_noise(0, (1000, 1000)), 0.0) is None
    assert lines == ["frames: no longer kept: the budget of 0.5 MB is reached after 0 frames "
                     "(detections are still recorded)"]
    assert not (tmp_path / "frames").exists()


def test_the_free_space_floor_stops_frames(tmp_path: Path) -> None:
    images = [_noise(seed, (32, 32)) for seed in range(6)]
    size = _png_bytes(images[0])
    min_free_bytes = 1_000_000
    asked: list[Path] = []

    def disk_free(path: Path) -> int:
        asked.append(path)
        return min_free_bytes + int(2.5 * size)  # room for two frames above the floor

    lines: list[str] = []
    recorder = _recorder(tmp_path / "frames", lines, min_free_bytes=min_free_bytes,
                         disk_free=disk_free)
    names = [recorder.write(image, float(k)) for k, image in enumerate(images)]
    assert all(names[:2]) and names[2:] == [None] * 4
    assert asked == [tmp_path]  # the first write asks; then it counts what it wrote
    assert len(lines) == 1 and "free space" in lines[0] and "floor of 1.0 MB" in lines[0]
    assert "after 2 frames" in lines[0]


def test_free_space_is_asked_again_every_20_writes(tmp_path: Path) -> None:
    answers = iter([_HUGE_FREE, 0])
    asked: list[Path] = []

    def disk_free(path: Path) -> int:
        asked.append(path)
        return next(answers)

    lines: list[str] = []
    recorder = _recorder(tmp_path / "frames", lines, min_free_bytes=1, disk_free=disk_free)
    names = [recorder.write(_noise(k, (4, 4)), float(k)) for k in range(25)]
    assert all(names[:20]) and names[20:] == [None] * 5
    assert len(asked) == 2 and len(lines) == 1 and "after 20 frames" in lines[0]


def test_a_failing_disk_free_stops_frames(tmp_path: Path) -> None:
    def disk_free(path: Path) -> int:
        raise FileNotFoundError(2, "No such file or directory", str(path))

    lines: list[str] = []
    recorder = _recorder(tmp_path / "frames", lines, disk_free=disk_free)
    assert recorder.write(_noise(0, (4, 4)), 0.0) is None
    assert len(lines) == 1 and "No such file or directory" in lines[0]


def test_an_unwritable_folder_stops_frames_without_raising(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    run_dir.write_text("a file where the run folder should be")
    lines: list[str] = []
    recorder = FrameRecorder(run_dir / "frames", budget_bytes=10**9, min_free_bytes=0,
                             log=lines.append)  # the real disk_free: it reads a file's disk too
    assert recorder.write(_noise(0, (8, 8)), 0.0) is None
    assert recorder.write(_noise(1, (8, 8)), 1.0) is None
    recorder.close()
    assert recorder.kept == 0 and recorder.bytes_written == 0
    assert recorder.stopped_reason is not None and "writing failed" in recorder.stopped_reason
    assert len(lines) == 1 and "Not a directory" in lines[0]


def test_losing_the_folder_mid_run_stops_frames(tmp_path: Path) -> None:
    frames_dir = tmp_path / "frames"
    lines: list[str] = []
    recorder = _recorder(frames_dir, lines)
    assert recorder.write(_noise(0, (8, 8)), 0.0) == "frames/000000.png"
    shutil.rmtree(frames_dir)
    frames_dir.write_text("not a folder any more")
    assert recorder.write(_noise(1, (8, 8)), 1.0) is None
    assert recorder.write(_noise(2, (8, 8)), 2.0) is None
    recorder.close()
    assert recorder.kept == 1 and len(lines) == 1 and "after 1 frames" in lines[0]


def test_a_failed_rename_leaves_no_tmp_file(tmp_path: Path) -> None:
    frames_dir = tmp_path / "frames"
    (frames_dir / "000000.png").mkdir(parents=True)  # the final name is taken by a folder
    (frames_dir / "000000.png" / "x").write_text("x")
    lines: list[str] = []
    recorder = _recorder(frames_dir, lines)
    assert recorder.write(_noise(0, (8, 8)), 0.0) is None
    recorder.close()
    assert recorder.stopped_reason is not None and len(lines) == 1
    assert _tmp_files(tmp_path) == []


def test_writes_after_close_are_ignored(tmp_path: Path) -> None:
    lines: list[str] = []
    recorder = _recorder(tmp_path / "frames", lines)
    assert recorder.write(_noise(0, (8, 8)), 0.0) is not None
    recorder.close()
    recorder.close()
    assert recorder.write(_noise(1, (8, 8)), 1.0) is None
    assert recorder.kept == 1 and lines == [] and recorder.stopped_reason is None


def test_a_frame_that_is_not_a_uint8_image_is_refused(tmp_path: Path) -> None:
    recorder = _recorder(tmp_path / "frames")
    with pytest.raises(InputError, match="uint8"):
        recorder.write(np.zeros((8, 8), dtype=np.float32), 0.0)
    with pytest.raises(InputError, match="shape"):
        recorder.write(np.zeros((8, 8, 4), dtype=np.uint8), 0.0)


@pytest.mark.parametrize(("kwargs", "key"), [
    ({"budget_bytes": 0}, "output.frames_budget_mb"),
    ({"budget_bytes": -1}, "output.frames_budget_mb"),
    ({"min_free_bytes": -1}, "output.min_free_mb"),
    ({"image_format": "bmp"}, "output.frames"),
    ({"jpeg_quality": 0}, "output.jpeg_quality"),
    ({"jpeg_quality": 101}, "output.jpeg_quality"),
])
def test_bad_arguments_name_their_key(tmp_path: Path, kwargs: dict[str, object],
                                      key: str) -> None:
    arguments: dict[str, object] = {"budget_bytes": 1000, "min_free_bytes": 0, **kwargs}
    with pytest.raises(ConfigError) as caught:
        FrameRecorder(tmp_path / "frames", **arguments)  # type: ignore[arg-type]
    assert caught.value.key == key
    assert not (tmp_path / "frames").exists()
