"""The bundle-adjustment refiner: whole-scan feature tracks and every view angle fitted at once."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ctpipe.data import PairEstimate, ScanObservations, ScanSolution
from ctpipe.hookspecs import hookimpl
from ctpipe.model import FailedEstimation, sampson_distance, wrap_deg
from ctpipe.solve.bundle import BundleSettings, solve_bundle
from ctpipe.solve.pairs import one_to_one
from ctpipe.stages import Refiner, param


@dataclass(frozen=True)
class BundleAdjustmentRefiner(BundleSettings, Refiner):
    """Track features through the scan and adjust every view angle and a 3-D point per track (reprojection error in pixels).

    Its parameters are the solver's :class:`~ctpipe.solve.bundle.BundleSettings` (declared
    there, once), followed by how the start angles and the pairs are chosen.
    """

    start: Literal["pair-graph", "nominal"] = param(
        "pair-graph", doc="start angles: the pair estimates chained on the view graph, or the nominal angles (when "
                          "known; for stages whose errors are tenths of a degree and scans of few points)")
    max_pair_deviation_deg: float | None = param(
        None, doc="ignore pairs whose angle differs from the nominal step by more than this (degrees; null: keep all), "
                  "e.g. a wrong consensus of identical balls", gt=0, le=180)
    nominal_sampson_threshold: float | None = param(
        None, doc="pairs beyond max_pair_deviation_deg: take as correspondences the matches within this Sampson "
                  "distance of the nominal step, each point once (null: leave the pair out)", gt=0, le=1)

    reads_descriptors = True   # a keypoint joins a track by its descriptor's distance (extend_tracks)

    def refine(self, observations: ScanObservations, *, rng: np.random.Generator) -> ScanSolution:
        nominal = observations.nominal_angles_deg
        start = None
        if self.start == "nominal" and nominal is not None:
            start = np.deg2rad(np.asarray(nominal, dtype=np.float64) - nominal[0])
        if self.max_pair_deviation_deg is not None and nominal is not None:
            observations = _without_deviating_pairs(observations, self.max_pair_deviation_deg,
                                                    self.nominal_sampson_threshold)
        solution = solve_bundle(observations, self, start_angles_rad=start)
        detector = {}
        if self.estimate_u0 or self.estimate_v0 or self.estimate_tilt:
            detector = {"u0_px": float(solution.geometry.u0_px), "v0_px": float(solution.geometry.v0_px),
                        "tilt_deg": float(np.rad2deg(solution.tilt_rad))}
        return ScanSolution(angles_rad=solution.angles_rad, pair_estimates=tuple(observations.estimates),
                            info=solution.info, **detector)


def _without_deviating_pairs(observations: ScanObservations, limit_deg: float,
                             nominal_threshold: float | None = None) -> ScanObservations:
    """The observations with every pair further than ``limit_deg`` from its nominal step replaced.

    With ``nominal_threshold`` such a pair's correspondences are chosen again at the nominal step
    (the matches within that Sampson distance of it, each point once): a consensus of identical
    balls near the mid-plane can be mirrored or wrapped while its balls are still the right
    ones. Without it, or with fewer than two such matches, the pair is left out (failed).
    """
    nominal = np.asarray(observations.nominal_angles_deg, dtype=np.float64)
    pairs = observations.pairs
    steps = wrap_deg(nominal[pairs[:, 1]] - nominal[pairs[:, 0]])
    estimates = []
    for k, (estimate, step) in enumerate(zip(observations.estimates, steps)):
        if not estimate or abs(wrap_deg(estimate.angle_deg - step)) <= limit_deg:
            estimates.append(estimate)
            continue
        reason = f"{estimate.angle_deg:.2f} deg is more than {limit_deg:g} deg from the nominal step {step:.2f}"
        if nominal_threshold is not None:
            q_a, q_b = observations.points_a[k], observations.points_b[k]
            distance = sampson_distance(np.deg2rad(step), q_a, q_b)
            mask = one_to_one(distance < nominal_threshold, distance, q_a, q_b)
            if mask.sum() >= 2:
                estimates.append(PairEstimate(np.deg2rad(step), mask, float(np.sqrt(np.mean(distance[mask] ** 2)))))
                continue
        estimates.append(FailedEstimation(reason))
    return dataclasses.replace(observations, estimates=tuple(estimates))


@hookimpl
def ctpipe_register_stages(registry) -> None:
    registry.add_refiner("bundle-adjustment", BundleAdjustmentRefiner)
