"""Track maintenance: stable ids, splits, confirmation, holding out of view, ending, history."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from companion.sat.fov import ConvexPolygon, Disk
from companion.sat.mixture import NO_LABEL, Mixture, make_mixture
from companion.sat.motion import TargetMotion
from companion.sat.tracks import Evidence, TrackLog, TrackParams, Tracks, grown_covs, maintain

# Stationary targets: a track's uncertainty does not grow with the time it is unseen.
PARAMS = TrackParams(gate_sq=10.0, confirm_length=3, timeout_s=5.0, window=4,
                     motion=TargetMotion(0.0))
WALKERS = TrackParams(gate_sq=10.0, confirm_length=3, timeout_s=5.0, window=4,
                      motion=TargetMotion(0.5, 100.0))
NONE = np.zeros(0, dtype=np.int64)


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


def test_a_held_still_track_is_not_taken_by_a_wide_estimate_that_no_detection_made() -> None:
    tracks, labelled = _run([_mix([[0.0, 0.0]], [1.0])] * 3)
    assert tracks.confirmed.tolist() == [True]
    # Its own light component still holds the track; beside it lies a wide unlabelled estimate
    # (prior mass spread for an hour, 15 m standard deviation) whose mean is 8 m away.
    frame = make_mixture([0.3, 0.6], [[0.0, 0.0], [8.0, 0.0]],
                         [labelled.covs[0], 225.0 * np.eye(2)], [0, NO_LABEL])
    for detected, continues in ((False, False), (True, True)):
        # Eq. held_gate: only an estimate a detection made may take the held track over.
        after, relabelled = maintain(
            tracks, frame, np.array([1]), np.array([False, detected]), 3.0, PARAMS
        )
        assert (relabelled.labels.tolist() == [NO_LABEL, 0]) is continues
        held_mean = np.allclose(after.means[0], [0.0, 0.0])
        assert held_mean is not continues
        assert after.size == (1 if continues else 2)
    # A walker's track (its window moves) may be continued by it: the walker may be there now.
    walking = tracks._replace(gp_mu=np.column_stack([tracks.gp_mu[:, :-1], [1.0]]))
    _, relabelled = maintain(
        walking, frame, np.array([1]), np.array([False, False]), 3.0, PARAMS
    )
    assert relabelled.labels.tolist() == [NO_LABEL, 0]


def test_log_views_are_immutable() -> None:
    log = TrackLog.empty(2)
    a = log.append(np.array([1]), 0.0, np.zeros((1, 2)), np.ones((1, 2, 2)))
    b = a.append(np.array([1]), 1.0, np.ones((1, 2)), np.ones((1, 2, 2)))
    c = a.append(np.array([1]), 2.0, 2 * np.ones((1, 2)), np.ones((1, 2, 2)))  # branch from a
    assert a.history(1)[0].tolist() == [0.0]
    assert b.history(1)[0].tolist() == [0.0, 1.0]
    assert c.history(1)[0].tolist() == [0.0, 2.0]


def test_appending_some_rows_logs_what_appending_those_rows_alone_logs() -> None:
    ids, means = np.array([4, 7, 9]), np.arange(6.0).reshape(3, 2)
    covs = np.arange(12.0).reshape(3, 2, 2)
    rows = np.array([2, 0])
    some = TrackLog.empty(2).append(ids, 3.0, means, covs, rows)
    alone = TrackLog.empty(2).append(ids[rows], 3.0, means[rows], covs[rows])
    for track_id in (4, 7, 9):
        for got, want in zip(some.history(track_id), alone.history(track_id), strict=True):
            assert np.array_equal(got, want)
    assert some.length == 2 and TrackLog.empty(2).append(ids, 3.0, means, covs, NONE).length == 0


def _confirmed_walker() -> tuple[Tracks, Mixture]:
    """One confirmed track of a walker at the origin, seen at t = 0, 1, 2 (no frame evidence)."""
    tracks = Tracks.empty(2, WALKERS.window)
    labelled = _mix([[0.0, 0.0]], [1.0])
    for t in (0.0, 1.0, 2.0):
        frame = Mixture(labelled.weights, labelled.means, labelled.covs, labelled.labels)
        tracks, labelled = maintain(tracks, frame, np.array([0]), np.array([True]), t, WALKERS)
    assert tracks.confirmed.tolist() == [True]
    return tracks, labelled


def _evidence(centre_xy: list[float], radius_m: float, clutter_per_m2: float = 1e-5) -> Evidence:
    return Evidence(Disk(np.array(centre_xy), radius_m), 0.98, clutter_per_m2, np.eye(2), 1e-3)


def test_an_unseen_movers_track_coasts_alone_with_a_growing_honest_covariance() -> None:
    tracks, _ = _confirmed_walker()
    motion = WALKERS.motion
    far = _evidence([500.0, 500.0], 20.0)  # frames that look elsewhere say nothing of it
    existence = tracks.existence[0]
    for t in (3.0, 10.0, 100.0, 400.0):
        tracks, _ = maintain(tracks, Mixture.empty(), NONE, np.zeros(0, dtype=bool), t, WALKERS,
                             far)
        assert tracks.ids.tolist() == [0], "out of view is not evidence: no timeout for movers"
        assert tracks.alone.tolist() == [True]
        assert tracks.existence[0] == existence
        var = grown_covs(tracks, t, motion)[0, 0, 0]
        # the component's 0.25 m^2 plus the integrated-OU displacement variance since t = 2 s
        np.testing.assert_allclose(var, 0.25 + motion.displacement_var_m2(t - 2.0), rtol=1e-9)
    assert grown_covs(tracks, 400.0, motion)[0, 0, 0] > 1000.0  # ~ 2 sigma_v^2 tau_c tau


def test_misses_in_view_end_a_coasting_track_and_a_redetection_continues_it() -> None:
    tracks, _ = _confirmed_walker()
    # 60 s unseen, then frames over its whole uncertainty miss it: r = 0.99 falls to 0.66 after
    # one (Bayes: r (1 - p_D) / (1 - r p_D)), and below 0.1 after two, which ends the track.
    seen, _ = maintain(tracks, Mixture.empty(), NONE, np.zeros(0, dtype=bool), 62.0, WALKERS)
    sd = float(np.sqrt(grown_covs(seen, 62.0, WALKERS.motion)[0, 0, 0]))
    whole = _evidence([0.0, 0.0], 6.0 * sd)
    once, _ = maintain(seen, Mixture.empty(), NONE, np.zeros(0, dtype=bool), 63.0, WALKERS, whole)
    np.testing.assert_allclose(once.existence, [0.99 * 0.02 / (1.0 - 0.99 * 0.98)], rtol=1e-6)
    gone, _ = maintain(once, Mixture.empty(), NONE, np.zeros(0, dtype=bool), 64.0, WALKERS, whole)
    assert gone.size == 0, "misses over the whole of it end the track"
    # A frame over half of it: the Gaussian moves away from what was seen, the track lives on.
    half, _ = maintain(seen, Mixture.empty(), NONE, np.zeros(0, dtype=bool), 63.0, WALKERS,
                       _evidence([-3.0 * sd, 0.0], 3.0 * sd))
    assert half.ids.tolist() == [0]
    assert half.means[0, 0] > 0.3 * sd
    assert 0.1 < half.existence[0] < seen.existence[0]
    # The walker is re-detected 15 m away, far outside its last component's gate but inside its
    # grown one: the estimate continues the same track rather than starting another.
    found = _mix([[15.0, 0.0]], [0.9])
    again, labelled = maintain(seen, found, np.array([0]), np.array([True]), 63.0, WALKERS)
    assert again.ids.tolist() == [0]
    assert labelled.labels.tolist() == [0]
    assert again.alone.tolist() == [False]
    assert again.seen_t_s.tolist() == [63.0]


def test_a_long_coasting_track_leaves_a_point_it_explains_worse_than_clutter_to_a_new_track() -> (
        None):
    """Eq. coast_gate: the grown gate takes an estimate where N(m_e; m_t, P_t + P_e) > kappa."""
    walker, _ = _confirmed_walker()
    tracks, _ = maintain(walker, Mixture.empty(), NONE, np.zeros(0, dtype=bool), 3.0, WALKERS)
    assert tracks.alone.tolist() == [True]
    t_s = 600.0  # unseen for ten minutes: a Gaussian some 60 m wide per axis
    sd = float(np.sqrt(grown_covs(tracks, t_s, WALKERS.motion)[0, 0, 0]))
    assert sd > 40.0
    point = _mix([[0.5 * sd, 0.0]], [0.9])  # well inside its gate (gate_sq = 10)
    density = np.exp(-0.5 * 0.25 * sd**2 / (sd**2 + 0.25)) / (2.0 * np.pi * (sd**2 + 0.25))

    def after(clutter_per_m2: float) -> tuple[Tracks, Mixture]:
        return maintain(tracks, point, np.array([0]), np.array([True]), t_s, WALKERS,
                        _evidence([0.5 * sd, 0.0], 25.0, clutter_per_m2))

    taken, labelled = after(0.5 * density)
    assert taken.ids.tolist() == [0] and labelled.labels.tolist() == [0]
    assert taken.alone.tolist() == [False]
    left, labelled = after(2.0 * density)
    assert left.ids.tolist() == [0, 1], "the point starts a tentative track of its own"
    assert labelled.labels.tolist() == [1]
    assert left.alone.tolist() == [True, False]
    assert left.seen_t_s[0] == tracks.seen_t_s[0], "the walker's track was not seen there"


def test_clutter_cannot_confirm_a_track_that_the_frames_do_not_support() -> None:
    """Three detections confirm a track when false alarms are rare, not in heavy clutter."""
    def three_hits(clutter_per_m2: float, weight: float) -> Tracks:
        tracks = Tracks.empty(2, PARAMS.window)
        labelled = _mix([[0.0, 0.0]], [weight])
        for t in (0.0, 1.0, 2.0):
            frame = Mixture(labelled.weights, labelled.means, labelled.covs, labelled.labels)
            tracks, labelled = maintain(tracks, frame, np.array([0]), np.array([True]), t,
                                        PARAMS, _evidence([0.0, 0.0], 25.0, clutter_per_m2))
        return tracks

    assert three_hits(1e-5, 0.6).confirmed.tolist() == [True]
    assert three_hits(1e-2, 0.6).confirmed.tolist() == [False]


def test_a_miss_in_view_counts_against_a_track_and_one_out_of_view_does_not() -> None:
    tracks, labelled = _run([_mix([[0.0, 0.0]], [1.0])] * 3)
    before = float(tracks.score[0])
    light = Mixture(np.array([0.3]), labelled.means, labelled.covs, labelled.labels)
    out, _ = maintain(tracks, light, NONE, np.array([False]), 3.0, PARAMS,
                      _evidence([100.0, 0.0], 20.0))
    assert out.score[0] == before
    seen, _ = maintain(tracks, light, NONE, np.array([False]), 3.0, PARAMS,
                       _evidence([0.0, 0.0], 20.0))
    np.testing.assert_allclose(seen.score[0], before + np.log(1.0 - 0.98), rtol=1e-6)


def test_a_track_pushed_out_of_the_search_area_ends() -> None:
    area = ConvexPolygon(np.array([[-50.0, -50.0], [50.0, -50.0], [50.0, 50.0], [-50.0, 50.0]]))
    params = replace(WALKERS, area=area)
    tracks, _ = _confirmed_walker()
    inside, _ = maintain(tracks, Mixture.empty(), NONE, np.zeros(0, dtype=bool), 3.0, params)
    assert inside.ids.tolist() == [0]
    outside = inside._replace(means=np.array([[400.0, 0.0]]))
    gone, _ = maintain(outside, Mixture.empty(), NONE, np.zeros(0, dtype=bool), 4.0, params)
    assert gone.size == 0


def test_a_mover_found_again_by_a_new_track_keeps_its_old_track() -> None:
    """The walker's old track is coasting; a second track confirms 8 m away: being the old target
    explains it better than a target not seen yet (density above the birth intensity)."""
    tracks, _ = _confirmed_walker()
    tracks, _ = maintain(tracks, Mixture.empty(), NONE, np.zeros(0, dtype=bool), 20.0, WALKERS)
    evidence = _evidence([8.0, 0.0], 25.0)
    labelled = _mix([[8.0, 0.0]], [0.9])
    for t in (21.0, 22.0, 23.0):
        frame = Mixture(labelled.weights, labelled.means, labelled.covs, labelled.labels)
        tracks, labelled = maintain(tracks, frame, np.array([0]), np.array([True]), t, WALKERS,
                                    evidence)
    assert tracks.ids.tolist() == [0], "one track, the old one"
    assert labelled.labels.tolist() == [0]
    np.testing.assert_allclose(tracks.means[0], [8.0, 0.0])
    assert tracks.seen_t_s.tolist() == [23.0]
    assert tracks.hits.tolist() == [6]
    # Far away (80 m), the new track is another target: both stay.
    far, _ = _confirmed_walker()
    far, _ = maintain(far, Mixture.empty(), NONE, np.zeros(0, dtype=bool), 20.0, WALKERS)
    labelled = _mix([[80.0, 0.0]], [0.9])
    for t in (21.0, 22.0, 23.0):
        frame = Mixture(labelled.weights, labelled.means, labelled.covs, labelled.labels)
        far, labelled = maintain(far, frame, np.array([0]), np.array([True]), t, WALKERS,
                                 _evidence([80.0, 0.0], 25.0))
    assert far.ids.tolist() == [0, 1]
