"""Refiners: from pair estimates to per-view angles of the whole scan."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import spsolve

from ctpipe.builtin.estimators import pair_estimate
from ctpipe.data import PairEstimate, ScanObservations, ScanSolution
from ctpipe.hookspecs import hookimpl
from ctpipe.model import FailedEstimation, fit_angle
from ctpipe.solve.graph import unwrap_pair_angles_deg
from ctpipe.stages import Refiner, param


def chain_pair_angles(n_views: int, pairs: np.ndarray, angles_rad: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Per-view angles from relative pair angles by weighted least squares on the view graph.

    Solves ``min sum_k w_k (theta[j_k] - theta[i_k] - angles_rad[k])^2`` with ``theta[0] = 0``.
    With consecutive pairs only this is the running sum. Pairs with a NaN angle are ignored;
    views not connected to view 0 get NaN.

    Parameters
    ----------
    pairs : ndarray of shape (P, 2), int
    angles_rad : ndarray of shape (P,)
    weights : ndarray of shape (P,), optional

    Returns
    -------
    ndarray of shape (n_views,)
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    angles_rad = np.asarray(angles_rad, dtype=np.float64)
    w = np.ones(len(pairs)) if weights is None else np.asarray(weights, dtype=np.float64)
    ok = np.isfinite(angles_rad) & (w > 0)
    pairs, angles_rad, w = pairs[ok], angles_rad[ok], w[ok]
    theta = np.full(n_views, np.nan)
    theta[0] = 0.0
    if len(pairs) == 0:
        return theta
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n_views, n_views))
    _, labels = connected_components(graph, directed=False)
    component = np.flatnonzero(labels == labels[0])
    if component.size == 1:
        return theta
    position = np.full(n_views, -1)
    position[component] = np.arange(component.size)
    inside = (position[pairs[:, 0]] >= 0) & (position[pairs[:, 1]] >= 0)
    i, j = position[pairs[inside, 0]], position[pairs[inside, 1]]
    rows = np.arange(inside.sum())
    incidence = sp.csr_matrix((np.r_[-np.ones(rows.size), np.ones(rows.size)], (np.r_[rows, rows], np.r_[i, j])),
                              shape=(rows.size, component.size))
    weighted = incidence.multiply(w[inside][:, None]).tocsr()
    normal = (incidence.T @ weighted)[1:, 1:].tocsc()
    rhs = (weighted.T @ angles_rad[inside])[1:]
    theta[component[1:]] = spsolve(normal, rhs) if component.size > 2 else rhs / normal.toarray().ravel()
    return theta


@dataclass(frozen=True)
class LeastSquaresRefiner(Refiner):
    """Refit each pair on its inliers (scale-invariant least squares), then chain pairs into view angles."""

    objective: Literal["sampson", "tls"] = param("sampson", doc="refit objective: Sampson distance or closed-form TLS")
    weighting: Literal["uniform", "inliers"] = param(
        "uniform", doc="weight of each pair when chaining: equal, or by its inlier count")

    def refine(self, observations: ScanObservations, *, rng: np.random.Generator) -> ScanSolution:
        refined: list[PairEstimate | FailedEstimation] = []
        for q_a, q_b, estimate in zip(observations.points_a, observations.points_b, observations.estimates):
            if not estimate:
                refined.append(estimate)
                continue
            mask = estimate.inlier_mask
            alpha = fit_angle(q_a[mask], q_b[mask], objective=self.objective)
            refined.append(alpha if isinstance(alpha, FailedEstimation) else pair_estimate(alpha, mask, q_a, q_b))
        angles = np.deg2rad(unwrap_pair_angles_deg(observations.pairs, np.rad2deg([e.angle_rad if e else np.nan for e in refined]),
                                                   observations.nominal_angles_deg))
        weights = np.array([e.n_inliers if e else 0 for e in refined], dtype=np.float64)
        theta = chain_pair_angles(observations.n_views, observations.pairs, angles,
                                  weights if self.weighting == "inliers" else None)
        return ScanSolution(angles_rad=theta, pair_estimates=tuple(refined))


@hookimpl
def ctpipe_register_stages(registry) -> None:
    registry.add_refiner("least-squares", LeastSquaresRefiner)
