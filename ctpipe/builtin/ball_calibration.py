"""The ``ball-calibration`` refiner: a ball phantom's angles and detector from all views at once."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ctpipe.data import ScanObservations, ScanSolution
from ctpipe.features import bright_view, edge_centres
from ctpipe.hookspecs import hookimpl
from ctpipe.solve.balls import PLACED_FLAG, BallCalibration, calibrate_balls
from ctpipe.solve.graph import solve_view_graph
from ctpipe.stages import Refiner, param

__all__ = ["BallCalibrationRefiner"]


@dataclass(frozen=True)
class BallCalibrationRefiner(Refiner):
    """Every ball a 3-D point on a circle about the axis: balls found by their trajectories, one bundle adjustment.

    Needs the ``beads`` detector's discs (centre, diameter, flag, the side a clip cuts) and the nominal angles; the
    pairs the matcher and estimator made are not used (:mod:`ctpipe.solve.balls`). Without
    nominal angles it solves the pairs on the view graph, and says so. The corrected
    angles are returned only where they explain the balls better than the nominal angles beyond
    noise (an F test of the reprojection errors), every view is fixed by two discs or more (or by one clean disc
    within which no other followed ball hides, named in the reason, since no other ball checks it), no other
    angle explains a view's discs as well with other balls on them, every view's standard
    error is within ``max_angle_se_deg``, and the balls agree on every view's angle (a jackknife
    over them); otherwise the nominal angles, with the reason
    in ``info["balls"]["reason"]``. The axis column, the principal row and the detector tilt
    fitted with the returned angles are the refined geometry (``geometry_vectors.csv``, the
    summary) where the corrected angles are kept, with the nominal angles where those explain
    the balls as well and the fitted detector explains them better than the scan's beyond noise,
    and with the corrected angles, not returned, where those are refused for some views alone and
    the balls agree on the detector (``info["balls"]["detector_reason"]``). Where the balls show
    the views' projections shifting each its own way (a source spot or a detector that drifts),
    each view's shift is fitted with its angle (``info["balls"]["view_shifts_px"]``), so that the
    drift is not taken for angle errors. Where the projections are at hand, the balls hidden within others' discs
    (found as one with them, or not at all) are looked for again on their rims where the balls put them, and the
    calibration is made again with those placed (``info["balls"]["hidden_discs_placed"]``: :func:`_with_hidden_discs`).
    """

    max_error_deg: float = param(2.0, doc="largest error a nominal angle may have: where balls are looked for, and "
                                 "the most a view is corrected by", gt=0, le=30)
    fit_detector: bool = param(True, doc="fit the axis column, the principal row and the detector tilt with the angles")
    p_value: float = param(1e-3, doc="keep the corrected angles where the F test of the balls' reprojection errors "
                           "against the nominal angles' is below this", gt=0, lt=1)
    max_angle_se_deg: float = param(0.02, doc="keep the corrected angles only where every view's standard error is "
                                    "within this (deg): a view whose balls barely pin it is not passed off as "
                                    "corrected", gt=0, le=30)

    view_shifts: Literal["auto", "never"] = param(
        "auto", doc="fit each view's own shift of the projection (a drifting source spot or detector) with its angle "
        "where the balls show one (auto: an F test once the angles settle, on scans of up to 400 views), or never")

    reads_descriptors = False   # the discs' centres and sizes only

    def refine(self, observations: ScanObservations, *, rng: np.random.Generator) -> ScanSolution:
        nominal = observations.nominal_angles_deg
        if nominal is None or len(observations.features) != observations.n_views:
            # Nothing to follow the balls from (no nominal angles) or no discs: the pair estimates
            # on the view graph, as the least-squares refiner solves them, and the reason.
            solution = solve_view_graph(observations)
            why = "no nominal angles" if nominal is None else "no discs found per view"
            return ScanSolution(solution.angles_rad, solution.pair_estimates,
                                {**solution.info, "balls": f"skipped: {why}; the pair estimates on the view graph"})
        detections = []
        for features in observations.features:
            flags = np.zeros(len(features.xy)) if features.class_id is None else np.asarray(features.class_id)
            side = np.zeros((len(features.xy), 2)) if features.clipped_side is None else features.clipped_side
            edge = 0.5 * np.asarray(features.size) if features.centre_edge_px is None else features.centre_edge_px
            se = np.full(len(features.xy), np.nan) if features.centre_se_px is None else features.centre_se_px
            detections.append(np.column_stack([features.xy, 0.5 * np.asarray(features.size), flags, side, edge, se]))
        calibrate = functools.partial(calibrate_balls, geometry=observations.geometry, nominal_angles_deg=nominal,
                                      max_error_deg=self.max_error_deg, fit_detector=self.fit_detector,
                                      p_value=self.p_value, max_angle_se_deg=self.max_angle_se_deg,
                                      fit_shifts=None if self.view_shifts == "auto" else False)
        found = calibrate(detections)
        placed = 0
        if observations.projections is not None and not observations.static_background_removed:
            # Balls the detector found as one with another, or not at all, looked for again where the balls put them.
            detections, placed = _with_hidden_discs(observations.projections, detections, found)
            if placed:
                found = calibrate(detections)
        angles = found.angles_deg
        info = {"balls": {**found.to_dict(), "hidden_discs_placed": placed},
                "chosen": "corrected" if found.kept else "nominal"}
        # The detector is given with the nominal angles too, where the balls show it (a stage that is right, a
        # detector that is not: what a lab checking its scanner asks).
        # The axis offset and the detector's distance with it, where the balls show them beyond noise.
        detector = ({"u0_px": found.u0_px, "v0_px": found.v0_px, "tilt_deg": found.tilt_deg,
                     **found.pose_beyond_noise(observations.geometry)} if found.detector_kept else {})
        return ScanSolution(np.deg2rad(angles - angles[0]), tuple(observations.estimates), info,
                            angle_se_deg=found.angle_se_deg if found.kept else None,
                            view_shifts_px=found.view_shifts_px,
                            drift_spot_share=(found.drift_spot_share if math.isfinite(found.drift_spot_share)
                                              else None), **detector)   # NaN where no shifts were fitted


#: A hidden ball's disc is taken where its rim places it within this of where the balls put it (px). On 19 cached
#: simulated scans the balls put them 0.001-0.1 px from their true centres (0.13-0.38 px where the first look was
#: refused) and the rims that placed them were 0.001-0.9 px off; a rim fit that settled on another ball's rim or a
#: blend's moved 2.4-31 px.
_HIDDEN_REACH_PX = 1.0
#: ... and its radius within this share of the radius the balls give it (as :data:`ctpipe.solve.balls._RADIUS_TOLERANCE`
#: takes a disc for its ball's), and its centre further than this share of its radius from every disc found in the
#: view (a rim fit from a ball nearly behind another settles on the nearer's rim).
_RADIUS_SHARE, _APART_SHARE = 0.1, 0.25


def _with_hidden_discs(projections, detections: list, found: BallCalibration) -> tuple[list, int]:
    """``detections`` with the discs of followed balls hidden within others (:attr:`BallCalibration.hidden_px`)
    placed on their rims, and how many were placed.

    The detector misses a ball whose disc others mostly cover (the middle of three in a row, 51-55 px from each of
    two 160 px across), or finds it as one with another; the view then rests on fewer discs, and the disc that hides
    it may not place its view (:func:`ctpipe.solve.balls._resting_views`). Where the balls put such a ball, the rim
    fit (:func:`ctpipe.features.edge_centres`, started there) places it on the arcs of its rim left uncovered: on a
    simulated 36-view scan (seed 1934), the middle ball 0.024 px from its true centre. A disc is taken where its rim
    fit settles near where it started (:data:`_HIDDEN_REACH_PX`, :data:`_RADIUS_SHARE`, :data:`_APART_SHARE`),
    flagged :data:`ctpipe.solve.balls.PLACED_FLAG`: its kind is weighed by its own residuals (such discs were
    0.02-0.25 px from their true centres where clean discs are 0.01-0.02) and no view rests on one alone.
    """
    detections = list(detections)
    placed = 0
    for view, hidden in enumerate(found.hidden_px):
        if not len(hidden):
            continue
        seen = detections[view]
        rows = np.column_stack([hidden[:, 1:4], np.zeros(len(hidden)), np.ones(len(hidden))])
        out, side, fitted, edge, se = edge_centres(bright_view(np.asarray(projections[view])), rows,
                                                   clipped_side=True, fitted=True, edge_radius=True, centre_se=True)
        near = np.hypot(out[:, 0] - hidden[:, 1], out[:, 1] - hidden[:, 2]) <= _HIDDEN_REACH_PX
        sized = np.abs(out[:, 2] / hidden[:, 3] - 1.0) <= _RADIUS_SHARE
        gap = np.hypot(out[:, None, 0] - seen[None, :, 0], out[:, None, 1] - seen[None, :, 1])
        apart = np.all(gap > _APART_SHARE * out[:, 2, None], axis=1)
        take = fitted & near & sized & apart & np.isfinite(se)
        if not np.any(take):
            continue
        flag = np.full(int(np.sum(take)), float(PLACED_FLAG))
        detections[view] = np.vstack([seen, np.column_stack([out[take, :3], flag, side[take], edge[take], se[take]])])
        placed += int(np.sum(take))
    return detections, placed


@hookimpl
def ctpipe_register_stages(registry) -> None:
    registry.add_refiner("ball-calibration", BallCalibrationRefiner)
