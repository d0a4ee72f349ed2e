"""The setpoint stream's schedule as the service sent it, one rule for every flight test.

The service sends a setpoint every period from its event loop; MAVSDK's offboard plugin resends
the last one at 20 Hz (docs/field-notes), so what PX4 receives does not pause when the service's
loop does. A stall of this 2-core virtual machine (110 to 260 ms seen in clean-clone runs, the
whole process frozen) delays one setpoint as sent and nothing else. The rule: the median period
as configured, at most 1 % of the gaps over 1.5 periods, and no gap as long as PX4's least
offboard rate allows (2 Hz): a service that falls behind, or blocks its loop for half a second,
fails it; one stall of the machine does not.
"""

from __future__ import annotations

import pytest

from benchmarks.soak import GapStats

PX4_LEAST_OFFBOARD_PERIOD_S = 0.5  # PX4 takes an offboard stream of 2 Hz at least
STALL_SHARE = 0.01  # at most this share of the gaps over 1.5 periods


def assert_on_schedule(sent: GapStats, period_s: float, figures: str = "") -> None:
    """Fail unless the gaps of a stream as sent (gap_stats over 1.5 periods) keep the rule."""
    assert sent.limit_s == pytest.approx(1.5 * period_s), sent
    assert sent.median_s == pytest.approx(period_s, abs=0.1 * period_s), (sent, figures)
    assert sent.over_limit <= STALL_SHARE * (sent.count - 1), (sent, figures)
    assert sent.max_s < PX4_LEAST_OFFBOARD_PERIOD_S, (sent, figures)
