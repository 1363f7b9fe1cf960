"""Feldkamp-Davis-Kress (FDK) reconstruction of a circular cone-beam scan with arbitrary angles.

Geometry
--------
The frames of :mod:`ctpipe.geometry` and :mod:`ctpipe.recon.volume`: an object point ``X`` is, in the
view at turntable angle ``theta``, at ``X_cam = R(theta) X + (0, 0, SOD)`` with ``R`` of
:func:`ctpipe.model.rotation_matrix`. The camera point ``(X, Y, Z)`` hits the detector pixel::

    col = u0_px + (X / Z) * SDD / pixel_pitch_u_mm
    row = v0_px + (Y / Z) * SDD / pixel_pitch_v_mm

Algorithm (Kak & Slaney, ch. 3.6)
---------------------------------
With ``p = (col - u0_px) * pitch_u * SOD / SDD`` and ``zeta`` the same along rows (coordinates on
a virtual detector through the rotation axis)::

    Q_k   = (w_k(p) * P_k(p, zeta) * SOD / sqrt(SOD^2 + p^2 + zeta^2))  *_p  ramp(p)
    f(X)  = sum_k  dbeta_k * (SOD / Z_k(X))^2 * Q_k(col_k(X), row_k(X))

``Z_k(X)`` is the depth of ``X`` in view ``k`` (its distance from the source along the central
ray), ``dbeta_k`` the angular interval the view stands for, and ``w_k`` the redundancy weight:
``1/2`` for a full scan (every ray is measured twice), Parker's weights for a short scan.
Projections are line integrals (density in 1/mm times mm), so ``f`` comes out in 1/mm.

The backprojection is voxel-driven: for a fixed ``(x, z)`` column of voxels and a view, the
detector column and the magnification are constant and the detector row is linear in ``y`` (the
rotation axis), so the inner loop over ``y`` is a linear walk down one pair of columns of the
filtered projection, stored transposed ``(views, cols, rows)`` to make that walk contiguous.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import numpy as np
from numba import prange
from scipy import fft as sp_fft

from ctpipe._shared import device
from ctpipe._shared.arrays import all_finite, percentile_in_place
from ctpipe._shared.checks import as_angles_deg, short_repr
from ctpipe._shared.jit import FASTMATH, njit
from ctpipe._shared.resources import available_cores, check_fits, memory_guard
from ctpipe.errors import InputError
from ctpipe.geometry import Geometry, check_geometry
from ctpipe.recon.volume import VolumeGrid

__all__ = ["FILTERS", "TRUNCATION", "fdk", "is_truncated", "view_weights", "parker_weights", "ramp_filter",
           "covers_full_circle", "short_scan_minimum_deg", "bin_detector", "binned_geometry"]

#: Apodisation windows of the ramp filter, from sharpest to smoothest.
FILTERS = ("ram-lak", "shepp-logan", "cosine", "hamming", "hann")

# Views filtered and backprojected per step: bounds the filtered buffer and paces ``progress``.
_CHUNK_VIEWS = 32


def _window(name: str, freq: np.ndarray) -> np.ndarray:
    """Window over normalised frequency ``freq`` in [0, 0.5] (cycles per pixel)."""
    if name == "ram-lak":
        return np.ones_like(freq)
    if name == "shepp-logan":
        return np.sinc(freq)
    if name == "cosine":
        return np.cos(np.pi * freq)
    if name == "hamming":
        return 0.54 + 0.46 * np.cos(2.0 * np.pi * freq)
    if name == "hann":
        return 0.5 + 0.5 * np.cos(2.0 * np.pi * freq)
    raise InputError(f"filter: {name!r} is not supported. Try one of {FILTERS}")


def ramp_filter(n_cols: int, filter: str = "hann") -> tuple[int, np.ndarray]:
    """Frequency response of the windowed discrete ramp filter for unit sample spacing.

    The exact band-limited ramp kernel is sampled in the spatial domain (``h[0] = 1/4``,
    ``h[n] = -1/(pi n)^2`` for odd ``n``, 0 for even ``n``) and Fourier transformed, which avoids
    the DC offset and the wrap-around of sampling ``|omega|`` directly (Kak & Slaney eq. 3.61).

    Parameters
    ----------
    n_cols : int
        Samples per detector row; rows are zero-padded to the next power of two >= 2 n_cols.
    filter : str
        One of :data:`FILTERS`.

    Returns
    -------
    n_pad : int
        Padded row length.
    response : ndarray of shape (n_pad // 2 + 1,), float64
        Real response for :func:`scipy.fft.rfft` of a padded row; divide the filtered row by the
        sample spacing in mm to get 1/mm.
    """
    n_pad = 1 << max(1, int(math.ceil(math.log2(2 * n_cols))))
    n = np.arange(n_pad)
    n = np.where(n <= n_pad // 2, n, n - n_pad)  # circular index: 0, 1, ..., -2, -1
    kernel = np.zeros(n_pad)
    kernel[n == 0] = 0.25
    odd = n % 2 == 1
    kernel[odd] = -1.0 / (np.pi * n[odd]) ** 2
    response = np.real(sp_fft.rfft(kernel))
    freq = np.arange(n_pad // 2 + 1) / n_pad
    return n_pad, response * _window(filter, freq)


def _fan_angles(geometry: Geometry) -> np.ndarray:
    """In-plane fan angle of every detector column, radians, shape (cols,).

    Positive along +x (increasing column), which is the sense in which a ray's direction turns
    with ``theta``: the ray (theta, gamma) has object-frame direction angle ``theta + gamma``.
    """
    cols = np.arange(geometry.detector_cols)
    return np.arctan((cols - geometry.u0_px) * geometry.pixel_pitch_u_mm / geometry.source_to_detector_mm)


def short_scan_minimum_deg(geometry: Geometry) -> float:
    """The least angular range (degrees) a Parker-weighted short scan with ``geometry`` needs: 180 + fan angle.

    The fan angle is twice the largest in-plane angle of a detector column from the central
    ray (columns measured from ``u0_px``, so an off-centre detector has the wider side's fan).
    """
    return 180.0 + 2.0 * math.degrees(float(np.max(np.abs(_fan_angles(geometry)))))


def covers_full_circle(angles_deg) -> bool:
    """True when :func:`fdk` with ``short_scan=None`` treats these angles as a full scan.

    See :func:`_covers_full_circle`: no circular gap wider than five typical steps.
    """
    return _covers_full_circle(np.deg2rad(np.asarray(angles_deg, dtype=np.float64)))


def _full_scan_step(theta_sorted: np.ndarray) -> float:
    gaps = np.diff(theta_sorted)
    return float(np.median(gaps)) if gaps.size else 2.0 * np.pi


def _covers_full_circle(angles_rad: np.ndarray) -> bool:
    """True when the views go all the way round: no circular gap wider than a few typical steps.

    The span ``max - min`` alone misleads on real and jittered scans: a full turn whose stage
    lost 2 deg to backlash spans 358 deg, yet leaves no wedge out, and Parker-weighting it as a
    short scan would throw away most of its data. The typical step is the mean of the other
    gaps (the covered range over its steps), and a gap under 2 deg never counts as a wedge: on a
    dense scan with jitter comparable to its step (1,440 views 0.25 deg apart, 0.2 deg jitter)
    sorting leaves many tiny gaps and a few of 1-1.2 deg, which against the median gap passed
    for a missing wedge.
    """
    wrapped = np.sort(np.mod(np.asarray(angles_rad, dtype=np.float64), 2.0 * np.pi))
    if wrapped.size < 3:
        return False
    gaps = np.diff(np.concatenate([wrapped, [wrapped[0] + 2.0 * np.pi]]))
    widest = float(gaps.max())
    typical = (float(gaps.sum()) - widest) / (gaps.size - 1)
    return widest <= max(5.0 * typical, math.radians(2.0))


def view_weights(angles_rad: np.ndarray, *, full_scan: bool) -> np.ndarray:
    """Angular interval each view stands for, radians, shape (V,).

    Half the gap to each neighbour in angle order, so irregular and unsorted angles integrate
    correctly. A full scan wraps around (angles taken modulo 2 pi, the intervals add up to
    2 pi); a short scan is the trapezoid rule over ``[min, max]``. For a partial range that is
    not Parker-weighted, the open end gets half the median step instead of the missing wedge.
    """
    theta = np.asarray(angles_rad, dtype=np.float64)
    n = theta.size
    if n == 1:
        return np.array([2.0 * np.pi if full_scan else 1.0])
    if full_scan:
        wrapped = np.mod(theta, 2.0 * np.pi)
        order = np.argsort(wrapped, kind="stable")
        s = wrapped[order]
        gaps = np.diff(np.concatenate([s, [s[0] + 2.0 * np.pi]]))  # gaps[i]: from s[i] to s[i+1]
        interval = 0.5 * (gaps + np.roll(gaps, 1))
    else:
        order = np.argsort(theta, kind="stable")
        s = theta[order]
        gaps = np.diff(s)
        interval = np.empty(n)
        interval[1:-1] = 0.5 * (gaps[1:] + gaps[:-1])
        interval[0] = 0.5 * gaps[0]
        interval[-1] = 0.5 * gaps[-1]
    out = np.empty(n)
    out[order] = interval
    return out


def parker_weights(beta_rad: np.ndarray, gamma_rad: np.ndarray, half_range_excess_rad: float) -> np.ndarray:
    """Parker's short-scan redundancy weights, shape (V, cols).

    Parameters
    ----------
    beta_rad : ndarray of shape (V,)
        View angle minus the first angle of the scan, in [0, pi + 2 delta].
    gamma_rad : ndarray of shape (cols,)
        Fan angle of each column (see :func:`_fan_angles`).
    half_range_excess_rad : float
        ``delta = (range - pi) / 2``; must be >= max |gamma|. Using the scan's own ``delta``
        rather than the half fan angle is the generalised ("overscan") form: the weights of the
        two measurements of a ray, ``(beta, gamma)`` and ``(beta + pi + 2 gamma, -gamma)``, still
        add up to 1.
    """
    delta = half_range_excess_rad
    b = np.asarray(beta_rad, dtype=np.float64)[:, None]
    g = np.asarray(gamma_rad, dtype=np.float64)[None, :]
    w = np.ones((b.shape[0], g.shape[1]))
    rise = b < 2.0 * (delta - g)
    fall = b > np.pi - 2.0 * g
    with np.errstate(divide="ignore", invalid="ignore"):
        w_rise = np.sin(np.pi / 4.0 * b / (delta - g)) ** 2
        w_fall = np.sin(np.pi / 4.0 * (np.pi + 2.0 * delta - b) / (delta + g)) ** 2
    w = np.where(rise, w_rise, w)
    w = np.where(fall, w_fall, w)
    w = np.where((b < 0) | (b > np.pi + 2.0 * delta), 0.0, w)
    return np.nan_to_num(w, nan=0.0)


def _validate(projections, geometry, angles_deg, grid, filter, short_scan, progress):
    check_geometry(geometry)
    if not isinstance(grid, VolumeGrid):
        raise InputError(f"grid: must be a ctpipe.recon.volume.VolumeGrid, got {type(grid).__name__}")
    if not isinstance(filter, str) or filter not in FILTERS:
        raise InputError(f"filter: {filter!r} is not supported. Try one of {FILTERS}")
    if short_scan not in (None, True, False):
        raise InputError(f"short_scan: must be None (decide from the angles), True or False, got {short_scan!r}")
    if progress is not None and not callable(progress):
        raise InputError(f"progress: must be a callable taking a number of views, or None, got {progress!r}")
    angles = as_angles_deg(angles_deg)
    proj = np.asarray(projections)
    if proj.ndim != 3 or not np.issubdtype(proj.dtype, np.floating):
        raise InputError(f"projections: must be a 3-D float array (views, rows, cols), got shape {proj.shape} "
                         f"and dtype {proj.dtype}")
    expected = (angles.size, geometry.detector_rows, geometry.detector_cols)
    if proj.shape != expected:
        raise InputError(f"projections: must have shape (len(angles_deg), detector_rows, detector_cols) = {expected}, "
                         f"got {proj.shape}")
    if not all_finite(proj):
        raise InputError("projections: contain NaN or infinite values")
    return proj, angles


def _scan_weights(angles_rad: np.ndarray, geometry: Geometry, short_scan: bool | None):
    """Per-view intervals (V,) and per-(view, column) redundancy weights (V, cols) or None."""
    gamma = _fan_angles(geometry)
    minimum_deg = short_scan_minimum_deg(geometry)
    order = np.sort(angles_rad)
    span = float(order[-1] - order[0])
    step = _full_scan_step(order)
    is_full = _covers_full_circle(angles_rad)
    use_parker = (not is_full) if short_scan is None else bool(short_scan)
    if not use_parker:
        intervals = view_weights(angles_rad, full_scan=True)
        if not is_full:
            # Limited-angle scan reconstructed as asked: no wrap-around across the missing wedge.
            intervals = view_weights(angles_rad, full_scan=False)
            ends = np.argsort(angles_rad, kind="stable")[[0, -1]]
            intervals[ends] += 0.5 * step
        return 0.5 * intervals, None
    if span >= 2.0 * np.pi:
        raise InputError(f"short_scan: True needs an angular range < 360 deg, got {math.degrees(span):.2f} deg")
    if math.degrees(span) < minimum_deg - 1e-6:
        raise InputError(
            f"angles_deg: a short scan needs an angular range of at least {minimum_deg:.2f} deg "
            f"(180 + fan angle {minimum_deg - 180.0:.2f} deg), got {math.degrees(span):.2f} deg; "
            "pass short_scan=False to reconstruct a limited-angle scan without Parker weights")
    delta = max(0.5 * (span - np.pi), float(np.max(np.abs(gamma))))
    redundancy = parker_weights(angles_rad - order[0], gamma, delta)
    return view_weights(angles_rad, full_scan=False), redundancy


# Voxel columns per tile edge: a 16 x 16 tile of (x, z) columns keeps its accumulator (16 x 16 x n_y
# floats) and the few detector columns one view projects it to in L2 while all views go by.
_TILE = 16


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def _backproject(acc, proj_t, cos_t, sin_t, weight, xs, zs, y0, dy, sod, su, sv, u0, v0):
    """Add the views of ``proj_t`` to ``acc``.

    acc : (n_x, n_z, n_y) float32, accumulated in place (y contiguous).
    proj_t : (V, cols + 2, rows + 2) float32 filtered views, transposed, one zero pixel of
        padding on every side so that bilinear reads fade to zero past the detector edges.
    u0, v0 : principal point in padded pixel coordinates.

    The inner loop is written so that LLVM vectorises it with gathers: whole-array indexing (a
    view such as ``proj_t[k, ui]`` counts as an alias and disables numba's noalias flag), loop
    bounds in closed form (a ``while`` that adjusts them blocks vectorisation) and a loop counter
    that starts at 0.
    """
    n_x, n_z, n_y = acc.shape
    n_views, n_u, n_v = proj_t.shape
    u_hi = n_u - 1.0
    # Stop a hair before the last padded row so that float32 rounding of v cannot read past it.
    v_hi = n_v - 1.0 - 1e-3
    tiles_z = (n_z + _TILE - 1) // _TILE
    n_tiles = ((n_x + _TILE - 1) // _TILE) * tiles_z
    for tile in prange(n_tiles):
        x_lo = (tile // tiles_z) * _TILE
        z_lo = (tile % tiles_z) * _TILE
        for k in range(n_views):
            c = cos_t[k]
            s = sin_t[k]
            w = weight[k]
            for ix in range(x_lo, min(x_lo + _TILE, n_x)):
                x = xs[ix]
                for iz in range(z_lo, min(z_lo + _TILE, n_z)):
                    z = zs[iz]
                    depth = s * x + c * z + sod
                    if depth <= 0.0:
                        continue
                    inv = 1.0 / depth
                    u = u0 + (c * x - s * z) * inv * su
                    if u < 0.0 or u >= u_hi:
                        continue
                    ui = int(u)
                    fu = u - ui
                    # The distance weight (SOD / depth)^2 of FDK, with the view's own interval.
                    wd = w * sod * sod * inv * inv
                    dv = dy * inv * sv
                    v_start = v0 + y0 * inv * sv
                    # Rows with 0 <= v < v_hi; v may come out a rounding error below 0, which
                    # truncates to row 0 (a zero pad) and is harmless.
                    lo = max(0, int(math.ceil(-v_start / dv)))
                    hi = min(n_y, int(math.ceil((v_hi - v_start) / dv)))
                    a0 = np.float32(wd * (1.0 - fu))
                    a1 = np.float32(wd * fu)
                    vs = np.float32(v_start)
                    dvf = np.float32(dv)
                    for t in range(hi - lo):
                        iy = lo + t
                        v = vs + np.float32(iy) * dvf
                        vi = np.int32(v)
                        fv = v - np.float32(vi)
                        p00 = proj_t[k, ui, vi]
                        p01 = proj_t[k, ui, vi + 1]
                        p10 = proj_t[k, ui + 1, vi]
                        p11 = proj_t[k, ui + 1, vi + 1]
                        acc[ix, iz, iy] += a0 * (p00 + fv * (p01 - p00)) + a1 * (p10 + fv * (p11 - p10))


@njit(parallel=True, cache=True)
def _to_volume_layout(acc):
    """(n_x, n_z, n_y) accumulator -> (n_y, n_z, n_x) volume, in parallel."""
    n_x, n_z, n_y = acc.shape
    out = np.empty((n_y, n_z, n_x), dtype=np.float32)
    for iy in prange(n_y):
        for iz in range(n_z):
            for ix in range(n_x):
                out[iy, iz, ix] = acc[ix, iz, iy]
    return out


#: Ways :func:`fdk` fills a detector row beyond its ends before the ramp filter.
TRUNCATION = ("auto", "zero", "extend")
#: ``truncation="auto"`` extends rows when the median view's edge columns carry more than this
#: share of the scan's (99th-percentile) line integral: the object is wider than the detector.
TRUNCATED_EDGE_FRACTION = 0.02
#: Edge columns averaged for the value a row is extended from (one column is too noisy).
_EDGE_COLUMNS = 3


def is_truncated(projections: np.ndarray) -> bool:
    """Whether the object reaches past the detector's left or right edge (a region-of-interest scan).

    Compares, view by view, the mean line integral of the outermost columns with the scan's
    99th percentile; the median view decides, so a few views that graze an edge do not. Both
    are taken on at most 64 views; the percentile on at most 128 of their rows (a 1024-view
    1024^2 scan's whole 64 views took 1.2 s, a quarter of its FDK on a GPU).
    """
    proj = np.asarray(projections)
    step = max(1, len(proj) // 64)
    views = proj[::step]
    left = np.abs(views[:, :, :_EDGE_COLUMNS], dtype=np.float32).mean(axis=(1, 2))
    right = np.abs(views[:, :, -_EDGE_COLUMNS:], dtype=np.float32).mean(axis=(1, 2))
    edges = np.maximum(left, right)
    peak = percentile_in_place(np.abs(views[:, :: max(1, proj.shape[1] // 128)], dtype=np.float32), 99)
    if not np.isfinite(peak) or peak <= 0:
        return False
    return bool(np.median(edges) > TRUNCATED_EDGE_FRACTION * peak)


def _extended_rows(weighted: np.ndarray, n_pad: int) -> np.ndarray:
    """Rows of ``weighted`` in ``n_pad`` samples, each end continued by a cos^2 roll-off to zero.

    Zero padding cuts a truncated row off at the detector edge, and the ramp filter turns that
    step into a bright rim and a cupped interior; continuing the row from its edge values
    (averaged over a few columns) smoothly to zero over half the padding on either side (the
    left half wraps round, as the padding is circular) keeps the step out of the filter.
    """
    n_cols = weighted.shape[-1]
    fall, rise = _roll_offs(n_cols, n_pad)
    out = np.zeros((*weighted.shape[:-1], n_pad), dtype=np.float32)
    out[..., :n_cols] = weighted
    right = weighted[..., -_EDGE_COLUMNS:].mean(axis=-1, keepdims=True)
    left = weighted[..., :_EDGE_COLUMNS].mean(axis=-1, keepdims=True)
    out[..., n_cols:n_cols + fall.size] = right * fall
    out[..., n_cols + fall.size:] = left * rise
    return out


def _roll_offs(n_cols: int, n_pad: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_extended_rows`' cos^2 fall after the right edge and rise before the left one (float32)."""
    n_tail = n_pad - n_cols
    right_len = n_tail // 2
    left_len = n_tail - right_len
    fall = np.cos(0.5 * np.pi * (np.arange(right_len) + 0.5) / right_len) ** 2
    rise = np.cos(0.5 * np.pi * (np.arange(left_len)[::-1] + 0.5) / left_len) ** 2
    return fall.astype(np.float32), rise.astype(np.float32)


def _filter_views(views: np.ndarray, pre_weight: np.ndarray, n_pad: int, response: np.ndarray,
                  scale: float, extend: bool = False) -> np.ndarray:
    """Weighted, ramp-filtered views, transposed and zero-padded: (V, cols + 2, rows + 2) float32."""
    n_views, n_rows, n_cols = views.shape
    weighted = views.astype(np.float32) * pre_weight
    if extend:
        weighted = _extended_rows(weighted, n_pad)
    spectrum = sp_fft.rfft(weighted, n=n_pad, axis=-1, workers=-1)
    spectrum *= (response * scale).astype(np.float32)
    filtered = sp_fft.irfft(spectrum, n=n_pad, axis=-1, workers=-1)[..., :n_cols]
    out = np.zeros((n_views, n_cols + 2, n_rows + 2), dtype=np.float32)
    out[:, 1:-1, 1:-1] = filtered.transpose(0, 2, 1)
    return out


def fdk(
    projections: np.ndarray,
    geometry: Geometry,
    angles_deg,
    grid: VolumeGrid,
    *,
    filter: str = "hann",
    short_scan: bool | None = None,
    truncation: str = "auto",
    progress: Callable[[int], object] | None = None,
) -> np.ndarray:
    """Reconstruct a volume from cone-beam projections taken at arbitrary turntable angles.

    Parameters
    ----------
    projections : ndarray of shape (V, rows, cols), float
        Line integrals (attenuation in 1/mm times path length in mm), one view per angle, rows
        and cols as in ``geometry``.
    geometry : Geometry
        Source, detector and principal point; ``u0_px``/``v0_px`` may be off the centre.
    angles_deg : array_like of shape (V,)
        Turntable angle of every view in degrees, in the sign convention of
        :mod:`ctpipe.model`. Need not be sorted nor uniform: each view is weighted by half the gap
        to each neighbour in angle.
    grid : VolumeGrid
        Where to reconstruct (object frame of :mod:`ctpipe.recon.volume`).
    filter : str
        Window of the ramp filter, one of :data:`FILTERS`; ``"hann"`` trades resolution for noise.
    short_scan : bool or None
        Parker-weight a short scan. ``None`` decides from the angles: a scan whose views leave a
        circular gap wider than five typical steps is a short scan, and must span at least 180 deg
        plus the fan angle.
        ``False`` on a short range reconstructs it as a limited-angle scan without Parker weights.
    truncation : {"auto", "zero", "extend"}
        What the ramp filter sees beyond the detector's left and right edges. ``"zero"``: zeros,
        right when the object fits in the field of view. ``"extend"``: each row continued from
        its edge values by a smooth roll-off to zero, for region-of-interest scans (an object
        wider than the field of view, the rule in micro-CT), where zeros leave a bright rim and a
        cupped interior. ``"auto"`` extends when :func:`is_truncated` finds the object reaching
        an edge, so scans that fit are reconstructed exactly as with ``"zero"``.
    progress : callable, optional
        Called as ``progress(n)`` after every ``n`` views backprojected (e.g. ``tqdm.update``).

    Returns
    -------
    ndarray of shape grid.shape = (n_y, n_z, n_x), float32
        Attenuation in 1/mm, indexed ``volume[iy, iz, ix]``.

    Raises
    ------
    InputError
        Projections not 3-D float, not of shape (V, rows, cols), or not finite; angles not 1-D
        finite; an unknown filter; a short scan shorter than 180 deg plus the fan angle.
    ctpipe._shared.resources.ResourceError
        The volume cannot fit in the memory available (checked before it is allocated).

    Notes
    -----
    Where :func:`ctpipe.gpu.active` is ``"cuda"`` the weighting, filtering and backprojection
    run on the GPU (:mod:`ctpipe.recon._cuda`), the same to float32 rounding, with the CPU as
    the fall-back.
    """
    proj, angles = _validate(projections, geometry, angles_deg, grid, filter, short_scan, progress)
    if truncation not in TRUNCATION:
        raise InputError(f"truncation: must be one of {', '.join(TRUNCATION)}, got {short_repr(truncation)}")
    what, n_bytes = _fdk_size(grid, geometry, len(angles))
    check_fits(what, n_bytes, hint="use a smaller grid")
    with memory_guard(what, n_bytes, hint="use a smaller grid"):
        extend = truncation == "extend" or (truncation == "auto" and is_truncated(proj))
        return _fdk(proj, angles, geometry, grid, filter, short_scan, progress, extend)


def _fdk_size(grid: VolumeGrid, geometry: Geometry, n_views: int) -> tuple[str, int]:
    """FDK's peak memory in words and bytes: the accumulator, its transposed copy, a chunk of filtered views."""
    rows, cols = geometry.shape
    chunk = min(n_views, _CHUNK_VIEWS) * (cols + 2) * (rows + 2) * 4
    n_bytes = 2 * grid.n_x * grid.n_y * grid.n_z * 4 + 3 * chunk
    return f"reconstructing a {grid.n_x} x {grid.n_y} x {grid.n_z} volume with FDK", n_bytes


def _weights_and_filter(geometry: Geometry, filter: str):
    """What both devices' FDK precompute: Feldkamp's cosine weight (rows, cols, float32), the padded
    row length, the ramp filter's response and its scale to 1/mm, and the backprojection's
    constants ``(sod, su, sv, u0, v0)`` (principal point padded)."""
    sod = geometry.source_to_object_mm
    sdd = geometry.source_to_detector_mm
    pu, pv = geometry.pixel_pitch_u_mm, geometry.pixel_pitch_v_mm
    rows, cols = geometry.shape
    u_mm = (np.arange(cols) - geometry.u0_px) * pu
    v_mm = (np.arange(rows) - geometry.v0_px) * pv
    # Feldkamp's cosine weight: the obliquity of each ray, same on the real and the virtual detector.
    cosine = (sdd / np.sqrt(sdd**2 + u_mm[None, :] ** 2 + v_mm[:, None] ** 2)).astype(np.float32)
    n_pad, response = ramp_filter(cols, filter)
    # The kernel is for unit spacing; the samples are pu * SOD / SDD apart on the virtual detector.
    scale = 1.0 / (pu * sod / sdd)
    constants = (sod, sdd / pu, sdd / pv, geometry.u0_px + 1.0, geometry.v0_px + 1.0)
    return cosine, n_pad, response, scale, constants


def _gpu_accumulator(geometry: Geometry, grid: VolumeGrid, filter: str, extend: bool):
    """:class:`ctpipe.recon._cuda.FdkAccumulator` for this geometry and grid, chunks of :data:`_CHUNK_VIEWS` views."""
    from ctpipe.recon._cuda import FdkAccumulator

    cosine, n_pad, response, scale, constants = _weights_and_filter(geometry, filter)
    # The GPU filters too: the same FFT, or for very long rows the same circular convolution.
    return FdkAccumulator((grid.n_x, grid.n_z, grid.n_y), grid.axis_mm("x"), grid.axis_mm("z"),
                          float(grid.axis_mm("y")[0]), grid.voxel_size_mm, constants,
                          (response * scale).astype(np.float32), n_pad, cosine, _CHUNK_VIEWS,
                          _roll_offs(geometry.detector_cols, n_pad) if extend else None, _EDGE_COLUMNS)


def _fdk(proj, angles, geometry: Geometry, grid: VolumeGrid, filter: str, short_scan, progress,
         extend: bool = False) -> np.ndarray:
    theta = np.deg2rad(angles)
    intervals, redundancy = _scan_weights(theta, geometry, short_scan)

    def backproject_all(add) -> None:
        """``add(part)`` for every chunk of views, in order, saying how far it got."""
        for start in range(0, theta.size, _CHUNK_VIEWS):
            part = slice(start, min(start + _CHUNK_VIEWS, theta.size))
            add(part)
            if progress is not None:
                progress(part.stop - part.start)

    if device.active() == "cuda":
        try:
            on_gpu = _gpu_accumulator(geometry, grid, filter, extend)
            backproject_all(lambda part: on_gpu.add(proj[part], None if redundancy is None else redundancy[part],
                                                    np.cos(theta[part]), np.sin(theta[part]), intervals[part]))
            return on_gpu.result()
        except Exception as error:  # noqa: BLE001 - memory, driver, compiler: the CPU answers
            device.fall_back("FDK", error)
    cosine, n_pad, response, scale, constants = _weights_and_filter(geometry, filter)
    xs = grid.axis_mm("x")
    zs = grid.axis_mm("z")
    y0 = float(grid.axis_mm("y")[0])
    acc = np.zeros((grid.n_x, grid.n_z, grid.n_y), dtype=np.float32)

    def add(part: slice) -> None:
        pre = cosine[None, :, :]
        if redundancy is not None:
            pre = pre * redundancy[part, None, :].astype(np.float32)
        _backproject(acc, _filter_views(proj[part], pre, n_pad, response, scale, extend), np.cos(theta[part]),
                     np.sin(theta[part]), intervals[part], xs, zs, y0, grid.voxel_size_mm, *constants)

    backproject_all(add)
    return _to_volume_layout(acc)


def bin_detector(projections: np.ndarray, geometry: Geometry, factor: int) -> tuple[np.ndarray, Geometry]:
    """Average ``factor x factor`` pixel blocks; the geometry keeps describing the same rays.

    Binned pixel ``k`` covers pixels ``factor k .. factor k + factor - 1``, centred at
    ``factor k + (factor - 1) / 2``, so the principal point maps to ``(u0 - (factor - 1) / 2) / factor``.
    Rows and columns beyond the last whole block are dropped (the principal point is unaffected).

    Parameters
    ----------
    projections : ndarray of shape (V, rows, cols)
    geometry : Geometry
    factor : int
        Block edge in pixels, >= 1.

    Returns
    -------
    binned : ndarray of shape (V, rows // factor, cols // factor), float32
    geometry : Geometry
    """
    if not (isinstance(factor, (int, np.integer)) and not isinstance(factor, bool) and factor >= 1):
        raise InputError(f"factor: must be an integer >= 1, got {factor!r}")
    if factor == 1:
        return projections, geometry
    v, rows, cols = projections.shape
    if rows < factor or cols < factor:
        raise InputError(f"factor: binning {factor} x {factor} needs a detector of at least that size, got {rows} x {cols}")
    blocks = projections[:, : rows - rows % factor, : cols - cols % factor].reshape(
        v, rows // factor, factor, cols // factor, factor)
    binned = np.empty((v, rows // factor, cols // factor), dtype=np.float32)

    def chunk(start: int) -> None:
        part = slice(start, start + _CHUNK_VIEWS)
        binned[part] = blocks[part].mean(axis=(2, 4), dtype=np.float32)

    starts = range(0, v, _CHUNK_VIEWS)
    if len(starts) == 1:
        chunk(0)   # one view at a time (the refiner's and the preview's streaming reads): no pool to start
    else:
        # Chunks of views in threads (NumPy's reductions let go of the GIL): the same numbers.
        with ThreadPoolExecutor(max_workers=available_cores()) as pool:
            list(pool.map(chunk, starts))
    return binned, binned_geometry(geometry, factor)


def binned_geometry(geometry: Geometry, factor: int) -> Geometry:
    """The geometry of :func:`bin_detector`'s output: same rays, ``factor`` times coarser pixels."""
    if factor == 1:
        return geometry
    shift = (factor - 1) / 2.0
    return Geometry(geometry.source_to_object_mm, geometry.source_to_detector_mm, geometry.detector_cols // factor,
                    geometry.detector_rows // factor, geometry.pixel_pitch_u_mm * factor,
                    geometry.pixel_pitch_v_mm * factor, (geometry.u0_px - shift) / factor,
                    (geometry.v0_px - shift) / factor)
