"""The per-view vector geometry puts every object point on the pixel ctpipe's camera model does."""

import dataclasses

import numpy as np
import pytest

from ctpipe.geometry import Geometry
from ctpipe.io.corrected import TO_ASTRA, cone_vectors, scanner_frame_deg
from ctpipe.solve.camera import project_points

GEOMETRY = Geometry(source_to_object_mm=150.0, source_to_detector_mm=400.0, detector_cols=200, detector_rows=120,
                    pixel_pitch_u_mm=0.4, pixel_pitch_v_mm=0.5, u0_px=104.3, v0_px=55.2)


def _pixel_from_vectors(row: np.ndarray, point_astra: np.ndarray, geometry: Geometry) -> np.ndarray:
    """Where the ray from the source through the point meets the detector, as (col, row) pixels."""
    source, centre, u, v = row[:3], row[3:6], row[6:9], row[9:]
    # source + t (point - source) = centre + a u + b v
    matrix = np.stack([point_astra - source, -u, -v], axis=1)
    t, a, b = np.linalg.solve(matrix, centre - source)
    return np.array([a + (geometry.detector_cols - 1) / 2.0, b + (geometry.detector_rows - 1) / 2.0])


@pytest.mark.parametrize("tilt_deg", [0.0, 1.5])
def test_cone_vectors_project_points_where_the_camera_model_does(tilt_deg):
    rng = np.random.default_rng(0)
    points = rng.uniform(-20, 20, (50, 3))
    angles_deg = rng.uniform(-180, 180, 50)
    expected = project_points(points, np.deg2rad(angles_deg), GEOMETRY, tilt_rad=np.deg2rad(tilt_deg))
    vectors = cone_vectors(GEOMETRY, angles_deg, tilt_deg=tilt_deg)
    got = np.array([_pixel_from_vectors(row, TO_ASTRA @ p, GEOMETRY) for row, p in zip(vectors, points)])
    np.testing.assert_allclose(got, expected, atol=1e-9)


@pytest.mark.parametrize("tilt_deg", [0.0, 0.4])
def test_a_views_shift_moves_its_projection_by_that_many_pixels(tilt_deg):
    """A view shifted by (du, dv) images every point du columns and dv rows on: its principal point moved."""
    rng = np.random.default_rng(1)
    points = rng.uniform(-20, 20, (30, 3))
    angles_deg = rng.uniform(-180, 180, 30)
    shifts = rng.uniform(-2.0, 2.0, (30, 2))
    expected = project_points(points, np.deg2rad(angles_deg), GEOMETRY, tilt_rad=np.deg2rad(tilt_deg)) + shifts
    vectors = cone_vectors(GEOMETRY, angles_deg, tilt_deg=tilt_deg, shifts_px=shifts)
    got = np.array([_pixel_from_vectors(row, TO_ASTRA @ p, GEOMETRY) for row, p in zip(vectors, points)])
    np.testing.assert_allclose(got, expected, atol=1e-9)


def test_cone_vectors_at_angle_zero_and_a_quarter_turn():
    g = dataclasses.replace(GEOMETRY, u0_px=(GEOMETRY.detector_cols - 1) / 2, v0_px=(GEOMETRY.detector_rows - 1) / 2)
    at_zero, quarter = cone_vectors(g, [0.0, 90.0])
    # Source on the -z side of ctpipe's frame, i.e. -y in ASTRA's; the detector centre opposite.
    np.testing.assert_allclose(at_zero[:3], [0.0, -150.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(at_zero[3:6], [0.0, 250.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(at_zero[9:], [0.0, 0.0, -0.5], atol=1e-12)   # rows run down the axis
    # A +90 deg turn of the turntable moves the source a quarter turn about the vertical axis.
    np.testing.assert_allclose(np.linalg.norm(quarter[:3]), 150.0)
    assert abs(quarter[2]) < 1e-12 and abs(quarter[1]) < 1e-9


def test_scanner_frame_keeps_differences_and_aligns_to_the_nominal_median():
    estimated = np.array([0.0, 1.1, 1.9, np.nan, 4.2])
    nominal = np.array([10.0, 11.0, 12.0, 13.0, 14.0])
    out = scanner_frame_deg(estimated, nominal)
    np.testing.assert_allclose(np.diff(out[:3]), np.diff(estimated[:3]))
    assert np.nanmedian(out - nominal) == pytest.approx(0.0)
    np.testing.assert_array_equal(scanner_frame_deg(estimated, None), estimated)


@pytest.mark.parametrize("tilt_deg, offset_mm", [(0.0, 1.2), (0.6, -0.8)])
def test_cone_vectors_of_an_axis_off_the_perpendicular_project_as_the_ball_calibration_models(tilt_deg, offset_mm):
    """The ball calibration's scanner (:func:`ctpipe.solve.balls.ellipse_centres` of balls of no size): the axis
    ``offset_mm`` off the source's perpendicular, at its fitted distance, ``(u0, v0)`` where the axis's point level
    with the source projects. The vectors put every point where that model does; with no offset, as before."""
    from ctpipe.solve.balls import ellipse_centres

    rng = np.random.default_rng(2)
    points = rng.uniform(-20, 20, (40, 3))
    angles_deg = rng.uniform(-180, 180, 40)
    geometry = dataclasses.replace(GEOMETRY, source_to_detector_mm=404.0)
    expected = ellipse_centres(points, np.zeros(len(points)), np.deg2rad(angles_deg), geometry, geometry.u0_px,
                               geometry.v0_px, np.deg2rad(tilt_deg), offset_mm)
    vectors = cone_vectors(geometry, angles_deg, tilt_deg=tilt_deg, axis_offset_mm=offset_mm)
    got = np.array([_pixel_from_vectors(row, TO_ASTRA @ p, geometry) for row, p in zip(vectors, points)])
    np.testing.assert_allclose(got, expected, atol=1e-9)
    # The axis images at (u0, v0) at the source's height, whatever the view.
    on_axis = np.array([_pixel_from_vectors(row, np.zeros(3), geometry) for row in vectors])
    np.testing.assert_allclose(on_axis, np.tile([geometry.u0_px, geometry.v0_px], (len(vectors), 1)), atol=1e-9)


@pytest.mark.parametrize("share", [1.0, 0.4])
def test_cone_vectors_of_a_drift_the_source_spot_shares_project_as_the_ball_calibration_models(share):
    """A view's shift ``t`` made ``share`` by the source spot: the axis's image moves by ``t`` and a point at distance
    ``z`` from the source by ``(1 - share) t + share t (SDD / z - 1) / (SDD / SOD - 1)`` (``ctpipe.solve.balls``'s
    model of a spot's drift: a ball nearer the spot moves further). The detector-only vectors miss that parallax."""
    from ctpipe.solve.balls import ellipse_centres

    rng = np.random.default_rng(3)
    points = rng.uniform(-40, 40, (40, 3))
    angles_deg = rng.uniform(-180, 180, 40)
    shifts = rng.uniform(-3.0, 3.0, (40, 2))
    tilt = np.deg2rad(0.7)
    bare = ellipse_centres(points, np.zeros(len(points)), np.deg2rad(angles_deg), GEOMETRY, GEOMETRY.u0_px,
                           GEOMETRY.v0_px, tilt, 0.5)
    theta = np.deg2rad(angles_deg)
    z = np.sin(theta) * points[:, 0] + np.cos(theta) * points[:, 2] + GEOMETRY.source_to_object_mm
    magnification = GEOMETRY.source_to_detector_mm / GEOMETRY.source_to_object_mm
    parallax = (GEOMETRY.source_to_detector_mm / z - 1.0) / (magnification - 1.0)
    expected = bare + shifts * (1.0 + share * (parallax - 1.0))[:, None]
    vectors = cone_vectors(GEOMETRY, angles_deg, tilt_deg=0.7, shifts_px=shifts, axis_offset_mm=0.5,
                           spot_share=share)
    got = np.array([_pixel_from_vectors(row, TO_ASTRA @ p, GEOMETRY) for row, p in zip(vectors, points)])
    np.testing.assert_allclose(got, expected, atol=1e-9)
    on_detector = cone_vectors(GEOMETRY, angles_deg, tilt_deg=0.7, shifts_px=shifts, axis_offset_mm=0.5)
    missed = np.array([_pixel_from_vectors(row, TO_ASTRA @ p, GEOMETRY) for row, p in zip(on_detector, points)])
    assert np.abs(missed - expected).max() > 0.1
