"""Conjugate rays: a truth-free check of a scan's angles that no reconstruction can bend to fit.

The sources of a circular scan all lie in one plane, the midplane, which the detector sees as
the row through the principal point (``v0_px``). Two views ``i`` and ``j`` of a full or short
scan whose sources are about half a turn apart both measure one ray exactly: the straight line
through their two sources. Whatever the object, the beam (monochromatic or not) or the
reconstruction, the two measured line integrals of that ray must be equal. Where that ray
falls on each detector depends only on the angle ``alpha = theta_j - theta_i`` between the views
(ctpipe's convention, :mod:`ctpipe.model`): with the source frame of :mod:`ctpipe.geometry` the
source of view ``j`` is seen from view ``i`` at::

    x_n = -cot(alpha / 2)   in view i,      x_n = +cot(alpha / 2)   in view j,

on the midplane row, normalised coordinates (``x_n = (u - u0) pitch_u / SDD``). A wrong
``alpha`` samples the two views at the wrong columns, half the angle error apart from the right
ones each (``d x_n / d alpha = 1 / (2 sin^2(alpha/2))``), and the two samples disagree by about
the projections' slope times that shift. The mean squared disagreement over every such pair of
views is the measure (:func:`conjugate_ray_costs`).

What it sees and what it does not:

- each pair measures ``e_j - e_i`` of the angle errors ``e`` of two views about half a turn
  apart: jitter, jumps, slips, a scale error (the pair steps too short or too long) and
  turn-periodic errors of odd order (``sin(theta)``: an eccentric table) are seen at first order;
  even orders (``sin(2 theta)``) only through the spread ``2 gamma`` of the pairs over the fan;
  a common offset of all views is not seen at all (nor does it matter);
- it compares measured data with measured data, so a reconstruction made from the same angles
  cannot absorb their errors, as it does in the reconstruct-and-reproject residual of
  :func:`ctpipe.solve.reprojection.consistency_costs`; on the test scan of
  ``tests/solve/test_conjugate.py`` a once-per-turn error of 0.3 deg raises this measure by
  about 70 % and that residual by 1 %;
- it needs no untruncated rows (unlike the integral consistency conditions of Grangeat's
  formula, Aichert et al., "Epipolar consistency in transmission imaging", IEEE TMI 34(11),
  2015, which integrate along detector lines): a region-of-interest scan whose sample is wider
  than the field of view is checked as well as any other, since a ray is compared with itself;
- it needs the midplane on the detector and views half a turn apart (a short scan of
  180 deg plus the fan angle has them for its first fan-angle's worth of views), and its power
  grows with the number of such pairs; at a few dozen views it says little, and
  :class:`ConjugateRayScore` carries the standard error that says how little;
- a detector turned in its own plane crosses the midplane along a slanted line, so reading the
  straight row makes conjugate rays disagree by the rows' vertical change, which a wrong slow
  band of the angles can partly hide; :func:`conjugate_ray_costs` fits the tilt (``slopes``,
  ``fit_tilt_deg``) to first order in the rows' slopes, right for an offset of a row or two at
  the detector's edge (0.3 deg on a 192-column detector is half a row; on a 2,048-column one,
  five rows, past what first order holds);
- a projection that is shifted as a whole (a drifting source spot or detector, see
  :mod:`ctpipe.sim.drift`) moves its samples as an angle error does: a random walk of 0.05 px a
  view hides a 0.3 deg once-per-turn error from it, so on drifting scans it says "no evidence"
  rather than "better";
- what does not turn with the sample (a table edge, a holder's clamp, a fixed filter) is the
  same in every view, so two conjugate samples of it differ wherever it is not mirror-symmetric
  about the axis, whatever the angles, and its edges pull the fitted axis column and the angles
  like an object's; on a full turn :func:`turning_part` takes it out exactly (the views' mean:
  that and the turn-symmetric part of the object, whose conjugate samples agree);
- what remains at the true angles is the midplane falling between two detector rows and the
  detector blur, which mix neighbouring rays that are not conjugate: a floor common to every
  candidate, which is why candidates are compared pair by pair (:class:`ConjugateRayScore`).

Half-turn pairs of projections are the classical way to find the centre of rotation (the
projection of the axis, ``u0_px`` here); :func:`conjugate_ray_costs` can fit ``u0_px`` for
each candidate, so an offset axis does not pass for an angle error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import prange
from scipy.ndimage import spline_filter1d

from ctpipe._shared.jit import njit
from ctpipe.errors import InputError
from ctpipe.geometry import Geometry, check_geometry
from ctpipe.recon.feldkamp import covers_full_circle

__all__ = ["midplane_rows", "midplane_row", "conjugate_pairs", "conjugate_ray_mismatch", "ConjugateRayScore",
           "conjugate_ray_costs", "turning_part"]


def turning_part(rows: np.ndarray, angles_deg, slopes: np.ndarray | None = None):
    """The midplane rows (and their slopes) less what does not turn with the sample, on a full turn.

    On a full turn the views' mean is the projection of everything that does not turn plus the
    turn average of what does; the latter is symmetric about the axis, so its two conjugate
    samples agree for any angles and any axis column, while a static part's disagree wherever it
    is not symmetric. Taking the mean out therefore leaves conjugate rays that only the turning
    sample's angles move. On a short scan no such average exists (a per-pixel median, as
    projection matching takes out, is not symmetric and makes conjugate rays disagree), so the
    rows are returned as they are.

    Measured on full-turn scans of the built-in sweep (seed 11, ``docs/wholescan.md``): the
    conjugate rays' z of correct estimates against the nominal angles went from +2.4 to -3.0 (a
    bead cylinder over a static table edge, 93 views) and from -1.8 to -3.5 (a bead cloud, 162
    views, nothing static: the turn-symmetric part alone). On a 250 deg scan (seed 0) the
    per-pixel median took a correct estimate's z from -2.4 to -1.0, which is why it is not taken.

    Parameters
    ----------
    rows, slopes : ndarray of shape (V, cols)
        :func:`midplane_rows` of line integrals; ``slopes`` optional.
    angles_deg : array_like of shape (V,)
        The views' angles, degrees (the nominal ones): whether they cover a full turn.

    Returns
    -------
    rows, slopes : ndarray of shape (V, cols)
        New arrays (``slopes`` None when not given).
    """
    rows = np.asarray(rows, dtype=np.float64)
    if slopes is not None:
        slopes = np.asarray(slopes, dtype=np.float64)
    if not covers_full_circle(angles_deg):
        return rows.copy(), None if slopes is None else slopes.copy()
    return rows - rows.mean(axis=0), None if slopes is None else slopes - slopes.mean(axis=0)


def midplane_rows(projections, geometry: Geometry, *, slopes: bool = False):
    """The row of every view through the principal point, shape (V, cols), float64.

    Interpolated linearly between the two detector rows around ``v0_px``; ``projections`` are
    line integrals (an array or a :class:`~ctpipe.io.scans.ViewStack`, read one view at a time).
    With ``slopes``, also each row's derivative along the detector rows (per row, central
    differences of the interpolated rows one row either side, clamped to the detector), in the
    same pass: ``(rows, slopes)``, which let :func:`conjugate_ray_costs` fit a detector tilt.

    Raises
    ------
    InputError
        When ``v0_px`` is not on the detector: the midplane is then not measured.
    """
    g = check_geometry(geometry)
    if not 0.0 <= g.v0_px <= g.detector_rows - 1:
        raise InputError(f"geometry.v0_px: the midplane row must be on the detector (0 to {g.detector_rows - 1}) "
                         f"for conjugate rays, got {g.v0_px:g}")
    rows = np.empty((len(projections), g.detector_cols), np.float64)
    derivative = np.zeros_like(rows) if slopes else None
    above, below = min(g.v0_px + 1.0, g.detector_rows - 1.0), max(g.v0_px - 1.0, 0.0)
    for view in range(len(projections)):
        image = np.asarray(projections[view], dtype=np.float64)
        if image.shape != g.shape:
            raise InputError(f"projections[{view}]: must be {g.detector_rows} x {g.detector_cols}, got {image.shape}")
        rows[view] = midplane_row(image, g)
        if slopes and above > below:
            derivative[view] = (_row_at(image, above) - _row_at(image, below)) / (above - below)
    return (rows, derivative) if slopes else rows


def _row_at(image: np.ndarray, v: float) -> np.ndarray:
    """The detector row at (fractional) row ``v``, linear between its two neighbours, clamped to the detector."""
    if image.shape[0] == 1:
        return image[0]
    v = min(max(v, 0.0), image.shape[0] - 1.0)
    low = min(int(math.floor(v)), image.shape[0] - 2)
    frac = v - low
    return (1.0 - frac) * image[low] + frac * image[low + 1]


def midplane_row(image: np.ndarray, geometry: Geometry) -> np.ndarray:
    """One view's row through the principal point, shape (cols,): linear between the two rows around
    ``v0_px`` (clamped to the detector; :func:`midplane_rows` refuses a ``v0_px`` off it)."""
    return _row_at(image, geometry.v0_px)


def _common_ray_columns(angles_deg: np.ndarray, geometry: Geometry, i: np.ndarray, j: np.ndarray,
                        u0_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Columns where the ray through the sources of views ``i`` and ``j`` meets each detector."""
    half = np.deg2rad(angles_deg[j] - angles_deg[i]) / 2.0
    with np.errstate(divide="ignore", invalid="ignore"):
        x_n = -np.cos(half) / np.sin(half)
    scale = geometry.source_to_detector_mm / geometry.pixel_pitch_u_mm
    return u0_px + x_n * scale, u0_px - x_n * scale


def conjugate_pairs(angles_deg, geometry: Geometry, *, margin_px: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The view pairs ``(i, j)``, ``i < j``, whose common ray is on both detectors, shapes (P,).

    Their sources are 90 to 270 deg apart (in practice half a turn give or take the fan angle,
    since the ray must reach the detector) and the ray meets both detectors at least
    ``margin_px`` inside its first and last column.
    """
    g = check_geometry(geometry)
    angles = np.asarray(angles_deg, dtype=np.float64)
    if angles.ndim != 1 or not np.all(np.isfinite(angles)):
        raise InputError(f"angles_deg: must be finite angles, one per view, got shape {angles.shape}")
    i, j = np.triu_indices(len(angles), 1)
    col_i, col_j = _common_ray_columns(angles, g, i, j, g.u0_px)
    high = g.detector_cols - 1 - margin_px
    with np.errstate(invalid="ignore"):
        keep = (np.cos(np.deg2rad(angles[j] - angles[i])) < 0.0) & (col_i >= margin_px) & (col_i <= high) \
            & (col_j >= margin_px) & (col_j <= high)
    return i[keep], j[keep]


def _spline(rows: np.ndarray) -> np.ndarray:
    """Cubic-spline coefficients of each row of ``rows`` along the row, computed once for many samplings."""
    return spline_filter1d(np.asarray(rows, dtype=np.float64), order=3, axis=-1, mode="nearest")


@njit(parallel=True, cache=True)
def _sample_rows(coefficients, views, cols, last):
    """Row ``views[k]``'s cubic spline at column ``cols[k]`` (clipped to ``[0, last]``), for every ``k``.

    What ``map_coordinates(2-D coefficients, [views, cols], order=3, mode="nearest",
    prefilter=False)`` gives at integer ``views`` (within 1e-15: a 2-D interpolating spline on
    a row is that row's 1-D spline), with four taps instead of sixteen, in parallel: the gate's
    axis and tilt searches sample the rows some 600 times.
    """
    n_cols = coefficients.shape[1]
    out = np.empty(views.size)
    for k in prange(views.size):
        x = cols[k]
        if not np.isfinite(x):
            out[k] = np.nan
            continue
        x = min(max(x, 0.0), last)
        first = int(np.floor(x))
        t = x - first
        t2 = t * t
        t3 = t2 * t
        weights = ((1.0 - t) ** 3 / 6.0, (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0, (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0,
                   t3 / 6.0)
        total = 0.0
        for m in range(4):
            total += weights[m] * coefficients[views[k], min(max(first - 1 + m, 0), n_cols - 1)]
        out[k] = total
    return out


def _mismatch(coefficients: np.ndarray, geometry: Geometry, angles: np.ndarray, i: np.ndarray, j: np.ndarray,
              u0_px: float, tilt: tuple[np.ndarray, float] | None = None) -> np.ndarray:
    """Measured minus conjugate line integral of each pair's common ray (NaN off a detector).

    ``tilt``: the spline coefficients of the rows' derivatives along the rows and ``tan`` of the
    detector's in-plane tilt. The source plane then crosses the detector along a slanted line,
    ``row = v0 + tan(tilt) (col - u0) pitch_u / pitch_v``, sampled to first order as ``row(col) +
    offset * slope(col)``.
    """
    col_i, col_j = _common_ray_columns(angles, geometry, i, j, u0_px)
    last = geometry.detector_cols - 1

    def sample(views, cols, coeffs=coefficients):
        return _sample_rows(coeffs, views, np.asarray(cols, dtype=np.float64), float(last))

    mismatch = sample(i, col_i) - sample(j, col_j)
    if tilt is not None and tilt[1] != 0.0:
        slope_coefficients, tan_tilt = tilt
        factor = tan_tilt * geometry.pixel_pitch_u_mm / geometry.pixel_pitch_v_mm
        mismatch += factor * ((col_i - u0_px) * sample(i, col_i, slope_coefficients)
                              - (col_j - u0_px) * sample(j, col_j, slope_coefficients))
    # A ray the angles put off either detector was not measured there: NaN, not the edge's value
    # (the edges are often air on both sides, which would agree and reward angles that push rays off).
    off = (col_i < 0.0) | (col_i > last) | (col_j < 0.0) | (col_j > last) | ~np.isfinite(col_i) | ~np.isfinite(col_j)
    mismatch[off] = np.nan
    return mismatch


def conjugate_ray_mismatch(rows: np.ndarray, geometry: Geometry, angles_deg, pairs: tuple[np.ndarray, np.ndarray], *,
                           u0_px: float | None = None) -> np.ndarray:
    """Measured minus conjugate line integral of every pair's common ray, shape (P,).

    ``rows`` from :func:`midplane_rows`; ``pairs`` from :func:`conjugate_pairs`; the rows are
    interpolated with cubic splines (linear interpolation adds a floor of its own at sharp edges)
    at the columns; NaN where ``angles_deg`` put a pair's ray off either detector.
    """
    g = check_geometry(geometry)
    i, j = (np.asarray(k, dtype=np.intp) for k in pairs)
    return _mismatch(_spline(rows), g, np.asarray(angles_deg, dtype=np.float64), i, j,
                     g.u0_px if u0_px is None else float(u0_px))


@dataclass(frozen=True)
class ConjugateRayScore:
    """How consistent one candidate set of angles is with the projections' conjugate rays.

    Attributes
    ----------
    cost : float
        Mean squared mismatch of the common rays, relative to the mean square of the line
        integrals sampled (dimensionless; lower is more consistent).
    u0_px : float
        The principal point column used (fitted when asked).
    n_pairs : int
        Pairs of views compared.
    versus : str
        The candidate this one is compared with (the reference), or "" for the reference itself.
    delta : float
        ``cost - cost(reference)``, over the same pairs.
    delta_se : float
        Standard error of ``delta``: the pairs are grouped by their first view (one view's
        error is shared by all its pairs), and neighbouring groups into blocks until the
        blocks are longer than the correlation of neighbouring views (:func:`_blocked_se`).
    dof : int
        Degrees of freedom of ``delta_se`` (the blocks it was taken over, less one): it is itself
        an estimate, so ``z`` is Student-t distributed with ``dof`` degrees of freedom, not normal.
    tilt_deg : float
        The detector's in-plane tilt used (fitted when asked, else 0).
    paired_views : int
        Views the pairs are grouped by (their first view): the terms ``delta_se`` is taken over,
        before any blocking.
    """

    cost: float
    u0_px: float
    n_pairs: int
    versus: str = ""
    delta: float = 0.0
    delta_se: float = 0.0
    dof: int = 0
    tilt_deg: float = 0.0
    paired_views: int = 0

    @property
    def z(self) -> float:
        """``delta / delta_se``: below -2, this candidate is more consistent than its reference beyond noise."""
        return self.delta / self.delta_se if self.delta_se > 0 else 0.0

    def to_dict(self) -> dict:
        return {"cost": self.cost, "u0_px": self.u0_px, "n_pairs": self.n_pairs, "versus": self.versus,
                "delta": self.delta, "delta_se": self.delta_se, "dof": self.dof, "tilt_deg": self.tilt_deg, "z": self.z,
                "paired_views": self.paired_views}


def _grid_then_golden(cost, grid: np.ndarray, cell: float, iterations: int) -> float:
    """The minimiser of ``cost``: the best of ``grid``, then a golden-section search ``cell`` either side of it."""
    best = float(grid[int(np.argmin([cost(x) for x in grid]))])
    low, high = max(best - cell, float(grid[0])), min(best + cell, float(grid[-1]))
    ratio = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = high - ratio * (high - low), low + ratio * (high - low)
    fa, fb = cost(a), cost(b)
    for _ in range(iterations):
        if fa < fb:
            high, b, fb = b, a, fa
            a = high - ratio * (high - low)
            fa = cost(a)
        else:
            low, a, fa = a, b, fb
            b = low + ratio * (high - low)
            fb = cost(b)
    return 0.5 * (low + high)


def _mean_squared_mismatch(coefficients, geometry, angles, pairs, u0_px: float, tilt=None) -> float:
    squared = _mismatch(coefficients, geometry, angles, *pairs, u0_px, tilt) ** 2
    checked = np.isfinite(squared)
    # Rays off the detector cannot be checked; an axis that leaves none checkable is no fit.
    return float(np.mean(squared[checked])) if checked.any() else math.inf


def _fit_u0_tilt(coefficients, geometry, angles, pairs, search_px: float, slope_coefficients,
                 max_tilt_deg: float) -> tuple[float, float]:
    """The ``u0_px`` and the detector tilt (deg, within ``max_tilt_deg``) that make the common rays agree best.

    By coordinates: the axis column without a tilt (:func:`_fit_u0`), the tilt at that column (a
    grid of nine over the range, then a golden-section search on the cell around the best; a
    column moves the samples along the rows, a tilt across them, so the two hardly interact),
    then the column again at that tilt.
    """
    u0 = _fit_u0(coefficients, geometry, angles, pairs, search_px) if search_px > 0 else geometry.u0_px

    def tilted(tilt_deg):
        return slope_coefficients, math.tan(math.radians(tilt_deg))

    grid = np.linspace(-max_tilt_deg, max_tilt_deg, 9)
    tilt_deg = _grid_then_golden(lambda t: _mean_squared_mismatch(coefficients, geometry, angles, pairs, u0, tilted(t)),
                                 grid, float(grid[1] - grid[0]), 16)
    if search_px > 0:
        u0 = _fit_u0(coefficients, geometry, angles, pairs, search_px, tilted(tilt_deg))
    return u0, tilt_deg


def _fit_u0(coefficients, geometry, angles, pairs, search_px: float, tilt=None) -> float:
    """The ``u0_px`` within ``search_px`` of the geometry's that makes the common rays agree best.

    A grid of half-pixel steps, then a golden-section search on the cell around its best.
    """
    centre = geometry.u0_px
    grid = centre + np.linspace(-search_px, search_px, int(2 * math.ceil(search_px / 0.5)) + 1)
    u0 = _grid_then_golden(lambda u: _mean_squared_mismatch(coefficients, geometry, angles, pairs, u, tilt),
                           grid, 0.5, 14)
    return float(np.clip(u0, centre - search_px, centre + search_px))


def _blocked_se(per_view: np.ndarray, min_blocks: int = 16) -> tuple[float, int]:
    """Standard error of ``per_view.sum()`` for a series whose neighbours are correlated, and its blocks.

    Neighbouring views see nearly the same structures, so their contributions are not
    independent and the plain ``std * sqrt(n)`` is too small. Flyvbjerg and Petersen's blocking
    (J. Chem. Phys. 91, 461, 1989): sum neighbours in pairs, again and again, and take the
    largest ``std * sqrt(n_blocks)`` while at least ``min_blocks`` blocks are left; an
    independent series gives about the same at every level, a correlated one grows until the
    blocks are longer than its correlation. Returns the standard error and the number of blocks
    it was taken over (its degrees of freedom are one fewer).
    """
    series = np.asarray(per_view, dtype=np.float64)
    best, blocks = float(np.std(series, ddof=1) * math.sqrt(len(series))), len(series)
    while len(series) // 2 >= min_blocks:
        series = series[: len(series) // 2 * 2].reshape(-1, 2).sum(axis=1)
        se = float(np.std(series, ddof=1) * math.sqrt(len(series)))
        if se > best:
            best, blocks = se, len(series)
    return best, blocks


def conjugate_ray_costs(projections, geometry: Geometry, candidates: dict[str, np.ndarray], *,
                        reference: str | None = None, fit_u0_px: float = 0.0,
                        rows: np.ndarray | None = None, slopes: np.ndarray | None = None,
                        fit_tilt_deg: float = 0.0) -> dict[str, ConjugateRayScore]:
    """Score candidate angle sets by their conjugate rays, each against a reference, without the truth.

    Parameters
    ----------
    projections : array-like of shape (V, rows, cols)
        Line integrals (``-log`` of flat-corrected intensities); only the midplane row is read.
    geometry : Geometry
    candidates : dict of str to ndarray of shape (V,)
        Angle sets in degrees (any common offset).
    reference : str, optional
        The candidate every other is compared with (its ``delta`` and ``delta_se``); default the
        first.
    fit_u0_px : float
        Fit the principal point column within this many pixels of the geometry's for each
        candidate (0: use the geometry's). A centre of rotation off by a pixel makes every pair
        disagree, and the best angles then are the ones that hide it best.
    rows : ndarray of shape (V, cols), optional
        :func:`midplane_rows` of the projections, if already read.
    slopes : ndarray of shape (V, cols), optional
        Their derivatives along the detector rows (``midplane_rows(..., slopes=True)``); read
        with the rows when ``fit_tilt_deg`` is set and they are not given.
    fit_tilt_deg : float
        Fit the detector's in-plane tilt within this many degrees either way with the
        reference's angles, and compare every candidate at that tilt (0: no tilt). A tilted
        detector crosses the source plane along a slanted line; read along the straight midplane
        row, conjugate rays disagree by the rows' vertical change, which angle errors can partly
        hide. The tilt is taken to first order (a row offset times the row's slope), right for
        offsets up to a row or two at the detector's edge.

    Returns
    -------
    dict of str to ConjugateRayScore
        In the order of ``candidates``. The pairs compared are those whose common ray is on both
        detectors at the reference's angles, so all scores are over the same rays; a ray that a
        candidate moves off a detector cannot be checked and counts as it does for the reference
        (neither reward nor charge).

    Raises
    ------
    InputError
        When no pair of views is about half a turn apart with its common ray on the detector (a
        scan of less than 180 deg, a midplane off the detector).
    """
    g = check_geometry(geometry)
    if not candidates:
        raise InputError("candidates: must name at least one set of angles")
    if rows is None:
        rows, slopes = midplane_rows(projections, g, slopes=True) if fit_tilt_deg > 0 else (midplane_rows(projections, g),
                                                                                            None)
    if fit_tilt_deg > 0 and (slopes is None or np.shape(slopes) != np.shape(rows)):
        raise InputError(f"slopes: fitting a tilt needs the rows' slopes, one per row, shape {np.shape(rows)}")
    n_views = rows.shape[0]
    sets = {}
    for name, angles in candidates.items():
        a = np.asarray(angles, dtype=np.float64)
        if a.shape != (n_views,) or not np.all(np.isfinite(a)):
            raise InputError(f"candidates[{name!r}]: must be {n_views} finite angles in degrees, got shape {a.shape}")
        sets[name] = a
    reference = next(iter(sets)) if reference is None else reference
    if reference not in sets:
        raise InputError(f"reference: {reference!r} is not a candidate. Try one of {sorted(sets)}")
    # The rays compared are those of the reference's pairs; a candidate that puts one off the
    # detector samples the edge there, and pays for it.
    pairs = conjugate_pairs(sets[reference], g, margin_px=1.0 + float(fit_u0_px))
    if len(pairs[0]) == 0:
        raise InputError("projections: no two views are half a turn apart with their common ray on the detector, "
                         "so conjugate rays cannot check the angles (a scan must cover 180 deg plus the fan angle)")
    scale = float(np.mean(rows ** 2)) or 1.0
    coefficients = _spline(rows)
    slope_coefficients = _spline(slopes) if fit_tilt_deg > 0 else None
    squared = {}
    u0s, tilts = {}, {}
    for name in [reference, *(n for n in sets if n != reference)]:
        angles = sets[name]
        if fit_tilt_deg > 0 and name == reference:
            u0s[name], tilts[name] = _fit_u0_tilt(coefficients, g, angles, pairs, fit_u0_px, slope_coefficients,
                                                  fit_tilt_deg)
        # The tilt is the scanner's, not the angles': fitted with the reference, kept for the others.
        tilts.setdefault(name, tilts[reference] if fit_tilt_deg > 0 else 0.0)
        tilt = (slope_coefficients, math.tan(math.radians(tilts[name]))) if fit_tilt_deg > 0 else None
        if name not in u0s:
            u0s[name] = _fit_u0(coefficients, g, angles, pairs, fit_u0_px, tilt) if fit_u0_px > 0 else g.u0_px
        value = _mismatch(coefficients, g, angles, *pairs, u0s[name], tilt) ** 2 / scale
        # A ray a candidate puts off a detector cannot be checked: it counts as the reference has it.
        squared[name] = value if name == reference else np.where(np.isnan(value), squared[reference], value)
    squared = {name: squared[name] for name in sets}
    groups = pairs[0]
    n_groups = len(np.unique(groups))
    scores = {}
    for name, sq in squared.items():
        if name == reference:
            scores[name] = ConjugateRayScore(float(np.mean(sq)), u0s[name], len(sq), tilt_deg=tilts[name],
                                             paired_views=n_groups)
            continue
        diff = sq - squared[reference]
        per_view = np.bincount(groups, weights=diff, minlength=n_views)[np.unique(groups)]
        se, blocks = _blocked_se(per_view) if n_groups > 1 else (math.inf, 1)
        scores[name] = ConjugateRayScore(float(np.mean(sq)), u0s[name], len(sq), reference, float(np.mean(diff)),
                                         se / len(diff), blocks - 1, tilts[name], n_groups)
    return scores
