"""The view graph of a scan: which view pairs to estimate and how their angles add up.

Views are taken in acquisition order. A full turn closes on itself: the last views are
neighbours of the first ones, so pairing them ("loop closure") turns the chain of pair angles
into a ring whose angles must add up to 360 deg, which removes the linear drift a chain
accumulates. A scan that goes on past one turn (a scanner's closing view at 360 deg, the
overlap of a 361 deg scan, a second turn) holds views taken at the same pose one turn apart:
those are paired too (:func:`turn_pairs`), so the whole turn is measured from the images.

The per-view angles solve the pair equations ``theta[j] - theta[i] = alpha_ij`` in the least
squares sense (:func:`chain_pair_angles`), or robustly (:func:`solve_pair_graph`): a pair whose
angle is grossly wrong (matches on a repeated structure, a slipped estimate) then stops
pulling the views around it once the other pairs through those views contradict it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu

from ctpipe.data import PairEstimate, ScanObservations, ScanSolution
from ctpipe.errors import InputError
from ctpipe.model import FailedEstimation, fit_angle
from ctpipe.solve.losses import Loss, check_loss, robust_weight
from ctpipe.solve.pairs import pair_estimate

__all__ = ["covers_full_turn", "turn_pairs", "view_pairs", "unwrap_pair_angles_deg", "chain_pair_angles", "solve_pair_graph",
           "PairGraphSolution", "solve_view_graph"]


def covers_full_turn(nominal_angles_deg) -> bool:
    """True when the nominal angles go all the way round in order, e.g. 360 views over 360 deg.

    The views must be monotonic and the gap from the last view back to the first (plus one or
    more full turns) no wider than 1.5 typical steps, so the last view is a neighbour of the first.
    """
    nominal = np.asarray(nominal_angles_deg, dtype=np.float64)
    if nominal.ndim != 1 or nominal.size < 3 or not np.all(np.isfinite(nominal)):
        return False
    steps = np.diff(nominal)
    if not (np.all(steps > 0) or np.all(steps < 0)):
        return False
    step = float(np.median(np.abs(steps)))
    span = abs(float(nominal[-1] - nominal[0])) + step
    turns = round(span / 360.0)
    return turns >= 1 and abs(span - 360.0 * turns) <= 0.5 * step


def turn_pairs(nominal_angles_deg) -> np.ndarray:
    """Pairs of views taken one turn apart, shape (K, 2), int64: ``(i, j)``, ``j > i``.

    View ``j`` is the view whose nominal angle lies nearest to one turn (360 deg, in the sense of
    the steps) after view ``i``'s, paired when it lies within half a typical step of it: the
    same pose, seen again. A Nikon or Waygate scan of a full turn saves ``Projections + 1``
    images, the last at 360 deg, which gives the one pair ``(0, V)``; a scan of 361 deg gives a
    pair for every view in its overlap; a scan of one turn or less gives none. The pair's angle,
    measured like any other, ties the end of the turn to its start: loop closure measured from
    the images, not assumed from the nominal angles.
    """
    nominal = np.asarray(nominal_angles_deg, dtype=np.float64)
    empty = np.zeros((0, 2), np.int64)
    if nominal.ndim != 1 or nominal.size < 2 or not np.all(np.isfinite(nominal)):
        return empty
    steps = np.diff(nominal)
    if not (np.all(steps > 0) or np.all(steps < 0)):
        return empty
    sense = 1.0 if steps[0] > 0 else -1.0
    ordered = sense * nominal  # increasing
    step = float(np.median(np.abs(steps)))
    target = ordered + 360.0
    j = np.clip(np.searchsorted(ordered, target), 1, nominal.size - 1)
    j = np.where(np.abs(ordered[j - 1] - target) < np.abs(ordered[j] - target), j - 1, j)
    keep = (np.abs(ordered[j] - target) <= 0.5 * step) & (j > np.arange(nominal.size))
    return np.stack([np.flatnonzero(keep), j[keep]], axis=1).astype(np.int64).reshape(-1, 2)


def view_pairs(n_views: int, baselines=(1,), nominal_angles_deg=None, *, loop_closure: bool = True) -> np.ndarray:
    """View pairs ``(i, i + k)`` for every baseline ``k``, shape (P, 2), int64.

    With ``loop_closure`` and nominal angles that cover a full turn (:func:`covers_full_turn`),
    the pairs wrap around: ``(i, (i + k) mod n_views)`` for the last ``k`` views too, so that
    every view has the same neighbours and the ring of pair angles closes. With
    ``loop_closure`` and nominal angles that go on past one turn, the views one turn apart are
    paired too (:func:`turn_pairs`), after the baselines' pairs.
    """
    closed = loop_closure and nominal_angles_deg is not None and covers_full_turn(nominal_angles_deg)
    pairs = []
    for k in baselines:
        stop = n_views if closed and k < n_views else n_views - k
        pairs.extend((i, (i + k) % n_views) for i in range(max(stop, 0)))
    if loop_closure and nominal_angles_deg is not None and len(nominal_angles_deg) == n_views:
        known = set(pairs)
        pairs.extend(pair for pair in map(tuple, turn_pairs(nominal_angles_deg).tolist()) if pair not in known)
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def unwrap_pair_angles_deg(pairs, pair_angles_deg, nominal_angles_deg=None) -> np.ndarray:
    """Pair angles as differences ``theta_j - theta_i`` of unwrapped view angles, degrees, shape (P,).

    An estimator returns a pair's turn in (-180, 180]; across the seam of a full turn the view
    angles differ by about 360 deg less (or more) than that. Each angle is moved by the whole
    number of turns that brings it nearest to the nominal difference. Without nominal angles
    the angles are returned as they are (pairs are assumed to turn by less than 180 deg).
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    angles = np.asarray(pair_angles_deg, dtype=np.float64).reshape(-1)
    if len(angles) != len(pairs):
        raise InputError(f"pair_angles_deg: must have one angle per pair ({len(pairs)}), got {len(angles)}")
    if nominal_angles_deg is None:
        return angles.copy()
    nominal = np.asarray(nominal_angles_deg, dtype=np.float64)
    expected = nominal[pairs[:, 1]] - nominal[pairs[:, 0]]
    return angles + 360.0 * np.round((expected - angles) / 360.0)


@dataclass(frozen=True, eq=False)
class PairGraphSolution:
    """Per-view angles solved from pair angles (:func:`solve_pair_graph`).

    Attributes
    ----------
    angles_deg : ndarray of shape (V,)
        Angle of every view relative to view 0 (``angles_deg[0] == 0``); NaN for views not
        connected to view 0 by usable pairs.
    residuals_deg : ndarray of shape (P,)
        ``theta[j] - theta[i] - alpha`` of every pair at the solution; NaN for pairs not used
        (NaN angle, zero weight, or outside view 0's component).
    robust_weights : ndarray of shape (P,)
        The loss's final weight of every pair in [0, 1] (1: fully trusted, as in plain least
        squares); 0 for pairs not used.
    n_iterations : int
        Reweighted solves after the first, plain one.
    converged : bool
        Whether the largest change of a view angle fell below the tolerance.
    """

    angles_deg: np.ndarray
    residuals_deg: np.ndarray
    robust_weights: np.ndarray
    n_iterations: int
    converged: bool


def _robust_weights(residuals: np.ndarray, loss: str, scale: float) -> np.ndarray:
    """IRLS weights ``rho'(z)`` with ``z = (r / scale)^2`` (:mod:`ctpipe.solve.losses`)."""
    return robust_weight((residuals / scale) ** 2, loss)


def _check_graph(n_views, pairs, angles, weights):
    if not isinstance(n_views, (int, np.integer)) or isinstance(n_views, bool) or n_views < 1:
        raise InputError(f"n_views: must be an integer >= 1, got {n_views!r}")
    pairs = np.asarray(pairs)
    if pairs.size == 0:
        pairs = pairs.reshape(0, 2)
    if pairs.ndim != 2 or pairs.shape[1] != 2 or not np.issubdtype(pairs.dtype, np.integer):
        raise InputError(f"pairs: must be an integer array of shape (P, 2), got {pairs.dtype} {pairs.shape}")
    if pairs.size and (pairs.min() < 0 or pairs.max() >= n_views):
        raise InputError(f"pairs: must index views 0..{n_views - 1}, got indices {pairs.min()}..{pairs.max()}")
    angles = np.asarray(angles, dtype=np.float64).reshape(-1)
    if len(angles) != len(pairs):
        raise InputError(f"pair angles: must have one angle per pair ({len(pairs)}), got {len(angles)}")
    w = np.ones(len(pairs)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if len(w) != len(pairs) or np.any(w < 0) or not np.all(np.isfinite(w)):
        raise InputError(f"weights: must be {len(pairs)} finite numbers >= 0, one per pair")
    return pairs.astype(np.int64), angles, w


@dataclass(frozen=True, eq=False)
class _GraphSolve:
    """What :func:`_solve` found, in the unit of the pair angles it was given."""

    angles: np.ndarray
    residuals: np.ndarray
    robust_weights: np.ndarray
    n_iterations: int
    converged: bool


def _solve(n_views: int, pairs: np.ndarray, angles: np.ndarray, w: np.ndarray, loss: str, scale: float,
           max_iterations: int, tolerance: float, pinned: np.ndarray | None = None) -> _GraphSolve:
    """Gauge ``theta[0] = 0``; angles in any unit, ``scale`` and ``tolerance`` in the same unit."""
    theta = np.full(n_views, np.nan)
    theta[0] = 0.0
    residuals = np.full(len(pairs), np.nan)
    robust = np.zeros(len(pairs))
    usable = np.isfinite(angles) & (w > 0) & (pairs[:, 0] != pairs[:, 1])
    if not usable.any():
        return _GraphSolve(theta, residuals, robust, 0, True)
    used = pairs[usable]
    graph = sp.coo_matrix((np.ones(len(used)), (used[:, 0], used[:, 1])), shape=(n_views, n_views))
    _, labels = connected_components(graph, directed=False)
    component = np.flatnonzero(labels == labels[0])
    if component.size == 1:
        return _GraphSolve(theta, residuals, robust, 0, True)
    position = np.full(n_views, -1)
    position[component] = np.arange(component.size)
    inside = usable & (position[pairs[:, 0]] >= 0) & (position[pairs[:, 1]] >= 0)
    i, j = position[pairs[inside, 0]], position[pairs[inside, 1]]
    alpha, prior = angles[inside], w[inside].copy()
    pin = np.zeros(alpha.size, bool) if pinned is None else pinned[inside]
    if pin.any():
        prior[pin] = PIN_WEIGHT * float(prior.max())
    rows = np.arange(inside.sum())
    # Incidence without view 0's column: the gauge theta[0] = 0 is built into the unknowns.
    incidence = sp.csr_matrix((np.r_[-np.ones(rows.size), np.ones(rows.size)], (np.r_[rows, rows], np.r_[i, j])),
                              shape=(rows.size, component.size))[:, 1:].tocsc()

    def solve(weights: np.ndarray) -> np.ndarray:
        weighted = incidence.multiply(weights[:, None]).tocsc()
        normal = (incidence.T @ weighted).tocsc()
        x = np.zeros(component.size)
        x[1:] = splu(normal).solve(weighted.T @ alpha)
        return x

    weights = np.ones(rows.size)
    x = solve(prior)
    iterations, converged = 0, loss == "linear"
    while not converged and iterations < max_iterations:
        weights = np.where(pin, 1.0, _robust_weights(x[j] - x[i] - alpha, loss, scale))
        previous, x = x, solve(prior * weights)
        iterations += 1
        converged = float(np.max(np.abs(x - previous))) <= tolerance
    theta[component] = x
    residuals[inside] = x[j] - x[i] - alpha
    robust[inside] = np.where(pin, 1.0, _robust_weights(residuals[inside], loss, scale))
    return _GraphSolve(theta, residuals, robust, iterations, converged)


def chain_pair_angles(n_views: int, pairs, angles_rad, weights=None) -> np.ndarray:
    """Per-view angles from relative pair angles by weighted least squares on the view graph.

    Solves ``min sum_k w_k (theta[j_k] - theta[i_k] - angles_rad[k])^2`` with ``theta[0] = 0``.
    With consecutive pairs only this is the running sum. Pairs with a NaN angle are ignored;
    views not connected to view 0 get NaN.

    Parameters
    ----------
    n_views : int
    pairs : ndarray of shape (P, 2), int
    angles_rad : ndarray of shape (P,)
        Unwrapped pair angles (:func:`unwrap_pair_angles_deg`), radians.
    weights : ndarray of shape (P,), optional
        Non-negative; 0 drops a pair.

    Returns
    -------
    ndarray of shape (n_views,), radians
    """
    pairs, angles, w = _check_graph(n_views, pairs, angles_rad, weights)
    return _solve(int(n_views), pairs, angles, w, "linear", 1.0, 0, 0.0).angles


#: How much more a pinned pair weighs than the heaviest other pair: enough to hold it to ~1e-6 of
#: the misclosure, little enough for the normal equations to stay well conditioned.
PIN_WEIGHT = 1e6


def solve_pair_graph(n_views: int, pairs, pair_angles_deg, weights=None, *,
                     loss: Literal["linear", "soft-l1", "huber", "cauchy"] = "soft-l1", scale_deg: float = 0.1,
                     max_iterations: int = 100, tolerance_deg: float = 1e-7, pinned=None) -> PairGraphSolution:
    """Per-view angles from pair angles with a robust loss, by iteratively reweighted least squares.

    Minimises ``sum_k w_k rho((theta[j_k] - theta[i_k] - alpha_k)^2 / scale_deg^2)`` with
    ``theta[0] = 0``, ``rho`` the loss of ``scipy.optimize.least_squares`` of that name
    (``linear``: plain least squares). Each iteration solves the sparse normal equations of the
    incidence system with the weights ``w_k rho'(z_k)`` of the previous residuals, starting
    from the plain least-squares solution. Residuals much larger than ``scale_deg`` get a
    weight ~ ``scale_deg / |r|`` (soft-l1, huber) or ~ ``(scale_deg / r)^2`` (cauchy), so a
    gross outlier pair stops dragging its views once other pairs (other baselines, the seam of
    a full turn) tie them.

    Parameters
    ----------
    n_views : int
    pairs : ndarray of shape (P, 2), int
    pair_angles_deg : ndarray of shape (P,)
        ``theta[j] - theta[i]`` measured, already unwrapped (:func:`unwrap_pair_angles_deg`);
        NaN for failed pairs, which are ignored.
    weights : ndarray of shape (P,), optional
        Prior weight of each pair (e.g. its inlier count), >= 0; 0 drops a pair.
    pinned : ndarray of shape (P,), bool, optional
        Pairs held to their measured angle (:data:`PIN_WEIGHT` times the heaviest pair, never
        down-weighted): the pairs of views one turn apart (:func:`turn_pairs`), whose angle is
        the whole turn measured at once. Under a robust loss a single loop-closing pair would
        otherwise take the chain's whole misclosure as its own residual and be voted out, which
        leaves the chain's drift (a scale bias of the pair angles, say) in the answer.
    loss : {"soft-l1", "huber", "cauchy", "linear"}
    scale_deg : float
        Residual (degrees) up to which a pair counts as an inlier; > 0. About the spread of the
        good pairs' errors.
    max_iterations : int
        Reweighted solves at most.
    tolerance_deg : float
        Stop when no view angle moves by more than this between iterations.

    Returns
    -------
    PairGraphSolution
        Views not connected to view 0 get NaN. Without any conflicting pair (a chain, or
        noise-free pairs) the answer is the exact least-squares one.
    """
    check_loss(loss)
    if not (isinstance(scale_deg, (int, float)) and np.isfinite(scale_deg) and scale_deg > 0):
        raise InputError(f"scale_deg: must be a finite number > 0, got {scale_deg!r}")
    if not isinstance(max_iterations, (int, np.integer)) or max_iterations < 0:
        raise InputError(f"max_iterations: must be an integer >= 0, got {max_iterations!r}")
    pairs, angles, w = _check_graph(n_views, pairs, pair_angles_deg, weights)
    pin = np.zeros(len(pairs), bool) if pinned is None else np.asarray(pinned, dtype=bool).reshape(-1)
    if pin.size != len(pairs):
        raise InputError(f"pinned: must be {len(pairs)} booleans, one per pair, got {pin.size}")
    found = _solve(int(n_views), pairs, angles, w, loss, float(scale_deg), int(max_iterations), float(tolerance_deg),
                   pin)
    return PairGraphSolution(found.angles, found.residuals, found.robust_weights, found.n_iterations, found.converged)


def solve_view_graph(observations: ScanObservations, *, objective: Literal["sampson", "tls"] = "sampson",
                     weighting: Literal["uniform", "inliers"] = "uniform", loss: Loss = "soft-l1",
                     scale_deg: float = 0.1) -> ScanSolution:
    """Per-view angles of a scan: every pair refit on its inliers, then the view graph solved robustly.

    Each pair estimate is refit on its inlier correspondences (:func:`ctpipe.model.fit_angle`
    with ``objective``), its angle unwrapped against the nominal ones
    (:func:`unwrap_pair_angles_deg`), and all pairs solved at once (:func:`solve_pair_graph`),
    weighted equally or by their inlier count; pairs of views one turn apart (:func:`turn_pairs`)
    are pinned. What the ``least-squares`` refiner does, and projection matching's default start.

    Returns
    -------
    ScanSolution
        The refit pair estimates, and in ``info`` the loss, iterations, pairs used and
        down-weighted, the median pair residual, views left without an angle and pinned pairs.
    """
    refined: list[PairEstimate | FailedEstimation] = []
    for q_a, q_b, estimate in zip(observations.points_a, observations.points_b, observations.estimates):
        if not estimate:
            refined.append(estimate)
            continue
        mask = estimate.inlier_mask
        alpha = fit_angle(q_a[mask], q_b[mask], objective=objective)
        refined.append(alpha if isinstance(alpha, FailedEstimation) else pair_estimate(alpha, mask, q_a, q_b))
    angles_deg = unwrap_pair_angles_deg(observations.pairs, np.rad2deg([e.angle_rad if e else np.nan for e in refined]),
                                        observations.nominal_angles_deg)
    weights = np.array([e.n_inliers if e else 0 for e in refined], dtype=np.float64)
    pinned = _turn_pair_mask(observations)
    graph = solve_pair_graph(observations.n_views, observations.pairs, angles_deg,
                             weights if weighting == "inliers" else None, loss=loss, scale_deg=scale_deg, pinned=pinned)
    used = graph.robust_weights > 0
    info = {"loss": loss, "scale_deg": scale_deg, "iterations": graph.n_iterations,
            "converged": graph.converged, "pairs_used": int(used.sum()),
            "pairs_down_weighted": int(np.count_nonzero(graph.robust_weights[used] < 0.5)),
            "median_abs_residual_deg": float(np.median(np.abs(graph.residuals_deg[used]))) if used.any() else None,
            "views_without_angle": int(np.count_nonzero(np.isnan(graph.angles_deg))),
            "pinned_turn_pairs": int(np.count_nonzero(pinned & np.isfinite(angles_deg)))}
    return ScanSolution(angles_rad=np.deg2rad(graph.angles_deg), pair_estimates=tuple(refined), info=info)


def _turn_pair_mask(observations: ScanObservations) -> np.ndarray:
    """Which of the observed pairs join views one turn apart (:func:`turn_pairs`)."""
    pinned = np.zeros(len(observations.pairs), bool)
    if observations.nominal_angles_deg is None:
        return pinned
    turns = {tuple(pair) for pair in turn_pairs(observations.nominal_angles_deg).tolist()}
    if turns:
        pinned[:] = [tuple(pair) in turns for pair in observations.pairs.tolist()]
    return pinned
