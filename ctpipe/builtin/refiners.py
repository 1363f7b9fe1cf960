"""Refiners: from pair estimates to per-view angles of the whole scan."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ctpipe.builtin.estimators import pair_estimate
from ctpipe.data import PairEstimate, ScanObservations, ScanSolution
from ctpipe.hookspecs import hookimpl
from ctpipe.model import FailedEstimation, fit_angle
from ctpipe.solve.graph import chain_pair_angles, solve_pair_graph, turn_pairs, unwrap_pair_angles_deg
from ctpipe.stages import Refiner, param

# chain_pair_angles lived here before the view graph had a module of its own.
__all__ = ["LeastSquaresRefiner", "chain_pair_angles"]


@dataclass(frozen=True)
class LeastSquaresRefiner(Refiner):
    """Refit each pair on its inliers, then solve the view graph of all pairs robustly.

    Every configured baseline and, on a full turn, the seam pairs (loop closure) enter one
    sparse system ``theta[j] - theta[i] = alpha_ij`` (:func:`ctpipe.solve.graph.solve_pair_graph`);
    the robust loss lets the other pairs through a view outvote a grossly wrong one. Pairs of
    views one turn apart (a scanner's closing view and view 0) are pinned: their angle is the
    whole turn, measured at once.
    """

    objective: Literal["sampson", "tls"] = param("sampson", doc="refit objective: Sampson distance or closed-form TLS")
    weighting: Literal["uniform", "inliers"] = param(
        "uniform", doc="weight of each pair when chaining: equal, or by its inlier count")
    loss: Literal["soft-l1", "huber", "cauchy", "linear"] = param(
        "soft-l1", doc="robust loss on pair residuals in the view graph (linear: plain least squares)")
    scale_deg: float = param(0.1, doc="pair residual (deg) beyond which the robust loss down-weights a pair",
                             gt=0, le=10)

    def refine(self, observations: ScanObservations, *, rng: np.random.Generator) -> ScanSolution:
        refined: list[PairEstimate | FailedEstimation] = []
        for q_a, q_b, estimate in zip(observations.points_a, observations.points_b, observations.estimates):
            if not estimate:
                refined.append(estimate)
                continue
            mask = estimate.inlier_mask
            alpha = fit_angle(q_a[mask], q_b[mask], objective=self.objective)
            refined.append(alpha if isinstance(alpha, FailedEstimation) else pair_estimate(alpha, mask, q_a, q_b))
        angles_deg = unwrap_pair_angles_deg(observations.pairs, np.rad2deg([e.angle_rad if e else np.nan for e in refined]),
                                            observations.nominal_angles_deg)
        weights = np.array([e.n_inliers if e else 0 for e in refined], dtype=np.float64)
        pinned = _turn_pair_mask(observations)
        graph = solve_pair_graph(observations.n_views, observations.pairs, angles_deg,
                                 weights if self.weighting == "inliers" else None, loss=self.loss,
                                 scale_deg=self.scale_deg, pinned=pinned)
        used = graph.robust_weights > 0
        info = {"loss": self.loss, "scale_deg": self.scale_deg, "iterations": graph.n_iterations,
                "converged": graph.converged, "pairs_used": int(used.sum()),
                "pairs_down_weighted": int(np.count_nonzero(graph.robust_weights[used] < 0.5)),
                "median_abs_residual_deg": float(np.median(np.abs(graph.residuals_deg[used]))) if used.any() else None,
                "views_without_angle": int(np.count_nonzero(np.isnan(graph.angles_deg))),
                "pinned_turn_pairs": int(np.count_nonzero(pinned & np.isfinite(angles_deg)))}
        return ScanSolution(angles_rad=np.deg2rad(graph.angles_deg), pair_estimates=tuple(refined), info=info)


def _turn_pair_mask(observations: ScanObservations) -> np.ndarray:
    """Which of the observed pairs join views one turn apart (:func:`ctpipe.solve.graph.turn_pairs`)."""
    pinned = np.zeros(len(observations.pairs), bool)
    if observations.nominal_angles_deg is None:
        return pinned
    turns = {tuple(pair) for pair in turn_pairs(observations.nominal_angles_deg).tolist()}
    if turns:
        pinned[:] = [tuple(pair) in turns for pair in observations.pairs.tolist()]
    return pinned


@hookimpl
def ctpipe_register_stages(registry) -> None:
    registry.add_refiner("least-squares", LeastSquaresRefiner)
