import numpy as np
import pytest

from ctpipe.errors import InputError
from ctpipe.solve.graph import covers_full_turn, solve_pair_graph, unwrap_pair_angles_deg, view_pairs
from ctpipe.solve.losses import LOSSES


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
    from ctpipe.solve.graph import chain_pair_angles

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


def _ring(n_views, baselines, rng, jitter_deg=0.2):
    nominal = np.arange(n_views) * 360.0 / n_views
    truth = nominal + rng.normal(0.0, jitter_deg, n_views)
    pairs = view_pairs(n_views, baselines, nominal)
    exact = unwrap_pair_angles_deg(pairs, np.mod(truth[pairs[:, 1]] - truth[pairs[:, 0]] + 180.0, 360.0) - 180.0,
                                   nominal)
    return nominal, truth - truth[0], pairs, exact


@pytest.mark.parametrize("loss", LOSSES)
def test_noise_free_pairs_give_the_exact_angles_with_every_loss(loss):
    _, truth, pairs, exact = _ring(90, (1, 2, 4), np.random.default_rng(1))
    weights = np.random.default_rng(2).uniform(0.5, 2.0, len(pairs))
    solution = solve_pair_graph(90, pairs, exact, weights, loss=loss, scale_deg=0.01)
    np.testing.assert_allclose(solution.angles_deg, truth, atol=1e-9)
    np.testing.assert_allclose(solution.residuals_deg, 0.0, atol=1e-9)
    assert solution.converged


def test_a_gross_outlier_pair_no_longer_drags_the_chain():
    rng = np.random.default_rng(3)
    _, truth, pairs, exact = _ring(120, (1, 2), rng)
    measured = exact + rng.normal(0.0, 0.01, len(pairs))
    bad = int(np.flatnonzero((pairs[:, 0] == 40) & (pairs[:, 1] == 41))[0])
    without = solve_pair_graph(120, np.delete(pairs, bad, 0), np.delete(measured, bad), loss="linear").angles_deg
    measured[bad] += 20.0                                     # a slipped pair
    plain = solve_pair_graph(120, pairs, measured, loss="linear").angles_deg
    assert np.abs(plain - without).max() > 3.0                # plain least squares spreads the 20 deg
    for loss in ("soft-l1", "huber", "cauchy"):
        solution = solve_pair_graph(120, pairs, measured, loss=loss, scale_deg=0.03)
        # As if the pair were not there: soft-l1 and huber bound its pull to about scale_deg,
        # cauchy's weight falls off fast enough to ignore it.
        assert np.abs(solution.angles_deg - without).max() < (0.01 if loss == "cauchy" else 0.03), loss
        assert solution.robust_weights[bad] < 0.01 < np.median(solution.robust_weights)


def test_loop_closure_removes_the_linear_drift_of_a_biased_chain():
    # Pair angles 3 % short, as the default scan's come out: chained, the error grows to 10 deg;
    # the seam pair makes the ring add up to 360 deg and takes the drift out.
    rng = np.random.default_rng(4)
    nominal, truth, pairs, exact = _ring(360, (1,), rng)
    wrapped = np.mod(exact + 180.0, 360.0) - 180.0             # as an estimator reports them
    measured = unwrap_pair_angles_deg(pairs, 0.97 * wrapped + rng.normal(0.0, 0.005, len(pairs)), nominal)
    seam = pairs[:, 1] < pairs[:, 0]
    for loss in ("linear", "soft-l1"):
        open_ = solve_pair_graph(360, pairs[~seam], measured[~seam], loss=loss).angles_deg - truth
        closed = solve_pair_graph(360, pairs, measured, loss=loss, scale_deg=0.5).angles_deg - truth
        assert np.abs(open_).max() > 9.0
        assert np.abs(closed - np.median(closed)).max() < 0.05 * np.abs(open_).max(), loss


def test_views_not_connected_to_view_0_get_nan_and_failed_pairs_are_ignored():
    pairs = np.array([[0, 1], [1, 2], [3, 4], [2, 3]])
    angles = np.array([1.0, 2.0, 4.0, np.nan])
    solution = solve_pair_graph(6, pairs, angles)
    np.testing.assert_allclose(solution.angles_deg[:3], [0.0, 1.0, 3.0], atol=1e-12)
    assert np.isnan(solution.angles_deg[3:]).all()
    assert np.isnan(solution.residuals_deg[2:]).all() and (solution.robust_weights[2:] == 0).all()
    assert np.isnan(solve_pair_graph(3, np.zeros((0, 2), int), np.zeros(0)).angles_deg[1:]).all()


def test_three_thousand_views_over_three_baselines_with_outliers():
    rng = np.random.default_rng(5)
    _, truth, pairs, exact = _ring(3000, (1, 2, 4), rng, jitter_deg=0.02)
    measured = exact + rng.normal(0.0, 0.002, len(pairs))
    bad = rng.choice(len(pairs), 30, replace=False)
    measured[bad] += rng.choice([-1.0, 1.0], 30) * rng.uniform(2.0, 10.0, 30)
    solution = solve_pair_graph(3000, pairs, measured, loss="soft-l1", scale_deg=0.005)
    error = solution.angles_deg - truth
    assert np.abs(error - np.median(error)).max() < 0.02
    assert set(np.flatnonzero(solution.robust_weights < 0.1)) == set(bad)


@pytest.mark.parametrize("kwargs, message", [
    ({"loss": "l1"}, "loss: 'l1' is not supported. Try one of ('linear', 'soft-l1', 'huber', 'cauchy')"),
    ({"scale_deg": 0.0}, "scale_deg: must be a finite number > 0, got 0.0"),
    ({"weights": -np.ones(2)}, "weights: must be 2 finite numbers >= 0"),
])
def test_bad_arguments_name_what_is_allowed(kwargs, message):
    with pytest.raises(InputError) as info:
        solve_pair_graph(3, np.array([[0, 1], [1, 2]]), np.array([1.0, 1.0]), **kwargs)
    assert message in str(info.value)


def test_the_least_squares_refiner_takes_a_loss_and_its_scale():
    from ctpipe.config import parse_pipeline
    from ctpipe.errors import ConfigError
    from ctpipe.plugins import get_registry

    registry = get_registry()
    config = parse_pipeline({"refiner": {"name": "least-squares", "loss": "huber", "scale_deg": 0.1}}, registry)
    assert dict(config.refiner.params) == {"loss": "huber", "scale_deg": 0.1}
    with pytest.raises(ConfigError) as info:
        parse_pipeline({"refiner": {"name": "least-squares", "loss": "l2"}}, registry)
    assert "refiner.loss" in str(info.value) and "soft-l1" in str(info.value)
    with pytest.raises(ConfigError) as info:
        parse_pipeline({"refiner": {"name": "least-squares", "scale_deg": 0}}, registry)
    assert "refiner.scale_deg" in str(info.value)


def test_turn_pairs_pair_views_one_turn_apart():
    from ctpipe.solve.graph import turn_pairs

    # A Nikon full turn: Projections = 16 of 22.5 deg and a 17th image at 360 deg.
    assert turn_pairs(np.arange(17) * 22.5).tolist() == [[0, 16]]
    assert turn_pairs(-np.arange(17) * 22.5).tolist() == [[0, 16]]
    assert turn_pairs(np.arange(16) * 22.5).tolist() == []          # one turn, no repeat
    assert turn_pairs(np.arange(200) * 1.0).tolist() == []          # a short scan
    # CT Pro 5.4's Lego scan: 1571 images of 0.2299575 deg span 361.03 deg; the last five
    # repeat the first five poses within half a step.
    nominal = 40.20631 + np.arange(1571) * 0.2299575
    pairs = turn_pairs(nominal)
    assert pairs.tolist() == [[0, 1566], [1, 1567], [2, 1568], [3, 1569], [4, 1570]]
    gap = nominal[pairs[:, 1]] - nominal[pairs[:, 0]] - 360.0
    assert np.all(np.abs(gap) <= 0.5 * 0.2299575)
    assert len(turn_pairs(np.arange(720) * 1.0)) == 360              # two turns


def test_view_pairs_add_the_closing_pair_with_loop_closure_only():
    nominal = np.arange(5) * 90.0  # four steps and a closing view at 360 deg
    assert view_pairs(5, (1,), nominal).tolist() == [[0, 1], [1, 2], [2, 3], [3, 4], [0, 4]]
    assert view_pairs(5, (1,), nominal, loop_closure=False).tolist() == [[0, 1], [1, 2], [2, 3], [3, 4]]
    angles = unwrap_pair_angles_deg([[0, 4]], [0.3], nominal)
    assert angles.tolist() == [360.3]  # measured: the closing view is 0.3 deg past one turn


def test_a_pinned_turn_pair_holds_the_measured_turn_against_a_biased_chain():
    # A chain whose steps all read 1 % low, closed by the pair of view 0 and the closing view,
    # which measures the turn at once: 360.2 deg.
    nominal = np.arange(37) * 10.0
    pairs = view_pairs(37, (1,), nominal)
    angles = np.where(pairs[:, 1] - pairs[:, 0] == 1, 9.9, 360.2 - 360.0)
    angles = unwrap_pair_angles_deg(pairs, angles, nominal)
    robust = solve_pair_graph(37, pairs, angles, loss="soft-l1", scale_deg=0.1)
    pinned = solve_pair_graph(37, pairs, angles, loss="soft-l1", scale_deg=0.1,
                              pinned=(pairs[:, 0] == 0) & (pairs[:, 1] == 36))
    # Unpinned, the one closing pair is a vote among 37 and gives way to the chain's drift.
    assert abs(robust.angles_deg[-1] - 360.2) > 0.05
    assert pinned.angles_deg[-1] == pytest.approx(360.2, abs=1e-4)
    assert pinned.robust_weights[-1] == 1.0
    np.testing.assert_allclose(np.diff(pinned.angles_deg), 360.2 / 36, atol=1e-4)
