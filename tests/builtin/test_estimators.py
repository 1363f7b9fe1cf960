import numpy as np
import pytest

from ctpipe.builtin.estimators import (HistogramEstimator, MedianEstimator, OpenCV5ptEstimator, Ransac1ptEstimator,
                                       ransac_iterations)
from ctpipe.data import PairEstimate
from ctpipe.evaluate.synthetic import make_correspondences
from ctpipe.model import FailedEstimation

# (estimator, MAE bound in degrees with 30 inliers + 70 re-paired outliers, sigma 1e-4)
ESTIMATORS = [
    (Ransac1ptEstimator(), 0.03),
    (Ransac1ptEstimator(noise_scale_factor=None), 0.15),
    (Ransac1ptEstimator(hypotheses="all", scoring="msac", sampson_threshold=5e-4, noise_scale_factor=None), 0.03),
    (HistogramEstimator(), 0.1),
    (MedianEstimator(), 1.0),
    (OpenCV5ptEstimator(), 0.5),
]


@pytest.mark.parametrize("estimator, bound_deg", ESTIMATORS, ids=lambda e: getattr(e, "__class__").__name__)
@pytest.mark.parametrize("alpha_deg", [-60.0, -2.0, 1.0, 30.0])
def test_every_estimator_survives_70_percent_outliers(estimator, bound_deg, alpha_deg):
    errors = []
    for rep in range(12):
        rng = np.random.default_rng([rep, int(alpha_deg * 10) + 1000])
        q_a, q_b, inlier = make_correspondences(np.deg2rad(alpha_deg), rng, n_inliers=30, n_outliers=70, sigma=1e-4)
        result = estimator.estimate(q_a, q_b, rng=np.random.default_rng(rep))
        assert isinstance(result, PairEstimate), result
        errors.append(abs(result.angle_deg - alpha_deg))
    assert np.median(errors) < bound_deg


def test_ransac_inliers_are_the_true_inliers():
    rng = np.random.default_rng(11)
    q_a, q_b, inlier = make_correspondences(np.deg2rad(4.0), rng, n_inliers=30, n_outliers=70, sigma=1e-4)
    result = Ransac1ptEstimator(hypotheses="all", scoring="msac", sampson_threshold=5e-4).estimate(
        q_a, q_b, rng=np.random.default_rng(0))
    assert np.mean(result.inlier_mask[inlier]) > 0.9
    assert np.mean(result.inlier_mask[~inlier]) < 0.05


def test_ransac_is_reproducible_with_a_seed_and_uses_only_the_given_rng():
    rng = np.random.default_rng(1)
    q_a, q_b, _ = make_correspondences(np.deg2rad(-12.0), rng)
    first = Ransac1ptEstimator().estimate(q_a, q_b, rng=np.random.default_rng(5))
    second = Ransac1ptEstimator().estimate(q_a, q_b, rng=np.random.default_rng(5))
    assert first.angle_rad == second.angle_rad and np.array_equal(first.inlier_mask, second.inlier_mask)


def test_iteration_count_is_the_papers_formula():
    assert ransac_iterations(0.999, 0.7) == 20  # log(0.001) / log(0.7) = 19.4
    assert ransac_iterations(0.99, 0.0) == 1


def test_no_consensus_fails_with_a_message_naming_the_threshold():
    rng = np.random.default_rng(0)
    q_a, q_b = rng.uniform(-0.5, 0.5, (40, 2)), rng.uniform(-0.5, 0.5, (40, 2))
    result = Ransac1ptEstimator(sampson_threshold=1e-6, min_consensus=0.5).estimate(q_a, q_b, rng=rng)
    assert isinstance(result, FailedEstimation)
    assert "no consensus" in str(result) and "sampson_threshold 1e-06" in str(result)


def test_unlucky_draws_do_not_fail_while_a_consensus_exists():
    # 3 inliers in 100 with p = 0.5 and eps = 0: the paper's N is 1 draw; ctpipe keeps drawing.
    rng = np.random.default_rng(2)
    q_a, q_b, _ = make_correspondences(np.deg2rad(10.0), rng, n_inliers=10, n_outliers=90, sigma=1e-5)
    estimator = Ransac1ptEstimator(probability=0.5, outlier_fraction=0.0, min_consensus=0.05,
                                   sampson_threshold=1e-4)
    for seed in range(10):
        result = estimator.estimate(q_a, q_b, rng=np.random.default_rng(seed))
        assert result and abs(result.angle_deg - 10.0) < 0.05


def test_histogram_and_median_report_inliers_near_their_angle():
    rng = np.random.default_rng(3)
    q_a, q_b, inlier = make_correspondences(np.deg2rad(20.0), rng, n_inliers=60, n_outliers=40, sigma=1e-4)
    for estimator in (HistogramEstimator(), MedianEstimator()):
        result = estimator.estimate(q_a, q_b, rng=rng)
        assert result.n_inliers >= 30
        assert np.mean(inlier[result.inlier_mask]) > 0.8


def test_opencv_5pt_reads_the_rotation_with_ctpipes_sign():
    rng = np.random.default_rng(4)
    for alpha_deg in (7.0, -7.0):
        q_a, q_b, _ = make_correspondences(np.deg2rad(alpha_deg), rng, n_inliers=50, n_outliers=0, sigma=1e-5)
        result = OpenCV5ptEstimator().estimate(q_a, q_b, rng=np.random.default_rng(0))
        assert result.angle_deg == pytest.approx(alpha_deg, abs=0.2)  # a 5-DOF minimal-sample fit is noisier
    too_few = OpenCV5ptEstimator().estimate(q_a[:4], q_b[:4], rng=np.random.default_rng(0))
    assert not too_few and "at least 5" in str(too_few)


def test_one_to_one_counts_each_ball_once_among_identical_candidates():
    """Identical balls: all-pairs gives every ball several candidates; the consensus keeps one each."""
    from ctpipe.geometry import Geometry
    from ctpipe.solve.camera import project_points

    geometry = Geometry(150.0, 600.0, 512, 512, 0.2, 0.2)
    rng = np.random.default_rng(4)
    balls = np.stack([rng.uniform(-15, 15, 8), rng.uniform(-20, 20, 8), rng.uniform(-15, 15, 8)], axis=1)
    a = project_points(balls, np.zeros(8), geometry)
    b = project_points(balls, np.full(8, np.deg2rad(22.5)), geometry)
    index = np.array([(i, j) for i in range(8) for j in range(8)])
    q_a, q_b = geometry.pixels_to_normalised(a[index[:, 0]]), geometry.pixels_to_normalised(b[index[:, 1]])
    kwargs = dict(hypotheses="all", scoring="msac", min_consensus=0.0, sampson_threshold=1e-3)
    plain = Ransac1ptEstimator(**kwargs).estimate(q_a, q_b, rng=np.random.default_rng(0))
    one = Ransac1ptEstimator(**kwargs, one_to_one=True).estimate(q_a, q_b, rng=np.random.default_rng(0))
    assert one.angle_deg == pytest.approx(22.5, abs=1e-6)
    kept = index[one.inlier_mask]
    assert sorted(kept[:, 0]) == list(range(8)) and len(set(kept[:, 1])) == 8
    assert np.all(kept[:, 0] == kept[:, 1])            # every ball with itself
    assert plain.n_inliers >= one.n_inliers


def test_min_inliers_refuses_a_consensus_of_one_ball():
    q_a = np.array([[0.01, 0.05], [0.02, -0.04]])
    q_b = np.array([[0.03, 0.051], [-0.02, -0.041]])
    kwargs = dict(hypotheses="all", min_consensus=0.0, sampson_threshold=1e-5)
    assert Ransac1ptEstimator(**kwargs).estimate(q_a, q_b, rng=np.random.default_rng(0))
    failed = Ransac1ptEstimator(**kwargs, min_inliers=3).estimate(q_a, q_b, rng=np.random.default_rng(0))
    assert not failed and "at least 3" in str(failed)
