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

Output: ``xy`` the centre, ``size`` the diameter, ``angle_deg`` NaN, ``response`` the contrast
(the fitted peak line integral, in the units of the image, or of ``-log`` of a dark one),
``descriptors`` ``[radius_px, contrast]`` (float32, L2) and in ``class_id`` a quality flag:
0 clean, 1 the disc overlaps another (centres closer than the sum of the radii: balls at
different depths projecting onto each other) or belongs to a crowd the model does not fully
explain, 2 the disc is cut by the image border (before 1). A ball whose centre is off the
image is not reported.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numba import njit, prange
from scipy import fft, ndimage
from scipy.spatial import cKDTree

from ctpipe._jit import FASTMATH
from ctpipe.data import Features
from ctpipe.errors import ConfigError
from ctpipe.hookspecs import hookimpl
from ctpipe.images import check_image
from ctpipe.stages import Detector, param

__all__ = ["BeadDetector"]

# Scale-normalised LoG, -s^2 LoG_s, at the centre of the chord profile sqrt(1 - d^2) (radius 1,
# height 1) is largest at s = 0.602, where it is 0.641 (quadrature; a flat disc: 1/sqrt(2), 2/e).
_SIGMA_PER_RADIUS = 0.602
_LOG_PEAK = 0.641
_SCALE_STEP = 2.0 ** 0.25
# Cells the disc is sampled on in the model, px (exactly integrated, so only the shape's fidelity
# depends on it, not the centre's symmetry).
_CELL_PX = 0.4
_MAX_CELLS = 96
_CELL_SAMPLES = 4
_DIAMETER_TOLERANCE = 1.2
# Overlapping neighbours fitted jointly with a ball; further ones are masked out of its window.
_MAX_NUISANCE = 3
# Candidates by the LoG response's roundness (smaller / larger curvature) and extent (response
# one radius out along the long axis / peak): round ones are fitted as one ball, elongated but
# short ones also as two overlapping balls, elongated and long ones (ridges) are dropped.
_MIN_ROUNDNESS = 0.3
_PAIR_ROUNDNESS = 0.6
_PAIR_EXTENT = 0.65
# Two balls replace one when they lower the sum of squares by this many noise variances.
_PAIR_EVIDENCE = 50.0
# Most balls a connected crowd is split into.
_MAX_CROWD = 12
# A fit is repeated without the pixels beyond this many robust deviations of its residual
# (dust on a ball), when they are fewer than this share of its window.
_OUTLIER_SIGMA = 12.0
_OUTLIER_PIXELS = 3
_MAX_OUTLIERS = 0.02
_CLEAN, _OVERLAP, _TRUNCATED = 0, 1, 2
# Default diameter range: 10 px to a third of the image's smaller side.
_AUTO_MIN_DIAMETER_PX = 10.0
# Radii of one octave of the scale space, in pixels of its pyramid level.
_LEVEL_RADIUS_PX = 4.0
# Smaller radii (down to 2 px at this level) go on the first level too; full resolution only
# for balls asked for under 8 px across.
_FIRST_LEVEL = 1
# Candidates found on a coarse level are located again this many levels finer.
_REFINE_LEVELS = 2
# Balls of one phantom project within this factor of their median radius (depth, overlaps).
_SIZE_SPREAD = 2.5
# Dead and hot pixels: beyond both neighbours by this many noise deviations and this fraction of
# the neighbours' distance from the image's median.
_SPIKE_SIGMA = 10.0
_SPIKE_FRACTION = 0.25


@dataclass(frozen=True)
class BeadDetector(Detector):
    """Balls of a calibration phantom: sub-pixel disc centres, radii and contrasts."""

    min_diameter_px: float | None = param(
        None, doc="smallest projected ball diameter, px (null: 10 px, and the balls' own size decides)", ge=2,
        le=4096)
    max_diameter_px: float | None = param(
        None, doc="largest projected ball diameter, px (null: a third of the image, and the balls' own size decides)",
        ge=2, le=4096)
    polarity: Literal["auto", "bright", "dark"] = param(
        "auto", doc="bright discs on dark (line integrals), dark on bright (raw intensities), or decide per image")
    min_contrast_sigma: float = param(5.0, doc="smallest ball height above background, in noise standard deviations",
                                      gt=0, le=1e6)
    max_beads: int = param(1000, doc="keep at most this many balls, highest contrast first", ge=1, le=1_000_000)
    centre_method: Literal["fit", "centroid"] = param(
        "fit", doc="sub-pixel centre: least-squares fit of a blurred disc model, or iterative weighted centroid")

    def __post_init__(self) -> None:
        super().__post_init__()
        if (self.min_diameter_px is not None and self.max_diameter_px is not None
                and self.min_diameter_px > self.max_diameter_px):
            raise ConfigError(f"BeadDetector.min_diameter_px: must be <= max_diameter_px ({self.max_diameter_px:g}), "
                              f"got {self.min_diameter_px:g}")

    def detect(self, image: np.ndarray) -> Features:
        """Find the balls of ``image``.

        Parameters
        ----------
        image : ndarray of shape (rows, cols)
            Line integrals (float) or raw intensities (any integer or float dtype).

        Returns
        -------
        Features
            One keypoint per ball, highest contrast first: ``xy`` the centre (x=col, y=row, px),
            ``size`` the diameter (px), ``response`` the contrast (image units), ``class_id``
            0 clean / 1 overlapping / 2 cut by the border, ``descriptors`` ``[radius_px, contrast]``.
            Empty when there is none.
        """
        image = check_image(image)
        integer = bool(np.issubdtype(image.dtype, np.integer))
        f = image.astype(np.float64)
        span = float(f.max() - f.min())
        if span == 0.0:
            return _features(np.zeros((0, 5)))
        noise = _noise_sigma(f, integer=integer, span=span)
        f = _despike(f, noise)
        auto = self.min_diameter_px is None and self.max_diameter_px is None
        d_min = _AUTO_MIN_DIAMETER_PX if self.min_diameter_px is None else self.min_diameter_px
        d_max = (max(min(f.shape) / 3.0, d_min) if self.max_diameter_px is None else self.max_diameter_px)
        r_min, r_max = 0.5 * min(d_min, d_max), 0.5 * d_max
        polarity = {"bright": (1.0,), "dark": (-1.0,)}.get(self.polarity, (1.0, -1.0))
        threshold = 0.7 * self.min_contrast_sigma * noise
        sign, candidates = _scale_space_candidates(f, r_min, r_max, threshold, polarity)
        if not len(candidates):
            return _features(np.zeros((0, 5)))
        if auto:
            # The balls' own size sets the range from here on: a scale step either way of the
            # candidates kept, as if it had been given.
            candidates = _of_the_balls_size(candidates)
            r_min = max(r_min, float(candidates[:, 2].min()) / _SCALE_STEP)
            r_max = min(r_max, float(candidates[:, 2].max()) * _SCALE_STEP)
        g, noise = _line_integrals(f, sign, noise, integer=integer)
        min_height = self.min_contrast_sigma * noise
        tophat = g - _background(g, int(math.ceil(2.0 * r_max)) + 3)
        # Heights from the top-hat (the LoG saw f, the fit sees g); structures wider than any
        # ball (a holder's edge) gave LoG responses but are background, gone from the top-hat.
        at = (np.clip(np.rint(candidates[:, 1]).astype(np.intp), 0, f.shape[0] - 1),
              np.clip(np.rint(candidates[:, 0]).astype(np.intp), 0, f.shape[1] - 1))
        candidates[:, 3] = tophat[at]
        candidates = candidates[(candidates[:, 3] >= 0.7 * min_height) & _across(tophat, candidates)]
        if not len(candidates):
            return _features(np.zeros((0, 5)))
        if self.centre_method == "fit":
            candidates = _recentred(tophat, candidates)
            beads = _fit_all(tophat, candidates, noise=noise, min_height=min_height)
            beads = _clusters(tophat, beads, noise=noise, min_height=min_height)[:, [0, 1, 2, 3, 5]]
        else:
            beads = _centroid_all(tophat, candidates)
            beads = np.column_stack([beads, np.zeros(len(beads))])
        beads = _select(beads, image.shape, min_height, r_min / _DIAMETER_TOLERANCE, r_max * _DIAMETER_TOLERANCE,
                        self.max_beads)
        return _features(beads)


def _features(beads: np.ndarray) -> Features:
    """Features of beads given as rows ``(cx, cy, r, contrast, flag)``."""
    return Features.build(xy=beads[:, :2], size=2.0 * beads[:, 2], angle_deg=np.full(len(beads), np.nan),
                          response=beads[:, 3], class_id=beads[:, 4].astype(np.int32),
                          descriptors=beads[:, 2:4].astype(np.float32), norm="L2")


# ---------------------------------------------------------------------------------------------
# Noise, polarity, background, candidates


def _noise_sigma(f: np.ndarray, *, integer: bool, span: float) -> float:
    """Robust per-pixel noise: MAD of the finest diagonal Haar band, with a floor."""
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
    return g, max(_noise_sigma(g, integer=False, span=span), floor)


def _background(g: np.ndarray, footprint: int) -> np.ndarray:
    """Background under bright balls: grey opening by a square wider than any ball.

    The opening follows any structure wider than the square, its edges included (a rod's edge
    stays sharp), and removes the balls. It is taken of the image smoothed by 1 px so that
    noise does not pull it down to the noise minima of every square.
    """
    return ndimage.grey_opening(ndimage.gaussian_filter(g, 1.0, mode="reflect"), size=(footprint, footprint),
                                mode="reflect")


def _despike(f: np.ndarray, noise: float) -> np.ndarray:
    """``f`` with dead and hot pixels, and lines of them one pixel wide, replaced by their neighbours.

    A pixel is a defect along x when it lies beyond both its left and right neighbours by more
    than ``_SPIKE_SIGMA`` noise deviations and more than ``_SPIKE_FRACTION`` of how far those
    neighbours stand from the image's median (a ball's own curvature over one pixel is a small
    fraction of its height; a dead or saturated pixel is not), likewise along y; a defect along
    either axis becomes the mean of the neighbours along it (both: of all four). Defects are no
    balls, but a dead pixel would outweigh the balls in the scale space and a line of them would
    pull any disc it crosses.
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


def _radii(r_min: float, r_max: float) -> np.ndarray:
    """Scale-space radii: one ``_SCALE_STEP`` below ``r_min`` to one above ``r_max``, so that balls
    at either end of the range are maxima in scale."""
    radii = [r_min / _SCALE_STEP]
    while radii[-1] < r_max * _SCALE_STEP:
        radii.append(radii[-1] * _SCALE_STEP)
    return np.asarray(radii)


def _log_stack(f: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """``-s^2 LoG_s * f`` (float32, (scales, rows, cols)) at ``s = 0.602 r`` for each of ``radii``.

    Computed by FFT with symmetric padding of 4 s.
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
    mode="nearest")`` would say, but looking only at the few points above the threshold."""
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
    clamped to the image."""
    coords = [y, x] if plane is None else [plane, y, x]
    return ndimage.map_coordinates(image, np.asarray(coords, dtype=np.float64), order=1, mode="nearest")


def _curvatures(stack, k, y, x):
    """Roundness of the response at each maximum and the direction of its long axis.

    Roundness is the ratio of the smaller to the larger principal curvature (1: a round peak, as
    a ball gives; near 0: a ridge, as a disc edge or two overlapping balls give): SIFT's edge
    test. Returns (roundness, axis_x, axis_y), the axis a unit vector.
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


# ---------------------------------------------------------------------------------------------
# The blurred projected-disc model


class _Disc:
    """One disc's cells: edges in units of its radius, and the chord profile (height 1) on them,
    each cell's mean over ``_CELL_SAMPLES^2`` points (so a cell the rim cuts holds its share)."""

    def __init__(self, r0: float):
        # Cells of _CELL_PX up to _MAX_CELLS across: a large disc's rim still falls on cells of a
        # small fraction of its radius, and the cost (cells^2 per pixel row) stays bounded.
        n = min(max(int(math.ceil(2.0 * r0 / _CELL_PX)), 8), _MAX_CELLS)
        self.edges = np.linspace(-1.0, 1.0, n + 1)
        offsets = (np.arange(_CELL_SAMPLES) + 0.5) / _CELL_SAMPLES
        v = (self.edges[:-1, None] + np.diff(self.edges)[:, None] * offsets[None, :]).ravel()
        chord = np.sqrt(np.clip(1.0 - v[:, None] ** 2 - v[None, :] ** 2, 0.0, None))
        self.chord = chord.reshape(n, _CELL_SAMPLES, n, _CELL_SAMPLES).mean(axis=(1, 3))


def _axis(pixels: np.ndarray, centre: float, radius: float, edges: np.ndarray, sigma: float):
    """Gaussian-PSF x pixel-box weights of each disc cell on each pixel along one axis, and their
    derivatives in centre, radius and sigma; each of shape (pixels, cells).

    Cell m spans ``u in [a_m, a_m+1]``, ``a = centre + radius * edges``. A pixel at x sees
    ``int g(x - u) du`` over it, ``g = E(. + 1/2) - E(. - 1/2)`` the PSF (cdf E, pdf n)
    integrated over the pixel box. With ``F(t) = t E(t) + s^2 n(t)`` (``F'' = n``, ``dF/ds = s n``)
    that integral is a double difference of F at the pixel edges and cell edges.
    """
    return _axis_kernel(float(pixels[0]), len(pixels), centre + radius * edges, edges, sigma)


@njit(cache=True)
def _axis_kernel(first_pixel, n_pixels, a, edges, sigma):
    n_edges = a.shape[0]
    cdf = np.empty((n_pixels + 1, n_edges))
    pdf = np.zeros((n_pixels + 1, n_edges))
    big_f = np.empty((n_pixels + 1, n_edges))
    reach = 0.5 + 8.0 * sigma  # beyond it E is 0 or 1 and n is 0 to double precision
    scale = 1.0 / (math.sqrt(2.0) * sigma)
    norm = 1.0 / (math.sqrt(2.0 * math.pi) * sigma)
    for i in range(n_pixels + 1):
        x = first_pixel - 0.5 + i
        for m in range(n_edges):
            t = x - a[m]
            if t > reach:
                cdf[i, m] = 1.0
                big_f[i, m] = t
            elif t < -reach:
                cdf[i, m] = 0.0
                big_f[i, m] = 0.0
            else:
                z = t * scale
                e = 0.5 * math.erfc(-z)
                n = norm * math.exp(-z * z)
                cdf[i, m] = e
                pdf[i, m] = n
                big_f[i, m] = t * e + sigma * sigma * n
    n_cells = n_edges - 1
    weights = np.empty((n_pixels, n_cells))
    d_centre = np.empty((n_pixels, n_cells))
    d_radius = np.empty((n_pixels, n_cells))
    d_sigma = np.empty((n_pixels, n_cells))
    for i in range(n_pixels):
        for m in range(n_cells):
            # D(x - a) = F(x - a + 1/2) - F(x - a - 1/2); dD/dt = g; dD/ds = s (n(+) - n(-))
            d0 = big_f[i + 1, m] - big_f[i, m]
            d1 = big_f[i + 1, m + 1] - big_f[i, m + 1]
            g0 = cdf[i + 1, m] - cdf[i, m]
            g1 = cdf[i + 1, m + 1] - cdf[i, m + 1]
            s0 = pdf[i + 1, m] - pdf[i, m]
            s1 = pdf[i + 1, m + 1] - pdf[i, m + 1]
            weights[i, m] = d0 - d1
            d_centre[i, m] = g1 - g0
            d_radius[i, m] = g1 * edges[m + 1] - g0 * edges[m]
            d_sigma[i, m] = sigma * (s0 - s1)
    return weights, d_centre, d_radius, d_sigma


@njit(fastmath=FASTMATH, cache=True)
def _disc_products(chord, x_weights, y_weights):  # pragma: no cover - numba
    """The model of one disc and its derivatives, each of shape (rows, cols): ``Wy C Wx^T`` and
    ``Wy C Dx^T`` for the three x derivatives, ``Dy C Wx^T`` for the three y derivatives.

    ``x_weights`` is ``(Wx, Dx_centre, Dx_radius, Dx_sigma)`` of shape (4, cols, cells), likewise
    ``y_weights``. A pixel sees only the cells within the PSF's reach (the weights are exactly zero
    beyond it), so each row of these matrices is a short band: the products run over the bands
    (a few cells per pixel for a large disc) rather than through BLAS over every cell, which
    also keeps them single-threaded under the pipeline's own threads.
    """
    cells = chord.shape[0]
    cols, rows = x_weights.shape[1], y_weights.shape[1]
    x_lo, x_hi = _bands(x_weights)
    y_lo, y_hi = _bands(y_weights)
    # t[k, p, j] = sum_m C[p, m] X_k[j, m]; C is symmetric, so C[m, p] runs along memory.
    t = np.zeros((4, cols, cells))
    for j in range(cols):
        for m in range(x_lo[j], x_hi[j]):
            a0, a1, a2, a3 = x_weights[0, j, m], x_weights[1, j, m], x_weights[2, j, m], x_weights[3, j, m]
            for p in range(cells):
                c = chord[m, p]
                t[0, j, p] += c * a0
                t[1, j, p] += c * a1
                t[2, j, p] += c * a2
                t[3, j, p] += c * a3
    tt = np.ascontiguousarray(t.transpose(0, 2, 1))
    out = np.zeros((7, rows, cols))
    # Only the columns the disc reaches (in a window of several balls, a fraction of them).
    j_first, j_last = cols, 0
    for j in range(cols):
        if x_hi[j] > x_lo[j]:
            j_first = min(j_first, j)
            j_last = j + 1
    for i in range(rows):
        for p in range(y_lo[i], y_hi[i]):
            b0, b1, b2, b3 = y_weights[0, i, p], y_weights[1, i, p], y_weights[2, i, p], y_weights[3, i, p]
            for j in range(j_first, j_last):
                t0 = tt[0, p, j]
                out[0, i, j] += b0 * t0
                out[1, i, j] += b0 * tt[1, p, j]
                out[2, i, j] += b0 * tt[2, p, j]
                out[3, i, j] += b0 * tt[3, p, j]
                out[4, i, j] += b1 * t0
                out[5, i, j] += b2 * t0
                out[6, i, j] += b3 * t0
    return out[0], out[1], out[2], out[3], out[4], out[5], out[6]


@njit(cache=True)
def _bands(weights):  # pragma: no cover - numba
    """Per row of ``weights`` (4, rows, cells), the range of cells where any of the four is nonzero."""
    rows, cells = weights.shape[1], weights.shape[2]
    lo = np.zeros(rows, np.int64)
    hi = np.zeros(rows, np.int64)
    for i in range(rows):
        first, last = cells, -1
        for m in range(cells):
            if (weights[0, i, m] != 0.0 or weights[1, i, m] != 0.0 or weights[2, i, m] != 0.0
                    or weights[3, i, m] != 0.0):
                if first == cells:
                    first = m
                last = m
        lo[i] = first if last >= 0 else 0
        hi[i] = last + 1 if last >= 0 else 0
    return lo, hi


class _Window:
    """Least-squares problem of one window of the top-hat image: a plane, a shared PSF sigma and
    one or more discs; pixels outside ``keep`` (other balls, not modelled) carry no weight.

    Parameters: ``[b0, bx, by, sigma]`` then ``[cx, cy, r, A]`` per disc.
    """

    def __init__(self, data: np.ndarray, xs: np.ndarray, ys: np.ndarray, keep: np.ndarray, starts: np.ndarray):
        self.keep = keep.ravel()
        self.data = data.ravel()[self.keep]
        self.xs, self.ys = xs, ys
        self.discs = [_Disc(r0) for r0 in starts[:, 2]]
        self.n_params = 4 + 4 * len(starts)
        self.all_kept = bool(self.keep.all())
        self.plane_full = np.stack([np.ones(len(ys) * len(xs)), np.tile(xs - xs.mean(), len(ys)),
                                    np.repeat(ys - ys.mean(), len(xs))])

    def start_and_bounds(self, starts: np.ndarray, b0: float):
        """Start vector and (lower, upper) bounds: centres within half a radius (+1 px) of the
        start, radii within a factor 1.5, heights >= 0, PSF sigma in [0.05, max(3, r)] px."""
        x0 = [b0, 0.0, 0.0, 0.8]
        lo = [-np.inf, -np.inf, -np.inf, 0.05]
        hi = [np.inf, np.inf, np.inf, max(3.0, float(starts[:, 2].max()))]
        for cx, cy, r0, height in starts[:, :4]:
            reach = 0.5 * r0 + 1.0
            x0 += [cx, cy, r0, max(height, 1e-12)]
            lo += [cx - reach, cy - reach, r0 / 1.5, 0.0]
            hi += [cx + reach, cy + reach, 1.5 * r0, np.inf]
        lo, hi = np.asarray(lo), np.asarray(hi)
        return np.clip(x0, lo, hi), (lo, hi)

    def _evaluate(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Model (pixels,) and Jacobian (pixels, parameters) at ``p``."""
        model, jac_t = self._evaluate_t(p)
        return model, jac_t.T

    def _evaluate_t(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Model (pixels,) and transposed Jacobian (parameters, pixels), C-contiguous, at ``p``."""
        sigma = p[3]
        full = np.empty((self.n_params, len(self.ys) * len(self.xs)))
        full[:3] = self.plane_full
        model = np.zeros((len(self.ys), len(self.xs)))
        d_sigma = full[3].reshape(model.shape)
        d_sigma[:] = 0.0
        for j, disc in enumerate(self.discs):
            cx, cy, r, amp = p[4 + 4 * j: 8 + 4 * j]
            wx, dx_c, dx_r, dx_s = _axis(self.xs, cx, r, disc.edges, sigma)
            wy, dy_c, dy_r, dy_s = _axis(self.ys, cy, r, disc.edges, sigma)
            unit, w_c, w_r, w_s, c_w, r_w, s_w = _disc_products(
                disc.chord, np.stack([wx, dx_c, dx_r, dx_s]), np.stack([wy, dy_c, dy_r, dy_s]))
            model += amp * unit
            d_sigma += amp * (s_w + w_s)
            rows_ = full[4 + 4 * j: 8 + 4 * j].reshape(4, *model.shape)
            np.multiply(w_c, amp, out=rows_[0])
            np.multiply(c_w, amp, out=rows_[1])
            np.multiply(r_w + w_r, amp, out=rows_[2])
            rows_[3] = unit
        model = model.ravel() + p[:3] @ self.plane_full
        if self.all_kept:
            return model, full
        return model[self.keep], np.ascontiguousarray(full[:, self.keep])

    def residuals_and_jacobian(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (pixels,) and the transposed Jacobian (parameters, pixels) at ``p``."""
        model, jac_t = self._evaluate_t(p)
        return model - self.data, jac_t


@dataclass(frozen=True)
class _Solution:
    """What :func:`_levenberg_marquardt` found: ``x``, half the sum of squares ``cost`` and ``status``
    (0: evaluations ran out, 2: the cost stopped falling, 3: the parameters stopped moving)."""

    x: np.ndarray
    cost: float
    status: int


def _levenberg_marquardt(fun, x0: np.ndarray, bounds, *, max_nfev: int, ftol: float = 1e-7,
                         xtol: float = 1e-8) -> _Solution:
    """Bounded Levenberg-Marquardt on ``fun(x) -> (residuals, transposed jacobian)``.

    A window holds 10^4-10^5 pixels and a handful of parameters, so each step solves the damped
    normal equations (parameters x parameters) instead of factoring the Jacobian as
    ``scipy.optimize.least_squares`` does (its SVD of the tall Jacobian cost more than the model).
    Columns are scaled by their norms (``x_scale="jac"``), steps are clipped to the bounds, and
    the stopping rules are scipy's: the cost falls by less than ``ftol`` of itself, or the step is
    below ``xtol (xtol + |x|)``.
    """
    lo, hi = bounds
    x = np.clip(np.asarray(x0, dtype=np.float64), lo, hi)
    r, jac_t = fun(x)
    cost, nfev = 0.5 * float(r @ r), 1
    damping = 1e-3
    while nfev < max_nfev:
        product = jac_t @ jac_t.T
        scale = np.maximum(np.sqrt(np.diag(product)), 1e-12)
        normal, gradient = product / np.outer(scale, scale), (jac_t @ r) / scale
        diagonal = np.diag(normal).copy()
        while nfev < max_nfev:
            step = -np.linalg.solve(normal + damping * np.diag(np.maximum(diagonal, 1e-12)), gradient) / scale
            x_new = np.clip(x + step, lo, hi)
            if np.linalg.norm(x_new - x) < xtol * (xtol + float(np.linalg.norm(x))):
                return _Solution(x, cost, 3)  # at the minimum: no step lowers the cost any more
            r_new, jac_new = fun(x_new)
            nfev += 1
            cost_new = 0.5 * float(r_new @ r_new)
            if np.isfinite(cost_new) and cost_new < cost:
                break
            damping *= 4.0
        else:
            return _Solution(x, cost, 0)
        moved = float(np.linalg.norm(x_new - x))
        fell = cost - cost_new
        x, r, jac_t, cost = x_new, r_new, jac_new, cost_new
        damping = max(damping / 3.0, 1e-9)
        if fell < ftol * cost:
            return _Solution(x, cost, 2)
        if moved < xtol * (xtol + float(np.linalg.norm(x))):
            return _Solution(x, cost, 3)
    return _Solution(x, cost, 0)


def _window_of(seeds: np.ndarray, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """Pixel ranges ``(x_lo, x_hi, y_lo, y_hi)`` covering ``1.3 r + 4`` px around every seed."""
    half = 1.3 * seeds[:, 2] + 4.0
    x_lo, x_hi = int(math.floor(np.min(seeds[:, 0] - half))), int(math.ceil(np.max(seeds[:, 0] + half))) + 1
    y_lo, y_hi = int(math.floor(np.min(seeds[:, 1] - half))), int(math.ceil(np.max(seeds[:, 1] + half))) + 1
    return max(x_lo, 0), min(x_hi, shape[1]), max(y_lo, 0), min(y_hi, shape[0])


def _fit_all(t: np.ndarray, candidates: np.ndarray, *, noise: float, min_height: float) -> np.ndarray:
    """Fit every candidate; rows ``(cx, cy, r, A, psf_sigma)`` of the balls found.

    A round candidate, or one of a chain, is fitted as one ball. When that leaves the window
    clearly unexplained (residual RMS above twice the noise and 1 % of the height), or the
    candidate is an elongated blob too short for a chain, it is split into 2, 3, 4 balls in a
    row (:func:`_split`): balls that overlap so much that they show one peak.
    """
    tree = cKDTree(candidates[:, :2])
    found = []
    for i, (cx, cy, r0, height, roundness, axis_x, axis_y, extent) in enumerate(candidates):
        if any(math.hypot(x - cx, y - cy) < 0.5 * min(r, r0) for x, y, r, _, _ in found):
            continue  # a stronger candidate's fit (one of a pair) found this ball already
        blob = roundness < _PAIR_ROUNDNESS and extent < _PAIR_EXTENT
        single = None
        if roundness >= _MIN_ROUNDNESS or not blob:
            seeds = np.array([[cx, cy, r0, height]])
            single = _fit_discs(t, _window_of(seeds, t.shape), seeds, candidates, tree, i, min_height)
        if single is None and blob or single is not None and _unexplained(single, noise):
            best = _split(t, candidates, tree, i, single, noise, min_height)
        else:
            best = single
        if best is not None:
            # A ball of a split may be one a stronger candidate found already.
            found.extend(disc for disc in best[0]
                         if not any(math.hypot(disc[0] - x, disc[1] - y) < 0.25 * min(r, disc[2])
                                    for x, y, r, _, _ in found))
    return np.asarray(found, dtype=np.float64).reshape(-1, 5)


def _unexplained(fit, noise: float) -> bool:
    """Whether a fit leaves more in its window than noise and the model's own mismatch."""
    discs, _, rms = fit
    return rms > 2.0 * noise and rms > 0.01 * float(discs[:, 3].max())


def _split(t, candidates, tree, own, single, noise, min_height):
    """Fit 2, 3, then 4 balls in a row where one did not do; the first that fails to lower the
    sum of squares by ``_PAIR_EVIDENCE`` noise variances and by a fifth ends the search.

    Seeds lie on the long axis of the blob's second moments (top-hat within 1.5 radii), spaced
    so that n balls have its length: the variance along less across is ``s^2 (n^2 - 1) / 12``.
    """
    if single is not None:
        cx, cy, r, height = single[0][0, :4]
        reach = 1.5 * r
    else:  # the LoG saw the blob, a little larger than its balls
        cx, cy, r0, height = candidates[own, :4]
        r, reach = 0.8 * r0, 1.5 * r0
    x_lo, x_hi, y_lo, y_hi = _window_of(np.array([[cx, cy, reach / 1.3]]), t.shape)
    xs = np.arange(x_lo, x_hi, dtype=np.float64)[None, :]
    ys = np.arange(y_lo, y_hi, dtype=np.float64)[:, None]
    weights = np.clip(t[y_lo:y_hi, x_lo:x_hi], 0.0, None) * ((xs - cx) ** 2 + (ys - cy) ** 2 <= reach**2)
    hypotheses = [_row_seeds(weights, x_lo, y_lo, n, r, height / 1.5) for n in (2, 3, 4)]
    if any(h is None for h in hypotheses):
        return single
    window = _window_of(np.concatenate(hypotheses + [np.array([[cx, cy, r, height]])]), t.shape)
    best = None
    if single is not None:
        best = _fit_discs(t, window, np.array([[cx, cy, r, height]]), candidates, tree, own, min_height)
    for seeds in hypotheses:
        fit = _fit_discs(t, window, seeds, candidates, tree, own, min_height)
        if fit is None:
            break
        discs = fit[0]
        apart = np.hypot(*(discs[:, None, :2] - discs[None, :, :2]).transpose(2, 0, 1)) + np.eye(len(discs)) * 1e9
        if np.any(discs[:, 3] < min_height) or np.any(apart < 0.25 * discs[:, 2].min()):
            break
        if best is not None and best[1] - fit[1] < max(_PAIR_EVIDENCE * noise**2, 0.2 * best[1]):
            break
        best = fit
    return best


def _row_seeds(weights: np.ndarray, x_lo: int, y_lo: int, n: int, r: float, height: float) -> np.ndarray | None:
    """Seeds ``(cx, cy, r, A)`` of ``n`` balls in a row matching the second moments of
    ``weights`` (a patch whose corner is pixel ``(x_lo, y_lo)``): on the long axis through the
    centroid, spaced ``s`` so that the variance along less across is ``s^2 (n^2 - 1) / 12``
    (at least 0.3 radii). None for a patch without weight."""
    mass = float(weights.sum())
    if mass <= 0:
        return None
    ys, xs = np.mgrid[y_lo:y_lo + weights.shape[0], x_lo:x_lo + weights.shape[1]].astype(np.float64)
    mx, my = float((weights * xs).sum()) / mass, float((weights * ys).sum()) / mass
    dx, dy = xs - mx, ys - my
    cov = np.array([[(weights * dx * dx).sum(), (weights * dx * dy).sum()],
                    [(weights * dx * dy).sum(), (weights * dy * dy).sum()]]) / mass
    spread, axes = np.linalg.eigh(cov)
    step = max(math.sqrt(12.0 * max(spread[1] - spread[0], 0.0) / max(n * n - 1, 1)), 0.3 * r)
    offsets = (np.arange(n) - 0.5 * (n - 1)) * step
    return np.column_stack([mx + offsets * axes[0, 1], my + offsets * axes[1, 1], np.full(n, r), np.full(n, height)])


def _fit_discs(t, window, seeds, candidates, tree, own, min_height, strict=True, max_nfev=30):
    """Least-squares fit of the ``seeds`` (rows ``(cx, cy, r, A)``) in ``window`` of the top-hat.

    Other candidates overlapping a seed's disc are fitted with them (the nearest
    ``_MAX_NUISANCE``), further ones reaching into the window are masked out. Returns
    ``(discs, cost, rms)``: rows ``(cx, cy, r, A, psf_sigma)`` of the fitted seeds, half the sum
    of squares and the RMS residual over the unmasked window; or None if the fit failed, did not
    converge (unless not ``strict``: a first guess in a crowd) or a disc moved more than its
    radius.
    """
    x_lo, x_hi, y_lo, y_hi = window
    xs = np.arange(x_lo, x_hi, dtype=np.float64)
    ys = np.arange(y_lo, y_hi, dtype=np.float64)
    reach = 1.3 * candidates[:, 2].max() + 4.0
    centre = 0.5 * (x_lo + x_hi - 1), 0.5 * (y_lo + y_hi - 1)
    near = tree.query_ball_point(centre, 0.5 * math.hypot(x_hi - x_lo, y_hi - y_lo) + reach)
    gaps = {}
    for j in near:
        if j == own or not _reaches(candidates[j], x_lo, x_hi, y_lo, y_hi):
            continue
        dist = np.hypot(seeds[:, 0] - candidates[j, 0], seeds[:, 1] - candidates[j, 1])
        if np.any(dist < 0.5 * np.maximum(seeds[:, 2], candidates[j, 2])):
            continue  # the same ball as a seed
        gaps[j] = float(np.min(dist - seeds[:, 2] - candidates[j, 2] - 0.2 * seeds[:, 2]))
    overlapping = sorted((g, j) for j, g in gaps.items() if g < 2.0)[:_MAX_NUISANCE]
    modelled = [j for _, j in overlapping]
    keep = np.ones((len(ys), len(xs)), bool)
    for j in set(gaps) - set(modelled):
        jx, jy, jr = candidates[j, :3]
        keep &= (xs[None, :] - jx) ** 2 + (ys[:, None] - jy) ** 2 > (1.15 * jr + 2.0) ** 2
    starts = np.concatenate([seeds[:, :4], candidates[modelled, :4]])
    data = t[y_lo:y_hi, x_lo:x_hi]
    converged = False
    for _ in range(2):
        problem = _Window(data, xs, ys, keep, starts)
        if len(problem.data) < 3 * problem.n_params:
            return None
        x0, bounds = problem.start_and_bounds(starts, float(np.median(problem.data)))
        try:
            result = _levenberg_marquardt(problem.residuals_and_jacobian, x0, bounds, max_nfev=max_nfev)
        except (ValueError, np.linalg.LinAlgError):
            return None
        if not np.all(np.isfinite(result.x)):
            return None
        fitted = result.x[4:].reshape(-1, 4)
        if result.status > 0:
            converged = True
            break
        # A nuisance disc fitted to nothing (a faint bump where two balls meet) has a loose centre
        # and radius that keep the fit from converging: drop such discs, fit again from there.
        faint = fitted[len(seeds):, 3] < max(min_height, 0.1 * float(fitted[:len(seeds), 3].min()))
        if not faint.any():
            break
        starts = np.concatenate([fitted[:len(seeds)], fitted[len(seeds):][~faint]])
    if converged:
        result, problem = _without_outliers(problem, result, data, xs, ys, keep, starts, bounds, min_height, max_nfev)
    if strict and not converged:
        return None
    if np.any(np.hypot(*(fitted[:len(seeds), :2] - seeds[:, :2]).T) > np.maximum(seeds[:, 2], 1.0)):
        return None
    discs = np.column_stack([fitted[:len(seeds)], np.full(len(seeds), result.x[3])])
    return discs, float(result.cost), math.sqrt(2.0 * result.cost / len(problem.data))


def _without_outliers(problem, result, data, xs, ys, keep, starts, bounds, min_height, max_nfev):
    """The fit again without the pixels it cannot explain: dust on a ball, a defect the despiking
    left. Pixels beyond ``_OUTLIER_SIGMA`` robust deviations of the residual (and a noise deviation),
    in clumps of ``_OUTLIER_PIXELS`` or more, grown by a pixel, are masked when they are fewer than
    ``_MAX_OUTLIERS`` of the window; returns ``(result, problem)`` of the fit used."""
    residual = problem.residuals_and_jacobian(result.x)[0]
    spread = 1.4826 * float(np.median(np.abs(residual)))
    bad = np.zeros(keep.shape, bool)
    bad[keep] = np.abs(residual) > max(_OUTLIER_SIGMA * spread, 0.2 * min_height)
    if bad.any():
        # Dust covers a few pixels together; noise (larger inside a strong ball than the window's
        # median says) exceeds the bound in a pixel here and there, never in a clump.
        labels, _ = ndimage.label(bad, np.ones((3, 3), bool))
        bad = np.bincount(labels.ravel())[labels] >= _OUTLIER_PIXELS
        bad[labels == 0] = False
    if not bad.any() or bad.sum() > _MAX_OUTLIERS * keep.sum():
        return result, problem
    trimmed = _Window(data, xs, ys, keep & ~ndimage.binary_dilation(bad, np.ones((3, 3), bool)), starts)
    if len(trimmed.data) < 3 * trimmed.n_params:
        return result, problem
    again = _levenberg_marquardt(trimmed.residuals_and_jacobian, result.x, bounds, max_nfev=max_nfev)
    return (again, trimmed) if again.status > 0 and np.all(np.isfinite(again.x)) else (result, problem)


def _render(balls: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The model image of fitted balls (rows ``(cx, cy, r, A, psf_sigma)``), without background."""
    image = np.zeros(shape)
    for cx, cy, r, height, sigma in balls.reshape(-1, 5):
        x_lo, x_hi, y_lo, y_hi = _window_of(np.array([[cx, cy, r + 3.0 * sigma]]), shape)
        if x_lo >= x_hi or y_lo >= y_hi:
            continue
        disc = _Disc(r)
        wx = _axis(np.arange(x_lo, x_hi, dtype=np.float64), cx, r, disc.edges, sigma)[0]
        wy = _axis(np.arange(y_lo, y_hi, dtype=np.float64), cy, r, disc.edges, sigma)[0]
        image[y_lo:y_hi, x_lo:x_hi] += height * (wy @ disc.chord @ wx.T)
    return image


def _clusters(t: np.ndarray, balls: np.ndarray, *, noise: float, min_height: float) -> np.ndarray:
    """Crowds of overlapping balls: the missing ones added, all fitted together.

    Scale space misses balls in crowds (a chain of overlapping balls hides its middle members;
    balls closer than a radius show one peak), and a ball fitted next to a neighbour nobody found
    stretches over it. The top-hat above a tenth of the balls' median height falls into
    connected regions; in each that holds several balls, or one that leaves more than noise
    unexplained, the region's mass over a ball's (``2 pi A r^2 / 3`` at the median height and
    radius: identical balls) counts its balls. The missing ones are seeded in a row through what
    the model leaves (:func:`_row_seeds`) and all are fitted together; kept if that lowers the
    sum of squares clearly (``_PAIR_EVIDENCE`` noise variances and a tenth) and every added ball
    has half the median height, up to three times and ``_MAX_CROWD`` balls.

    Returns rows ``(cx, cy, r, A, psf_sigma, unresolved)``, the last 1 for the balls of a region
    whose model leaves half a ball's mass or more unexplained.
    """
    balls = balls[balls[:, 3] >= min_height]  # faint fits (a bump where balls meet) are no balls
    if not len(balls):
        return np.zeros((0, 6))
    r_ref, height_ref = float(np.median(balls[:, 2])), float(np.median(balls[:, 3]))
    ball_mass = 2.0 * math.pi / 3.0 * height_ref * r_ref**2
    labels, _ = ndimage.label(ndimage.gaussian_filter(t, 1.0) > max(0.7 * min_height, 0.1 * height_ref))
    at = labels[np.clip(np.rint(balls[:, 1]).astype(np.intp), 0, t.shape[0] - 1),
                np.clip(np.rint(balls[:, 0]).astype(np.intp), 0, t.shape[1] - 1)]
    residual = t - _render(balls, t.shape)
    keep = np.ones(len(balls), bool)
    added = []
    for label, region in enumerate(ndimage.find_objects(labels), start=1):
        if region is None:
            continue
        inside = labels[region] == label
        members = np.nonzero(at == label)[0]
        area = int(inside.sum())
        if area > _MAX_CROWD * math.pi * r_ref**2 or area < 0.5 * math.pi * r_ref**2:
            continue  # larger than a crowd of balls (clutter), or smaller than one
        rms = float(np.sqrt(np.mean(residual[region][inside] ** 2)))
        if len(members) < 2 and (rms <= 2.0 * noise or rms <= 0.01 * height_ref):
            continue  # one ball, explained
        y_lo, x_lo = region[0].start, region[1].start
        pad = int(math.ceil(0.3 * r_ref)) + 4
        window = (max(x_lo - pad, 0), min(region[1].stop + pad, t.shape[1]),
                  max(y_lo - pad, 0), min(region[0].stop + pad, t.shape[0]))
        pool = np.delete(balls[:, :4], members, axis=0)
        # Whether or not some were fitted as one, identical balls weigh the same.
        count = int(round(float(np.clip(t[region], 0.0, None)[inside].sum()) / ball_mass))
        # More balls than the mass holds: the faint extra ones are the kinks where balls meet.
        faint = [m for m in members[np.argsort(balls[members, 3])][:max(len(members) - max(count, 1), 0)]
                 if balls[m, 3] < 0.5 * height_ref]
        keep[faint] = False
        current = balls[np.setdiff1d(members, faint)]
        cost = _model_cost(t, window, current)
        for _ in range(3):
            # All the missing balls at once, then one joint fit: fitted alone, the balls found would
            # stretch over the rest. Their places in a row through what the model leaves.
            rest = np.clip((t - _render(current, t.shape))[region], 0.0, None) * inside
            n = min(count, _MAX_CROWD) - len(current)
            if n < 1 and not len(current):
                break
            # No ball missing: fit those found together, each with all the others in place.
            seeds = _row_seeds(rest, x_lo, y_lo, n, r_ref, height_ref) if n >= 1 else np.zeros((0, 4))
            if seeds is None:
                break
            trial = _fit_crowd(t, window, np.concatenate([current[:, :4], seeds]), pool, min_height)
            if trial is None or np.any(trial[0][:, 3] < min_height):
                break
            trial_cost = _model_cost(t, window, trial[0])
            # Added balls must explain clearly more, and look like the others (half their height).
            if n >= 1 and (cost - trial_cost < max(_PAIR_EVIDENCE * noise**2, 0.1 * cost)
                           or np.any(trial[0][len(current):, 3] < 0.5 * height_ref)) or trial_cost >= cost:
                break
            current, cost = trial[0], trial_cost
            if n < 1 or trial[2] <= 2.0 * noise or trial[2] <= 0.01 * height_ref:
                break
        # Half a ball's mass or more left unexplained: these balls' centres are not to be trusted.
        rest = np.clip((t - _render(current, t.shape))[region], 0.0, None) * inside
        unresolved = float(rest.sum()) >= 0.5 * ball_mass
        keep[members] = False
        added.append(np.column_stack([current[:, :5], np.full(len(current), float(unresolved))]))
    balls = np.column_stack([balls[:, :5], np.zeros(len(balls))])
    return np.concatenate([balls[keep]] + added) if added else balls


def _fit_crowd(t, window, seeds, pool, min_height):
    """Joint fit of ``seeds`` in ``window``, the balls of ``pool`` reaching in as neighbours."""
    everything = np.concatenate([seeds[:, :4], pool[:, :4]])
    tree = cKDTree(everything[:, :2])
    return _fit_discs(t, window, seeds[:, :4], everything, tree, -1, min_height, strict=False,
                      max_nfev=15 + 5 * len(seeds))


def _model_cost(t, window, balls) -> float:
    """Half the sum of squares of ``window`` of ``t`` less the model of ``balls`` (rows
    ``(cx, cy, r, A, psf_sigma)``, possibly none) about its median."""
    x_lo, x_hi, y_lo, y_hi = window
    rest = (t - _render(balls, t.shape))[y_lo:y_hi, x_lo:x_hi]
    return 0.5 * float(np.sum((rest - np.median(rest)) ** 2))


def _reaches(candidate: np.ndarray, x_lo: int, x_hi: int, y_lo: int, y_hi: int) -> bool:
    """Whether a candidate's (blurred, possibly underestimated) disc touches the window."""
    cx, cy, r = candidate[:3]
    extent = 1.15 * r + 2.0
    dx = max(x_lo - 0.5 - cx, 0.0, cx - (x_hi - 0.5))
    dy = max(y_lo - 0.5 - cy, 0.0, cy - (y_hi - 0.5))
    return dx * dx + dy * dy < extent * extent


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


@hookimpl
def ctpipe_register_stages(registry) -> None:
    registry.add_detector("beads", BeadDetector)
