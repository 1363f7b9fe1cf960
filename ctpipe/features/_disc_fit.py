"""Sub-pixel ball centres by fitting the disc model: single balls, splits, crowds, dust.

:func:`_fit_all` fits every candidate (splitting a blob into 2, 3, 4 balls in a row where one
does not explain it), :func:`_clusters` resolves crowds of overlapping balls by their mass, and
:func:`_without_outliers` masks dust the model cannot explain. Used by :mod:`ctpipe.features.balls`.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ctpipe.features._disc_model import _levenberg_marquardt, _render, _Window, _window_of
from ctpipe.features._scale_space import _MIN_ROUNDNESS, _PAIR_EXTENT, _PAIR_ROUNDNESS

# Overlapping neighbours fitted jointly with a ball; further ones are masked out of its window.
_MAX_NUISANCE = 3
# Two balls replace one when they lower the sum of squares by this many noise variances.
_PAIR_EVIDENCE = 50.0
# Most balls a connected crowd is split into.
_MAX_CROWD = 12
# A fit is repeated without the pixels beyond this many robust deviations of its residual
# (dust on a ball), when they are fewer than this share of its window.
_OUTLIER_SIGMA = 12.0
_OUTLIER_PIXELS = 3
_MAX_OUTLIERS = 0.02


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
