import numpy as np
import pytest

from ctpipe.solve.graph import covers_full_turn, unwrap_pair_angles_deg, view_pairs


def test_a_full_turn_is_recognised_from_its_nominal_angles():
    assert covers_full_turn(np.arange(360) * 1.0)
    assert covers_full_turn(-np.arange(90) * 4.0)
    assert covers_full_turn(np.arange(720) * 1.0)            # two turns
    assert not covers_full_turn(np.arange(200) * 1.0)        # a short scan
    assert not covers_full_turn(np.r_[np.arange(180), np.arange(180)] * 2.0)  # not monotonic
    assert not covers_full_turn(np.arange(2) * 180.0)


def test_view_pairs_wrap_around_a_full_turn_only():
    full = np.arange(6) * 60.0
    assert view_pairs(6, (1,), full).tolist() == [[0, 1], [1, 2], [2, 3], [3, 4], [4, 5], [5, 0]]
    assert view_pairs(6, (1,), full, loop_closure=False).tolist() == [[0, 1], [1, 2], [2, 3], [3, 4], [4, 5]]
    assert view_pairs(6, (2,), np.arange(6) * 20.0).tolist() == [[0, 2], [1, 3], [2, 4], [3, 5]]
    assert view_pairs(6, (1,)).tolist() == [[0, 1], [1, 2], [2, 3], [3, 4], [4, 5]]
    assert len(view_pairs(360, (1, 2, 4), np.arange(360) * 1.0)) == 3 * 360


def test_pair_angles_across_the_seam_unwrap_against_the_nominal_difference():
    nominal = np.arange(360) * 1.0
    pairs = np.array([[0, 1], [359, 0], [358, 1], [0, 180]])
    measured = np.array([1.1, 0.9, 2.8, -179.6])
    unwrapped = unwrap_pair_angles_deg(pairs, measured, nominal)
    np.testing.assert_allclose(unwrapped, [1.1, 0.9 - 360.0, 2.8 - 360.0, 180.4])
    np.testing.assert_allclose(unwrap_pair_angles_deg(pairs, measured), measured)


def test_least_squares_closes_the_loop_with_the_seam_pairs():
    from ctpipe.builtin.refiners import chain_pair_angles

    rng = np.random.default_rng(0)
    nominal = np.arange(90) * 4.0
    truth = nominal + rng.normal(0, 0.2, 90)
    pairs = view_pairs(90, (1,), nominal)
    noise = rng.normal(0, 0.1, len(pairs)) + 0.02      # a common bias makes an open chain drift
    pair_angles = np.mod(truth[pairs[:, 1]] - truth[pairs[:, 0]] + 180.0, 360.0) - 180.0 + noise
    closed = chain_pair_angles(90, pairs, np.deg2rad(unwrap_pair_angles_deg(pairs, pair_angles, nominal)))
    open_ = chain_pair_angles(90, pairs[:-1], np.deg2rad(pair_angles[:-1]))
    err = lambda theta: np.rad2deg(theta) - (truth - truth[0])
    assert np.abs(err(closed) - np.median(err(closed))).max() < np.abs(err(open_) - np.median(err(open_))).max()
    with pytest.raises(Exception):
        unwrap_pair_angles_deg(pairs, pair_angles[:-1], nominal)
