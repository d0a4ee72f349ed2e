"""Time one GP prediction (companion.sat.gp) for track histories of 100, 1,000 and 5,000 points.

Run: python benchmarks/bench_gp.py [--repeats N] [--seed S]

Compares the windowed predictor (default GpParams.window) through gp_predict and through
GpPredictor (10 tracks per call, time per track, with a warm cache as in steady state and with
no cache), against the exact GP over the whole history and the paper's GPML/MATLAB times.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from functools import partial

import numpy as np
import numpy.typing as npt

from companion.sat.gp import GpParams, GpPredictor, gp_predict

FloatArray = npt.NDArray[np.float64]

HISTORY_LENGTHS = (100, 1_000, 5_000)
PAPER_GPML_S = {100: 0.29, 1_000: 0.35, 5_000: 3.53}  # the paper's footnote, MATLAB GPML
N_TRACKS = 10
TARGET_US = 100.0  # 0.1 ms per prediction
# The exact GP is O(n^3): fewer repeats for long histories keep the run under a minute.
FULL_REPEATS = {100: 200, 1_000: 10, 5_000: 3}
T_UTM = np.array([500000.0, 4000000.0])  # a UTM-sized origin, metres


def _history(rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
    """A paper-style track history at 1 Hz: 0.05 m/s straight leg plus 0.3 m noise."""
    t_s = np.arange(n, dtype=np.float64)
    heading = rng.uniform(0.0, 2.0 * np.pi)
    vel = 0.05 * np.array([np.cos(heading), np.sin(heading)])
    y = T_UTM + t_s[:, None] * vel + 0.3 * rng.standard_normal((n, 2))
    return t_s, y


def _time_ns(call: Callable[[], object], repeats: int) -> FloatArray:
    """Wall time of each of `repeats` calls, in nanoseconds (after one warm-up call)."""
    call()
    out = np.empty(repeats, dtype=np.float64)
    for i in range(repeats):
        start = time.perf_counter_ns()
        call()
        out[i] = time.perf_counter_ns() - start
    return out


def _fmt(samples_ns: FloatArray, per: int = 1) -> str:
    med = float(np.median(samples_ns)) / per / 1e3
    p95 = float(np.percentile(samples_ns, 95)) / per / 1e3
    return f"{med:8.1f} / {p95:8.1f}"


def main() -> None:
    """Print the timing table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=2000, help="repeats of windowed calls")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    params = GpParams()
    width = params.window

    print(
        f"GP prediction time, window = {params.window} points, {N_TRACKS} tracks per batched call"
    )
    print("times in microseconds, median / p95; full GP in milliseconds")
    header = (
        f"{'history':>8} | {'GPML (paper)':>12} | {'gp_predict':>19} | "
        f"{'GpPredictor warm':>19} | {'GpPredictor cold':>19} | {'full exact GP (ms)':>19}"
    )
    print(header)
    print("-" * len(header))
    worst_us = 0.0
    for n in HISTORY_LENGTHS:
        tracks = [_history(rng, n) for _ in range(N_TRACKS)]
        t_s, y = tracks[0]
        t_star = float(t_s[-1] + 1.0)

        single = _time_ns(partial(gp_predict, params, t_s, y, t_star), args.repeats)

        t_win = np.stack([tr[0][-width:] for tr in tracks])
        y_win = np.stack([tr[1][-width:] for tr in tracks])
        counts = np.full(N_TRACKS, width, dtype=np.int64)
        warm = GpPredictor(params)
        cold = GpPredictor(params, cache_size=0)
        batch_warm = _time_ns(partial(warm.predict, t_win, y_win, counts, t_star), args.repeats)
        batch_cold = _time_ns(partial(cold.predict, t_win, y_win, counts, t_star), args.repeats)

        full_params = GpParams(window=n)
        full = _time_ns(partial(gp_predict, full_params, t_s, y, t_star), FULL_REPEATS[n])

        worst_us = max(
            worst_us,
            float(np.median(single)) / 1e3,
            float(np.median(batch_warm)) / N_TRACKS / 1e3,
            float(np.median(batch_cold)) / N_TRACKS / 1e3,
        )
        print(
            f"{n:>8} | {PAPER_GPML_S[n] * 1e3:>9.0f} ms | {_fmt(single)} | "
            f"{_fmt(batch_warm, N_TRACKS)} | {_fmt(batch_cold, N_TRACKS)} | "
            f"{np.median(full) / 1e6:8.2f} / {np.percentile(full, 95) / 1e6:8.2f}"
        )
    verdict = "met" if worst_us < TARGET_US else "NOT met"
    print(
        f"target < {TARGET_US:.0f} us per windowed prediction: {verdict} "
        f"(worst median {worst_us:.1f} us)"
    )


if __name__ == "__main__":
    main()
