"""Track maintenance: stable ids, splits, confirmation, holding out of view, ending, history."""

from __future__ import annotations

import numpy as np

from companion.sat.mixture import NO_LABEL, Mixture, make_mixture
from companion.sat.tracks import TrackLog, TrackParams, Tracks, maintain

PARAMS = TrackParams(gate_sq=10.0, confirm_length=3, timeout_s=5.0, window=4)


def _mix(xy: list[list[float]], weights: list[float], labels: list[int] | None = None) -> Mixture:
    return make_mixture(weights, xy, [0.25 * np.eye(2)] * len(xy), labels)


def _run(
    frames: list[Mixture], detected: bool = True, tracks: Tracks | None = None, t0: float = 0.0
) -> tuple[Tracks, Mixture]:
    tracks = tracks or Tracks.empty(2, PARAMS.window)
    labelled = frames[0]
    for k, given in enumerate(frames):
        # Carry last step's labels over to this step's components (the filter's labels survive
        # predict/update); frames that set labels themselves keep theirs.
        labels = given.labels if np.any(given.labels != NO_LABEL) else labelled.labels
        if labels.size != given.size:
            labels = np.full(given.size, NO_LABEL)
        frame = Mixture(given.weights, given.means, given.covs, labels)
        est = np.flatnonzero(frame.weights > 0.5)
        tracks, labelled = maintain(
            tracks, frame, est, np.full(frame.size, detected), t0 + k, PARAMS
        )
    return tracks, labelled


def test_ids_are_stable_and_tracks_confirm_after_three_detections() -> None:
    frames = [_mix([[0.0 + 0.1 * k, 0.0], [20.0, 5.0 - 0.1 * k]], [1.0, 1.0]) for k in range(5)]
    tracks, labelled = _run(frames[:2])
    assert tracks.ids.tolist() == [0, 1]
    assert not tracks.confirmed.any()
    tracks, labelled = _run(frames[2:], tracks=tracks, t0=2.0)
    assert tracks.ids.tolist() == [0, 1]
    assert tracks.confirmed.all()
    assert tracks.life.tolist() == [5, 5]
    assert labelled.labels.tolist() == [0, 1]
    t, means, covs = tracks.log.history(1)
    assert t.tolist() == [0.0, 1.0, 2.0, 3.0, 4.0]
    np.testing.assert_allclose(means[:, 1], [5.0, 4.9, 4.8, 4.7, 4.6])
    assert covs.shape == (5, 2, 2)
    # GP window: the 4 most recent positions, right-aligned
    assert tracks.win_count.tolist() == [4, 4]
    np.testing.assert_allclose(tracks.win_t_s[0], [1.0, 2.0, 3.0, 4.0])


def test_unlabelled_estimate_continues_a_gated_track_and_far_one_starts_a_new_track() -> None:
    tracks, _ = _run([_mix([[0.0, 0.0]], [1.0])])
    frame = make_mixture([1.0, 1.0], [[0.3, 0.0], [40.0, 0.0]], [0.25 * np.eye(2)] * 2)
    tracks, labelled = maintain(
        tracks, frame, np.array([0, 1]), np.array([True, True]), 1.0, PARAMS
    )
    assert tracks.ids.tolist() == [0, 1]
    assert labelled.labels.tolist() == [0, 1]


def test_a_split_keeps_the_id_on_the_closer_estimate() -> None:
    tracks, _ = _run([_mix([[0.0, 0.0]], [1.0])])
    # Two components of one track's lineage (both labelled 0) now hold two targets apart.
    frame = make_mixture([1.0, 1.0], [[1.2, 0.0], [0.1, 0.0]], [0.25 * np.eye(2)] * 2, [0, 0])
    tracks, labelled = maintain(
        tracks, frame, np.array([0, 1]), np.array([True, True]), 1.0, PARAMS
    )
    assert tracks.ids.tolist() == [0, 1]
    assert labelled.labels.tolist() == [1, 0]
    np.testing.assert_allclose(tracks.means[0], [0.1, 0.0])


def test_copies_of_one_estimate_support_one_track() -> None:
    tracks, _ = _run([_mix([[0.0, 0.0]], [1.0])])
    # A component of weight 2 is two targets in Layer 2, but copies cannot be told apart.
    frame = make_mixture([2.0], [[0.1, 0.0]], [0.25 * np.eye(2)], [0])
    rows = np.flatnonzero(frame.weights > 0.5)  # what the filter passes: each row once
    tracks, labelled = maintain(tracks, frame, rows, np.array([True]), 1.0, PARAMS)
    assert tracks.ids.tolist() == [0]
    assert labelled.labels.tolist() == [0]


def test_tentative_track_ends_at_its_first_miss_and_is_not_confirmed_without_detections() -> None:
    tracks, _ = _run([_mix([[0.0, 0.0]], [1.0])])
    tracks, _ = maintain(tracks, Mixture.empty(), np.zeros(0, dtype=np.int64),
                         np.zeros(0, dtype=bool), 1.0, PARAMS)
    assert tracks.size == 0
    # A component seen once and then kept out of view (no detections) stays tentative.
    frames = [_mix([[0.0, 0.0]], [0.9])] * 6
    tracks, _ = _run(frames[:1])
    tracks, _ = _run(frames[1:], detected=False, tracks=tracks, t0=1.0)
    assert tracks.size == 1
    assert tracks.hits.tolist() == [1]
    assert not tracks.confirmed.any()


def test_confirmed_track_is_held_by_its_light_component_and_ends_after_the_timeout() -> None:
    frames = [_mix([[0.0, 0.0]], [1.0])] * 3
    tracks, labelled = _run(frames)
    assert tracks.confirmed.tolist() == [True]
    # The component drops below the extraction weight (left at the edge of the FOV) but lives.
    light = Mixture(np.array([0.2]), labelled.means, labelled.covs, labelled.labels)
    tracks, labelled = maintain(
        tracks, light, np.zeros(0, dtype=np.int64), np.array([False]), 3.0, PARAMS
    )
    assert tracks.ids.tolist() == [0]
    assert tracks.last_t_s.tolist() == [3.0]
    assert labelled.labels.tolist() == [0]
    # Then it is gone from the mixture: the track coasts for timeout_s, then ends.
    for t in (4.0, 8.0):
        tracks, _ = maintain(tracks, Mixture.empty(), np.zeros(0, dtype=np.int64),
                             np.zeros(0, dtype=bool), t, PARAMS)
        assert tracks.ids.tolist() == [0]
    tracks, _ = maintain(tracks, Mixture.empty(), np.zeros(0, dtype=np.int64),
                         np.zeros(0, dtype=bool), 8.5, PARAMS)
    assert tracks.size == 0


def test_log_views_are_immutable() -> None:
    log = TrackLog.empty(2)
    a = log.append(np.array([1]), 0.0, np.zeros((1, 2)), np.ones((1, 2, 2)))
    b = a.append(np.array([1]), 1.0, np.ones((1, 2)), np.ones((1, 2, 2)))
    c = a.append(np.array([1]), 2.0, 2 * np.ones((1, 2)), np.ones((1, 2, 2)))  # branch from a
    assert a.history(1)[0].tolist() == [0.0]
    assert b.history(1)[0].tolist() == [0.0, 1.0]
    assert c.history(1)[0].tolist() == [0.0, 2.0]
