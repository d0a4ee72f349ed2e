"""PoseBuffer: interpolation, slerp, gaps, reboots and bounded memory."""

from __future__ import annotations

import math
import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.errors import ConfigError, InputError
from companion.rotation import quaternion_from_euler
from companion.vehicle.pose_buffer import GeoPoseSample, PoseBuffer, Quaternion, slerp

LEVEL: Quaternion = (1.0, 0.0, 0.0, 0.0)


def _yaw_q(yaw_deg: float) -> Quaternion:
    q = quaternion_from_euler(0.0, 0.0, math.radians(yaw_deg))
    return (q[0], q[1], q[2], q[3])


def _same_rotation(a: Quaternion, b: Quaternion) -> bool:
    return abs(abs(sum(x * y for x, y in zip(a, b, strict=True))) - 1.0) < 1e-12


def _linear(t_s: float) -> tuple[float, float, float, float]:
    return 47.0 + 1e-5 * t_s, 8.0 - 2e-5 * t_s, 500.0 + 3.0 * t_s, 20.0 + 3.0 * t_s


def _moving(times_s: list[float]) -> PoseBuffer:
    buffer = PoseBuffer()
    for t_s in times_s:
        buffer.add_position(t_s, *_linear(t_s))
        buffer.add_attitude(t_s, LEVEL)
    return buffer


def test_position_interpolation_is_exact_on_linear_motion() -> None:
    buffer = _moving([0.1 * i for i in range(20)])
    for t_s in (0.0, 0.237, 1.05, 1.9):
        pose = buffer.at(t_s)
        assert pose is not None and pose.t_s == t_s
        got = (pose.lat_deg, pose.lon_deg, pose.alt_amsl_m, pose.alt_rel_m)
        assert got == pytest.approx(_linear(t_s), rel=0.0, abs=1e-9)
        assert pose.q_wxyz == LEVEL
    extrapolated = buffer.at(1.95)  # 0.05 s past the last sample: along the last segment
    assert extrapolated is not None and extrapolated.alt_amsl_m == pytest.approx(505.85)


def test_out_of_order_and_repeated_samples() -> None:
    times_s = [0.1 * i for i in range(20)]
    shuffled = []  # late by up to 0.4 s: out of order, not a reboot
    for start in range(0, 20, 5):
        block = times_s[start:start + 5]
        random.Random(start).shuffle(block)
        shuffled += block
    buffer = _moving(shuffled + times_s[-5:])
    assert buffer.position_count == buffer.attitude_count == 20
    reference = _moving(times_s)
    assert all(buffer.at(t) == reference.at(t) for t in (0.05, 0.93, 1.9))
    buffer.add_position(1.0, 0.0, 0.0, 0.0, 0.0)  # a repeat replaces
    pose = buffer.at(1.0)
    assert pose is not None and pose.lat_deg == 0.0 and buffer.position_count == 20


def test_slerp_midpoint_of_a_90_deg_yaw_turn_and_the_sign_of_q() -> None:
    for end in (_yaw_q(90.0), tuple(-c for c in _yaw_q(90.0))):
        buffer = PoseBuffer()
        for t_s in (0.0, 0.2):
            buffer.add_position(t_s, 47.0, 8.0, 500.0, 20.0)
        buffer.add_attitude(0.0, _yaw_q(0.0))
        buffer.add_attitude(0.2, (end[0], end[1], end[2], end[3]))
        mid, quarter = buffer.at(0.1), buffer.at(0.05)
        assert mid is not None and _same_rotation(mid.q_wxyz, _yaw_q(45.0))
        assert quarter is not None and _same_rotation(quarter.q_wxyz, _yaw_q(22.5))
    assert _same_rotation(slerp(_yaw_q(10.0), _yaw_q(10.0 + 1e-6), 0.5), _yaw_q(10.0 + 5e-7))


def test_longitude_interpolates_across_the_antimeridian() -> None:
    buffer = PoseBuffer()
    buffer.add_position(0.0, 0.0, 179.9999, 0.0, 0.0)
    buffer.add_position(0.2, 0.0, -179.9997, 0.0, 0.0)
    for t_s in (0.0, 0.2):
        buffer.add_attitude(t_s, LEVEL)
    first, last = buffer.at(0.025), buffer.at(0.15)
    assert first is not None and first.lon_deg == pytest.approx(179.99995, abs=1e-9)
    assert last is not None and last.lon_deg == pytest.approx(-179.9998, abs=1e-9)


def test_gaps_and_times_outside_the_samples_give_none() -> None:
    buffer = _moving([0.0, 0.1, 0.7, 0.8])  # 0.6 s gap between 0.1 and 0.7
    assert buffer.at(0.4) is None
    assert buffer.at(0.1) is not None and buffer.at(0.7) is not None  # seen: answered
    assert buffer.at(-0.05) is not None and buffer.at(0.85) is not None
    assert buffer.at(-0.15) is None and buffer.at(0.95) is None
    buffer.add_attitude(0.45, LEVEL)
    assert buffer.at(0.4) is None  # the position still has its gap
    lone = PoseBuffer()
    lone.add_position(5.0, 47.0, 8.0, 500.0, 20.0)
    assert lone.at(5.0) is None  # no attitude yet
    lone.add_attitude(5.02, LEVEL)
    assert lone.at(5.05) == GeoPoseSample(5.05, 47.0, 8.0, 500.0, 20.0, LEVEL)  # held


def test_the_newest_pose_is_at_the_newest_position_while_attitudes_run_ahead() -> None:
    """A lossy link: the last position at 13.28 s, attitudes on to 13.5 s. at(13.5) would
    extrapolate the position 0.22 s and says None; newest() is the pose at 13.28 s. Once the
    attitudes are max_gap_s ahead, the position stream has stopped: None."""
    buffer = _moving([13.0 + 0.04 * i for i in range(8)])  # to 13.28
    assert buffer.newest() == buffer.at(13.28)
    for t_s in (13.3, 13.4, 13.5):
        buffer.add_attitude(t_s, _yaw_q(10.0))
    assert buffer.at(13.5) is None
    here = buffer.newest()
    assert here is not None and here.t_s == 13.28 and here.alt_rel_m == _linear(13.28)[3]
    buffer.add_attitude(13.79, LEVEL)
    assert buffer.newest() is None
    assert PoseBuffer().newest() is None
    lone = PoseBuffer()
    lone.add_position(5.0, 47.0, 8.0, 500.0, 20.0)
    assert lone.newest() is None  # no attitude yet


def test_a_reboot_clears_the_buffer() -> None:
    buffer = _moving([100.0 + 0.1 * i for i in range(10)])
    buffer.add_position(100.2, *_linear(100.2))  # late, but not a reboot
    assert buffer.reboots == 0
    buffer.add_attitude(0.3, LEVEL)
    assert buffer.reboots == 1 and buffer.position_count == 0 and buffer.attitude_count == 1
    assert buffer.at(100.5) is None
    buffer.add_position(0.3, *_linear(0.3))
    assert buffer.at(0.3) is not None


@settings(max_examples=60, deadline=None)
@given(rate_hz=st.sampled_from([5, 10, 50]), max_age_ms=st.integers(100, 3000),
       steps=st.lists(st.integers(-3, 4), min_size=1, max_size=200))
def test_memory_is_bounded_by_max_age_at_the_sample_rate(rate_hz: int, max_age_ms: int,
                                                         steps: list[int]) -> None:
    """Samples on a rate_hz grid, stepping back (late, repeated) or forward at random."""
    max_age_s = max_age_ms / 1000.0
    bound = math.floor(max_age_s * rate_hz + 1e-6) + 1
    buffer = PoseBuffer(max_age_s=max_age_s)
    k = 1000
    for step in steps:
        k = max(0, k + step)
        buffer.add_position(k / rate_hz, 47.0, 8.0, 500.0, 20.0)
        buffer.add_attitude(k / rate_hz, LEVEL)
        assert buffer.position_count <= bound and buffer.attitude_count <= bound


def test_bad_input_is_named() -> None:
    buffer = PoseBuffer()
    with pytest.raises(InputError, match="lat_deg"):
        buffer.add_position(0.0, 91.0, 8.0, 500.0, 20.0)
    with pytest.raises(InputError, match=r"position\.t_s"):
        buffer.add_position(math.nan, 47.0, 8.0, 500.0, 20.0)
    with pytest.raises(InputError, match="unit quaternion"):
        buffer.add_attitude(0.0, (2.0, 0.0, 0.0, 0.0))
    with pytest.raises(InputError, match="q_wxyz"):
        buffer.add_attitude(0.0, (1.0, 0.0, 0.0))  # type: ignore[arg-type]
    with pytest.raises(InputError, match="t_s"):
        buffer.at(math.inf)
    with pytest.raises(ConfigError, match="max_gap_s"):
        PoseBuffer(max_gap_s=0.0)
