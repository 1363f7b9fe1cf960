"""Conformance checks every stage must pass; third-party plugins can run them in their tests.

>>> from ctpipe.testing import check_stage
>>> check_stage(MyDetector())          # raises AssertionError with what broke
"""

from __future__ import annotations

import numpy as np

from ctpipe.data import Features, Matches, PairEstimate, ScanObservations, ScanSolution
from ctpipe.errors import InputError
from ctpipe.evaluate.synthetic import make_correspondences
from ctpipe.geometry import Geometry
from ctpipe.model import FailedEstimation
from ctpipe.stages import Detector, Estimator, Matcher, Refiner, Stage

__all__ = ["check_stage", "check_detector", "check_matcher", "check_estimator", "check_refiner", "textured_image"]


def textured_image(shape: tuple[int, int] = (256, 256), seed: int = 0) -> np.ndarray:
    """A deterministic float32 image of overlapping blobs and edges, rich in keypoints."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float32)
    image = np.zeros(shape, np.float32)
    for _ in range(60):
        r0, c0 = rng.uniform(0, shape[0]), rng.uniform(0, shape[1])
        radius = rng.uniform(3, 14)
        image += rng.uniform(0.3, 1.0) * (((rows - r0) ** 2 + (cols - c0) ** 2) < radius ** 2)
    return image


def _raises_input_error(call, what: str) -> None:
    try:
        call()
    except InputError:
        return
    raise AssertionError(f"{what} must raise ctpipe.errors.InputError")


def check_detector(detector: Detector) -> Features:
    """Shapes, dtypes, ordering, determinism, no mutation, and clear errors on bad images."""
    image = textured_image()
    before = image.copy()
    features = detector.detect(image)
    assert isinstance(features, Features), f"detect() must return Features, got {type(features).__name__}"
    assert np.array_equal(image, before), "detect() modified its input image"
    n = len(features)
    assert n > 0, "no keypoints on a textured test image"
    assert features.xy.dtype == np.float32 and features.xy.shape == (n, 2)
    assert np.all((features.xy >= -0.5) & (features.xy <= np.array(image.shape[::-1]) - 0.5)), "keypoint outside image"
    assert np.all(np.diff(features.response) <= 0), "keypoints must be ordered by response, strongest first"
    finite = np.isfinite(features.angle_deg)
    assert np.all((features.angle_deg[finite] >= 0) & (features.angle_deg[finite] < 360)), "angle_deg outside [0, 360)"
    again = detector.detect(image)
    assert np.array_equal(features.xy, again.xy) and np.array_equal(features.descriptors, again.descriptors), \
        "detect() is not deterministic"
    empty = detector.detect(np.zeros((64, 64), np.float32))
    assert isinstance(empty, Features) and len(empty) == 0 and empty.descriptors.ndim == 2
    _raises_input_error(lambda: detector.detect(np.zeros((8, 8, 3), np.float32)), "a 3-D image")
    _raises_input_error(lambda: detector.detect(np.full((32, 32), np.nan, np.float32)), "an image of NaN")
    _raises_input_error(lambda: detector.detect(np.zeros((0, 0), np.float32)), "an empty image")
    return features


def check_matcher(matcher: Matcher, features: Features | None = None) -> Matches:
    """Matching a feature set with itself pairs (almost) every keypoint with itself."""
    if features is None:
        from ctpipe.builtin.opencv_detectors import SiftDetector

        features = SiftDetector().detect(textured_image())
    matches = matcher.match(features, features)
    assert isinstance(matches, Matches)
    assert matches.index_ab.dtype == np.int64 and matches.index_ab.shape == (len(matches), 2)
    assert matches.distance.shape == (len(matches),)
    if len(matches):
        assert matches.index_ab.min() >= 0 and matches.index_ab.max() < len(features)
    same = np.mean(matches.index_ab[:, 0] == matches.index_ab[:, 1]) if len(matches) else 0.0
    assert same > 0.9, f"only {same:.0%} of self-matches pair a keypoint with itself"
    return matches


def check_estimator(estimator: Estimator, *, tolerance_deg: float = 0.05) -> None:
    """Recovers +alpha as +alpha (and -alpha as -alpha), fails cleanly on no data."""
    for alpha_deg in (5.0, -5.0, 40.0):
        rng = np.random.default_rng(7)
        q_a, q_b, _ = make_correspondences(np.deg2rad(alpha_deg), rng, n_inliers=60, n_outliers=0, sigma=1e-6)
        before = (q_a.copy(), q_b.copy())
        result = estimator.estimate(q_a, q_b, rng=np.random.default_rng(0))
        assert np.array_equal(q_a, before[0]) and np.array_equal(q_b, before[1]), "estimate() modified its input"
        assert isinstance(result, PairEstimate), f"no estimate on clean data at {alpha_deg} deg: {result}"
        assert abs(result.angle_deg - alpha_deg) < tolerance_deg, \
            f"estimated {result.angle_deg:.4f} deg for a rotation of {alpha_deg} deg"
        assert result.inlier_mask.dtype == bool and result.inlier_mask.shape == (len(q_a),)
    failed = estimator.estimate(np.zeros((0, 2)), np.zeros((0, 2)), rng=np.random.default_rng(0))
    assert isinstance(failed, FailedEstimation) and not failed and str(failed), "no data must give a FailedEstimation"


def check_refiner(refiner: Refiner) -> ScanSolution:
    """Consecutive pair estimates of known angles chain into the right per-view angles."""
    geometry = Geometry(500.0, 1000.0, 256, 256, 0.4, 0.4)
    steps_deg = np.array([1.0, 1.5, -0.5, 2.0])
    truth = np.concatenate([[0.0], np.cumsum(steps_deg)])
    points_a, points_b, estimates, matches = [], [], [], []
    for k, step in enumerate(steps_deg):
        q_a, q_b, _ = make_correspondences(np.deg2rad(step), np.random.default_rng(k), n_inliers=40, n_outliers=0,
                                           sigma=0.0)
        points_a.append(q_a)
        points_b.append(q_b)
        estimates.append(PairEstimate(float(np.deg2rad(step)), np.ones(len(q_a), bool), 0.0))
        matches.append(Matches(np.stack([np.arange(len(q_a))] * 2, axis=1).astype(np.int64),
                               np.zeros(len(q_a), np.float32)))
    observations = ScanObservations(
        geometry=geometry, n_views=len(truth), features=(), pairs=np.stack([np.arange(4), np.arange(1, 5)], axis=1),
        matches=tuple(matches), points_a=tuple(points_a), points_b=tuple(points_b), estimates=tuple(estimates))
    solution = refiner.refine(observations, rng=np.random.default_rng(0))
    assert isinstance(solution, ScanSolution)
    assert solution.angles_rad.shape == (len(truth),) and solution.angles_rad[0] == 0.0
    np.testing.assert_allclose(np.rad2deg(solution.angles_rad), truth, atol=1e-6)
    return solution


def check_stage(stage: Stage) -> None:
    """Run the conformance check that fits the stage's kind."""
    checks = {"detector": check_detector, "matcher": check_matcher, "estimator": check_estimator,
              "refiner": check_refiner}
    checks[stage.kind](stage)
