"""The least-squares refiner: from pair estimates to per-view angles of the whole scan."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ctpipe.data import ScanObservations, ScanSolution
from ctpipe.hookspecs import hookimpl
from ctpipe.solve.graph import solve_view_graph
from ctpipe.stages import Refiner, param

__all__ = ["LeastSquaresRefiner"]


@dataclass(frozen=True)
class LeastSquaresRefiner(Refiner):
    """Refit each pair on its inliers, then solve the view graph of all pairs robustly.

    Every configured baseline and, on a full turn, the seam pairs (loop closure) enter one
    sparse system ``theta[j] - theta[i] = alpha_ij`` (:func:`ctpipe.solve.graph.solve_pair_graph`);
    the robust loss lets the other pairs through a view outvote a grossly wrong one. Pairs of
    views one turn apart (a scanner's closing view and view 0) are pinned: their angle is the
    whole turn, measured at once. The numerics: :func:`ctpipe.solve.graph.solve_view_graph`.
    """

    objective: Literal["sampson", "tls"] = param("sampson", doc="refit objective: Sampson distance or closed-form TLS")
    weighting: Literal["uniform", "inliers"] = param(
        "uniform", doc="weight of each pair when chaining: equal, or by its inlier count")
    loss: Literal["soft-l1", "huber", "cauchy", "linear"] = param(
        "soft-l1", doc="robust loss on pair residuals in the view graph (linear: plain least squares)")
    scale_deg: float = param(0.1, doc="pair residual (deg) beyond which the robust loss down-weights a pair",
                             gt=0, le=10)

    reads_descriptors = False   # the pairs' inliers only

    def refine(self, observations: ScanObservations, *, rng: np.random.Generator) -> ScanSolution:
        return solve_view_graph(observations, objective=self.objective, weighting=self.weighting, loss=self.loss,
                                scale_deg=self.scale_deg)


@hookimpl
def ctpipe_register_stages(registry) -> None:
    registry.add_refiner("least-squares", LeastSquaresRefiner)
