"""Balls of a calibration phantom: sub-pixel centres of the disc-like blobs they project.

A sphere of radius ``R`` and attenuation ``mu`` projects to the chord profile
``p(d) = 2 mu sqrt(R^2 - d^2)`` (``d``: distance on the detector from its projected centre,
scaled by the magnification), blurred by the detector. Line integrals show it as a bright disc
on a dark field, raw intensities (``exp(-p)``) as a dark disc on a bright field. All balls look
alike, so descriptors are of no use; what a calibration needs is each centre, to a small
fraction of a pixel, and to know which centres to trust.

Method
    1. Noise: the robust standard deviation of the finest diagonal Haar band
       (``median(|HH|) / 0.6745``, Donoho's estimator), floored at the quantisation of integer
       images and at 1e-4 of a float image's range, so that noise-free images work.
    2. Defects: a pixel beyond both neighbours along x (or y) by 10 noise deviations and a quarter
       of their distance from the median is a dead or hot pixel, or part of a dead line one pixel
       wide, and takes their mean (numba).
    3. Scale space: the scale-normalised Laplacian of Gaussian ``-s^2 LoG_s`` (FFT, symmetric
       padding) at ``s = 0.602 r`` (where its response to a chord profile of radius ``r``
       peaks, at 0.641 times its height) for ``r`` over the diameter range in steps of
       ``2^(1/4)``, each octave of radii on its own level of a pyramid of 2 x 2 block means
       (radii 4-8 px at that level from level 1 on, full resolution only for balls under 8 px;
       with the radius below and above for the maxima across
       octaves): the range 10 px to a third of the image costs about as much on 2000^2 as on
       256^2. Polarity ``auto``: the sign of the strongest candidate. Candidates: maxima in
       (scale, row, col) strictly inside the radius range (a speck, dead pixel or line thinner
       than the smallest ball peaks at its smallest radius) that imply a height of
       ``0.7 min_contrast_sigma`` noise deviations, with the roundness (smaller / larger curvature)
       and long axis of the response at each (SIFT's edge test) and how far it stays up along that
       axis; a coarse candidate is located again on a level two octaves finer. Without a diameter
       range the balls decide their size: the candidates within 2.5x of the median radius of the
       strong round ones are kept (identical balls; dust and the blob a group of balls makes
       together are of other sizes), and that range is used from here on.
    4. Background: dark images of positive intensities become line integrals (``-log``): a
       ball then adds its chord profile to whatever lies behind it, and overlapping balls add.
       A grey opening by a square wider than any ball (of the image smoothed by 1 px) is the
       background; it follows the holder, a rod and their edges, and the top-hat (image less
       opening) keeps the balls. Candidates must stand out of it, elongated ones across their
       axis too (not the inner side of an edge).
    5. Sub-pixel centre (``centre_method="fit"``): round candidates start from the top-hat's
       centroid; bounded Levenberg-Marquardt (damped normal equations, analytic Jacobian) at full
       resolution on a window of ``1.3 r + 4`` px::

           model = b0 + bx x + by y + sum_j A_j (PSF * pixel box * chord_j)(x - cx_j, y - cy_j)

       with a Gaussian PSF of fitted sigma and exact integration over each pixel. Each disc is
       cut into cells of about 0.4 px tied to its centre, over which PSF and pixel box are
       integrated in closed form (at most 96 cells across, each holding the chord's mean over
       it; ``F(t) = t E(t) + s^2 n(t)`` is the Gaussian's double
       antiderivative; numba): the model is separable (``A Wy C Wx^T``) and exactly symmetric
       about the centre, so its discretisation cannot pull the centre. Candidates overlapping
       the ball are fitted with it, farther ones masked out; clumps of pixels the fit leaves beyond 12
       robust deviations (dust on the ball), if under 2 % of the window, are masked and it is
       fitted again. A fit that leaves its window
       unexplained (residual RMS above twice the noise and 1 % of the height), or a short
       elongated candidate, is split into 2, 3, 4 balls in a row along the blob's long axis,
       kept when they lower the sum of squares clearly.
    6. Crowds: regions of the top-hat above a tenth of the balls' median height that hold
       several balls or leave part unexplained are counted by mass (``2 pi A r^2 / 3`` per
       ball: identical balls), the missing balls seeded in a row through the residual, and all
       fitted together: a chain of seven overlapping balls seen end-on is resolved, two balls a
       sixth of a radius apart too. ``centre_method="centroid"`` replaces 5-6 by the iterative
       intensity-weighted centroid of the top-hat (``r + 2`` px, 1 px taper), which is a little
       less precise and does not separate overlapping balls.
    7. Kept: heights of at least ``min_contrast_sigma`` noise deviations, diameters within 20 %
       of the range, centres on the image; fits of one ball by two candidates merged.

Accuracy (``benchmarks/bench_beads.py``: 512^2 images of 30 balls of peak line integral 1, a
0.7 px Gaussian PSF, Poisson noise), RMS centre error: 0.003-0.011 px for diameters 8-40 px at
1e5-1e4 photons per pixel, within 1.1-1.5x the Cramer-Rao bound, both polarities; under 1e-3 px
without noise (the renderer's own sampling), 1e-5 px on the model's own images. Overlapping
balls: 0.005-0.06 px, worst when centres are a quarter diameter apart; there the line
integrals add before the detector blurs intensities, which the model (blurring line integrals)
does not follow. 0.16-0.28 s per 512^2 image of 30 balls on one core (diameters 8-20 px); 2-4 s
per 2000^2 view of six balls 160 px across (``benchmarks/bench_ball_scan_2k.py``), about 0.7 s
of it scale space and background. The centre does not depend on the PSF being Gaussian
(the model stays symmetric); radius and contrast absorb the mismatch.

Output (:func:`find_balls`): rows ``(cx, cy, r, contrast, flag)``, highest contrast first, the
contrast the fitted peak line integral (in the units of the image, or of ``-log`` of a dark one)
and the flag 0 clean, 1 the disc overlaps another (centres closer than the sum of the radii:
balls at different depths projecting onto each other) or belongs to a crowd the model does not
fully explain, 2 the disc is cut by the image border (before 1). A ball whose centre is off the
image is not reported. The ``beads`` detector (:mod:`ctpipe.builtin.beads`) packs them as
keypoints.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange
from scipy import ndimage
from scipy.spatial import cKDTree

from ctpipe._shared.jit import FASTMATH, njit
from ctpipe.features._disc_fit import _clusters, _fit_all
from ctpipe.features._disc_model import _render, _window_of
from ctpipe.features._scale_space import (_MIN_ROUNDNESS, _SCALE_STEP, _across, _of_the_balls_size, _recentred,
                                          _scale_space_candidates)
from ctpipe.images import check_image

__all__ = ["find_balls", "noise_sigma", "despike", "render_ball_model"]

_DIAMETER_TOLERANCE = 1.2
_CLEAN, _OVERLAP, _TRUNCATED = 0, 1, 2
# Default diameter range: 10 px to a third of the image's smaller side.
_AUTO_MIN_DIAMETER_PX = 10.0
# Dead and hot pixels: beyond both neighbours by this many noise deviations and this fraction of
# the neighbours' distance from the image's median.
_SPIKE_SIGMA = 10.0
_SPIKE_FRACTION = 0.25


def find_balls(image, *, min_diameter_px: float | None = None, max_diameter_px: float | None = None,
               polarity: str = "auto", min_contrast_sigma: float = 5.0, max_beads: int = 1000,
               centre_method: str = "fit") -> np.ndarray:
    """Find the balls of a calibration phantom in one projection (the method above).

    Parameters
    ----------
    image : ndarray of shape (rows, cols)
        Line integrals (float) or raw intensities (any integer or float dtype).
    min_diameter_px, max_diameter_px : float or None
        Range of projected ball diameters, px. Both None: 10 px to a third of the image, and
        the balls' own size narrows it (identical balls).
    polarity : {"auto", "bright", "dark"}
        Bright discs on dark (line integrals), dark on bright (raw intensities), or decided by
        the stronger candidate.
    min_contrast_sigma : float
        Smallest ball height above background, in noise standard deviations.
    max_beads : int
        Keep at most this many balls, highest contrast first.
    centre_method : {"fit", "centroid"}
        Sub-pixel centre: least-squares fit of the blurred disc model, or iterative weighted
        centroid of the top-hat.

    Returns
    -------
    ndarray of shape (n, 5), float64
        Rows ``(cx, cy, r, contrast, flag)``: centre (x = col, y = row, px), radius (px),
        contrast (image units, or ``-log`` units of a dark image), flag 0 clean / 1 overlapping
        or in an unresolved crowd / 2 cut by the border; highest contrast first.

    Raises
    ------
    InputError
        ``image`` is not a finite, non-empty 2-D numeric array.
    ValueError
        ``polarity`` or ``centre_method`` is none of the choices.
    """
    if polarity not in ("auto", "bright", "dark") or centre_method not in ("fit", "centroid"):
        raise ValueError(f"find_balls: polarity must be auto, bright or dark and centre_method fit or centroid, "
                         f"got {polarity!r} and {centre_method!r}")
    image = check_image(image)
    integer = bool(np.issubdtype(image.dtype, np.integer))
    f = image.astype(np.float64)
    span = float(f.max() - f.min())
    if span == 0.0:
        return np.zeros((0, 5))
    noise = noise_sigma(f, integer=integer, span=span)
    f = despike(f, noise)
    auto = min_diameter_px is None and max_diameter_px is None
    d_min = _AUTO_MIN_DIAMETER_PX if min_diameter_px is None else min_diameter_px
    d_max = (max(min(f.shape) / 3.0, d_min) if max_diameter_px is None else max_diameter_px)
    r_min, r_max = 0.5 * min(d_min, d_max), 0.5 * d_max
    signs = {"bright": (1.0,), "dark": (-1.0,)}.get(polarity, (1.0, -1.0))
    threshold = 0.7 * min_contrast_sigma * noise
    sign, candidates = _scale_space_candidates(f, r_min, r_max, threshold, signs)
    if not len(candidates):
        return np.zeros((0, 5))
    if auto:
        # The balls' own size sets the range from here on: a scale step either way of the
        # candidates kept, as if it had been given.
        candidates = _of_the_balls_size(candidates)
        r_min = max(r_min, float(candidates[:, 2].min()) / _SCALE_STEP)
        r_max = min(r_max, float(candidates[:, 2].max()) * _SCALE_STEP)
    g, noise = _line_integrals(f, sign, noise, integer=integer)
    min_height = min_contrast_sigma * noise
    tophat = g - _background(g, int(math.ceil(2.0 * r_max)) + 3)
    # Heights from the top-hat (the LoG saw f, the fit sees g); structures wider than any
    # ball (a holder's edge) gave LoG responses but are background, gone from the top-hat.
    at = (np.clip(np.rint(candidates[:, 1]).astype(np.intp), 0, f.shape[0] - 1),
          np.clip(np.rint(candidates[:, 0]).astype(np.intp), 0, f.shape[1] - 1))
    candidates[:, 3] = tophat[at]
    candidates = candidates[(candidates[:, 3] >= 0.7 * min_height) & _across(tophat, candidates)]
    if not len(candidates):
        return np.zeros((0, 5))
    if centre_method == "fit":
        candidates = _recentred(tophat, candidates)
        beads = _fit_all(tophat, candidates, noise=noise, min_height=min_height)
        beads = _clusters(tophat, beads, noise=noise, min_height=min_height)[:, [0, 1, 2, 3, 5]]
    else:
        beads = _centroid_all(tophat, candidates)
        beads = np.column_stack([beads, np.zeros(len(beads))])
    found = _select(beads, image.shape, min_height, r_min / _DIAMETER_TOLERANCE, r_max * _DIAMETER_TOLERANCE,
                    max_beads)
    if auto and not len(found):
        # The strongest blobs were a crowd whose size no ball has (a ball bar seen along its rod,
        # its balls in a chain): look again over the whole default range, the size not narrowed.
        return find_balls(image, min_diameter_px=d_min, max_diameter_px=d_max, polarity=polarity,
                          min_contrast_sigma=min_contrast_sigma, max_beads=max_beads, centre_method=centre_method)
    return found


def render_ball_model(balls: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The image the disc model of :func:`find_balls` draws for given balls, without background.

    Parameters
    ----------
    balls : ndarray of shape (n, 5)
        Rows ``(cx, cy, r, height, psf_sigma)``: centre and radius (px), peak line integral and
        the Gaussian PSF's standard deviation (px).
    shape : tuple of int
        ``(rows, cols)`` of the image.

    Returns
    -------
    ndarray of shape ``shape``, float64
        The chord profiles blurred by the PSF and integrated over each pixel, summed.
    """
    return _render(np.asarray(balls, dtype=np.float64), shape)


# ---------------------------------------------------------------------------------------------
# Noise, defects, line integrals, background


def noise_sigma(f: np.ndarray, *, integer: bool, span: float) -> float:
    """Robust per-pixel noise: MAD of the finest diagonal Haar band, with a floor.

    Parameters
    ----------
    f : ndarray of shape (rows, cols), float
        The image.
    integer : bool
        Whether its values are integer counts: the floor is then their quantisation,
        ``1 / sqrt(12)``.
    span : float
        ``max - min`` of the image; a float image's floor is ``1e-4 span``, so that noise-free
        images work.

    Returns
    -------
    float
        ``median(|HH|) / 0.6745`` (Donoho's estimator) of the finest diagonal Haar band of
        2 x 2 blocks, or the floor if that is larger.

    Notes
    -----
    Not ``skimage.restoration.estimate_sigma``: that is the same estimator on a Daubechies-2
    band, so a different value (and different detection thresholds), and it needs PyWavelets,
    which ctpipe does not depend on. The Haar band here is four strided slices.
    """
    rows, cols = (f.shape[0] // 2) * 2, (f.shape[1] // 2) * 2
    floor = 1.0 / math.sqrt(12.0) if integer else 1e-4 * span
    if rows == 0 or cols == 0:
        return floor
    q = f[:rows, :cols]
    hh = (q[0::2, 0::2] - q[0::2, 1::2] - q[1::2, 0::2] + q[1::2, 1::2]) / 2.0
    return max(float(np.median(np.abs(hh))) / 0.6745, floor)


def _line_integrals(f: np.ndarray, sign: float, noise: float, *, integer: bool) -> tuple[np.ndarray, float]:
    """The image the balls are fitted on (bright, additive) and its noise.

    Bright images are taken as line integrals. Dark ones as intensities, made line integrals by
    ``-log``: there a ball adds its chord profile whatever lies behind it (a holder, a rod: in
    intensities it would scale the ball's contrast), and overlapping balls add where their
    transmissions multiply. Zero counts of integer images are taken as half a count; a float
    image with pixels <= 0 cannot be intensities and is only negated.
    """
    if sign > 0:
        return f, noise
    if integer:
        f = np.maximum(f, 0.5)
    elif f.min() <= 0.0:
        return -f, noise
    g = -np.log(f)
    span = float(g.max() - g.min())
    # The integer quantisation floor, carried through the log at the typical level.
    floor = (1.0 / math.sqrt(12.0)) / float(np.median(f)) if integer else 1e-4 * span
    return g, max(noise_sigma(g, integer=False, span=span), floor)


def _background(g: np.ndarray, footprint: int) -> np.ndarray:
    """Background under bright balls: grey opening by a square wider than any ball.

    The opening follows any structure wider than the square, its edges included (a rod's edge
    stays sharp), and removes the balls. It is taken of the image smoothed by 1 px so that
    noise does not pull it down to the noise minima of every square.
    """
    return ndimage.grey_opening(ndimage.gaussian_filter(g, 1.0, mode="reflect"), size=(footprint, footprint),
                                mode="reflect")


def despike(f: np.ndarray, noise: float) -> np.ndarray:
    """``f`` with dead and hot pixels, and lines of them one pixel wide, replaced by their neighbours.

    A pixel is a defect along x when it lies beyond both its left and right neighbours by more
    than ``_SPIKE_SIGMA`` noise deviations and more than ``_SPIKE_FRACTION`` of how far those
    neighbours stand from the image's median (a ball's own curvature over one pixel is a small
    fraction of its height; a dead or saturated pixel is not), likewise along y; a defect along
    either axis becomes the mean of the neighbours along it (both: of all four). Defects are no
    balls, but a dead pixel would outweigh the balls in the scale space and a line of them would
    pull any disc it crosses.

    Parameters
    ----------
    f : ndarray of shape (rows, cols)
        The image (computed in float32).
    noise : float
        Its noise standard deviation (:func:`noise_sigma`).

    Returns
    -------
    ndarray of shape (rows, cols), float64
        The image with its defects replaced; the border rows and columns are left as they are.
    """
    out = f.astype(np.float32)
    _despike_kernel(out, f.astype(np.float32), np.float32(_SPIKE_SIGMA * noise), np.float32(np.median(f)),
                    np.float32(_SPIKE_FRACTION))
    return out.astype(np.float64)


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def _despike_kernel(out, f, floor, level, fraction):  # pragma: no cover - numba
    rows, cols = f.shape
    for i in prange(1, rows - 1):
        for j in range(1, cols - 1):
            v = f[i, j]
            left, right, up, down = f[i, j - 1], f[i, j + 1], f[i - 1, j], f[i + 1, j]
            lo_x, hi_x = min(left, right), max(left, right)
            lo_y, hi_y = min(up, down), max(up, down)
            reach_x = max(floor, fraction * max(abs(lo_x - level), abs(hi_x - level)))
            reach_y = max(floor, fraction * max(abs(lo_y - level), abs(hi_y - level)))
            along_x = v > hi_x + reach_x or v < lo_x - reach_x
            along_y = v > hi_y + reach_y or v < lo_y - reach_y
            if along_x and along_y:
                out[i, j] = 0.25 * (left + right + up + down)
            elif along_x:
                out[i, j] = 0.5 * (left + right)
            elif along_y:
                out[i, j] = 0.5 * (up + down)


# ---------------------------------------------------------------------------------------------
# Iterative weighted centroid


def _centroid_all(t: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """Weighted centroid of the top-hat around each round candidate, re-centred until it moves
    less than 1e-3 px; rows ``(cx, cy, r, A)``."""
    found = []
    for cx, cy, r0 in candidates[candidates[:, 4] >= _MIN_ROUNDNESS, :3]:
        x, y = cx, cy
        for _ in range(20):
            x_lo, x_hi, y_lo, y_hi = _window_of(np.array([[x, y, r0]]), t.shape)
            xs = np.arange(x_lo, x_hi, dtype=np.float64)[None, :]
            ys = np.arange(y_lo, y_hi, dtype=np.float64)[:, None]
            window = t[y_lo:y_hi, x_lo:x_hi]
            d = np.sqrt((xs - x) ** 2 + (ys - y) ** 2)
            ring = window[d > 1.2 * r0 + 2.0]
            base = float(np.median(ring)) if ring.size else 0.0
            # A 1 px taper rather than a hard edge, so the weights move smoothly with the centre.
            w = np.clip(window - base, 0.0, None) * np.clip(r0 + 2.5 - d, 0.0, 1.0)
            mass = float(w.sum())
            if mass <= 0:
                break
            new_x, new_y = float((w * xs).sum()) / mass, float((w * ys).sum()) / mass
            moved = math.hypot(new_x - x, new_y - y)
            x, y = new_x, new_y
            if moved < 1e-3:
                break
        if mass <= 0 or math.hypot(x - cx, y - cy) > r0:
            continue
        # A chord profile of height A and radius r has mass 2 pi A r^2 / 3 and <d^2> = 2 r^2 / 5,
        # plus 2 s^2 + 1/6 from a PSF of sigma s (taken as 0.7 px) and the pixel box.
        second = float((w * ((xs - x) ** 2 + (ys - y) ** 2)).sum()) / mass
        r = math.sqrt(max(second - 2.0 * 0.7**2 - 1.0 / 6.0, 0.25) / 0.4)
        found.append((x, y, r, 3.0 * mass / (2.0 * math.pi * r * r)))
    return np.asarray(found, dtype=np.float64).reshape(-1, 4)


# ---------------------------------------------------------------------------------------------
# Selection and flags


def _select(beads: np.ndarray, shape: tuple[int, int], min_height: float, r_low: float, r_high: float,
            max_beads: int) -> np.ndarray:
    """Keep plausible balls, merge duplicates, cap the count, flag overlaps and truncation.

    ``beads``: rows ``(cx, cy, r, A, unresolved)``; returns rows ``(cx, cy, r, A, flag)``,
    highest A first. A ball is flagged overlapping when its disc reaches another's or when it
    belongs to a crowd whose model leaves part of it unexplained (``unresolved``).
    """
    rows, cols = shape
    x, y, r, height, _ = beads.T
    keep = ((height >= min_height) & (r >= r_low) & (r <= r_high)
            & (x >= -0.5) & (x <= cols - 0.5) & (y >= -0.5) & (y <= rows - 0.5))
    beads = beads[keep]
    beads = beads[np.argsort(-beads[:, 3], kind="stable")]
    if len(beads) > 1:
        tree = cKDTree(beads[:, :2])
        alive = np.ones(len(beads), bool)
        # Two fits of one ball land within a fraction of a pixel; two balls fitted together stay
        # apart even when they overlap almost entirely.
        for i, j in sorted(tree.query_pairs(0.1 * beads[:, 2].max())):
            if alive[i] and alive[j] and math.dist(beads[i, :2], beads[j, :2]) < 0.1 * min(beads[i, 2], beads[j, 2]):
                alive[j] = False
        beads = beads[alive]
    beads = beads[:max_beads]
    flags = np.where(beads[:, 4] > 0, _OVERLAP, _CLEAN)
    if len(beads) > 1:
        tree = cKDTree(beads[:, :2])
        for i, j in tree.query_pairs(2.0 * beads[:, 2].max()):
            if math.dist(beads[i, :2], beads[j, :2]) < beads[i, 2] + beads[j, 2]:
                flags[i] = flags[j] = _OVERLAP
    x, y, r = beads[:, 0], beads[:, 1], beads[:, 2]
    flags[(x - r < -0.5) | (y - r < -0.5) | (x + r > cols - 0.5) | (y + r > rows - 0.5)] = _TRUNCATED
    return np.column_stack([beads[:, :4], flags])
