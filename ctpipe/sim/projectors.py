"""Cone-beam forward projectors: exact line integrals through primitives, and a voxel projector.

Geometry
--------
The frames of :mod:`ctpipe.geometry` and :mod:`ctpipe.recon.volume`: an object point ``X`` is, in the
view at turntable angle ``theta``, at ``X_cam = R(theta) X + (0, 0, SOD)`` with ``R`` of
:func:`ctpipe.model.rotation_matrix`. The source is the camera origin, the detector the plane
``z = SDD``, and the camera point ``(X, Y, Z)`` hits the pixel::

    col = u0_px + (X / Z) * SDD / pixel_pitch_u_mm
    row = v0_px + (Y / Z) * SDD / pixel_pitch_v_mm

Pixel centres are at integer ``(col, row)``; the ray of a pixel runs from the source to its
centre. In the object frame the source is ``S = -R^T (0, 0, SOD)`` and the ray direction of
the camera vector ``d_cam = ((col - u0) pitch_u, (row - v0) pitch_v, SDD)`` is ``R^T d_cam``.
A misaligned detector (:mod:`ctpipe.sim.drift`) enters :func:`project_analytic` exactly: a
principal point per view, and a tilt ``phi`` that turns the pixel offsets in the detector plane,
``d_cam = (cos phi a - sin phi b, sin phi a + cos phi b, SDD)`` with ``a = (col - u0) pitch_u``,
``b = (row - v0) pitch_v``.

Projections are float32 arrays ``(views, rows, cols)`` of line integrals: density (1/mm) times
length (mm), integrated over the segment from the source to the detector.

Voxel projector
---------------
Joseph's method: a ray is sampled on every voxel-centre plane across its dominant axis (the
axis it advances fastest along) and the volume is interpolated bilinearly in the other two;
each sample stands for the step length ``voxel * |d| / |d_dominant|``. The volume is copied into
one zero-padded layout per dominant axis with that axis last (contiguous), so every ray reads
four contiguous streams, and the zero pad makes the bilinear weights fade to zero past the grid
without branches. :meth:`VoxelProjector.back` runs the same loops and scatters the same weights,
so it is the exact transpose of :meth:`VoxelProjector.forward` (up to float32 rounding).
"""

from __future__ import annotations

import itertools
import math
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterator

import numba
import numpy as np
from numba import prange

from ctpipe._shared import device
from ctpipe._shared.arrays import all_finite
from ctpipe._shared.checks import as_angles_deg
from ctpipe._shared.jit import FASTMATH, njit
from ctpipe._shared.resources import available_cores, check_fits
from ctpipe.errors import InputError, ResourceError
from ctpipe.geometry import Geometry, check_geometry
from ctpipe.recon.volume import VolumeGrid
from ctpipe.sim._chords import pixel_chords, primitive_pixels, unit_frame_ray
from ctpipe.sim._joseph import _pixel_ray, _ray_sum, _ray_sum_pair
from ctpipe.sim.primitives import KINDS, Primitives, local_maps

__all__ = ["project_analytic", "analytic_work", "voxel_work", "VoxelProjector", "MAX_SUB_RAYS", "MAX_VOXEL_STEPS"]

# Views per call of the analytic kernel: paces ``progress`` without starving the threads.
_CHUNK_VIEWS = 16

# Voxel samples per call of the forward projection's kernel: about a second on two cores.
_SAMPLES_PER_CALL = 1e9

#: The most sub-ray/primitive intersections :func:`project_analytic` takes on (counted on the
#: pixel boxes it visits, an upper bound). The default validate scan needs 1.3e9 (360 views at
#: supersample 2), 4-8 s on two cores; 2e11, 160 times that, takes 10-20 minutes. Larger
#: requests are refused before any work.
MAX_SUB_RAYS = 2e11

# The kernel's time for one primitive in one view before its first pixel (its box, its conic), in
# sub-rays: about 250 ns against 4 ns a sub-ray (200,000 grains beside the cone of rays, 36 views).
_PRIMITIVE_VIEW_SUB_RAYS = 64

#: The most voxel samples (one bilinear read of the volume on a ray) a simulation of a voxel phantom
#: takes on (:func:`voxel_work`, an upper bound). Joseph's forward projection takes about 1.5 ns a
#: sample on two cores against the analytic projector's 4 ns an intersection (both measured on
#: 512^2 views of 128^3-256^3 volumes and the granular phantom), so 6e11 is the same 10-20 minutes.
MAX_VOXEL_STEPS = 6e11


# --------------------------------------------------------------------------- validation

def _check_array(name: str, value, expected: tuple[int, ...], axes: str) -> np.ndarray:
    array = np.asarray(value)
    if not np.issubdtype(array.dtype, np.floating):
        raise InputError(f"{name}: must be a float array, got dtype {array.dtype}")
    if array.shape != expected:
        raise InputError(f"{name}: must have shape {axes} = {expected}, got {array.shape}")
    if not all_finite(array):
        raise InputError(f"{name}: contains NaN or infinite values")
    return np.ascontiguousarray(array, dtype=np.float32)


def _check_int(name: str, value, low: int) -> int:
    if not (isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= low):
        raise InputError(f"{name}: must be an integer >= {low}, got {value!r}")
    return int(value)


# --------------------------------------------------------------------------- analytic projector

@njit(cache=True, fastmath=False)
def _ellipse_conic(a0, a1, a2, pa0, pa1, pa2, pb0, pb1, pb2, pz0, pz1, pz2):
    """The image of the unit ball seen from ``a``: the sub-ray ``b = pa au + pb bv + pz`` hits it iff
    ``q00 au^2 + 2 q01 au bv + 2 q02 au + q11 bv^2 + 2 q12 bv + q22 < 0``.

    That form is ``|b|^2 (|a|^2 - 1) - (a . b)^2``, the negative discriminant of ``|a + t b|^2 = 1``.
    ``q00 > 0`` exactly when the line through the source along ``pa`` misses the ball, which holds
    for a ball wholly in front of the source; the set is then an ellipse.
    """
    k = a0 * a0 + a1 * a1 + a2 * a2 - 1.0
    da = a0 * pa0 + a1 * pa1 + a2 * pa2
    db = a0 * pb0 + a1 * pb1 + a2 * pb2
    dz = a0 * pz0 + a1 * pz1 + a2 * pz2
    q00 = k * (pa0 * pa0 + pa1 * pa1 + pa2 * pa2) - da * da
    q01 = k * (pa0 * pb0 + pa1 * pb1 + pa2 * pb2) - da * db
    q02 = k * (pa0 * pz0 + pa1 * pz1 + pa2 * pz2) - da * dz
    q11 = k * (pb0 * pb0 + pb1 * pb1 + pb2 * pb2) - db * db
    q12 = k * (pb0 * pz0 + pb1 * pz1 + pb2 * pz2) - db * dz
    q22 = k * (pz0 * pz0 + pz1 * pz1 + pz2 * pz2) - dz * dz
    return q00, q01, q02, q11, q12, q22


@njit(cache=True, fastmath=False)
def _ellipse_columns(q00, q01, q02, q11, q12, q22, r, v0, u0, pu, pv, ss):
    """Inclusive column span of pixel row ``r`` whose sub-rays can hit the ellipse (``q00 > 0``);
    empty (``lo > hi``) when none can.

    The span of every sub-row is solved exactly and widened by 0.01 px (and the discriminant
    by a relative 1e-9), so rounding never drops a sub-ray that grazes the ellipse.
    """
    lo = math.inf
    hi = -math.inf
    for jv in range(ss):
        bv = (r + (jv + 0.5) / ss - 0.5 - v0) * pv
        half_b = q01 * bv + q02
        c = (q11 * bv + 2.0 * q12) * bv + q22
        disc = half_b * half_b - q00 * c
        if disc <= -1e-9 * (half_b * half_b + abs(q00 * c)):
            continue
        root = math.sqrt(max(disc, 0.0))
        lo = min(lo, (-half_b - root) / q00)
        hi = max(hi, (-half_b + root) / q00)
    if lo > hi:
        return 1, 0
    # Sub-ray columns sit at col + (ju + 0.5) / ss - 0.5, within half a pixel of the centre.
    reach = 0.5 - 0.5 / ss + 0.01
    return int(math.ceil(lo / pu + u0 - reach)), int(math.floor(hi / pu + u0 + reach))


@njit(parallel=True, fastmath=False, cache=True)
def _project_primitives(out, cos_t, sin_t, kind, centre, maps, corners, density, sod, sdd, pu, pv, u0_v, v0_v,
                        cos_tilt, sin_tilt, ss):
    """Add the line integrals of every primitive to ``out`` (V, rows, cols), one view per thread.

    corners : (N, 8, 3) object-frame corners of each primitive's oriented box
    (:func:`ctpipe.sim._chords.primitive_pixels`).
    u0_v, v0_v : (V,) principal point of every view (pixels).
    cos_tilt, sin_tilt : the detector's in-plane rotation; pixel offsets ``(a pu, b pv)`` from the
    principal point sit at camera ``(ct a pu - st b pv, st a pu + ct b pv)``. With ``(1, 0)`` every
    product is exact, so an untilted detector gives the numbers of the plain mapping.
    """
    n_views, n_rows, n_cols = out.shape
    n_prim = kind.shape[0]
    inv_ss2 = 1.0 / (ss * ss)
    for v in prange(n_views):
        c = cos_t[v]
        s = sin_t[v]
        u0 = u0_v[v]
        v0 = v0_v[v]
        for n in range(n_prim):
            c0, c1, r0, r1, n_behind = primitive_pixels(corners, n, c, s, sod, sdd, pu, pv, u0, v0, cos_tilt,
                                                         sin_tilt, n_rows, n_cols)
            if c0 > c1 or r0 > r1:
                continue
            ray = unit_frame_ray(centre, maps, n, c, s, sod, sdd)
            a0, a1, a2, ax0, ax1, ax2, ay0, ay1, ay2, az0, az1, az2 = ray
            k_n = kind[n]
            rho = density[n] * inv_ss2
            # An ellipsoid in front of the source images to an ellipse: its rows give tighter
            # column spans than the box corners (every sub-ray outside them misses).
            tight = k_n == 0 and n_behind == 0
            if tight:
                # Sub-ray of pixel offsets (au, bv): b = pa au + pb bv + pz (detector tilt folded in).
                pa0 = ax0 * cos_tilt + ay0 * sin_tilt
                pa1 = ax1 * cos_tilt + ay1 * sin_tilt
                pa2 = ax2 * cos_tilt + ay2 * sin_tilt
                pb0 = ay0 * cos_tilt - ax0 * sin_tilt
                pb1 = ay1 * cos_tilt - ax1 * sin_tilt
                pb2 = ay2 * cos_tilt - ax2 * sin_tilt
                q00, q01, q02, q11, q12, q22 = _ellipse_conic(a0, a1, a2, pa0, pa1, pa2, pb0, pb1, pb2,
                                                              az0, az1, az2)
                tight = q00 > 0.0
            for r in range(r0, r1 + 1):
                cr0 = c0
                cr1 = c1
                if tight:
                    cr0, cr1 = _ellipse_columns(q00, q01, q02, q11, q12, q22, r, v0, u0, pu, pv, ss)
                    cr0 = max(cr0, c0)
                    cr1 = min(cr1, c1)
                for col in range(cr0, cr1 + 1):
                    total = pixel_chords(k_n, ray, r, col, u0, v0, pu, pv, cos_tilt, sin_tilt, sdd, ss)
                    if total != 0.0:
                        out[v, r, col] += np.float32(rho * total)


def project_analytic(primitives: Primitives, geometry: Geometry, angles_deg, *, supersample: int = 1,
                     blur_px: float = 0.0, progress: Callable[[int], object] | None = None,
                     detector_offsets_px=None, detector_tilt_deg: float = 0.0,
                     axis_offset_mm: float = 0.0, spot_offsets_px=None) -> np.ndarray:
    """Exact line integrals through analytic primitives.

    Every pixel integrates the ray from the source to its centre (or the mean of
    ``supersample x supersample`` sub-rays spread evenly over the pixel) through each primitive in
    closed form: the ray is mapped into the primitive's unit frame, where the chord is the
    parameter gap ``t_out - t_in`` times the ray length. A primitive only visits the pixels inside
    the perspective image of its oriented bounding box, and an ellipsoid, row by row, only those
    its image ellipse reaches, so the cost is the pixels it covers. A shape the turntable maps onto
    itself (an ellipsoid or cylinder centred on the axis, round across it: a container) is
    projected once and added to every view, when all views share the detector.

    Parameters
    ----------
    primitives : Primitives
        Shapes in the object frame, densities in 1/mm (overlaps add).
    geometry : Geometry
    angles_deg : array_like of shape (V,)
        Turntable angle of every view, degrees.
    supersample : int
        Sub-rays per pixel edge (>= 1); 1 is the ray through the pixel centre.
    blur_px : float
        Standard deviation in pixels of a Gaussian detector blur applied to every view
        (``scipy.ndimage.gaussian_filter``, reflecting edges); 0 for none.
    progress : callable, optional
        Called with the number of views finished so far, after every chunk of views.
    detector_offsets_px : array_like of shape (V, 2), optional
        Per view ``(du, dv)`` pixels added to the principal point ``(u0_px, v0_px)``: the true
        detector of a misaligned scan (:mod:`ctpipe.sim.drift`); a positive ``du`` moves the
        projection towards larger columns. None: the geometry's principal point in every view.
    detector_tilt_deg : float
        In-plane rotation of the detector about the principal point, degrees, from the camera
        ``x`` axis towards ``y`` (:mod:`ctpipe.sim.drift`); 0 for none.
    axis_offset_mm : float
        How far the turntable's axis lies off the source's perpendicular to the detector, along the camera ``x``
        (mm): an object point sits at ``X_cam = R(theta) X + (axis_offset_mm, 0, SOD)`` (a stage moved sideways, or,
        the same, a detector yawed by ``asin(axis_offset_mm / SOD)`` about its columns' perpendicular; the axis
        images ``axis_offset_mm * SDD / (SOD * pitch_u)`` columns from the principal point). Each view then projects
        the primitives moved by ``R(theta)^T (axis_offset_mm, 0, 0)``, one view at a time. 0 for none.
    spot_offsets_px : array_like of shape (V, 2), optional
        Per view, how far the source spot has moved, given as ``(du, dv)``, the pixels it moves the rotation axis's
        image by (:mod:`ctpipe.sim.drift`, ``drift.at: source``). A spot moved by ``s`` mm in its plane, the detector
        still, is the object moved by ``-s`` and the detector by ``-s`` with the spot still: the axis's image moves by
        ``-s (M - 1) / pitch`` px (``M = SDD / SOD``) and a point at distance ``z`` from the spot by ``-s (SDD / z -
        1) / pitch``, so a ball nearer the spot moves further (parallax). Added to ``detector_offsets_px``; each view
        is then projected on its own. None: the spot still.

    Returns
    -------
    ndarray of shape (V, detector_rows, detector_cols), float32
        Line integrals (dimensionless: 1/mm times mm).
    """
    if not isinstance(primitives, Primitives):
        raise InputError(f"primitives: must be a ctpipe.sim.primitives.Primitives, got {type(primitives).__name__}")
    geometry = check_geometry(geometry)
    angles = as_angles_deg(angles_deg)
    supersample = _check_int("supersample", supersample, 1)
    if not (isinstance(blur_px, (int, float, np.floating, np.integer)) and not isinstance(blur_px, bool)
            and math.isfinite(blur_px) and blur_px >= 0):
        raise InputError(f"blur_px: must be a finite number >= 0 (pixels, 0 = no blur), got {blur_px!r}")
    if progress is not None and not callable(progress):
        raise InputError(f"progress: must be a callable taking a number of views, or None, got {progress!r}")

    spot_mm = None
    if spot_offsets_px is not None:
        spot = np.asarray(spot_offsets_px, dtype=np.float64)
        if spot.shape != (angles.size, 2) or not np.all(np.isfinite(spot)):
            raise InputError(f"spot_offsets_px: must be finite, one (du, dv) per view ({angles.size}, 2), got shape "
                             f"{spot.shape}")
        gain = geometry.magnification - 1.0   # M - 1
        pitch = np.array([geometry.pixel_pitch_u_mm, geometry.pixel_pitch_v_mm])
        # The spot's move in mm (camera x, y) that moves the axis's image by ``spot`` px.
        spot_mm = -spot * pitch / gain
        still = np.zeros((angles.size, 2)) if detector_offsets_px is None else np.asarray(detector_offsets_px,
                                                                                          dtype=np.float64)
        # The detector moved by -s: its principal point by +s / pitch px.
        detector_offsets_px = still + spot_mm / pitch
    u0_v, v0_v = _principal_points(geometry, angles.size, detector_offsets_px)
    tilt_deg = detector_tilt_deg
    if not (isinstance(tilt_deg, (int, float, np.floating, np.integer)) and not isinstance(tilt_deg, bool)
            and math.isfinite(tilt_deg) and abs(tilt_deg) <= 45):
        raise InputError(f"detector_tilt_deg: must be a finite number of degrees in [-45, 45], got {tilt_deg!r}")
    if not (isinstance(axis_offset_mm, (int, float, np.floating, np.integer)) and not isinstance(axis_offset_mm, bool)
            and math.isfinite(axis_offset_mm) and abs(axis_offset_mm) < 0.5 * geometry.source_to_object_mm):
        raise InputError(f"axis_offset_mm: must be a finite number of mm within half the source-to-object distance "
                         f"({0.5 * geometry.source_to_object_mm:g} mm), got {axis_offset_mm!r}")
    if axis_offset_mm or spot_mm is not None:
        offsets = (np.zeros((angles.size, 2)) if detector_offsets_px is None
                   else np.asarray(detector_offsets_px, dtype=np.float64))   # checked by _principal_points
        # The object moved by -s (camera frame) where the spot moved by s, besides the axis's own offset.
        moves = np.zeros((angles.size, 2)) if spot_mm is None else -spot_mm
        moves[:, 0] += float(axis_offset_mm)
        return _project_off_axis(primitives, geometry, angles, offsets, moves,
                                 supersample=supersample, blur_px=blur_px, progress=progress,
                                 detector_tilt_deg=detector_tilt_deg)
    tilt = math.radians(detector_tilt_deg)
    # cos(0) and sin(0) are exactly 1 and 0: the untilted kernel reproduces the plain mapping bit for bit.
    cos_tilt, sin_tilt = math.cos(tilt), math.sin(tilt)
    check_fits(f"projecting {angles.size} views of {geometry.detector_rows} x {geometry.detector_cols}",
               angles.size * geometry.detector_rows * geometry.detector_cols * 4 * (2 if blur_px > 0 else 1),
               hint="use fewer views or a smaller detector")
    theta = np.deg2rad(angles)
    # A shape that the turntable maps onto itself projects the same in every view that shares the
    # detector: project it once and add that image to every view.
    shared_detector = np.all(u0_v == u0_v[0]) and np.all(v0_v == v0_v[0])
    still = _turn_invariant(primitives) if shared_detector else np.zeros(len(primitives), bool)
    moving = _kernel_shapes(primitives.subset(~still) if still.any() else primitives)
    fixed = _kernel_shapes(primitives.subset(still))
    work = _work(moving[3], fixed[3], geometry, theta, u0_v, v0_v, cos_tilt, sin_tilt, supersample)
    if work > MAX_SUB_RAYS:
        raise ResourceError(
            f"projecting {len(primitives)} primitives into {angles.size} views of {geometry.detector_rows} x "
            f"{geometry.detector_cols} at supersample {supersample} needs about {work:.1e} ray-primitive "
            f"intersections, more than the {MAX_SUB_RAYS:.0e} (10-20 minutes on two cores) ctpipe takes on; use "
            "fewer views, a smaller detector or supersample, or fewer primitives in the cone of rays")
    out = np.zeros((angles.size, geometry.detector_rows, geometry.detector_cols), dtype=np.float32)
    constants = (float(geometry.source_to_object_mm), float(geometry.source_to_detector_mm),
                 float(geometry.pixel_pitch_u_mm), float(geometry.pixel_pitch_v_mm))
    kernel = _project_primitives
    if device.active() == "cuda":
        from ctpipe.sim import _cuda

        def kernel(out, cos_t, sin_t, kind, centre, maps, corners, density, sod, sdd, pu, pv, *rest):
            before = out.copy()
            try:
                _cuda.project_primitives(out, cos_t, sin_t, (kind, centre, maps, corners, density),
                                         (sod, sdd, pu, pv), *rest)
            except Exception as error:  # noqa: BLE001 - memory, driver, compiler: the CPU answers
                device.fall_back("the analytic projection", error)
                out[...] = before
                _project_primitives(out, cos_t, sin_t, kind, centre, maps, corners, density, sod, sdd, pu, pv, *rest)
    if still.any():
        image = np.zeros((1, *out.shape[1:]), np.float32)
        kernel(image, np.ones(1), np.zeros(1), *fixed, *constants, u0_v[:1], v0_v[:1], cos_tilt, sin_tilt, supersample)
    args = (*moving, *constants)
    # Chunks of at most about 1e8 intersections (well under a second), so that Ctrl-C and SIGTERM,
    # which Python handles between calls, stop a large scene promptly.
    per_view = work / angles.size
    chunk = int(min(_CHUNK_VIEWS, max(1, 1e8 // max(per_view, 1.0))))
    for start in range(0, angles.size, chunk):
        stop = min(start + chunk, angles.size)
        if still.any():
            out[start:stop] = image
        if not still.all():
            kernel(out[start:stop], np.cos(theta[start:stop]), np.sin(theta[start:stop]), *args, u0_v[start:stop],
                   v0_v[start:stop], cos_tilt, sin_tilt, supersample)
        if blur_px > 0:
            from scipy.ndimage import gaussian_filter

            def blur(k: int) -> None:
                out[k] = gaussian_filter(out[k], sigma=float(blur_px))

            # SciPy's filters let go of the GIL: the chunk's views in threads.
            with ThreadPoolExecutor(max_workers=available_cores()) as pool:
                list(pool.map(blur, range(start, stop)))
        if progress is not None:
            progress(stop)
    return out


def _project_off_axis(primitives: Primitives, geometry: Geometry, angles: np.ndarray, offsets_px: np.ndarray,
                      moves_mm: np.ndarray, *, progress, **settings) -> np.ndarray:
    """:func:`project_analytic` with the object moved in the camera frame by ``moves_mm`` (V, 2: along camera
    ``x`` and ``y``), an axis off the source's perpendicular or a spot that moved: view by view, the primitives moved
    by ``R(theta)^T (mx, my, 0)``, which puts them at ``R(theta) X + (mx, my, SOD)`` in the camera frame."""
    import dataclasses

    out = np.empty((angles.size, geometry.detector_rows, geometry.detector_cols), dtype=np.float32)
    for k, theta in enumerate(np.deg2rad(angles)):
        mx, my = moves_mm[k]
        moved = np.array([mx * math.cos(theta), my, -mx * math.sin(theta)])
        shifted = dataclasses.replace(primitives, centre_mm=primitives.centre_mm + moved)
        out[k] = project_analytic(shifted, geometry, angles[k:k + 1], detector_offsets_px=offsets_px[k:k + 1],
                                  **settings)[0]
        if progress is not None:
            progress(k + 1)
    return out


def analytic_work(primitives: Primitives, geometry: Geometry, angles_deg, *, supersample: int = 1) -> float:
    """Ray-primitive intersections :func:`project_analytic` computes for these views (an upper bound).

    What :data:`MAX_SUB_RAYS` limits, for the geometry's own detector (no per-view offsets or
    tilt): a simulation can be weighed with it before anything is projected.
    """
    geometry = check_geometry(geometry)
    theta = np.deg2rad(as_angles_deg(angles_deg))
    u0_v, v0_v = _principal_points(geometry, theta.size, None)
    still = _turn_invariant(primitives)
    corners = _box_corners(primitives.centre_mm, primitives.half_size_mm, primitives.rotation)
    return _work(corners[~still], corners[still], geometry, theta, u0_v, v0_v, 1.0, 0.0, supersample)


def voxel_work(geometry: Geometry, grid: VolumeGrid, angles_deg) -> float:
    """Voxel samples a forward projection of a volume on ``grid`` takes for these views (an upper bound).

    What :data:`MAX_VOXEL_STEPS` limits: every pixel the grid's box casts its shadow on, at up to
    8 views spread over ``angles_deg``, times the most voxel planes a ray can cross (the grid's
    longest side: Joseph's method samples one plane across the ray's dominant axis at a time).
    """
    geometry = check_geometry(geometry)
    theta = np.deg2rad(as_angles_deg(angles_deg))
    u0_v, v0_v = _principal_points(geometry, theta.size, None)
    corners = _box_corners(np.asarray(grid.centre_mm)[None], grid.extent_mm[None] / 2.0, np.eye(3)[None])
    shadow = _sub_rays(corners, geometry, theta, u0_v, v0_v, 1.0, 0.0)
    return shadow * max(grid.n_x, grid.n_y, grid.n_z)


def _work(moving_corners: np.ndarray, fixed_corners: np.ndarray, geometry: Geometry, theta: np.ndarray,
          u0_v: np.ndarray, v0_v: np.ndarray, cos_tilt: float, sin_tilt: float, supersample: int) -> float:
    """Sub-ray intersections of the moving boxes in every view and of the turn-invariant ones in one.

    Each primitive costs the kernel :data:`_PRIMITIVE_VIEW_SUB_RAYS` in every view it is
    projected in, before its first pixel: counted too, so that many small or far primitives are
    not free.
    """
    pixels = (_sub_rays(moving_corners, geometry, theta, u0_v, v0_v, cos_tilt, sin_tilt)
              + _sub_rays(fixed_corners, geometry, theta[:1], u0_v, v0_v, cos_tilt, sin_tilt))
    placed = len(moving_corners) * len(theta) + len(fixed_corners) * min(len(theta), 1)
    return pixels * supersample ** 2 + placed * _PRIMITIVE_VIEW_SUB_RAYS


def _box_corners(centre_mm: np.ndarray, half_size_mm: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """The corners (N, 8, 3) of N boxes (centres and half sizes (N, 3), rotations (N, 3, 3)), mm."""
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    # corner = centre + rotation @ (sign * half_size).
    return np.ascontiguousarray(centre_mm[:, None, :] + np.einsum(
        "nij,nkj->nki", rotation, signs[None, :, :] * half_size_mm[:, None, :]))


def _kernel_shapes(primitives: Primitives) -> tuple:
    """The per-primitive arrays :func:`_project_primitives` takes: kind, centre, unit maps, box corners, density."""
    return (primitives.kind, primitives.centre_mm, local_maps(primitives),
            _box_corners(primitives.centre_mm, primitives.half_size_mm, primitives.rotation), primitives.density_per_mm)


def _sub_rays(corners: np.ndarray, geometry: Geometry, theta: np.ndarray, u0_v: np.ndarray, v0_v: np.ndarray,
              cos_tilt: float, sin_tilt: float) -> float:
    """Pixels the kernel visits for boxes ``corners`` (N, 8, 3) over the views ``theta``, as it bounds them.

    Counted at up to 8 views spread over the scan and scaled to all of them: a box wholly
    behind the source visits none, one across the source plane the whole detector, any other the
    pixel rectangle of its corners' images (an ellipsoid visits fewer: this is an upper bound).
    """
    if len(corners) == 0 or len(theta) == 0:
        return 0.0
    rows, cols = geometry.detector_rows, geometry.detector_cols
    sod, sdd = geometry.source_to_object_mm, geometry.source_to_detector_mm
    picks = np.unique(np.linspace(0, len(theta) - 1, min(len(theta), 8)).round().astype(int))
    total = 0.0
    for v in picks:
        c, s = math.cos(theta[v]), math.sin(theta[v])
        x, y, z = corners[..., 0], corners[..., 1], corners[..., 2]
        depth = s * x + c * z + sod
        behind = depth <= 1e-9 * sod
        with np.errstate(divide="ignore", invalid="ignore"):
            xd = (c * x - s * z) / depth * sdd
            yd = y / depth * sdd
        uu = np.where(behind, np.nan, u0_v[v] + (cos_tilt * xd + sin_tilt * yd) / geometry.pixel_pitch_u_mm)
        vv = np.where(behind, np.nan, v0_v[v] + (cos_tilt * yd - sin_tilt * xd) / geometry.pixel_pitch_v_mm)
        inside = ~behind.any(axis=1)
        width = np.zeros(len(corners))
        height = np.zeros(len(corners))
        if inside.any():
            u, w = uu[inside], vv[inside]
            width[inside] = np.clip(np.clip(u.max(1) + 0.5, -1, cols) - np.clip(u.min(1) - 0.5, -1, cols) + 1, 0, cols)
            height[inside] = np.clip(np.clip(w.max(1) + 0.5, -1, rows) - np.clip(w.min(1) - 0.5, -1, rows) + 1, 0, rows)
        across = behind.any(axis=1) & ~behind.all(axis=1)
        total += float(np.sum(width * height)) + float(np.count_nonzero(across)) * rows * cols
    return total * len(theta) / len(picks)


def _turn_invariant(primitives: Primitives) -> np.ndarray:
    """Bool (N,): primitives that every turntable rotation maps onto themselves.

    An ellipsoid or cylinder whose own ``y`` axis is the turntable axis (object ``y``), with equal
    half sizes across it and its centre on the axis: a container, a sample tube, a round holder.
    Tolerances of 1e-9 (relative, and mm for the centre) leave only rounding-level differences.
    """
    axis = primitives.rotation[:, :, 1]  # the object-frame direction of each local y axis
    half = primitives.half_size_mm
    return (np.isin(primitives.kind, (KINDS.index("ellipsoid"), KINDS.index("cylinder")))
            & (np.abs(np.abs(axis[:, 1]) - 1.0) <= 1e-9)
            & (np.abs(half[:, 0] - half[:, 2]) <= 1e-9 * half[:, 0])
            & np.all(np.abs(primitives.centre_mm[:, [0, 2]]) <= 1e-9, axis=1))


def _principal_points(geometry: Geometry, n_views: int, offsets_px) -> tuple[np.ndarray, np.ndarray]:
    """Per-view ``(u0, v0)``, each float64 (V,): the geometry's, plus ``offsets_px`` (V, 2) when given."""
    u0 = np.full(n_views, float(geometry.u0_px))
    v0 = np.full(n_views, float(geometry.v0_px))
    if offsets_px is None:
        return u0, v0
    offsets = np.asarray(offsets_px, dtype=np.float64)
    if offsets.shape != (n_views, 2) or not np.all(np.isfinite(offsets)):
        raise InputError(f"detector_offsets_px: must be finite pixels (du, dv) of shape (len(angles_deg), 2) = "
                         f"{(n_views, 2)}, got shape {offsets.shape}")
    return u0 + offsets[:, 0], v0 + offsets[:, 1]


# --------------------------------------------------------------------------- voxel projector

@njit(parallel=True, fastmath=FASTMATH, cache=True)
def _to_layouts(volume, vol_x, vol_z, vol_y, with_y):
    """Copy ``volume[iy, iz, ix]`` into the padded stepping layouts.

    vol_x : (n_y + 2, n_z + 2, n_x)  rays stepping along x, bilinear in (y, z)
    vol_z : (n_y + 2, n_x + 2, n_z)  rays stepping along z, bilinear in (y, x)
    vol_y : (n_z + 2, n_x + 2, n_y)  rays stepping along y, bilinear in (z, x); only if with_y
    The pads must already be zero.
    """
    n_y, n_z, n_x = volume.shape
    for iy in prange(n_y):
        for iz in range(n_z):
            for ix in range(n_x):
                value = volume[iy, iz, ix]
                vol_x[iy + 1, iz + 1, ix] = value
                vol_z[iy + 1, ix + 1, iz] = value
    if with_y:
        for iz in prange(n_z):
            for ix in range(n_x):
                for iy in range(n_y):
                    vol_y[iz + 1, ix + 1, iy] = volume[iy, iz, ix]


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def _from_layouts(out, buf_x, buf_z, buf_y, with_y):
    """``out[iy, iz, ix]`` = sum over buffers of the interior of every layout (the adjoint of
    :func:`_to_layouts`, summed over the per-thread buffers)."""
    n_y, n_z, n_x = out.shape
    n_buf = buf_x.shape[0]
    for iy in prange(n_y):
        for iz in range(n_z):
            for ix in range(n_x):
                acc = np.float32(0.0)
                for b in range(n_buf):
                    acc += buf_x[b, iy + 1, iz + 1, ix] + buf_z[b, iy + 1, ix + 1, iz]
                    if with_y:
                        acc += buf_y[b, iz + 1, ix + 1, iy]
                out[iy, iz, ix] = acc


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _ray_scatter(vol, value, k0, k1, p0, dp, q0, dq, n_p, n_q):
    for k in range(k0, k1):
        p = p0 + k * dp
        q = q0 + k * dq
        ip = min(max(int(p), 0), n_p)
        iq = min(max(int(q), 0), n_q)
        fp = np.float32(p - ip)
        fq = np.float32(q - iq)
        w_hi = value * fp
        w_lo = value - w_hi
        vol[ip, iq, k] += w_lo - w_lo * fq
        vol[ip, iq + 1, k] += w_lo * fq
        vol[ip + 1, iq, k] += w_hi - w_hi * fq
        vol[ip + 1, iq + 1, k] += w_hi * fq


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def _forward(out, vol_x, vol_z, vol_y, cos_t, sin_t, sod, sdd, pu, pv, u0, v0, origin, voxel, n_x, n_y, n_z):
    """Joseph line integrals of every pixel of every view into ``out`` (V, rows, cols); a view per thread."""
    n_views, n_rows, n_cols = out.shape
    for v in prange(n_views):
        c = cos_t[v]
        s = sin_t[v]
        for row in range(n_rows):
            for col in range(n_cols):
                axis, k0, k1, p0, dp, q0, dq, step, n_p, n_q = _pixel_ray(c, s, sod, sdd, pu, pv, u0, v0, origin,
                                                                          voxel, n_x, n_y, n_z, row, col)
                vol = vol_x if axis == 0 else vol_z if axis == 1 else vol_y
                out[v, row, col] = _ray_sum(vol, k0, k1, p0, dp, q0, dq, n_p, n_q) * np.float32(step)


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def _to_pair_layouts(first, second, vol_x, vol_z, vol_y, with_y):
    """:func:`_to_layouts` of two volumes at once, interleaved on a last axis of 2: a ray's four
    neighbours in both volumes then come in the same cache lines."""
    n_y, n_z, n_x = first.shape
    for iy in prange(n_y):
        for iz in range(n_z):
            for ix in range(n_x):
                a = first[iy, iz, ix]
                b = second[iy, iz, ix]
                vol_x[iy + 1, iz + 1, ix, 0] = a
                vol_x[iy + 1, iz + 1, ix, 1] = b
                vol_z[iy + 1, ix + 1, iz, 0] = a
                vol_z[iy + 1, ix + 1, iz, 1] = b
    if with_y:
        for iz in prange(n_z):
            for ix in range(n_x):
                for iy in range(n_y):
                    vol_y[iz + 1, ix + 1, iy, 0] = first[iy, iz, ix]
                    vol_y[iz + 1, ix + 1, iy, 1] = second[iy, iz, ix]


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def _forward_pair(out_a, out_b, vol_x, vol_z, vol_y, cos_t, sin_t, sod, sdd, pu, pv, u0, v0, origin, voxel, n_x, n_y,
                  n_z):
    """:func:`_forward` of the two volumes of a pair layout into ``out_a`` and ``out_b``."""
    n_views, n_rows, n_cols = out_a.shape
    for v in prange(n_views):
        c = cos_t[v]
        s = sin_t[v]
        for row in range(n_rows):
            for col in range(n_cols):
                axis, k0, k1, p0, dp, q0, dq, step, n_p, n_q = _pixel_ray(c, s, sod, sdd, pu, pv, u0, v0, origin,
                                                                          voxel, n_x, n_y, n_z, row, col)
                vol = vol_x if axis == 0 else vol_z if axis == 1 else vol_y
                total_a, total_b = _ray_sum_pair(vol, k0, k1, p0, dp, q0, dq, n_p, n_q)
                out_a[v, row, col] = total_a * np.float32(step)
                out_b[v, row, col] = total_b * np.float32(step)


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def _back(buf_x, buf_z, buf_y, proj, cos_t, sin_t, sod, sdd, pu, pv, u0, v0, origin, voxel, n_x, n_y, n_z):
    """Scatter every view with the weights of :func:`_forward`; buffer ``b`` takes views b, b + B, ..."""
    n_views, n_rows, n_cols = proj.shape
    n_buf = buf_x.shape[0]
    for b in prange(n_buf):
        bx = buf_x[b]
        bz = buf_z[b]
        by = buf_y[b]
        for v in range(b, n_views, n_buf):
            c = cos_t[v]
            s = sin_t[v]
            for row in range(n_rows):
                for col in range(n_cols):
                    value = proj[v, row, col]
                    if value == 0.0:
                        continue
                    axis, k0, k1, p0, dp, q0, dq, step, n_p, n_q = _pixel_ray(c, s, sod, sdd, pu, pv, u0, v0,
                                                                              origin, voxel, n_x, n_y, n_z, row, col)
                    buf = bx if axis == 0 else bz if axis == 1 else by
                    _ray_scatter(buf, value * np.float32(step), k0, k1, p0, dp, q0, dq, n_p, n_q)


class VoxelProjector:
    """Ray-driven Joseph projector of a voxel volume and its exact adjoint.

    Parameters
    ----------
    geometry : Geometry
        Detector and distances.
    grid : VolumeGrid
        Where the voxels of the volumes sit in the object frame.

    Notes
    -----
    ``forward`` computes ``A x`` and ``back`` computes ``A^T y`` for the same matrix ``A``
    (``<A x, y> = <x, A^T y>`` up to float32 rounding), which is what iterative reconstruction
    needs; ``back`` is not a filtered backprojection (see :func:`ctpipe.recon.feldkamp.fdk`). The forward
    projection runs a view per thread; the back projection scatters into one volume buffer per
    thread (memory: threads x 2 padded volumes). Where :func:`ctpipe.gpu.active` is ``"cuda"``
    both run on the GPU (:mod:`ctpipe.sim._cuda`: a ray per thread, the same ray stepping), with
    the CPU as the fall-back.
    """

    def __init__(self, geometry: Geometry, grid: VolumeGrid) -> None:
        self._geometry = check_geometry(geometry)
        if not isinstance(grid, VolumeGrid):
            raise InputError(f"grid: must be a ctpipe.recon.volume.VolumeGrid, got {type(grid).__name__}")
        self._grid = grid
        g = geometry
        # A ray can advance fastest along y (the rotation axis) only when |dy| > max(|dx|, |dz|),
        # which needs |dy| > SDD / sqrt(2); narrower cones never need the y layout.
        reach_v = max(abs(g.v0_px), abs(g.detector_rows - 1 - g.v0_px)) * g.pixel_pitch_v_mm
        self._with_y = reach_v * math.sqrt(2.0) >= g.source_to_detector_mm

    @property
    def geometry(self) -> Geometry:
        return self._geometry

    @property
    def grid(self) -> VolumeGrid:
        return self._grid

    def _common(self, angles_deg):
        g, grid = self._geometry, self._grid
        theta = np.deg2rad(as_angles_deg(angles_deg))
        return (np.cos(theta), np.sin(theta), float(g.source_to_object_mm), float(g.source_to_detector_mm),
                float(g.pixel_pitch_u_mm), float(g.pixel_pitch_v_mm), float(g.u0_px), float(g.v0_px),
                np.asarray(grid.origin_mm, dtype=np.float64), float(grid.voxel_size_mm), grid.n_x, grid.n_y, grid.n_z)

    def _layout_shapes(self, n_buf: int):
        n_y, n_z, n_x = self._grid.shape
        y_shape = (n_buf, n_z + 2, n_x + 2, n_y) if self._with_y else (n_buf, 1, 1, 1)
        return (n_buf, n_y + 2, n_z + 2, n_x), (n_buf, n_y + 2, n_x + 2, n_z), y_shape

    def forward(self, volume: np.ndarray, angles_deg) -> np.ndarray:
        """Line integrals of ``volume`` in the views at ``angles_deg``.

        Parameters
        ----------
        volume : ndarray of shape grid.shape = (n_y, n_z, n_x), float
            Density in 1/mm, indexed ``volume[iy, iz, ix]``.
        angles_deg : array_like of shape (V,)
            Turntable angles, degrees.

        Returns
        -------
        ndarray of shape (V, detector_rows, detector_cols), float32
            Line integrals (1/mm times mm).
        """
        volume = _check_array("volume", volume, self._grid.shape, "grid.shape (n_y, n_z, n_x)")
        common = self._common(angles_deg)
        shape_x, shape_z, shape_y = self._layout_shapes(1)
        check_fits(f"projecting {common[0].size} views of {self._geometry.detector_rows} x "
                   f"{self._geometry.detector_cols} from a {self._grid.n_x} x {self._grid.n_y} x {self._grid.n_z} volume",
                   4 * (common[0].size * self._geometry.shape[0] * self._geometry.shape[1]
                        + sum(math.prod(shape[1:]) for shape in (shape_x, shape_z, shape_y))),
                   hint="use fewer views, a smaller detector or a smaller grid")
        vol_x = np.zeros(shape_x[1:], dtype=np.float32)
        vol_z = np.zeros(shape_z[1:], dtype=np.float32)
        vol_y = np.zeros(shape_y[1:], dtype=np.float32)
        _to_layouts(volume, vol_x, vol_z, vol_y, self._with_y)
        if device.active() == "cuda":
            from ctpipe.sim import _cuda

            try:
                return _cuda.forward((vol_x, vol_z, vol_y), common[0], common[1], common[2:], self._geometry.shape)
            except Exception as error:  # noqa: BLE001 - memory, driver, compiler: the CPU answers
                device.fall_back("the forward projection", error)
        out = np.empty((common[0].size, *self._geometry.shape), dtype=np.float32)
        # A chunk of views per call, about a second of work each (views are independent: the same
        # numbers as one call), so that Ctrl-C reaches a Python caller between two of them.
        samples_per_view = self._geometry.detector_rows * self._geometry.detector_cols * max(self._grid.shape)
        chunk = max(2 * numba.get_num_threads(), int(_SAMPLES_PER_CALL // samples_per_view))
        for start in range(0, out.shape[0], chunk):
            part = slice(start, start + chunk)
            _forward(out[part], vol_x, vol_z, vol_y, common[0][part], common[1][part], *common[2:])
        return out

    def forward_pair(self, first: np.ndarray, second: np.ndarray, angles_deg, *,
                     chunk_views: int = 32) -> Iterator[tuple[slice, np.ndarray, np.ndarray]]:
        """Line integrals of two volumes along the same rays, a chunk of views at a time.

        One pass for both: each ray's plane range and interpolation weights are computed once
        and both volumes are read from one interleaved layout, built once for all the chunks.
        This is what projection matching needs every iteration (a reconstruction and its
        derivative with respect to the turntable angle), at about 60 % of two :meth:`forward` calls.

        Parameters
        ----------
        first, second : ndarray of shape grid.shape = (n_y, n_z, n_x), float
        angles_deg : array_like of shape (V,)
            Turntable angles, degrees.
        chunk_views : int
            Views per chunk: memory is the pair layout plus two chunks of views.

        Yields
        ------
        views : slice
            The chunk's views (indices into ``angles_deg``).
        projected_first, projected_second : ndarray of shape (chunk, detector_rows, detector_cols), float32
            The same as ``forward(first, angles_deg[views])`` and ``forward(second, angles_deg[views])``.
        """
        first = _check_array("first", first, self._grid.shape, "grid.shape (n_y, n_z, n_x)")
        second = _check_array("second", second, self._grid.shape, "grid.shape (n_y, n_z, n_x)")
        chunk_views = _check_int("chunk_views", chunk_views, 1)
        common = self._common(angles_deg)
        shape_x, shape_z, shape_y = (shape[1:] + (2,) for shape in self._layout_shapes(1))
        n_chunk = min(chunk_views, common[0].size)
        check_fits(f"projecting two {self._grid.n_x} x {self._grid.n_y} x {self._grid.n_z} volumes into "
                   f"{self._geometry.detector_rows} x {self._geometry.detector_cols} views",
                   4 * (2 * n_chunk * self._geometry.shape[0] * self._geometry.shape[1]
                        + sum(math.prod(shape) for shape in (shape_x, shape_z, shape_y))),
                   hint="use a smaller grid")
        vol_x = np.zeros(shape_x, dtype=np.float32)
        vol_z = np.zeros(shape_z, dtype=np.float32)
        vol_y = np.zeros(shape_y, dtype=np.float32)
        _to_pair_layouts(first, second, vol_x, vol_z, vol_y, self._with_y)
        if device.active() == "cuda":
            from ctpipe.sim import _cuda

            try:
                # The layouts go to the GPU and the first chunk is projected here, so that a GPU that
                # refuses the work hands it to the CPU now; the other chunks as they are asked for.
                chunks = _cuda.forward_pair((vol_x, vol_z, vol_y), common[0], common[1], common[2:],
                                             self._geometry.shape, n_chunk)
                first_chunk = next(chunks, None)
                return itertools.chain(() if first_chunk is None else (first_chunk,), chunks)
            except Exception as error:  # noqa: BLE001 - memory, driver, compiler: the CPU answers
                device.fall_back("the paired forward projection", error)
        # Checked and laid out now, projected as the chunks are asked for.
        return self._pair_chunks((vol_x, vol_z, vol_y), common, n_chunk)

    def _pair_chunks(self, layouts, common, n_chunk: int) -> Iterator[tuple[slice, np.ndarray, np.ndarray]]:
        cos_t, sin_t, rest = common[0], common[1], common[2:]
        for start in range(0, cos_t.size, n_chunk):
            views = slice(start, min(start + n_chunk, cos_t.size))
            out_a = np.empty((views.stop - start, *self._geometry.shape), dtype=np.float32)
            out_b = np.empty_like(out_a)
            _forward_pair(out_a, out_b, *layouts, cos_t[views], sin_t[views], *rest)
            yield views, out_a, out_b

    def back(self, projections: np.ndarray, angles_deg) -> np.ndarray:
        """The adjoint of :meth:`forward`: scatter every line integral back along its ray.

        Parameters
        ----------
        projections : ndarray of shape (V, detector_rows, detector_cols), float
        angles_deg : array_like of shape (V,)
            Turntable angles, degrees.

        Returns
        -------
        ndarray of shape grid.shape = (n_y, n_z, n_x), float32
            ``A^T projections``, in mm times the projection unit.
        """
        common = self._common(angles_deg)
        expected = (common[0].size, *self._geometry.shape)
        projections = _check_array("projections", projections, expected,
                                   "(len(angles_deg), detector_rows, detector_cols)")
        if device.active() == "cuda":
            from ctpipe.sim import _cuda

            try:
                buffers = _cuda.back(projections, [shape[1:] for shape in self._layout_shapes(1)], common[0],
                                      common[1], common[2:])
                out = np.empty(self._grid.shape, dtype=np.float32)
                _from_layouts(out, *(buffer[None] for buffer in buffers), self._with_y)
                return out
            except Exception as error:  # noqa: BLE001 - memory, driver, compiler: the CPU answers
                device.fall_back("the back projection", error)
        n_buf = max(1, min(numba.get_num_threads(), expected[0]))
        shape_x, shape_z, shape_y = self._layout_shapes(n_buf)
        check_fits(f"back-projecting onto a {self._grid.n_x} x {self._grid.n_y} x {self._grid.n_z} volume "
                   f"({n_buf} thread buffers)",
                   4 * (math.prod(self._grid.shape) + sum(math.prod(shape) for shape in (shape_x, shape_z, shape_y))),
                   hint="use a smaller grid")
        buf_x = np.zeros(shape_x, dtype=np.float32)
        buf_z = np.zeros(shape_z, dtype=np.float32)
        buf_y = np.zeros(shape_y, dtype=np.float32)
        _back(buf_x, buf_z, buf_y, projections, *common)
        out = np.empty(self._grid.shape, dtype=np.float32)
        _from_layouts(out, buf_x, buf_z, buf_y, self._with_y)
        return out
