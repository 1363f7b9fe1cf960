"""Projection of object points into views, with the detector unknowns bundle adjustment can fit.

Model
-----
An object point ``X`` (object frame of :mod:`ctpipe.recon.volume`, mm) is seen in the view at
turntable angle ``theta`` at::

    P = R(theta) X,   Z = P_z + source_to_object_mm
    (x_n, y_n) = (P_x / Z, P_y / Z)
    (u - u0_px) * pixel_pitch_u_mm = SDD * ( cos(tilt) x_n - sin(tilt) y_n)
    (v - v0_px) * pixel_pitch_v_mm = SDD * ( sin(tilt) x_n + cos(tilt) y_n)

``(u, v)`` is the pixel ``(x=col, y=row)``, ``R`` is :func:`ctpipe.model.rotation_matrix` and
``tilt_rad`` turns the detector in its own plane (about the central ray); with ``tilt_rad = 0``
this is exactly :meth:`ctpipe.geometry.Geometry.normalised_to_pixels`. The rotation axis
crosses the central ray, so ``u0_px`` is also the column the axis projects to (the centre of
rotation), and ``v0_px`` the row along which features only move sideways.
"""

from __future__ import annotations

import numpy as np

from ctpipe.errors import InputError
from ctpipe.geometry import Geometry

__all__ = ["project_points", "pixels_to_rays", "projection_jacobians"]


def _focal_px(geometry: Geometry) -> np.ndarray:
    return geometry.source_to_detector_mm / np.array([geometry.pixel_pitch_u_mm, geometry.pixel_pitch_v_mm])


def _check_points(points_mm, angles_rad) -> tuple[np.ndarray, np.ndarray]:
    points = np.asarray(points_mm, dtype=np.float64)
    angles = np.asarray(angles_rad, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"points_mm: must have shape (N, 3), got {points.shape}")
    if angles.shape != (len(points),):
        raise InputError(f"angles_rad: must have shape ({len(points)},), one angle per point, got {angles.shape}")
    return points, angles


def project_points(points_mm, angles_rad, geometry: Geometry, *, tilt_rad: float = 0.0) -> np.ndarray:
    """Pixel positions of object points seen at the given turntable angles.

    Parameters
    ----------
    points_mm : ndarray of shape (N, 3)
        Object-frame positions ``(x, y, z)`` in mm.
    angles_rad : ndarray of shape (N,)
        Turntable angle of the view each point is seen in.
    geometry : Geometry
        SOD, SDD, pixel pitches and the principal point ``(u0_px, v0_px)``.
    tilt_rad : float
        In-plane detector rotation, radians.

    Returns
    -------
    ndarray of shape (N, 2)
        ``(x=col, y=row)`` in pixels; NaN for points at or behind the source.
    """
    points, angles = _check_points(points_mm, angles_rad)
    return _project(points, angles, geometry, tilt_rad, behind=np.nan)


def _project(points: np.ndarray, angles: np.ndarray, geometry: Geometry, tilt_rad: float, *, behind=None) -> np.ndarray:
    """The projection without checks; ``behind`` replaces points at or behind the source (None:
    keep the formula's value, which a least-squares fit can still move back in front)."""
    c, s = np.cos(angles), np.sin(angles)
    px = c * points[:, 0] - s * points[:, 2]
    z = s * points[:, 0] + c * points[:, 2] + geometry.source_to_object_mm
    with np.errstate(divide="ignore", invalid="ignore"):
        xn, yn = px / z, points[:, 1] / z
    if behind is not None:
        xn, yn = np.where(z > 0, xn, behind), np.where(z > 0, yn, behind)
    ct, st = np.cos(tilt_rad), np.sin(tilt_rad)
    f = _focal_px(geometry)
    return np.stack([geometry.u0_px + f[0] * (ct * xn - st * yn), geometry.v0_px + f[1] * (st * xn + ct * yn)], axis=1)


def pixels_to_rays(xy_px, geometry: Geometry, *, tilt_rad: float = 0.0) -> np.ndarray:
    """Normalised ray coordinates ``(x_n, y_n)`` of pixels, the inverse of the detector map.

    Parameters
    ----------
    xy_px : ndarray of shape (N, 2)
        ``(x=col, y=row)`` in pixels.

    Returns
    -------
    ndarray of shape (N, 2)
        ``(P_x / Z, P_y / Z)`` in the source frame of the view.
    """
    xy = np.asarray(xy_px, dtype=np.float64).reshape(-1, 2)
    a = (xy - np.array([geometry.u0_px, geometry.v0_px])) / _focal_px(geometry)
    ct, st = np.cos(tilt_rad), np.sin(tilt_rad)
    return np.stack([ct * a[:, 0] + st * a[:, 1], -st * a[:, 0] + ct * a[:, 1]], axis=1)


def projection_jacobians(points_mm, angles_rad, geometry: Geometry, *, tilt_rad: float = 0.0):
    """Projections and their derivatives, for bundle adjustment.

    Parameters
    ----------
    points_mm : ndarray of shape (N, 3)
    angles_rad : ndarray of shape (N,)
    geometry : Geometry
    tilt_rad : float

    Returns
    -------
    uv : ndarray of shape (N, 2)
        Projections in pixels, as :func:`project_points`.
    d_angle : ndarray of shape (N, 2)
        ``d(u, v) / d theta``, pixels per radian.
    d_point : ndarray of shape (N, 2, 3)
        ``d(u, v) / d X``, pixels per mm.
    d_detector : ndarray of shape (N, 2, 3)
        ``d(u, v) / d(u0_px, v0_px, tilt_rad)``: identity columns for the principal point,
        pixels per radian for the tilt.
    """
    points, angles = _check_points(points_mm, angles_rad)
    c, s = np.cos(angles), np.sin(angles)
    px = c * points[:, 0] - s * points[:, 2]
    py = points[:, 1]
    pz = s * points[:, 0] + c * points[:, 2]
    inv_z = 1.0 / (pz + geometry.source_to_object_mm)
    xn, yn = px * inv_z, py * inv_z
    n = len(points)
    # d(xn, yn)/dtheta with dP/dtheta = (-P_z, 0, P_x); d(xn, yn)/dX = d(xn, yn)/dP R(theta), written out.
    dxn_dtheta = (-pz - xn * px) * inv_z
    dyn_dtheta = -yn * px * inv_z
    dxn_dx = np.stack([(c - xn * s) * inv_z, np.zeros(n), (-s - xn * c) * inv_z], axis=1)
    dyn_dx = np.stack([-yn * s * inv_z, inv_z, -yn * c * inv_z], axis=1)
    ct, st = np.cos(tilt_rad), np.sin(tilt_rad)
    f = _focal_px(geometry)
    m = np.array([[f[0] * ct, -f[0] * st], [f[1] * st, f[1] * ct]])
    uv = np.stack([geometry.u0_px + m[0, 0] * xn + m[0, 1] * yn, geometry.v0_px + m[1, 0] * xn + m[1, 1] * yn], axis=1)
    d_angle = np.stack([m[0, 0] * dxn_dtheta + m[0, 1] * dyn_dtheta, m[1, 0] * dxn_dtheta + m[1, 1] * dyn_dtheta], axis=1)
    d_point = np.stack([m[0, 0] * dxn_dx + m[0, 1] * dyn_dx, m[1, 0] * dxn_dx + m[1, 1] * dyn_dx], axis=1)
    d_detector = np.zeros((n, 2, 3))
    d_detector[:, 0, 0] = 1.0
    d_detector[:, 1, 1] = 1.0
    d_detector[:, 0, 2] = f[0] * (-st * xn - ct * yn)
    d_detector[:, 1, 2] = f[1] * (ct * xn - st * yn)
    return uv, d_angle, d_point, d_detector
