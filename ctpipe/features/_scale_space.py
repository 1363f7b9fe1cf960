"""Ball candidates of the ball finder: scale-normalised LoG maxima on an image pyramid.

Each candidate comes with its height, the roundness and long axis of the response there (SIFT's
edge test) and how far the response stays up along that axis; :func:`_scale_space_candidates`
finds them, :func:`_recentred` and :func:`_across` check them against the top-hat image. Used by
:mod:`ctpipe.features.balls`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange
from scipy import fft, ndimage
from scipy.spatial import cKDTree

from ctpipe._shared.jit import FASTMATH, njit
from ctpipe.features._disc_model import _window_of

# Scale-normalised LoG, -s^2 LoG_s, at the centre of the chord profile sqrt(1 - d^2) (radius 1,
# height 1) is largest at s = 0.602, where it is 0.641 (quadrature; a flat disc: 1/sqrt(2), 2/e).
_SIGMA_PER_RADIUS = 0.602
_LOG_PEAK = 0.641
_SCALE_STEP = 2.0 ** 0.25
# Candidates by the LoG response's roundness (smaller / larger curvature) and extent (response
# one radius out along the long axis / peak): round ones are fitted as one ball, elongated but
# short ones also as two overlapping balls, elongated and long ones (ridges) are dropped.
_MIN_ROUNDNESS = 0.3
_PAIR_ROUNDNESS = 0.6
_PAIR_EXTENT = 0.65
# Radii of one octave of the scale space, in pixels of its pyramid level.
_LEVEL_RADIUS_PX = 4.0
# Smaller radii (down to 2 px at this level) go on the first level too; full resolution only
# for balls asked for under 8 px across.
_FIRST_LEVEL = 1
# Candidates found on a coarse level are located again this many levels finer.
_REFINE_LEVELS = 2
# Balls of one phantom project within this factor of their median radius (depth, overlaps).
_SIZE_SPREAD = 2.5


def _radii(r_min: float, r_max: float) -> np.ndarray:
    """Scale-space radii: one ``_SCALE_STEP`` below ``r_min`` to one above ``r_max``, so that balls
    at either end of the range are maxima in scale."""
    radii = [r_min / _SCALE_STEP]
    while radii[-1] < r_max * _SCALE_STEP:
        radii.append(radii[-1] * _SCALE_STEP)
    return np.asarray(radii)


def _log_stack(f: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """``-s^2 LoG_s * f`` (float32, (scales, rows, cols)) at ``s = 0.602 r`` for each of ``radii``.

    Computed by FFT with symmetric padding of 4 s. Not ``ndimage.gaussian_laplace``: on a 512^2
    image and 8 radii it took 326 ms against 115 ms here (its kernels grow with s, the FFT's
    cost does not), and its truncated kernels move the response by 0.8 % of its peak.
    """
    sigmas = _SIGMA_PER_RADIUS * np.asarray(radii, dtype=np.float64)
    pad = int(math.ceil(4.0 * sigmas[-1]))
    rows, cols = f.shape
    shape = (fft.next_fast_len(rows + 2 * pad, real=True), fft.next_fast_len(cols + 2 * pad, real=True))
    padded = np.pad(f.astype(np.float32), ((pad, shape[0] - rows - pad), (pad, shape[1] - cols - pad)),
                    mode="symmetric")
    spectrum = fft.rfft2(padded)
    fy = fft.fftfreq(shape[0])[:, None]
    fx = fft.rfftfreq(shape[1])[None, :]
    q2 = (4.0 * np.pi**2 * (fx**2 + fy**2)).astype(np.float32)
    stack = np.empty((len(sigmas), rows, cols), np.float32)
    for k, s in enumerate(sigmas):
        # -s^2 LoG_s has the transfer function s^2 |w|^2 exp(-s^2 |w|^2 / 2).
        response = fft.irfft2(spectrum * (s * s * q2 * np.exp(-0.5 * s * s * q2)), s=shape)
        stack[k] = response[pad:pad + rows, pad:pad + cols]
    return stack


def _scale_space_candidates(f: np.ndarray, r_min: float, r_max: float, min_height: float,
                            signs: tuple[float, ...]) -> tuple[float, np.ndarray]:
    """Blobs of radius ``r_min`` .. ``r_max`` in ``f``: the polarity and its candidates.

    The scale-normalised LoG runs on a pyramid of 2 x 2 block means: the radii of octave ``L``
    (``_LEVEL_RADIUS_PX`` to twice that at level ``L``, i.e. ``2^L`` times that in full-resolution
    pixels) on level ``L``, so a 2000^2 image with balls 160 px across costs about as much as a
    256^2 one. Each level also computes the radius below and above its own, so that maxima in
    (scale, row, col) are found across octaves; only maxima inside the radius range count (not
    on its first or last radius): a speck, a dead pixel or a line thinner than the smallest ball
    peaks at the smallest scale and is no candidate. ``signs``: 1 bright balls, -1 dark ones;
    given both, the polarity whose strongest candidate is stronger wins.

    Returns ``(sign, candidates)``, the candidates as rows ``(cx, cy, r, height, roundness, axis_x,
    axis_y, extent)`` in full-resolution pixels, strongest first.
    """
    radii = _radii(r_min, r_max)
    level_of = np.maximum(np.floor(np.log2(radii / _LEVEL_RADIUS_PX)), _FIRST_LEVEL).astype(int)
    level_of[radii < 2.0 ** (_FIRST_LEVEL + 1)] = 0   # under 2 px on the first level: full resolution
    pyramid = [f - np.median(f)]
    found = {sign: [] for sign in signs}
    for level in range(int(level_of.max()) + 1):
        if level:
            rows, cols = (pyramid[-1].shape[0] // 2) * 2, (pyramid[-1].shape[1] // 2) * 2
            pyramid.append(pyramid[-1][:rows, :cols].reshape(rows // 2, 2, cols // 2, 2).mean(axis=(1, 3)))
        level_image = pyramid[level]
        own = np.nonzero(level_of == level)[0]
        if not len(own) or min(level_image.shape) < 3:
            continue
        planes = np.arange(max(own[0] - 1, 0), min(own[-1] + 2, len(radii)))
        scale = 2.0 ** level
        stack = _log_stack(level_image, radii[planes] / scale)
        # Maxima on this level's own radii, never on the first or last radius of the range.
        allowed = np.isin(planes, own) & (planes > 0) & (planes < len(radii) - 1)
        for sign in signs:
            if sign < 0:
                np.negative(stack, out=stack)
            rows_ = _candidates(stack, radii[planes] / scale, min_height, allowed)
            rows_[:, 2] *= scale
            fine = max(level - _REFINE_LEVELS, 1)
            if level > fine:
                rows_[:, :2] = _finer(pyramid[fine], rows_, sign, level, fine)
                scale = 2.0 ** fine
            # Block means of 2^L pixels: level pixel i covers full pixels i 2^L .. (i + 1) 2^L - 1.
            rows_[:, :2] = (rows_[:, :2] + 0.5) * scale - 0.5
            scale = 2.0 ** level
            found[sign].append(rows_)
    best = {}
    for sign, parts in found.items():
        rows_ = np.concatenate(parts) if parts else np.zeros((0, 8))
        best[sign] = _suppress(rows_[np.argsort(-rows_[:, 3], kind="stable")])
    sign = max(signs, key=lambda s: float(best[s][0, 3]) if len(best[s]) else -np.inf)
    return sign, best[sign]


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def _peaks_kernel(stack, threshold, allowed, peaks):  # pragma: no cover - numba
    """``peaks[k, i, j]``: ``stack[k, i, j]`` is above ``threshold``, on an ``allowed`` plane, and no
    smaller than any of its 26 neighbours (edges clamped), as ``maximum_filter(size=3,
    mode="nearest")`` would say, but looking only at the few points above the threshold (the
    same peaks in 14 ms instead of 84 ms on an 8 x 512^2 stack)."""
    planes, rows, cols = stack.shape
    for i in prange(rows):
        for k in range(planes):
            if not allowed[k]:
                continue
            for j in range(cols):
                v = stack[k, i, j]
                if not v > threshold:
                    continue
                top = True
                for dk in range(-1, 2):
                    kk = min(max(k + dk, 0), planes - 1)
                    for di in range(-1, 2):
                        ii = min(max(i + di, 0), rows - 1)
                        for dj in range(-1, 2):
                            jj = min(max(j + dj, 0), cols - 1)
                            if stack[kk, ii, jj] > v:
                                top = False
                if top:
                    peaks[k, i, j] = True


def _finer(image: np.ndarray, rows_: np.ndarray, sign: float, level: int, fine: int) -> np.ndarray:
    """Candidate centres found on pyramid ``level`` (rows ``(x, y, r_full, ...)`` in that level's
    pixels), located again on the finer level ``fine`` (its ``image``): the LoG maximum at each
    candidate's radius within a few pixels, with a parabola through its neighbours. A ball found
    on a coarse level is off by a fraction of a coarse pixel, many full pixels; its fit should
    start closer than that. Returns ``(x, y)`` in the fine level's pixels."""
    factor = 2.0 ** (level - fine)
    xy = (rows_[:, :2] + 0.5) * factor - 0.5
    out = xy.copy()
    reach = int(math.ceil(factor)) + 1
    for radius in np.unique(rows_[:, 2]):
        which = np.nonzero(rows_[:, 2] == radius)[0]
        plane = sign * _log_stack(image, np.array([radius / 2.0 ** fine]))
        for i in which:
            x0, y0 = int(round(xy[i, 0])), int(round(xy[i, 1]))
            y_lo, y_hi = max(y0 - reach, 0), min(y0 + reach + 1, image.shape[0])
            x_lo, x_hi = max(x0 - reach, 0), min(x0 + reach + 1, image.shape[1])
            if y_lo >= y_hi or x_lo >= x_hi:
                continue
            patch = plane[0, y_lo:y_hi, x_lo:x_hi]
            py, px = np.unravel_index(int(np.argmax(patch)), patch.shape)
            y, x = np.array([y_lo + py]), np.array([x_lo + px])
            k = np.zeros(1, np.intp)
            out[i] = x[0] + _parabola(plane, k, y, x, 0, 1)[0], y[0] + _parabola(plane, k, y, x, 1, 0)[0]
    return out


def _of_the_balls_size(candidates: np.ndarray) -> np.ndarray:
    """The candidates of the phantom's ball size: within ``_SIZE_SPREAD`` of the median radius of
    the round candidates at least half as high as the highest round one.

    A calibration phantom's balls are identical; only their depth changes the size they
    project, by far less than that factor. Dust, a holder's blobs and the large-scale blob a
    group of balls makes together are of other sizes.
    """
    round_ = candidates[candidates[:, 4] >= _PAIR_ROUNDNESS]
    if not len(round_):
        round_ = candidates
    strong = round_[round_[:, 3] >= 0.5 * round_[:, 3].max()]
    r_ref = float(np.median(strong[:, 2]))
    keep = (candidates[:, 2] >= r_ref / _SIZE_SPREAD) & (candidates[:, 2] <= r_ref * _SIZE_SPREAD)
    return candidates[keep]


def _candidates(stack: np.ndarray, radii: np.ndarray, min_height: float, allowed: np.ndarray) -> np.ndarray:
    """Scale-space maxima of the LoG stack above ``min_height`` (in the stack's units of height)
    on the planes ``allowed``: rows ``(cx, cy, r, height, roundness, axis_x, axis_y, extent)``."""
    threshold = _LOG_PEAK * min_height
    peaks = np.zeros(stack.shape, np.bool_)
    _peaks_kernel(stack, np.float32(threshold), allowed.astype(np.bool_), peaks)
    k, y, x = np.nonzero(peaks)
    if not len(k):
        return np.zeros((0, 8))
    roundness, axis_x, axis_y = _curvatures(stack, k, y, x)
    value = stack[k, y, x].astype(np.float64)
    r = radii[k]
    # How far the response stays up along the peak's long axis: two balls seen as one elongated
    # blob drop within a radius; a chain of balls, a disc's edge or a wire do not.
    extent = np.maximum(_bilinear(stack, y + r * axis_y, x + r * axis_x, plane=k),
                        _bilinear(stack, y - r * axis_y, x - r * axis_x, plane=k)) / value
    # Sub-pixel start: a parabola through the response and its two neighbours along each axis.
    dx = _parabola(stack, k, y, x, 0, 1)
    dy = _parabola(stack, k, y, x, 1, 0)
    return np.stack([x + dx, y + dy, r, value / _LOG_PEAK, roundness, axis_x, axis_y, extent], axis=1)


def _recentred(t: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """Round candidates moved to the centroid of the top-hat ``t`` within 1.1 radii (three
    rounds), where that moves them less than a quarter radius.

    The LoG of a large ball on a coarse pyramid level places it a few full pixels off; a fit
    started there needs several more model evaluations, each costing as much as this whole
    correction. Elongated candidates (overlapping balls) keep their LoG position: a centroid would
    pull them onto each other.
    """
    out = candidates.copy()
    for row in out:
        cx, cy, r = row[:3]
        if row[4] < _PAIR_ROUNDNESS:
            continue
        x, y = cx, cy
        for _ in range(3):
            x_lo, x_hi, y_lo, y_hi = _window_of(np.array([[x, y, r]]), t.shape)
            xs = np.arange(x_lo, x_hi, dtype=np.float64)[None, :]
            ys = np.arange(y_lo, y_hi, dtype=np.float64)[:, None]
            w = np.clip(t[y_lo:y_hi, x_lo:x_hi], 0.0, None) * ((xs - x) ** 2 + (ys - y) ** 2 <= (1.1 * r) ** 2)
            mass = float(w.sum())
            if mass <= 0:
                break
            x, y = float((w * xs).sum()) / mass, float((w * ys).sum()) / mass
        if mass > 0 and math.hypot(x - cx, y - cy) < 0.25 * r:
            row[0], row[1] = x, y
    return out


def _across(t: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """Whether each candidate stands out of the top-hat ``t`` across its long axis.

    Round candidates always do. An elongated one must fall below 60 % of its height 1.3 radii
    to both sides: a chain of overlapping balls does, the inner side of a disc's edge (a plateau
    wider than any ball, left in the top-hat by the opening) does not.
    """
    cx, cy, r, height, roundness, axis_x, axis_y = candidates[:, :7].T
    steep_x, steep_y = -axis_y, axis_x
    sides = np.maximum(_bilinear(t, cy + 1.3 * r * steep_y, cx + 1.3 * r * steep_x),
                       _bilinear(t, cy - 1.3 * r * steep_y, cx - 1.3 * r * steep_x))
    return (roundness >= _MIN_ROUNDNESS) | (sides < 0.6 * height)


def _bilinear(image: np.ndarray, y: np.ndarray, x: np.ndarray, plane: np.ndarray | None = None) -> np.ndarray:
    """``image`` (2-D, or 3-D with ``plane`` the plane of each point) at fractional ``(y, x)``,
    clamped to the image: ``ndimage.map_coordinates`` of order 1."""
    coords = [y, x] if plane is None else [plane, y, x]
    return ndimage.map_coordinates(image, np.asarray(coords, dtype=np.float64), order=1, mode="nearest")


def _curvatures(stack, k, y, x):
    """Roundness of the response at each maximum and the direction of its long axis.

    Roundness is the ratio of the smaller to the larger principal curvature (1: a round peak, as
    a ball gives; near 0: a ridge, as a disc edge or two overlapping balls give): SIFT's edge
    test. Returns (roundness, axis_x, axis_y), the axis a unit vector.

    Three-point differences at the maxima only. ``skimage.feature.hessian_matrix`` works on
    whole planes (``ndimage.correlate`` with these stencils too): 87 ms (56 ms for dxx alone)
    against 0.2 ms here for 29 maxima of an 8 x 512^2 stack, and not bit-identical (skimage's
    ``np.gradient`` of ``np.gradient`` differences over 2 px: roundness off by up to 0.004).
    """
    ym, yp = np.maximum(y - 1, 0), np.minimum(y + 1, stack.shape[1] - 1)
    xm, xp = np.maximum(x - 1, 0), np.minimum(x + 1, stack.shape[2] - 1)
    centre = stack[k, y, x].astype(np.float64)
    dxx = stack[k, y, xp] + stack[k, y, xm] - 2.0 * centre
    dyy = stack[k, yp, x] + stack[k, ym, x] - 2.0 * centre
    dxy = 0.25 * (stack[k, yp, xp] - stack[k, yp, xm] - stack[k, ym, xp] + stack[k, ym, xm])
    half_trace = 0.5 * (dxx + dyy)
    spread = np.sqrt((0.5 * (dxx - dyy)) ** 2 + dxy**2)
    steep, shallow = half_trace - spread, half_trace + spread  # both < 0 at a round maximum
    with np.errstate(divide="ignore", invalid="ignore"):
        roundness = np.where(steep < 0, shallow / steep, 0.0)
    theta = 0.5 * np.arctan2(2.0 * dxy, dxx - dyy)  # eigenvector of the shallow curvature
    return roundness, np.cos(theta), np.sin(theta)


def _parabola(stack, k, y, x, ax, ay):
    lo = (np.maximum(y - ay, 0), np.maximum(x - ax, 0))
    hi = (np.minimum(y + ay, stack.shape[1] - 1), np.minimum(x + ax, stack.shape[2] - 1))
    a, b, c = stack[k, lo[0], lo[1]], stack[k, y, x], stack[k, hi[0], hi[1]]
    curvature = a - 2.0 * b + c
    with np.errstate(divide="ignore", invalid="ignore"):
        step = np.where(curvature < 0, 0.5 * (a - c) / curvature, 0.0)
    return np.clip(step, -0.5, 0.5)


def _suppress(found: np.ndarray) -> np.ndarray:
    """Drop each candidate closer than half a radius to a stronger one (rows sorted strongest first)."""
    if len(found) < 2:
        return found
    tree = cKDTree(found[:, :2])
    keep = np.ones(len(found), bool)
    for i, j in sorted(tree.query_pairs(0.5 * found[:, 2].max())):
        if keep[i] and keep[j] and math.dist(found[i, :2], found[j, :2]) < 0.5 * min(found[i, 2], found[j, 2]):
            keep[j] = False
    return found[keep]
