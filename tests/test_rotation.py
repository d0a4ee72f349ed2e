"""Run rotation: oldest run folders go first, and nothing but run folders ever goes."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from companion.errors import ConfigError
from companion.record.rotation import Removed, make_room, run_folders, tree_bytes

_HUGE_FREE = 10**15


def _run(root: Path, name: str, n_bytes: int) -> Path:
    """A run folder holding n_bytes, split between a top file and a nested one (sparse)."""
    run = root / name
    (run / "frames").mkdir(parents=True)
    with (run / "steps.jsonl").open("wb") as fh:
        fh.truncate(n_bytes // 2)
    with (run / "frames" / "000000.png").open("wb") as fh:
        fh.truncate(n_bytes - n_bytes // 2)
    return run


def _names(root: Path) -> list[str]:
    return sorted(p.name for p in root.iterdir())


def test_oldest_runs_go_first_until_under_the_total(tmp_path: Path) -> None:
    names = ["run-20261101T080000Z-10", "run-20261102T080000Z", "run-20261101T080000Z-2",
             "run-20261101T080000Z"]
    for name in names:
        _run(tmp_path, name, 100)
    assert [p.name for p in run_folders(tmp_path)] == [
        "run-20261101T080000Z", "run-20261101T080000Z-2", "run-20261101T080000Z-10",
        "run-20261102T080000Z"]
    lines: list[str] = []
    removed = make_room(tmp_path, max_total_bytes=150, min_free_bytes=0,
                        disk_free=lambda _: _HUGE_FREE, log=lines.append)
    assert removed == [Removed(tmp_path / "run-20261101T080000Z", 100),
                       Removed(tmp_path / "run-20261101T080000Z-2", 100),
                       Removed(tmp_path / "run-20261101T080000Z-10", 100)]
    assert _names(tmp_path) == ["run-20261102T080000Z"]
    assert len(lines) == 3 and all(line.startswith("runs: removed run-") for line in lines)


def test_nothing_goes_when_the_runs_fit(tmp_path: Path) -> None:
    for name in ["run-20261101T080000Z", "run-20261102T080000Z"]:
        _run(tmp_path, name, 100)
    lines: list[str] = []
    assert make_room(tmp_path, max_total_bytes=200, min_free_bytes=10,
                     disk_free=lambda _: 10, log=lines.append) == []
    assert len(_names(tmp_path)) == 2 and lines == []


def test_the_log_line(tmp_path: Path) -> None:
    _run(tmp_path, "run-20261101T080000Z", 123_400_000)
    _run(tmp_path, "run-20261102T080000Z", 4_900_000_000)
    lines: list[str] = []
    make_room(tmp_path, max_total_bytes=5_000_000_000, min_free_bytes=500_000_000,
              disk_free=lambda _: _HUGE_FREE, log=lines.append)
    assert lines == ["runs: removed run-20261101T080000Z (123.4 MB) to keep the runs under "
                     "5000 MB and 500 MB free"]


def test_a_kept_run_stays_even_when_oldest(tmp_path: Path) -> None:
    for name in ["run-20261101T080000Z", "run-20261102T080000Z", "run-20261103T080000Z"]:
        _run(tmp_path, name, 100)
    keep = [tmp_path / "." / "run-20261101T080000Z"]  # another spelling of the same folder
    lines: list[str] = []
    removed = make_room(tmp_path, max_total_bytes=0, min_free_bytes=0, keep=keep,
                        disk_free=lambda _: _HUGE_FREE, log=lines.append)
    assert [r.path.name for r in removed] == ["run-20261102T080000Z", "run-20261103T080000Z"]
    assert _names(tmp_path) == ["run-20261101T080000Z"]
    assert lines[-1].startswith("runs: warning: the runs kept total")  # the kept run is over 0


def test_only_real_run_folders_are_touched(tmp_path: Path) -> None:
    root, outside = tmp_path / "runs", tmp_path / "outside"
    root.mkdir()
    _run(outside, "run-19990101T000000Z", 1000)  # what the symlinks point at
    (outside / "precious.bin").write_bytes(b"x" * 50)
    (root / "notes.txt").write_text("not a run")
    (root / "other").mkdir()
    (root / "other" / "data.bin").write_bytes(b"x" * 50)
    (root / "run-not-a-folder").write_text("a file named run-*")
    (root / "run-00000000T000000Z").symlink_to(outside / "run-19990101T000000Z")
    run = _run(root, "run-20261101T080000Z", 100)
    (run / "link-out").symlink_to(outside / "precious.bin")
    (run / "dir-out").symlink_to(outside)
    assert tree_bytes(run) == 100 + len(os.readlink(run / "link-out")) + len(
        os.readlink(run / "dir-out"))  # links count themselves; their targets are not walked
    removed = make_room(root, max_total_bytes=0, min_free_bytes=0,
                        disk_free=lambda _: _HUGE_FREE)
    assert [r.path for r in removed] == [run]
    assert _names(root) == ["notes.txt", "other", "run-00000000T000000Z", "run-not-a-folder"]
    assert (root / "other" / "data.bin").read_bytes() == b"x" * 50
    assert (outside / "precious.bin").read_bytes() == b"x" * 50
    assert tree_bytes(outside / "run-19990101T000000Z") == 1000


def test_the_free_space_floor_drives_deletions(tmp_path: Path) -> None:
    for day in range(1, 5):
        _run(tmp_path, f"run-202611{day:02d}T080000Z", 100)
    capacity_bytes = 1000

    def disk_free(path: Path) -> int:  # the disk holds the runs and nothing else
        return capacity_bytes - sum(tree_bytes(run) for run in run_folders(path))

    lines: list[str] = []
    removed = make_room(tmp_path, max_total_bytes=10**9, min_free_bytes=750,
                        disk_free=disk_free, log=lines.append)
    assert [r.path.name for r in removed] == ["run-20261101T080000Z", "run-20261102T080000Z"]
    assert disk_free(tmp_path) == 800 and len(lines) == 2


def test_an_impossible_floor_warns_and_returns(tmp_path: Path) -> None:
    for day in range(1, 4):
        _run(tmp_path, f"run-202611{day:02d}T080000Z", 100)
    keep = {tmp_path / "run-20261103T080000Z"}
    lines: list[str] = []
    removed = make_room(tmp_path, max_total_bytes=10**9, min_free_bytes=10**12, keep=keep,
                        disk_free=lambda _: 5_000_000, log=lines.append)
    assert len(removed) == 2 and _names(tmp_path) == ["run-20261103T080000Z"]
    assert lines[-1] == ("runs: warning: only 5.0 MB free, below the floor of 1000000 MB, and "
                         "no run folder is left to remove")


def test_a_missing_root_is_nothing_to_do(tmp_path: Path) -> None:
    def disk_free(path: Path) -> int:
        raise AssertionError("not asked")

    assert make_room(tmp_path / "nowhere", max_total_bytes=0, min_free_bytes=10**12,
                     disk_free=disk_free) == []


@pytest.mark.parametrize(("max_total_bytes", "min_free_bytes", "key"), [
    (-1, 0, "output.max_runs_mb"),
    (0, -1, "output.min_free_mb"),
])
def test_negative_limits_name_their_key(tmp_path: Path, max_total_bytes: int,
                                        min_free_bytes: int, key: str) -> None:
    with pytest.raises(ConfigError) as caught:
        make_room(tmp_path, max_total_bytes=max_total_bytes, min_free_bytes=min_free_bytes)
    assert caught.value.key == key
