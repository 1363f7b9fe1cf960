"""Circular bundle adjustment: every view angle and a 3-D point per track, in one least-squares fit.

Unknowns are the turntable angle of every view (the views in ``fixed_views`` stay where they
are: the gauge, normally view 0), the object-frame point of every track, and optionally the
detector's principal point ``u0_px`` (the centre of rotation), ``v0_px`` and its in-plane
``tilt_rad`` (model of :mod:`ctpipe.solve.camera`). The residual of an observation is its
reprojection error in pixels; a robust loss (soft-L1 or Huber with a scale in pixels) keeps
wrong matches from pulling.

Solver
------
Levenberg-Marquardt on the normal equations with the 3x3 point blocks eliminated (Schur
complement): the reduced system over the free angles (and the few detector unknowns) is dense,
``V x V``, and solved by Cholesky. Its cost is ``O(V^3)`` per iteration plus ``O(sum of track
length^2)`` to assemble, independent of the number of points otherwise; see
``benchmarks/bench_refiners.py``. The robust loss enters through per-observation weights
``rho'(|r|^2)`` (iteratively reweighted, the Triggs correction left out), steps are accepted on
the robust cost itself.

:func:`solve_bundle` runs the whole thing on a scan: tracks from the verified matches, static
tracks dropped, bundle adjustment, outliers dropped, then rounds of guided track extension and
re-adjustment.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg  # noqa: F401  (sp.linalg)

from ctpipe.data import ScanObservations
from ctpipe.errors import InputError
from ctpipe.geometry import Geometry
from ctpipe.stages import Parameters, param
from ctpipe.solve.camera import _project, projection_jacobians
from ctpipe.solve.graph import chain_pair_angles, covers_full_turn, unwrap_pair_angles_deg
from ctpipe.solve.losses import check_loss, robust_loss
from ctpipe.solve.tracks import (Tracks, build_tracks, extend_tracks, static_tracks, triangulate_tracks,
                                 verified_match_distances)

__all__ = ["BundleResult", "BundleSettings", "BundleSolution", "bundle_adjust", "solve_bundle", "pair_graph_angles"]

@dataclass(frozen=True, eq=False)
class BundleResult:
    """What :func:`bundle_adjust` found.

    Attributes
    ----------
    angles_rad : ndarray of shape (V,)
        Adjusted view angles (fixed and unobserved views as given).
    points_mm : ndarray of shape (T, 3)
        Adjusted object-frame point of every track.
    geometry : Geometry
        The input geometry with the adjusted ``u0_px``/``v0_px``.
    tilt_rad : float
        Adjusted in-plane detector tilt.
    residuals_px : ndarray of shape (N, 2)
        Final reprojection errors (prediction - observation), pixels.
    rms_px_initial, rms_px_final : float
        RMS reprojection error norm before and after.
    cost_initial, cost_final : float
        Half the summed robust cost, pixels squared.
    iterations : int
        Accepted Levenberg-Marquardt steps.
    converged : bool
    seconds : float
    """

    angles_rad: np.ndarray
    points_mm: np.ndarray
    geometry: Geometry
    tilt_rad: float
    residuals_px: np.ndarray
    rms_px_initial: float
    rms_px_final: float
    cost_initial: float
    cost_final: float
    iterations: int
    converged: bool
    seconds: float


class _Problem:
    """Residuals, Jacobian blocks and the Schur-complement step of one bundle adjustment."""

    def __init__(self, tracks: Tracks, geometry: Geometry, free_view: np.ndarray, detector: tuple[bool, bool, bool],
                 loss: str, scale_px: float):
        self.tracks = tracks
        self.geometry = geometry
        self.loss, self.scale = loss, scale_px
        self.detector = np.array(detector, bool)
        # Column of each view in the reduced system, -1 for fixed ones.
        self.column = np.full(tracks.n_views, -1, np.int64)
        self.free_views = np.flatnonzero(free_view)
        self.column[self.free_views] = np.arange(self.free_views.size)
        self.n_angles = self.free_views.size
        self.n_detector = int(self.detector.sum())
        self.obs_column = self.column[tracks.view]

    def evaluate(self, angles, points, detector_values):
        """Residuals and their Jacobian blocks at a point of the parameter space."""
        geometry = dataclasses.replace(self.geometry, u0_px=float(detector_values[0]), v0_px=float(detector_values[1]))
        uv, d_angle, d_point, d_detector = projection_jacobians(points[self.tracks.track], angles[self.tracks.view],
                                                                geometry, tilt_rad=float(detector_values[2]))
        return uv - self.tracks.xy_px, d_angle, d_point, d_detector[:, :, self.detector]

    def residuals(self, angles, points, detector_values):
        """Residuals only (a trial step is judged on its cost before any Jacobian is worth computing)."""
        geometry = dataclasses.replace(self.geometry, u0_px=float(detector_values[0]), v0_px=float(detector_values[1]))
        return _project(points[self.tracks.track], angles[self.tracks.view], geometry,
                        float(detector_values[2])) - self.tracks.xy_px

    def cost(self, residuals) -> float:
        rho, _ = robust_loss(np.sum(residuals**2, axis=1), self.loss, self.scale)
        return 0.5 * float(np.sum(rho)) if np.all(np.isfinite(rho)) else np.inf

    def normal_blocks(self, residuals, d_angle, d_point, d_detector):
        t = self.tracks
        _, w = robust_loss(np.sum(residuals**2, axis=1), self.loss, self.scale)
        n_t = t.n_tracks
        wa = d_angle * w[:, None]
        wp = d_point * w[:, None, None]
        free = self.obs_column >= 0
        blocks = {}
        blocks["C_aa"] = np.bincount(self.obs_column[free], np.sum(wa * d_angle, axis=1)[free], self.n_angles)
        blocks["g_a"] = np.bincount(self.obs_column[free], np.sum(wa * residuals, axis=1)[free], self.n_angles)
        pp = (wp[:, 0, :, None] * d_point[:, 0, None, :] + wp[:, 1, :, None] * d_point[:, 1, None, :]).reshape(-1, 9)
        blocks["P"] = np.stack([np.bincount(t.track, pp[:, k], n_t) for k in range(9)], axis=1).reshape(n_t, 3, 3)
        gp = wp[:, 0, :] * residuals[:, :1] + wp[:, 1, :] * residuals[:, 1:]
        blocks["g_p"] = np.stack([np.bincount(t.track, gp[:, k], n_t) for k in range(3)], axis=1)
        blocks["W_a"] = wa[:, :1] * d_point[:, 0, :] + wa[:, 1:] * d_point[:, 1, :]  # (N, 3), one (view, track) each
        if self.n_detector:
            wd = d_detector * w[:, None, None]
            blocks["C_dd"] = np.einsum("nki,nkj->ij", wd, d_detector)
            blocks["g_d"] = np.einsum("nki,nk->i", wd, residuals)
            ad = np.einsum("nk,nkj->nj", wa, d_detector)
            blocks["C_ad"] = np.stack([np.bincount(self.obs_column[free], ad[free, k], self.n_angles)
                                       for k in range(self.n_detector)], axis=1)
            dp = np.einsum("nki,nkj->nij", wd, d_point).reshape(len(w), -1)
            blocks["W_d"] = np.stack([np.bincount(t.track, dp[:, k], n_t) for k in range(dp.shape[1])],
                                     axis=1).reshape(n_t, self.n_detector, 3)
        return blocks

    def solve(self, blocks, damping: float):
        """The Levenberg-Marquardt step ``(d_angles, d_points, d_detector)`` at one damping."""
        t = self.tracks
        n_a, n_d, n_t = self.n_angles, self.n_detector, t.n_tracks
        point_diag = np.diagonal(blocks["P"], axis1=1, axis2=2)
        floor = 1e-12 * max(float(point_diag.max(initial=0.0)), 1e-300)
        P = blocks["P"] + (damping * point_diag + floor)[:, :, None] * np.eye(3)
        P_inv = np.linalg.inv(P)
        free = self.obs_column >= 0
        obs = np.flatnonzero(free)
        # Y = W P^-1 restricted to the free angles: one 1x3 block per observation.
        Y_a = np.einsum("nj,njk->nk", blocks["W_a"][obs], P_inv[t.track[obs]])
        rows = np.repeat(self.obs_column[obs], 3)
        cols = (3 * t.track[obs][:, None] + np.arange(3)).ravel()
        shape = (n_a, 3 * n_t)
        Y = sp.csr_matrix((Y_a.ravel(), (rows, cols)), shape=shape)
        W = sp.csr_matrix((blocks["W_a"][obs].ravel(), (rows, cols)), shape=shape)
        size = n_a + n_d
        c_aa = blocks["C_aa"]
        diagonal = c_aa * (1.0 + damping) + 1e-12 * max(float(c_aa.max(initial=0.0)), 1e-300)
        S_aa = (sp.diags(diagonal) - Y @ W.T).tocsr()
        # rhs: -g_c + W P^-1 g_p
        p_g = np.einsum("tij,tj->ti", P_inv, blocks["g_p"])
        rhs = np.zeros(size)
        rhs[:n_a] = -blocks["g_a"] + W @ p_g.ravel()
        if n_d:
            W_d = blocks["W_d"]  # (T, n_d, 3)
            Y_d = np.einsum("tdj,tjk->tdk", W_d, P_inv)  # (T, n_d, 3)
            Wd_flat = W_d.transpose(1, 0, 2).reshape(n_d, -1)
            Yd_flat = Y_d.transpose(1, 0, 2).reshape(n_d, -1)
            S_ad = blocks["C_ad"] - Y @ Wd_flat.T
            c_dd = blocks["C_dd"]
            S_dd = c_dd + damping * np.diag(np.diag(c_dd)) - Yd_flat @ Wd_flat.T
            S_dd += 1e-12 * max(float(np.abs(np.diag(c_dd)).max(initial=0.0)), 1e-300) * np.eye(n_d)
            rhs[n_a:] = -blocks["g_d"] + Wd_flat @ p_g.ravel()
        else:
            S_ad, S_dd = np.zeros((n_a, 0)), np.zeros((0, 0))
        step_c = _solve_reduced(S_aa, np.asarray(S_ad), S_dd, rhs)
        step_a, step_d = step_c[:n_a], step_c[n_a:]
        # Back-substitution: d_p = P^-1 (-g_p - W^T d_c).
        wt = np.zeros((n_t, 3))
        contribution = blocks["W_a"][obs] * step_a[self.obs_column[obs]][:, None]
        for k in range(3):
            wt[:, k] = np.bincount(t.track[obs], contribution[:, k], n_t)
        if n_d:
            wt += np.einsum("tdj,d->tj", blocks["W_d"], step_d)
        step_p = np.einsum("tij,tj->ti", P_inv, -blocks["g_p"] - wt)
        return step_a, step_p, step_d

    def predicted_decrease(self, blocks, step_a, step_p, step_d, damping) -> float:
        """Decrease of the Gauss-Newton model (its damped form, as Nielsen's gain ratio uses)."""
        point_diag = np.diagonal(blocks["P"], axis1=1, axis2=2)
        g = -(np.dot(step_a, blocks["g_a"]) + np.sum(step_p * blocks["g_p"]))
        d = damping * (np.dot(step_a**2, blocks["C_aa"]) + np.sum(step_p**2 * point_diag))
        if self.n_detector:
            g -= np.dot(step_d, blocks["g_d"])
            d += damping * np.dot(step_d**2, np.diag(blocks["C_dd"]))
        return 0.5 * (g + d)


def _solve_reduced(S_aa: sp.csr_matrix, S_ad: np.ndarray, S_dd: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve the symmetric positive definite reduced system ``[[S_aa, S_ad], [S_ad^T, S_dd]] x = rhs``.

    Short tracks tie only nearby views, so ``S_aa`` is banded (plus the corners of a closed
    turn): sparse LU in a fill-reducing order. Long tracks make it dense: Cholesky.
    """
    n_a, n_d = S_aa.shape[0], S_dd.shape[0]
    size = n_a + n_d
    if size == 0:
        return np.zeros(0)
    if S_aa.nnz > 0.3 * n_a * n_a or n_a < 50:
        S = np.empty((size, size))
        S[:n_a, :n_a] = S_aa.toarray()
        S[:n_a, n_a:] = S_ad
        S[n_a:, :n_a] = S_ad.T
        S[n_a:, n_a:] = S_dd
        try:
            return scipy.linalg.cho_solve(scipy.linalg.cho_factor(S, lower=True, check_finite=False), rhs,
                                          check_finite=False)
        except (np.linalg.LinAlgError, ValueError):
            return scipy.linalg.solve(S, rhs, assume_a="sym", check_finite=False)
    S = sp.bmat([[S_aa, sp.csr_matrix(S_ad)], [sp.csr_matrix(S_ad.T), sp.csr_matrix(S_dd)]], format="csc")
    factor = sp.linalg.splu(S, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return factor.solve(rhs)


def bundle_adjust(tracks: Tracks, angles_rad, points_mm, geometry: Geometry, *, tilt_rad: float = 0.0,
                  fixed_views=(0,), estimate_u0: bool = False, estimate_v0: bool = False, estimate_tilt: bool = False,
                  loss: Literal["soft-l1", "huber", "linear"] = "soft-l1", loss_scale_px: float = 1.0,
                  max_iterations: int = 50, tolerance: float = 1e-8) -> BundleResult:
    """Adjust view angles, track points and (optionally) the detector to the observed keypoints.

    Parameters
    ----------
    tracks : Tracks
        The observations (pixels).
    angles_rad : ndarray of shape (V,)
        Start angles; views with a NaN angle or without observations are left out (and returned
        as given).
    points_mm : ndarray of shape (T, 3)
        Start point of every track, e.g. :func:`ctpipe.solve.tracks.triangulate_tracks`.
    geometry : Geometry
        SOD, SDD, pitches and the start principal point.
    tilt_rad : float
        Start in-plane detector tilt.
    fixed_views : sequence of int
        Views whose angle is held (the gauge: one is enough, view 0 by default).
    estimate_u0, estimate_v0, estimate_tilt : bool
        Also adjust the principal point's column (the centre of rotation), its row, the tilt.
    loss : {"soft-l1", "huber", "linear"}
    loss_scale_px : float
        Residual norm (pixels) where the robust loss starts to flatten.
    max_iterations : int
        Levenberg-Marquardt iterations (each solves the reduced system at least once).
    tolerance : float
        Stop when an iteration decreases the cost by less than this fraction, or moves no angle
        by more than ``tolerance / 1000`` radians (noise-free data converge to ~1e-12 rad).

    Returns
    -------
    BundleResult
    """
    start = time.perf_counter()
    angles = np.array(angles_rad, dtype=np.float64)
    points = np.array(points_mm, dtype=np.float64)
    if angles.shape != (tracks.n_views,):
        raise InputError(f"angles_rad: must have one angle per view ({tracks.n_views},), got {angles.shape}")
    if points.shape != (tracks.n_tracks, 3):
        raise InputError(f"points_mm: must have shape ({tracks.n_tracks}, 3), one point per track, got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise InputError("points_mm: must be finite, got NaN or infinite values")
    if not (loss_scale_px > 0):
        raise InputError(f"loss_scale_px: must be > 0, got {loss_scale_px!r}")
    check_loss(loss)
    fixed = np.asarray(fixed_views, dtype=np.int64).reshape(-1)
    if fixed.size and (fixed.min() < 0 or fixed.max() >= tracks.n_views):
        raise InputError(f"fixed_views: must index views 0..{tracks.n_views - 1}, got {fixed.tolist()}")
    unknown = np.unique(tracks.view[~np.isfinite(angles[tracks.view])])
    if unknown.size:
        raise InputError(f"angles_rad: every observed view needs a finite start angle, got NaN for views "
                         f"{unknown[:10].tolist()}{' ...' if unknown.size > 10 else ''}")
    observed = np.zeros(tracks.n_views, bool)
    observed[tracks.view] = True
    if len(tracks) and not observed[fixed].any():
        raise InputError(f"fixed_views: none of views {fixed.tolist()} is observed by a track, so nothing would hold "
                         "the angles (they could all turn together); fix an observed view")
    free_view = observed & np.isfinite(angles)
    free_view[fixed] = False
    detector_flags = (estimate_u0, estimate_v0, estimate_tilt)
    detector_values = np.array([geometry.u0_px, geometry.v0_px, tilt_rad], dtype=np.float64)
    problem = _Problem(tracks, geometry, free_view, detector_flags, loss, loss_scale_px)
    residuals = problem.residuals(angles, points, detector_values)
    cost = problem.cost(residuals)
    cost_initial = cost
    rms_initial = float(np.sqrt(np.mean(np.sum(residuals**2, axis=1)))) if len(tracks) else 0.0
    damping, growth = 1e-4, 2.0
    iterations, converged = 0, len(tracks) == 0
    for _ in range(max_iterations if len(tracks) else 0):
        residuals, *jacobians = problem.evaluate(angles, points, detector_values)
        blocks = problem.normal_blocks(residuals, *jacobians)
        accepted = False
        for _attempt in range(20):
            step_a, step_p, step_d = problem.solve(blocks, damping)
            new_angles = angles.copy()
            new_angles[problem.free_views] += step_a
            new_points = points + step_p
            new_detector = detector_values.copy()
            new_detector[problem.detector] += step_d
            new_residuals = problem.residuals(new_angles, new_points, new_detector)
            new_cost = problem.cost(new_residuals)
            predicted = problem.predicted_decrease(blocks, step_a, step_p, step_d, damping)
            if new_cost < cost:
                gain = (cost - new_cost) / predicted if predicted > 0 else 1.0
                damping *= max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
                growth = 2.0
                accepted = True
                break
            damping *= growth
            growth *= 2.0
        if not accepted:
            converged = True
            break
        iterations += 1
        decrease = cost - new_cost
        angles, points, detector_values = new_angles, new_points, new_detector
        residuals, cost = new_residuals, new_cost
        largest_step = float(np.max(np.abs(step_a), initial=0.0))
        if decrease <= tolerance * max(cost, 1e-300) or largest_step < 1e-3 * tolerance or cost < 1e-30:
            converged = True
            break
    rms_final = float(np.sqrt(np.mean(np.sum(residuals**2, axis=1)))) if len(tracks) else 0.0
    adjusted = dataclasses.replace(geometry, u0_px=float(detector_values[0]), v0_px=float(detector_values[1]))
    return BundleResult(angles_rad=angles, points_mm=points, geometry=adjusted, tilt_rad=float(detector_values[2]),
                        residuals_px=residuals, rms_px_initial=rms_initial, rms_px_final=rms_final,
                        cost_initial=float(cost_initial), cost_final=float(cost), iterations=iterations,
                        converged=bool(converged), seconds=time.perf_counter() - start)


@dataclass(frozen=True)
class BundleSettings(Parameters):
    """How :func:`solve_bundle` builds tracks and adjusts them: declared once, with bounds.

    The ``bundle-adjustment`` refiner (:mod:`ctpipe.builtin.bundle`) subclasses these, so they
    are its parameters too, validated the same way from Python and YAML. Static tracks:
    :func:`ctpipe.solve.tracks.static_tracks`.
    """

    loss: Literal["soft-l1", "huber", "linear"] = param("soft-l1", doc="robust loss of the reprojection error")
    loss_scale_px: float = param(0.5, doc="reprojection error (px) where the robust loss starts to flatten", gt=0,
                                  le=1000)
    min_track_length: int = param(2, doc="drop tracks seen in fewer views", ge=2, le=100_000)
    outlier_threshold_px: float = param(0.8, doc="drop observations with a larger reprojection error (px)", gt=0,
                                         le=1000)
    extension_rounds: int = param(0, doc="rounds of guided track extension, each followed by an adjustment", ge=0,
                                 le=100)
    extension_radius_px: float = param(0.8, doc="largest distance (px) from a track's prediction to a keypoint it takes",
                                       gt=0, le=1000)
    extension_window_views: int = param(8, doc="views beyond its observations a track is searched in per round", ge=1,
                                        le=100_000)
    descriptor_quantile: float = param(
        0.95, doc="a keypoint joins a track within this quantile of the verified matches' descriptor distances",
        gt=0, le=1)
    drop_static: bool = param(True, doc="drop tracks that stay put where a rigid point would move (silhouettes, defects)")
    static_min_motion_px: float = param(1.0, doc="judge a track static only if a rigid point would move this much (px)",
                                        gt=0, le=1000)
    static_fraction: float = param(0.5, doc="static: moving less than this share of a rigid point's motion", gt=0, lt=1)
    estimate_u0: bool = param(False, doc="also adjust the principal point column (centre of rotation)")
    estimate_v0: bool = param(False, doc="also adjust the principal point row")
    estimate_tilt: bool = param(False, doc="also adjust the in-plane detector tilt")
    max_iterations: int = param(50, doc="Levenberg-Marquardt iterations per adjustment", ge=1, le=10_000)


@dataclass(frozen=True, eq=False)
class BundleSolution:
    """What :func:`solve_bundle` found for a scan.

    Attributes
    ----------
    angles_rad : ndarray of shape (V,)
        Angle of every view relative to view 0 (``angles_rad[0] == 0``); NaN where a view has
        neither a pair-graph angle nor a nominal one.
    info : dict
        Plain JSON figures: tracks, lengths, observations, dropped static tracks and outliers,
        RMS reprojection error before and after, iterations, seconds; ``fallback`` says why the
        pair graph was returned when there was nothing to adjust.
    tracks : Tracks
        The final tracks.
    points_mm : ndarray of shape (T, 3)
        Their adjusted object-frame points.
    geometry : Geometry
        The geometry with the adjusted principal point (as given unless estimated).
    tilt_rad : float
        The adjusted in-plane detector tilt (0 unless estimated).
    """

    angles_rad: np.ndarray
    info: dict[str, Any]
    tracks: Tracks
    points_mm: np.ndarray
    geometry: Geometry
    tilt_rad: float = 0.0


def pair_graph_angles(observations: ScanObservations) -> np.ndarray:
    """Per-view angles (rad, view 0 = 0) chained from the pair estimates, weighted by inliers.

    Pair angles are unwrapped against the nominal ones (seam pairs of a full turn), then solved
    by least squares on the view graph (:func:`ctpipe.solve.graph.chain_pair_angles`);
    views not connected to view 0 are NaN.
    """
    estimates = observations.estimates
    angles_deg = unwrap_pair_angles_deg(observations.pairs, np.rad2deg([e.angle_rad if e else np.nan for e in estimates]),
                                        observations.nominal_angles_deg)
    weights = np.array([e.n_inliers if e else 0 for e in estimates], dtype=np.float64)
    return chain_pair_angles(observations.n_views, observations.pairs, np.deg2rad(angles_deg), weights)


def _keep_observations(tracks: Tracks, keep: np.ndarray, points: np.ndarray, min_length: int):
    """Select observations and carry each surviving track's point along."""
    counts = np.bincount(tracks.track[keep], minlength=tracks.n_tracks)
    kept_ids = np.flatnonzero(counts >= min_length)
    return tracks.select(keep, min_length=min_length), points[kept_ids]


def solve_bundle(observations: ScanObservations, settings: BundleSettings | None = None, *,
                 start_angles_rad=None) -> BundleSolution:
    """Angles of every view of a scan by bundle adjustment of its feature tracks.

    Steps: start angles (given, or the pair graph :func:`pair_graph_angles`, views it cannot
    reach filled from the nominal angles); tracks from the verified matches
    (:func:`ctpipe.solve.tracks.build_tracks`); static tracks dropped; linear triangulation;
    bundle adjustment with view 0 fixed; observations beyond ``outlier_threshold_px`` dropped and
    adjusted again; then ``extension_rounds`` rounds of guided extension
    (:func:`ctpipe.solve.tracks.extend_tracks`) each followed by an adjustment.

    Parameters
    ----------
    observations : ScanObservations
        Features, matches and pair estimates of the whole scan.
    settings : BundleSettings, optional
    start_angles_rad : ndarray of shape (V,), optional
        Start angles (view 0 first); default the pair graph's.

    Returns
    -------
    BundleSolution
        With no features or no track (nothing to adjust) the start angles, and
        ``info["fallback"]`` saying why.
    """
    settings = settings or BundleSettings()
    clock = time.perf_counter()
    n_views = observations.n_views
    if start_angles_rad is None:
        start = pair_graph_angles(observations)
    else:
        start = np.array(start_angles_rad, dtype=np.float64)
        if start.shape != (n_views,):
            raise InputError(f"start_angles_rad: must have one angle per view ({n_views},), got {start.shape}")
    nominal = observations.nominal_angles_deg
    if nominal is not None and np.isfinite(start[0]):
        missing = ~np.isfinite(start)
        start[missing] = start[0] + np.deg2rad(np.asarray(nominal)[missing] - nominal[0])
    geometry = observations.geometry
    info: dict[str, Any] = {"start": "given" if start_angles_rad is not None else "pair graph"}
    tracks = build_tracks(observations, min_length=settings.min_track_length)
    tracks = tracks.select(np.isfinite(start[tracks.view]), min_length=settings.min_track_length)
    info["initial_tracks"] = tracks.summary()

    def fallback(reason: str) -> BundleSolution:
        angles = start - start[0] if np.isfinite(start[0]) else start
        info["fallback"] = reason
        info["seconds"] = time.perf_counter() - clock
        return BundleSolution(angles, info, tracks, np.zeros((tracks.n_tracks, 3)), geometry)

    if not observations.features:
        return fallback("no features to build tracks from: pair-graph angles returned")
    if tracks.n_tracks == 0:
        return fallback("no feature tracks (no verified matches): pair-graph angles returned")
    if settings.drop_static:
        static = static_tracks(tracks, start, geometry, min_motion_px=settings.static_min_motion_px,
                               static_fraction=settings.static_fraction)
        info["static_tracks"] = int(static.sum())
        tracks = tracks.select_tracks(~static)
        if tracks.n_tracks == 0:
            return fallback("every feature track is static: pair-graph angles returned")
    observed = np.zeros(n_views, bool)
    observed[tracks.view] = True
    fixed = 0 if observed[0] else int(np.flatnonzero(observed)[0])
    info["fixed_view"] = fixed
    wrap = nominal is not None and covers_full_turn(nominal)
    distances = verified_match_distances(observations)
    max_distance = float(np.quantile(distances, settings.descriptor_quantile)) if distances.size else np.inf
    options = dict(fixed_views=(fixed,), estimate_u0=settings.estimate_u0, estimate_v0=settings.estimate_v0,
                   estimate_tilt=settings.estimate_tilt, loss=settings.loss, loss_scale_px=settings.loss_scale_px,
                   max_iterations=settings.max_iterations)
    angles, tilt = start.copy(), 0.0
    points = triangulate_tracks(tracks, angles, geometry)
    # Screen before the angles move: a track chained through one wrong (but epipolar-consistent)
    # match cannot be fitted by one point at the start angles, which are locally good; left in,
    # it would turn the angles to fit itself (a two-view track can, at the cost of nothing).
    screen = bundle_adjust(tracks, angles, points, geometry, fixed_views=np.arange(n_views), loss=settings.loss,
                           loss_scale_px=settings.loss_scale_px, max_iterations=settings.max_iterations)
    bad = np.sqrt(np.sum(screen.residuals_px**2, axis=1)) > settings.outlier_threshold_px
    info["screened_observations"] = int(bad.sum())
    tracks, points = _keep_observations(tracks, ~bad, screen.points_mm, settings.min_track_length)
    if tracks.n_tracks == 0 or not np.isin(fixed, tracks.view):
        return fallback("no feature track fits one point at the start angles: pair-graph angles returned")
    rounds, iterations, outliers, added, merged = [], 0, 0, 0, 0
    rms_initial = None
    for round_index in range(settings.extension_rounds + 1):
        if round_index:
            tracks, points, grown = extend_tracks(tracks, observations.features, geometry, angles, points,
                                                  tilt_rad=tilt, radius_px=settings.extension_radius_px,
                                                  max_descriptor_distance=max_distance,
                                                  window_views=settings.extension_window_views, wrap=wrap)
            added += grown["attached"]
            merged += grown["merged"]
            if grown["attached"] == 0 and grown["merged"] == 0:
                break
        for _pass in range(3):
            result = bundle_adjust(tracks, angles, points, geometry, tilt_rad=tilt, **options)
            rms_initial = result.rms_px_initial if rms_initial is None else rms_initial
            iterations += result.iterations
            angles, points, geometry, tilt = result.angles_rad, result.points_mm, result.geometry, result.tilt_rad
            bad = np.sqrt(np.sum(result.residuals_px**2, axis=1)) > settings.outlier_threshold_px
            if not bad.any() or _pass == 2:
                break
            outliers += int(bad.sum())
            tracks, points = _keep_observations(tracks, ~bad, points, settings.min_track_length)
            if tracks.n_tracks == 0 or not np.isin(fixed, tracks.view):
                return fallback("no feature track survived the outlier rejection: pair-graph angles returned")
        rounds.append({"tracks": tracks.n_tracks, "observations": len(tracks), "rms_px": result.rms_px_final,
                       "iterations": result.iterations})
    final = result
    info.update(tracks.summary())
    info.update({"outlier_observations": outliers, "extended_observations": added, "merged_tracks": merged, "rounds": rounds,
                 "rms_px_before": float(rms_initial), "rms_px_after": float(final.rms_px_final),
                 "iterations": iterations, "converged": final.converged,
                 "seconds": time.perf_counter() - clock})
    if settings.estimate_u0 or settings.estimate_v0 or settings.estimate_tilt:
        info.update({"u0_px": final.geometry.u0_px, "v0_px": final.geometry.v0_px, "tilt_deg": float(np.rad2deg(final.tilt_rad))})
    return BundleSolution(final.angles_rad - final.angles_rad[0], info, tracks, final.points_mm, final.geometry,
                          final.tilt_rad)
