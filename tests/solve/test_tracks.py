"""Feature tracks: union-find over verified matches, triangulation, static tracks, guided extension."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ctpipe.data import Matches, PairEstimate, ScanObservations
from ctpipe.errors import InputError
from ctpipe.geometry import Geometry
from ctpipe.solve.camera import project_points
from ctpipe.solve.simulated import synthetic_scan
from ctpipe.solve.tracks import (Tracks, build_tracks, descriptor_distances, extend_tracks, static_tracks,
                                 triangulate_tracks)

GEOMETRY = Geometry(150.0, 390.0, 256, 256, 0.8, 0.8)


def _observations(features, pairs, index_ab, masks=None):
    n_views = len(features)
    matches = tuple(Matches(np.asarray(ab, np.int64).reshape(-1, 2), np.zeros(len(ab), np.float32)) for ab in index_ab)
    masks = masks or [np.ones(len(m), bool) for m in matches]
    estimates = tuple(PairEstimate(0.01, np.asarray(mask, bool), 0.0) for mask in masks)
    empty = tuple(np.zeros((len(m), 2)) for m in matches)
    return ScanObservations(geometry=GEOMETRY, n_views=n_views, features=tuple(features),
                            pairs=np.asarray(pairs, np.int64), matches=matches, points_a=empty, points_b=empty,
                            estimates=estimates)


def test_tracks_join_verified_matches_and_drop_conflicts_and_outliers():
    scan = synthetic_scan(4, 1, rng=0)
    features = scan.observations.features  # one keypoint per view at most; we only need counts
    f = [dataclasses.replace(features[0]) for _ in range(4)]
    from ctpipe.data import Features
    f = [Features.build(xy=np.arange(10.0).reshape(5, 2) + v, size=np.ones(5), angle_deg=np.zeros(5),
                        response=-np.arange(5.0), descriptors=np.zeros((5, 4), np.float32), norm="L2") for v in range(4)]
    pairs = [(0, 1), (1, 2), (2, 3), (0, 2)]
    # keypoint 0 runs 0-1-2-3; keypoint 1 of view 0 matches two keypoints of view 2 via 1 -> conflict;
    # keypoint 4 pairs (0, 1) only as an unverified (masked) match.
    index_ab = [[(0, 0), (1, 1), (4, 4)], [(0, 0), (1, 1)], [(0, 0)], [(1, 2)]]
    masks = [[True, True, False], [True, True], [True], [True]]
    tracks = build_tracks(_observations(f, pairs, index_ab, masks), min_length=2)
    assert tracks.n_tracks == 1
    assert tracks.view.tolist() == [0, 1, 2, 3] and tracks.keypoint.tolist() == [0, 0, 0, 0]
    np.testing.assert_array_equal(tracks.xy_px, [[v, 1.0 + v] for v in range(4)])
    assert build_tracks(_observations(f, pairs, index_ab, masks), min_length=5).n_tracks == 0


def test_tracks_close_the_loop_across_the_seam_of_a_full_turn():
    scan = synthetic_scan(36, 300, rng=2, track_length=(4, 6))
    tracks = build_tracks(scan.observations)
    seam = np.zeros(tracks.n_tracks, bool)
    np.logical_or.at(seam, tracks.track, tracks.view == 35)
    crossing = np.zeros(tracks.n_tracks, bool)
    np.logical_or.at(crossing, tracks.track, tracks.view == 0)
    assert np.count_nonzero(seam & crossing) > 5
    # Every synthetic point is one track, all observations found.
    assert tracks.n_tracks == 300 and len(tracks) == sum(len(f) for f in scan.observations.features)


def test_triangulation_is_exact_on_noise_free_observations():
    scan = synthetic_scan(40, 200, rng=3, range_deg=60.0)
    tracks = build_tracks(scan.observations)
    points = triangulate_tracks(tracks, scan.true_angles_rad, GEOMETRY)
    # The synthetic points are numbered in the order their tracks appear.
    first_keypoint = tracks.xy_px[np.searchsorted(tracks.track, np.arange(tracks.n_tracks))]
    reprojected = project_points(points, scan.true_angles_rad[tracks.view[np.searchsorted(tracks.track, np.arange(tracks.n_tracks))]], GEOMETRY)
    np.testing.assert_allclose(reprojected, first_keypoint, atol=1e-3)
    matched = np.linalg.norm(points[:, None, :] - scan.points_mm[None, :, :], axis=2).min(axis=1)
    assert matched.max() < 1e-3  # keypoints are float32: ~1e-5 px'



def test_static_tracks_are_the_ones_that_do_not_move():
    scan = synthetic_scan(60, 300, rng=4, n_static=12, range_deg=60.0, track_length=(8, 12))
    tracks = build_tracks(scan.observations)
    static = static_tracks(tracks, scan.true_angles_rad, GEOMETRY)
    lengths = tracks.lengths
    # The static features are matched in every view: the 12 tracks of length 60.
    assert set(np.flatnonzero(static)) <= set(np.flatnonzero(lengths == 60))
    assert not np.any(static[lengths < 60])
    # Those far enough from the central row and the axis (a rigid point there would move
    # vertically by x_n y_n dtheta, over 2 px across the scan) are all found.
    mean_xy = np.stack([np.bincount(tracks.track, tracks.xy_px[:, k]) for k in (0, 1)], axis=1) / lengths[:, None]
    rays = GEOMETRY.pixels_to_normalised(mean_xy)
    motion_px = np.abs(rays[:, 0] * rays[:, 1]) * np.deg2rad(60.0) * GEOMETRY.source_to_detector_mm / GEOMETRY.pixel_pitch_v_mm
    clear = (lengths == 60) & (motion_px > 6.0)
    assert clear.sum() >= 3 and np.all(static[clear])


def test_extension_reattaches_dropped_observations_and_merges_split_tracks():
    scan = synthetic_scan(30, 150, rng=5, range_deg=30.0, track_length=(10, 14))
    full = build_tracks(scan.observations)
    points = triangulate_tracks(full, scan.true_angles_rad, GEOMETRY)
    # Forget every third observation and split every track in two halves.
    keep = np.arange(len(full)) % 3 != 1
    halves = full.track * 2 + (full.view > np.bincount(full.track, full.view)[full.track] / full.lengths[full.track])
    split = Tracks.from_arrays(halves[keep], full.view[keep], full.xy_px[keep], n_views=30, keypoint=full.keypoint[keep])
    start = triangulate_tracks(split, scan.true_angles_rad, GEOMETRY)
    grown, grown_points, stats = extend_tracks(split, scan.observations.features, GEOMETRY, scan.true_angles_rad, start,
                                               radius_px=0.5, window_views=3)
    assert stats["attached"] > 0 and stats["merged"] > 0
    assert len(grown) > len(split) and grown.n_tracks < split.n_tracks and grown_points.shape == (grown.n_tracks, 3)
    # Nothing wrong attached: every observation of a grown track is the same synthetic point.
    xy_of_point = {}
    for t, v, xy in zip(full.track, full.view, full.xy_px):
        xy_of_point[(v, tuple(xy))] = t
    owners = np.array([xy_of_point[(v, tuple(xy))] for v, xy in zip(grown.view, grown.xy_px)])
    for t in range(grown.n_tracks):
        assert np.unique(owners[grown.track == t]).size == 1
    # A descriptor threshold of zero attaches nothing.
    _, _, none = extend_tracks(split, scan.observations.features, GEOMETRY, scan.true_angles_rad, start,
                               radius_px=0.5, window_views=3, max_descriptor_distance=0.0)
    assert none == {"attached": 0, "merged": 0}
    del points


def test_descriptor_distances_follow_the_norm():
    a = np.array([[0b1111_0000]], np.uint8)
    b = np.array([[0b0000_0000]], np.uint8)
    assert descriptor_distances(a, b, "HAMMING")[0] == 4
    assert descriptor_distances(a, b, "HAMMING2")[0] == 2
    x, y = np.array([[3.0, 0.0]], np.float32), np.array([[0.0, 4.0]], np.float32)
    assert descriptor_distances(x, y, "L2")[0] == 5 and descriptor_distances(x, y, "L1")[0] == 7
    with pytest.raises(InputError, match="Try one of L2"):
        descriptor_distances(x, y, "COSINE")


def test_tracks_reject_two_observations_in_one_view():
    with pytest.raises(InputError, match="two observations in one view"):
        Tracks.from_arrays([0, 0], [1, 1], np.zeros((2, 2)), n_views=3)
