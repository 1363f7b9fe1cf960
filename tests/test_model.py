import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from ctpipe.model import (CircularMotion, FailedEstimation, angles_from_correspondences, essential_matrix,
                          fit_angle, rotation_matrix, sampson_distance)
from ctpipe.evaluate.synthetic import cylinder_points, make_correspondences, project

ANGLES_DEG = [-179.0, -120.0, -90.0, -45.0, -5.0, -1.0, -0.01, 0.0, 0.01, 1.0, 5.0, 45.0, 90.0, 120.0, 179.0]


@pytest.mark.parametrize("alpha_deg", ANGLES_DEG)
def test_noise_free_correspondences_give_the_exact_angle(alpha_deg):
    rng = np.random.default_rng(1)
    points = cylinder_points(50, rng)
    q_a, q_b = project(points, 0.0, 200.0), project(points, np.deg2rad(alpha_deg), 200.0)
    alpha = np.deg2rad(alpha_deg)
    np.testing.assert_allclose(angles_from_correspondences(q_a, q_b), alpha, atol=1e-9)
    assert abs(fit_angle(q_a, q_b) - alpha) < 1e-9
    assert abs(fit_angle(q_a, q_b, objective="tls") - alpha) < 1e-9
    assert np.max(sampson_distance(alpha, q_a, q_b)) < 1e-12


def test_turning_counter_clockwise_seen_from_above_is_positive():
    # A point between the axis and the source moves towards larger columns (+x) for +alpha.
    near_point = np.array([[0.0, 0.0, -50.0]])
    before = project(near_point, 0.0, 200.0)
    after = project(near_point, np.deg2rad(3.0), 200.0)
    assert after[0, 0] > before[0, 0]
    # and the estimators return the sign they were given, both ways
    for alpha_deg in (3.0, -3.0):
        rng = np.random.default_rng(0)
        q_a, q_b, _ = make_correspondences(np.deg2rad(alpha_deg), rng, n_outliers=0, sigma=0.0)
        assert np.sign(fit_angle(q_a, q_b)) == np.sign(alpha_deg)
        assert np.sign(fit_angle(q_b, q_a)) == -np.sign(alpha_deg)


def test_essential_matrix_is_the_epipolar_constraint_of_the_rotation_about_the_axis():
    alpha, d = np.deg2rad(23.0), 200.0
    rotation = rotation_matrix(alpha)
    translation = (np.eye(3) - rotation) @ np.array([0.0, 0.0, d])
    skew = np.array([[0, -translation[2], translation[1]], [translation[2], 0, -translation[0]],
                     [-translation[1], translation[0], 0]])
    unnormalised = skew @ rotation
    e = essential_matrix(alpha)
    np.testing.assert_allclose(e * np.linalg.norm(translation), unnormalised, atol=1e-12)
    assert np.linalg.norm(essential_matrix(0.0)) > 0  # unlike the unnormalised E, not zero at 0


def _sampson_from_definition(e, q_a, q_b):
    qa = np.c_[q_a, np.ones(len(q_a))]
    qb = np.c_[q_b, np.ones(len(q_b))]
    residual = np.einsum("ni,ij,nj->n", qb, e, qa)
    eq = qa @ e.T
    etq = qb @ e
    return np.abs(residual) / np.sqrt(eq[:, 0] ** 2 + eq[:, 1] ** 2 + etq[:, 0] ** 2 + etq[:, 1] ** 2)


def test_sampson_distance_matches_the_definition_and_is_scale_free():
    rng = np.random.default_rng(2)
    q_a, q_b, _ = make_correspondences(np.deg2rad(12.0), rng, n_inliers=20, n_outliers=20, sigma=1e-3)
    for alpha_deg in (-30.0, 0.0, 11.0, 170.0):
        e = essential_matrix(np.deg2rad(alpha_deg))
        expected = _sampson_from_definition(e, q_a, q_b)
        np.testing.assert_allclose(sampson_distance(np.deg2rad(alpha_deg), q_a, q_b), expected, rtol=1e-10)
        np.testing.assert_allclose(_sampson_from_definition(7.5 * e, q_a, q_b), expected, rtol=1e-10)


def test_sampson_distance_approximates_the_geometric_error_for_small_noise():
    # Numerically: move the 4 coordinates of a correspondence the least (Euclidean) so that it
    # satisfies the constraint exactly; for small noise this equals the Sampson distance.
    from scipy.optimize import minimize

    rng = np.random.default_rng(5)
    alpha = np.deg2rad(20.0)
    q_a, q_b, _ = make_correspondences(alpha, rng, n_inliers=5, n_outliers=0, sigma=1e-4)
    e = essential_matrix(alpha)
    for k in range(5):
        x0 = np.r_[q_a[k], q_b[k]]

        def constraint(p):
            return np.r_[p[2:], 1.0] @ e @ np.r_[p[:2], 1.0]

        solution = minimize(lambda p: np.sum((p - x0) ** 2), x0, constraints=[{"type": "eq", "fun": constraint}],
                            method="SLSQP", options={"ftol": 1e-20, "maxiter": 200})
        geometric = np.linalg.norm(solution.x - x0)
        assert sampson_distance(alpha, q_a[k:k + 1], q_b[k:k + 1])[0] == pytest.approx(geometric, rel=1e-3)


def test_sampson_refit_reaches_the_minimum_of_the_summed_sampson_distances():
    rng = np.random.default_rng(4)
    q_a, q_b, _ = make_correspondences(np.deg2rad(33.0), rng, n_inliers=80, n_outliers=0, sigma=3e-4)
    fitted = fit_angle(q_a, q_b)
    best = minimize_scalar(lambda a: np.sum(sampson_distance(a, q_a, q_b) ** 2),
                           bounds=(fitted - 0.01, fitted + 0.01), method="bounded", options={"xatol": 1e-12})
    assert abs(fitted - best.x) < 1e-9


def test_small_angle_trap_unnormalised_algebraic_refit_collapses_to_zero_ours_does_not():
    alpha = np.deg2rad(1.0)
    rng = np.random.default_rng(9)
    q_a, q_b, _ = make_correspondences(alpha, rng, n_inliers=100, n_outliers=0, sigma=1e-4)
    qa = np.c_[q_a, np.ones(len(q_a))]
    qb = np.c_[q_b, np.ones(len(q_b))]

    def unnormalised_algebraic_cost(a):
        t = (np.eye(3) - rotation_matrix(a)) @ np.array([0.0, 0.0, 200.0])
        skew = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
        return np.sum(np.einsum("ni,ij,nj->n", qb, skew @ rotation_matrix(a), qa) ** 2)

    # The unnormalised E is zero at 0, so the algebraic cost's global minimum is alpha = 0
    # whatever the data: a refit that minimises it returns ~0 instead of 1 deg.
    grid = np.deg2rad(np.linspace(-5.0, 5.0, 2001))
    naive = grid[np.argmin([unnormalised_algebraic_cost(a) for a in grid])]
    assert abs(naive) < 0.1 * alpha
    assert abs(fit_angle(q_a, q_b) - alpha) < np.deg2rad(0.02)
    assert abs(fit_angle(q_a, q_b, objective="tls") - alpha) < np.deg2rad(0.02)


def test_degenerate_correspondences_fail_with_a_reason():
    q = np.array([[0.1, 0.0], [0.2, 0.0]])
    result = fit_angle(q, q)
    assert isinstance(result, FailedEstimation) and not result and "principal row" in str(result)
    assert isinstance(fit_angle(np.zeros((0, 2)), np.zeros((0, 2))), FailedEstimation)
    assert not CircularMotion.from_estimate(q, q)


def test_model_protocol_residuals():
    rng = np.random.default_rng(0)
    q_a, q_b, _ = make_correspondences(np.deg2rad(-7.0), rng, n_outliers=0, sigma=0.0)
    model = CircularMotion.from_estimate(q_a, q_b)
    assert model.angle_deg == pytest.approx(-7.0, abs=1e-9)
    assert np.all(model.residuals(q_a, q_b) < 1e-12)


def test_wrap_deg_gives_the_signed_turn_either_way_round_the_seam():
    from ctpipe.model import wrap_deg

    np.testing.assert_allclose(wrap_deg([359.0, -359.0, 180.0, -180.0, 0.5, 720.25]),
                               [-1.0, 1.0, -180.0, -180.0, 0.5, 0.25])
    assert wrap_deg(-0.1) == pytest.approx(-0.1)
