"""Corrected angles and geometry back out, in forms the user's reconstructor reads.

The pipeline's angles are relative to view 0; a reconstructor wants them in the scanner's own
frame, where the volume sits as the nominal angles put it. :func:`scanner_frame_deg` moves them
there (the common offset that makes estimated minus nominal zero in the median).

:func:`cone_vectors` gives the per-view vector geometry of ASTRA's ``cone_vec`` (and of any
reconstructor that takes a source, a detector centre and the detector's row and column vectors
per view, as TIGRE's and CIL's vector geometries do): it carries the angle and, when bundle
adjustment estimated them, the centre of rotation (``u0_px``), ``v0_px`` and the detector tilt; when a ball
calibration showed it, the axis's offset from the source's perpendicular (the source and the detector placed about
the offset axis: ``S = R^T (-offset, 0, -SOD)``, the detector's centre likewise less the offset).

Frame of the vectors
--------------------
ASTRA's frame has ``z`` vertical (the rotation axis) and ``x, y`` horizontal; ctpipe's object
frame (:mod:`ctpipe.recon.volume`) has ``y`` along the rotation axis pointing the way detector
rows increase (down the image) and ``z`` from the source towards the detector at angle 0. A
ctpipe object point ``(x, y, z)`` is the ASTRA point ``(x, z, -y)`` (a proper rotation, so
nothing is mirrored). Per view, with ``R`` the turntable rotation of
:func:`ctpipe.model.rotation_matrix` and the detector map of :mod:`ctpipe.solve.camera`::

    source       S = R^T (0, 0, -SOD)
    column step  u = R^T ( cos(tilt) pitch_u, -sin(tilt) pitch_u, 0)
    row step     v = R^T ( sin(tilt) pitch_v,  cos(tilt) pitch_v, 0)
    centre       d = R^T (0, 0, SDD - SOD) + (c_col - u0) u + (c_row - v0) v

with ``(c_col, c_row) = ((cols - 1) / 2, (rows - 1) / 2)`` the detector's centre pixel, then
each mapped to ASTRA's frame. ASTRA's ``u`` runs from pixel (row 0, col 0) to (row 0, col 1) and
``v`` from (row 0, col 0) to (row 1, col 0), as here; the projections go to ASTRA as
``(rows, views, cols)``. ``tests/io/test_corrected.py`` checks that these vectors put every
point on the pixel ctpipe's camera model does.
"""

from __future__ import annotations

import numpy as np

from ctpipe.geometry import Geometry
from ctpipe.model import rotation_matrix

__all__ = ["scanner_frame_deg", "cone_vectors", "CONE_VECTOR_COLUMNS", "TO_ASTRA"]

#: Column names of :func:`cone_vectors`' rows (ASTRA's ``cone_vec`` order).
CONE_VECTOR_COLUMNS = ("src_x", "src_y", "src_z", "d_x", "d_y", "d_z", "u_x", "u_y", "u_z", "v_x", "v_y", "v_z")

#: ctpipe object frame -> ASTRA frame: (x, y, z) -> (x, z, -y).
TO_ASTRA = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def scanner_frame_deg(angles_deg, nominal_deg) -> np.ndarray:
    """Angles relative to view 0 moved into the nominal angles' frame (median offset of the views with both).

    Without nominal angles (None) the angles are returned as they are.
    """
    angles = np.asarray(angles_deg, dtype=np.float64)
    if nominal_deg is None:
        return angles.copy()
    nominal = np.asarray(nominal_deg, dtype=np.float64)
    both = np.isfinite(angles) & np.isfinite(nominal)
    return angles + (float(np.median(nominal[both] - angles[both])) if both.any() else 0.0)


def cone_vectors(geometry: Geometry, angles_deg, *, tilt_deg: float = 0.0, shifts_px=None,
                 axis_offset_mm: float = 0.0, spot_share: float = 0.0) -> np.ndarray:
    """ASTRA ``cone_vec`` rows, one per view: source, detector centre, column step, row step (mm).

    Parameters
    ----------
    geometry : Geometry
        With the principal point (centre of rotation) to use.
    angles_deg : array_like of shape (V,)
        Turntable angles in ctpipe's convention.
    tilt_deg : float
        In-plane detector tilt, as bundle adjustment reports it.
    shifts_px : array_like of shape (V, 2) or None
        Each view's own shift of the projection ``(du, dv)`` (px): that view's principal point is
        ``(u0_px + du, v0_px + dv)``, its detector moved by ``-du`` columns and ``-dv`` rows
        (:attr:`ctpipe.data.ScanSolution.view_shifts_px`).
    axis_offset_mm : float
        How far the rotation axis lies off the source's perpendicular to the detector, along the camera ``x``, at
        the axis (mm; :attr:`ctpipe.data.ScanSolution.axis_offset_mm`): an object point is at ``R X + (offset, 0,
        SOD)`` in the camera frame, and ``(u0_px, v0_px)`` is where the axis's point level with the source projects,
        the principal point ``offset SDD / SOD`` mm from it along the (tilted) columns
        (:func:`ctpipe.solve.balls.ellipse_centres`). 0: the axis on the perpendicular, as before.
    spot_share : float
        How much of each view's shift the source spot made, 0 to 1
        (:attr:`ctpipe.data.ScanSolution.drift_spot_share`): the detector is moved by ``-(1 - share)`` of the
        shift and the source by ``-share t / (M - 1)``, ``t`` the shift in mm along the detector's columns and
        rows and ``M = SDD / SOD``. The axis's image then moves by the whole shift and a point at distance ``z``
        from the source by ``share (SDD / z - 1) / (M - 1)`` of it besides the detector's part, as the ball
        calibration models a spot's drift (:func:`ctpipe.solve.balls._adjust`). 0: every shift the detector's.

    Returns
    -------
    ndarray of shape (V, 12)
        Columns :data:`CONE_VECTOR_COLUMNS`, in ASTRA's frame (see the module docstring).
    """
    g = geometry
    tilt = np.deg2rad(float(tilt_deg))
    ct, st = np.cos(tilt), np.sin(tilt)
    u_cam = np.array([ct * g.pixel_pitch_u_mm, -st * g.pixel_pitch_u_mm, 0.0])
    v_cam = np.array([st * g.pixel_pitch_v_mm, ct * g.pixel_pitch_v_mm, 0.0])
    # The principal point: the image of the source's perpendicular, ``offset SDD / SOD`` mm along the camera x from the
    # axis's image (u0, v0).
    along = float(axis_offset_mm) * g.source_to_detector_mm / g.source_to_object_mm
    u_p = g.u0_px - along * ct / g.pixel_pitch_u_mm
    v_p = g.v0_px - along * st / g.pixel_pitch_v_mm
    centre_cam = (np.array([0.0, 0.0, g.source_to_detector_mm])
                  + ((g.detector_cols - 1) / 2.0 - u_p) * u_cam + ((g.detector_rows - 1) / 2.0 - v_p) * v_cam)
    shift = np.array([float(axis_offset_mm), 0.0, g.source_to_object_mm])
    angles = np.deg2rad(np.asarray(angles_deg, dtype=np.float64))
    shifts = np.zeros((len(angles), 2)) if shifts_px is None else np.asarray(shifts_px, dtype=np.float64)
    share = float(spot_share)
    gain = g.magnification - 1.0     # M - 1: the axis's image per spot's move
    rows = []
    for angle, (du, dv) in zip(angles, shifts):
        to_object = rotation_matrix(angle).T
        moved = du * u_cam + dv * v_cam
        source = to_object @ (-share * moved / gain - shift)
        centre = to_object @ (centre_cam - (1.0 - share) * moved - shift)
        rows.append(np.concatenate([TO_ASTRA @ source, TO_ASTRA @ centre, TO_ASTRA @ (to_object @ u_cam),
                                    TO_ASTRA @ (to_object @ v_cam)]))
    return np.array(rows).reshape(-1, 12)
