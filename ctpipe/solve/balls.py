"""Global ball-phantom calibration: every ball a 3-D point on a circle about the axis, all views at once.

A ball phantom (a ball bar, balls in foam, a bead cloud) is the one scan where the answer can be
exact: each ball's projected centre is a point of known motion. Pairwise correspondences of
identical balls break on real scans (balls that merge or overlap, balls missed in some views,
dust, a holder: issue 34 measured a real 17-view scan ending tens of degrees off), so here
nothing is decided pair by pair:

1. **Balls from trajectories.** Every pair of detections in two views well apart in angle is
   triangulated with the nominal angles; a candidate ball is scored by the views in which a
   detection lies where it projects (within what the nominal angles' error allows). The best
   supported candidate is refined on its detections and kept, its detections claimed, and so
   on (sequential RANSAC of 3-D points, as turntable structure from motion does:
   Fitzgibbon, Cross and Zisserman 1998). Dust, a holder's edges and a merged blob follow no
   3-D point through the scan and are left out; a holder's end on the axis follows one that does
   not move, which fixes no angle, and is left out too (:data:`_MIN_ORBIT_RADII`). A ball's discs
   keep its size at its depth: a disc of another size (two overlapping balls found as one, larger)
   is not that ball's (:data:`_RADIUS_TOLERANCE`), here and in every assignment.
2. **One bundle adjustment** of every view's angle, every ball's position and the detector
   (the axis column ``u0``, the principal row ``v0``, the in-plane tilt, how far the axis lies off the source's
   perpendicular to the detector, and the source-to-detector distance) on the detections
   assigned to a ball one-to-one in each view; assignment and adjustment alternate. Robust:
   Huber's loss at one pixel from the nominal angles, Cauchy's once a round has settled them, so
   that a disc pulled tenths of a pixel by a clip edge counts for less than linearly (on the
   cached detections of 19 scans of 24 views of ``benchmarks/bench_ball_phantom_mixed.py``,
   worst view 0.0054-0.0130 deg against 0.0062-0.0135 with Huber's throughout: better on 16,
   the same on 2, 0.0002 worse on 1; ``docs/calibration-phantoms.md``). Observations are
   weighted by what their residuals show: each ball by its own root mean square (a faint ball's
   rim is pulled in some views), and each kind of flagged disc (overlapping another, cut by the
   border, its rim across the edge of a clipped background) by its residuals' against the clean
   discs' (a quarter of a clean disc's weight in the first round); and each disc by its centre's
   standard error against its ball's others, where the detector reports it (:func:`_se_weights`:
   a rim placed from part of its arc). A ball's projected disc is an
   ellipse whose centre is not the projection of the ball's centre (Clackdoyle and Mennessier 2011):
   the model predicts the ellipse's centre (:func:`ellipse_centres`), of the sphere whose edge placed the disc (a
   hollow or coated ball's shell's inside, where the detector placed it there: a sphere that much smaller, whose
   ellipse centre lies nearer the principal point). Where a clipped background
   cuts a faint ball's rim on one side (the open beam beyond it, a holder not), its circle is
   pulled away from that side by twice the cut's depth times the side the detector reports
   (:attr:`ctpipe.data.Features.clipped_side`); the depth is one more unknown per ball, fitted
   with the rest (additional parameters for a systematic error, as a photogrammetric bundle
   adjustment calibrates its lens). On 18 scans of the mixed ball phantom drawn after the
   choice, the worst view within 0.01 deg on 8 of 9 scans of 24 views against 5 without it, RMS
   better on 16 (``docs/calibration-phantoms.md``). A disc whose rim another ball's disc overlaps is found a few
   hundredths of a pixel away from that ball, more the more of it the other covers, and scatters along that direction
   more than across it: the push is modelled as one more unknown for the scan, times the share of the disc each
   neighbour's covers along the direction to it (:func:`_overlaps`), and the scatter, per share covered,
   estimated from the residuals, weighs such discs along it (:func:`_overlap_whitening`). Between rounds, each view's
   angle is searched
   again in one dimension with the balls and the detector as the others fix them
   (:func:`_relocate_views`), so that a view whose discs went to the wrong balls is found again.
   A ball dropped while the angles were still the nominal ones (its discs given to a neighbour
   at the same height, pixels off) is looked for again among the leftover discs once the others
   have settled the angles (:data:`_READMIT_ERROR_RAD`), and the rounds run again with it. A disc
   pixels off its ball where the rest of its view and ball fit (two or three balls merged into one
   disc) is left out of the rounds after (:func:`_leave_out_gross`), and so is a disc tenths of a pixel off within
   which a followed ball with no disc of its own lies (the two found as one: :func:`_leave_out_blends`). Where a
   followed ball has no disc of its own in a view and its disc would overlap another's, the calibration says where the
   balls put it (:attr:`BallCalibration.hidden_px`): the ``ball-calibration`` refiner looks for its rim there on the
   projections, and calibrates again with the discs so placed (flagged :data:`PLACED_FLAG`, their kind weighed by its
   own residuals). A view's
   angle is adjusted on two discs or more, or on one clean disc no followed ball hides within. Where the projections
   drift (a source spot that wanders as the tube warms, a detector that moves), every disc of a view is shifted
   alike: taken for angle errors, a drift of 0.2-0.7 px left simulated views 0.01-0.12 deg off, or refused. So once
   the first round has settled, the same adjustment with a shift ``(du, dv)`` per view is tried from its solution;
   where it explains the balls better beyond noise (an F test at ``p_value``) and every view's shift is pinned to
   :data:`_MAX_SHIFT_SE_PX`, the shifts are fitted from then on, in the verdict's fits too (their mean, and the
   columns' once-a-turn part, which a common translation of the balls explains as well, held as gauges; as projection
   matching does).
3. **A verdict from the balls themselves.** The same fit with the angles held at the nominal
   ones; the corrected angles are kept only where they explain the balls better beyond noise
   (an F test of the residuals, the angles' degrees of freedom against the rest), none moved
   further than the nominal angles' stated error allows, no view's discs lie a median of
   more than a pixel from their balls (:data:`_LOST_VIEW_PX`: its balls are not followed), every
   view shows two discs or more of the followed balls, or one clean disc (a view with fewer was never adjusted; one
   with one clean disc is named in the reason, its standard error scaled as the jackknife finds the others'), no
   other angle explains a view's discs as well with other balls on them (:func:`_ambiguous_views`),
   every view's standard error is within ``max_angle_se_deg``, and the balls agree on every view's
   angle: left out a ball at a time, the refits do not move it by a standard error beyond
   ``max_angle_se_deg`` by more than the jackknife's own spread allows (:func:`_jackknife_se`: on
   two scans whose background was clipped at 80 % of the open beam, rims cut unevenly by what the
   clip hides behind them, views 0.03 and 0.07 deg off had standard errors of 0.016 deg at most;
   the jackknife refuses both. It does not catch a bias the balls of a view share:
   ``docs/calibration-phantoms.md``, "A harsh clip"). A view whose other discs fix it no better than
   ``max_angle_se_deg`` without one ball's rests on that ball's disc, which nothing checks: that disc
   must be clean or overlap another only, with no followed ball hidden within it (:func:`_resting_views`), its
   standard error is scaled as a view of one disc's, and the reason names it; a refit whose discs fix the view ten
   times more loosely still (:data:`_UNCOUNTED_TIMES`) is not counted in its jackknife. Last, the corrections must
   stand out from what the balls disagree on (:func:`_beyond_disagreement`): the F test takes the residuals as
   independent, and the discs of hardened or coated balls share biases of hundredths of a pixel
   that the angles absorb. Told the true angles as nominal, 10 of 19 cached simulated scans kept
   corrections 0.002-0.015 deg off them (F test p 1e-4 to 1e-17), each within its views' jackknife
   (chi-square p 0.005-0.91); told angles 0.5 deg off, the same scans pass at p 0. A view's correction over its
   jackknife's spread counts as Student's t with the refits' degrees of freedom less one, the spread being itself
   estimated from a few balls.
4. **The detector out, whichever angles are returned.** A lab checks its scanner with a ball
   phantom, and its stage may be right: then the nominal angles come back, but the axis column,
   the principal row and the tilt the balls show are still what the lab asked. Fitted with the
   returned angles, the detector is given where the angles are corrected (it is part of the
   correction the F test accepted), or, with the nominal angles, where they explain the balls as
   well as the corrected ones (the F test above finds no difference) and the fitted detector
   explains them better than the scan's own beyond noise (an F test of its unknowns). Where the
   corrected angles are refused for some views alone (a view its balls barely pin, or on which they
   disagree) while they explain the balls beyond noise, the nominal angles, off by the stage's
   error, would bend the detector (0.26 px on a simulated scan); the detector the corrected angles
   fit is given instead, where the balls agree on it within :data:`_MAX_DETECTOR_SE`
   (:func:`_refused_angles_detector`).

Gauges: a common turn of every view only turns the phantom, so each adjustment holds the free
views' mean angle where it starts (the corrected angles carry whatever common turn that leaves;
the ``ball-calibration`` refiner returns them from view 0's); the source-to-object distance stays the
nominal one (balls of unknown positions and size fix the geometry only up to scale: a phantom, with its axis,
scaled about the source projects the same). The detector does not scale with them, so its distance from the source
is fitted, and the magnification with it.

The scanner, as a full calibration takes it (Noo, Clackdoyle, Mennessier, White and Roney 2000; Yang et al. 2006;
CtCalib, Sensors 24:5139, 2024): the source, a detector at any pose, and an axis. Tipping the axis towards the
source, or the detector about its rows' direction, moves the balls' trajectories as the principal row does, to first
order: ``v0`` takes it (a synthetic scan with the axis tipped 0.5 deg: the views within 0.004 deg, ``v0`` moved
38 px). Two parts of the pose do not fold into ``u0``, ``v0`` and the tilt, and each bent the angles where it was left
out (synthetic discs with 0.02 px of noise, told angles 0.5 deg off): the axis off the source's perpendicular (a
stage moved sideways, or a detector yawed by 0.5 deg: views up to 0.026 deg off, kept) and the distance from the
source to the detector (1 % off: up to 0.048 deg, refused). Both are fitted (:func:`ellipse_centres`), from the
round where an F test shows them: fitted always, they cost up to 0.0007 deg on scans of the exact geometry.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass, field

import numpy as np

from ctpipe.errors import InputError
from ctpipe.geometry import Geometry
from ctpipe.solve.camera import pixels_to_rays

__all__ = ["BallCalibration", "calibrate_balls", "ellipse_centres", "PLACED_FLAG"]


#: The detector's unknowns: the axis column, the principal row, the in-plane tilt (rad), the axis's offset from the
#: source's perpendicular to the detector (mm, at the axis), the source-to-detector distance (mm).
_DETECTOR_UNKNOWNS = 5
#: Of them, those of the detector's plane (the first three), fitted whenever the detector is; the axis offset and the
#: distance only where the balls show them (``calibrate_balls``).
_PLANE_UNKNOWNS = 3


#: The axis offset and the source-to-detector distance go into the geometry only beyond this many standard errors from
#: the scan's own (:meth:`BallCalibration.pose_beyond_noise`).
_POSE_SES = 3.0


@dataclass(frozen=True)
class BallCalibration:
    """What :func:`calibrate_balls` found.

    Attributes
    ----------
    angles_deg : ndarray of shape (V,)
        The returned angles: the corrected ones where the verdict keeps them, else the nominal ones.
    corrected_deg : ndarray of shape (V,)
        The bundle adjustment's angles, whatever the verdict.
    angle_se_deg : ndarray of shape (V,)
        Standard error of every corrected angle (NaN where a view had too few balls), the common
        turn, which nothing fixes, held; where one ball's disc alone pins a view, scaled by how far the other views'
        jackknife exceeds their own (the median ratio, at least 1).
    kept : bool
        Whether the corrected angles are returned.
    reason : str
        Why, in words.
    balls_mm : ndarray of shape (B, 3)
        Every ball's fitted centre, object frame.
    u0_px, v0_px, tilt_deg : float
        The detector fitted with the returned angles: axis column, principal row, in-plane tilt
        (camera convention); with the corrected angles where ``detector_reason`` says so though they are not returned.
        ``(u0_px, v0_px)`` is where the axis's point level with the source projects.
    axis_offset_mm : float
        Fitted with them: how far the rotation axis lies from the source's perpendicular to the detector, along the
        detector's columns, at the axis (mm; the principal point lies ``axis_offset_mm * SDD / (SOD * pitch_u)``
        columns below ``u0_px``). The same as a detector turned by ``asin(axis_offset_mm / SOD)`` about its columns'
        perpendicular in its plane (a yaw), the axis on the perpendicular.
    source_to_detector_mm : float
        Fitted with them, at the scan's own source-to-object distance (a phantom of unknown size fixes the rest
        only up to a scale about the source): the magnification is this over ``source_to_object_mm``. This and the
        axis offset are fitted only where an F test shows them (``pose_p_value`` below ``p_value``); else they are the
        scan's own (0 and its stated distance), their standard errors NaN.
    pose_p_value : float
        The F test of the axis offset and the distance fitted against held at the scan's own, made once the first
        round has settled the angles (NaN where not made: the detector not fitted, or the rounds never settled).
    detector_se : ndarray of shape (5,)
        Standard errors of ``u0_px`` (px), ``v0_px`` (px), ``tilt_deg`` (deg), ``axis_offset_mm`` (mm) and
        ``source_to_detector_mm`` (mm); NaN where not computed.
    angle_jackknife_se_deg : ndarray of shape (V,) or None
        Every view's angle's standard error by the delete-a-group jackknife over the balls (NaN where
        not computed): how far the balls disagree on it.
    detector_kept : bool
        Whether the fitted detector is the one to use (see the module docstring, step 4).
    detector_reason : str
        Why, in words.
    rms_px, nominal_rms_px : float
        Reprojection RMS of the fitted observations with the corrected and with the nominal angles.
    ball_rms_px : ndarray of shape (B,)
        Each ball's reprojection RMS with the corrected angles.
    f_statistic, p_value : float
        The F test of the corrected against the nominal angles.
    correction_p_value : float
        The chi-square test of the corrections against the balls' disagreement on each view's angle
        (:func:`_beyond_disagreement`); NaN where not computed.
    view_shifts_px : ndarray of shape (V, 2) or None
        Each view's projection's shift ``(du, dv)`` (px) where the axis images, fitted with the returned angles
        where the balls show one and pin each to :data:`_MAX_SHIFT_SE_PX` (a drifting source spot or detector;
        their mean is held at zero: the detector takes it); None where not fitted, or where the verdict found a view
        the balls do not fix.
    drift_spot_share : float
        Of the views' shifts, the share a source spot's move makes (0-1), fitted with them: a spot's move shifts a
        ball's disc by ``(SDD / z - 1) / (SDD / SOD - 1)`` times the axis's image, ``z`` the ball's distance from the
        source, a detector's move every disc alike (0: the detector moved, 1: the spot). NaN where no shifts are
        given.
    shift_p_value : float
        The F test of the views' shifts against none (NaN where not made).
    observations : int
        Detections fitted (assigned to a ball, flagged or not).
    shell_observations : int
        Of those, the ones whose centre the detector placed on a hollow or coated ball's shell's inside (a seventh
        column below the disc's radius).
    left_out : int
        Discs assigned to a ball but left out of the adjustment as gross errors (:func:`_leave_out_gross`: two or
        three balls merged into one disc, a disc merged with a holder), where the rest of their view and ball fit, or as
        blends with a followed ball found in no disc of its own (:func:`_leave_out_blends`).
    assigned : list of ndarray
        Per view, the ball of each detection (-1: none).
    ball_cut_px : ndarray of shape (B,)
        How deep a clipped background cuts each ball's rim (px), fitted where its discs say on
        which side (NaN where none of a ball's discs is cut on one side only).
    hidden_px : list of ndarray of shape (H_k, 4)
        Per view, the followed balls with no disc of their own in it (none found, or the one found left out) whose
        disc the corrected fit projects onto another disc of the view, on the image: rows ``(ball, x, y, r)``, where
        the disc's centre and radius (px) would be (with the view's shift, where fitted). What the detector may
        look for again there (the ``ball-calibration`` refiner's second look).
    overlap_pull_px : float
        How far the detector placed a disc away from another ball's disc covering all of it (px; a share of that
        where the other covers part of it: :func:`_overlaps`), fitted with the corrected angles; NaN where no
        disc overlaps another.
    overlap_scatter_px : float
        How far such discs scatter along the balls that overlap them, beyond clean discs, a share of this per share
        covered (px: :func:`_overlap_scatter_px`), as the fit weighed them; NaN where no disc overlaps another.
    lag_p_value : float
        The F test of whether each ball's discs are pulled towards where it was the view before, as a detector's lag
        (afterglow) pulls them (:func:`_lag_test`; the views taken as recorded in the order given); NaN where it
        could not be tested. Where ``lag_shown``, the summary says so: the angles may be off by a hundredth of a
        degree.
    lag_pull_px : ndarray of shape (B,) or None
        Those pulls, per ball (px, towards the view before), as the test fitted them; the angles are fitted without.
    lag_shown : bool
        Whether ``lag_p_value`` is below the calibration's ``p_value`` and the pulls, fitted, move some view's angle
        by more than a quarter of ``max_angle_se_deg`` (:data:`_LAG_MOVE_SHARE`).
    lag_move_deg : float
        The most the pulls, fitted, move a view's angle (deg, the common turn taken out); NaN where not tested.
    """

    angles_deg: np.ndarray
    corrected_deg: np.ndarray
    angle_se_deg: np.ndarray
    kept: bool
    reason: str
    balls_mm: np.ndarray
    u0_px: float
    v0_px: float
    tilt_deg: float
    rms_px: float
    nominal_rms_px: float
    ball_rms_px: np.ndarray
    f_statistic: float
    p_value: float
    observations: int
    assigned: list = field(default_factory=list)
    ball_cut_px: np.ndarray | None = None
    detector_se: np.ndarray = field(default_factory=lambda: np.full(_DETECTOR_UNKNOWNS, np.nan))
    angle_jackknife_se_deg: np.ndarray | None = None
    detector_kept: bool = False
    detector_reason: str = ""
    shell_observations: int = 0
    left_out: int = 0
    correction_p_value: float = math.nan
    view_shifts_px: np.ndarray | None = None
    shift_p_value: float = math.nan
    drift_spot_share: float = math.nan
    hidden_px: list = field(default_factory=list)
    overlap_pull_px: float = math.nan
    overlap_scatter_px: float = math.nan
    lag_pull_px: np.ndarray | None = None
    lag_p_value: float = math.nan
    lag_shown: bool = False
    lag_move_deg: float = math.nan
    axis_offset_mm: float = 0.0
    source_to_detector_mm: float = math.nan
    pose_p_value: float = math.nan

    def pose_beyond_noise(self, geometry: Geometry) -> dict:
        """Of the axis offset and the source-to-detector distance, those that differ from the scan's own (``geometry``:
        the axis on the source's perpendicular, its stated distance) by more than :data:`_POSE_SES` of their standard
        errors, by their :class:`ctpipe.data.ScanSolution` keys: what the geometry a user reconstructs with takes.
        Where the balls barely show the cone's perspective (a small cone angle, few balls), both are fitted loosely and
        the scanner's own values, good to a few tenths of a millimetre, are the better ones."""
        se = self.detector_se
        fitted = {"axis_offset_mm": (self.axis_offset_mm, 0.0, se[3]),
                  "source_to_detector_mm": (self.source_to_detector_mm, geometry.source_to_detector_mm, se[4])}
        return {key: float(value) for key, (value, own, error) in fitted.items()
                if math.isfinite(value) and math.isfinite(error) and abs(value - own) > _POSE_SES * error}

    def to_dict(self) -> dict:
        return {"kept": self.kept, "reason": self.reason, "balls": len(self.balls_mm),
                "balls_mm": np.round(self.balls_mm, 4).tolist(), "u0_px": self.u0_px, "v0_px": self.v0_px,
                "tilt_deg": self.tilt_deg, "axis_offset_mm": self.axis_offset_mm,
                "source_to_detector_mm": None if not math.isfinite(self.source_to_detector_mm) else
                self.source_to_detector_mm, "pose_p_value": None if not math.isfinite(self.pose_p_value) else
                self.pose_p_value, "detector_se": [None if not np.isfinite(e) else float(e)
                                                           for e in self.detector_se],
                "detector_kept": self.detector_kept, "detector_reason": self.detector_reason, "rms_px": self.rms_px,
                "max_jackknife_se_deg": (None if self.angle_jackknife_se_deg is None
                                         or not np.any(np.isfinite(self.angle_jackknife_se_deg))
                                         else float(np.nanmax(self.angle_jackknife_se_deg))),
                "nominal_rms_px": self.nominal_rms_px,
                "ball_rms_px": np.round(self.ball_rms_px, 4).tolist(), "f_statistic": self.f_statistic,
                "p_value": self.p_value, "correction_p_value": self.correction_p_value,
                "observations": self.observations,
                "overlap_pull_px": None if not math.isfinite(self.overlap_pull_px) else round(self.overlap_pull_px, 4),
                "overlap_scatter_px": (None if not math.isfinite(self.overlap_scatter_px)
                                       else round(self.overlap_scatter_px, 4)),
                "lag_p_value": None if not math.isfinite(self.lag_p_value) else self.lag_p_value,
                "lag_shown": self.lag_shown,
                "lag_move_deg": None if not math.isfinite(self.lag_move_deg) else round(self.lag_move_deg, 5),
                "lag_pull_px": None if self.lag_pull_px is None or not np.any(np.isfinite(self.lag_pull_px))
                else np.round(self.lag_pull_px, 4).tolist(),
                "shell_observations": self.shell_observations, "left_out": self.left_out,
                "shift_p_value": None if not math.isfinite(self.shift_p_value) else self.shift_p_value,
                "view_shifts_px": None if self.view_shifts_px is None else np.round(self.view_shifts_px, 4).tolist(),
                "drift_spot_share": None if not math.isfinite(self.drift_spot_share) else self.drift_spot_share,
                **({} if self.ball_cut_px is None else
                   {"ball_cut_px": [None if not np.isfinite(c) else round(float(c), 4) for c in self.ball_cut_px]}),
                "views_per_ball": [int(sum(int(np.sum(a == b)) for a in self.assigned))
                                   for b in range(len(self.balls_mm))]}


def ellipse_centres(points_mm: np.ndarray, radii_mm: np.ndarray, angles_rad: np.ndarray, geometry: Geometry,
                    u0_px: float, v0_px: float, tilt_rad: float, axis_offset_mm: float = 0.0,
                    source_to_detector_mm: float | None = None) -> np.ndarray:
    """Pixel centres of the discs (ellipses) balls of ``radii_mm`` at ``points_mm`` project to, shape (N, 2).

    The cone of rays tangent to a ball of radius ``r`` whose centre lies at distance ``D`` from
    the source, at angle ``gamma`` from the central ray, cuts the detector in an ellipse whose
    centre lies, along the direction away from the principal point, at
    ``SDD sin(2 gamma) / (cos(2 gamma) + cos(2 alpha))`` with ``sin(alpha) = r / D``, not at the
    centre's projection ``SDD tan(gamma)`` (Clackdoyle and Mennessier 2011). The bias grows as
    ``tan(gamma) alpha^2``: a few hundredths of a pixel for small balls near the axis, tenths of
    a pixel for balls a hundred pixels across at the detector's edge.

    The axis lies ``axis_offset_mm`` along the camera's ``x`` from the source's perpendicular to the detector (the
    principal ray), and the detector ``source_to_detector_mm`` from the source (the geometry's where None);
    ``(u0_px, v0_px)`` is where the axis's point level with the source projects, the tilt turning the detector about
    it. With no offset, that is the principal point, as before.
    """
    c, s = np.cos(angles_rad), np.sin(angles_rad)
    px = c * points_mm[:, 0] - s * points_mm[:, 2] + axis_offset_mm
    py = points_mm[:, 1]
    z = s * points_mm[:, 0] + c * points_mm[:, 2] + geometry.source_to_object_mm
    xn, yn = px / z, py / z
    t = np.hypot(xn, yn)
    distance = np.sqrt(px ** 2 + py ** 2 + z ** 2)
    sin_alpha = np.clip(radii_mm / distance, 0.0, 0.99)
    cos_2alpha = 1.0 - 2.0 * sin_alpha ** 2
    gamma = np.arctan(t)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(t > 1e-12, np.sin(2 * gamma) / (np.cos(2 * gamma) + cos_2alpha) / t,
                         1.0 / (0.5 * (1.0 + cos_2alpha)))
    xn, yn = xn * scale, yn * scale
    ct, st = math.cos(tilt_rad), math.sin(tilt_rad)
    sdd = geometry.source_to_detector_mm if source_to_detector_mm is None else source_to_detector_mm
    fu, fv = sdd / geometry.pixel_pitch_u_mm, sdd / geometry.pixel_pitch_v_mm
    # (u0, v0) is where the axis's point level with the source projects: the principal point lies off it by the
    # axis's offset from the source's perpendicular.
    xa = axis_offset_mm / geometry.source_to_object_mm
    xn = xn - xa
    return np.stack([u0_px + fu * (ct * xn - st * yn), v0_px + fv * (st * xn + ct * yn)], axis=1)


def _nominal_detector(geometry: Geometry) -> np.ndarray:
    """The scan's own detector, as :func:`_adjust` fits it: ``(u0, v0, tilt, axis offset, source to detector)``."""
    return np.array([geometry.u0_px, geometry.v0_px, 0.0, 0.0, geometry.source_to_detector_mm])


def _rays(xy_px: np.ndarray, angle_rad: float, geometry: Geometry) -> tuple[np.ndarray, np.ndarray]:
    """Source (3,) and unit directions (N, 3) of the rays through pixels ``xy_px``, object frame."""
    rays = pixels_to_rays(xy_px, geometry)
    d = np.column_stack([rays, np.ones(len(rays))])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    # Camera P = R X + (0, 0, SOD), R = [[c, 0, -s], [0, 1, 0], [s, 0, c]]: X = R^T (P - (0, 0, SOD)).
    rt = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    source = rt @ np.array([0.0, 0.0, -geometry.source_to_object_mm])
    return source, d @ rt.T


def _triangulate(s1, d1, s2, d2) -> tuple[np.ndarray, np.ndarray]:
    """Midpoints (N, M, 3) and gaps (N, M) of the closest approach of every ray of 1 with every ray of 2."""
    w = s1 - s2
    b = d1 @ d2.T                                   # (N, M)
    d = (d1 @ w)[:, None]                           # (N, 1)
    e = (d2 @ w)[None, :]                           # (1, M)
    denom = np.maximum(1.0 - b ** 2, 1e-12)
    t1 = (b * e - d) / denom
    t2 = (e - b * d) / denom
    p1 = s1 + t1[..., None] * d1[:, None, :]
    p2 = s2 + t2[..., None] * d2[None, :, :]
    return 0.5 * (p1 + p2), np.linalg.norm(p1 - p2, axis=-1)


def _project(points, angles, geometry, detector, radii=None):
    radii = np.zeros(len(points)) if radii is None else radii
    return ellipse_centres(points, radii, angles, geometry, *detector)


#: A disc is a ball's only where its radius is within this fraction of the ball's own at that depth. A ball's
#: discs keep their size through the turn (to 2 % in 99 of 100 discs fitted within a pixel, on 19 cached scans of
#: 16-24 views; 6 of 2193 beyond 10 %), while of the discs 3 px or more off their ball (a merged pair, a disc
#: merged with a holder) 7 of 17 are beyond 10 %, up to 30 %; merged coated balls found as one, 25-40 %.
_RADIUS_TOLERANCE = 0.1


def _depth_mm(points: np.ndarray, angles: np.ndarray, geometry: Geometry) -> np.ndarray:
    """Distance from the source along the central ray of balls at ``points`` (N, 3) in views at ``angles`` (N,)."""
    return np.sin(angles) * points[:, 0] + np.cos(angles) * points[:, 2] + geometry.source_to_object_mm


def _disc_radius_px(points, radii_mm, angles, geometry) -> np.ndarray:
    """The radius (px) the discs of balls of ``radii_mm`` at ``points`` have in views at ``angles`` (all (N,...))."""
    pitch = min(geometry.pixel_pitch_u_mm, geometry.pixel_pitch_v_mm)
    depth = _depth_mm(points, angles, geometry)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(depth > 0, radii_mm * geometry.source_to_detector_mm / (pitch * depth), np.nan)


def _view_discs(balls, radii_mm, angle: float, geometry: Geometry, detector) -> tuple[np.ndarray, np.ndarray]:
    """Where a view at ``angle`` (rad) with ``detector`` (the five unknowns of :func:`_nominal_detector`) puts every
    ball's disc: the centres (B, 2) and the radii (B,), px."""
    at = np.full(len(balls), angle)
    return _project(balls, at, geometry, detector, radii_mm), _disc_radius_px(balls, radii_mm, at, geometry)


def _radius_fits(found_px, expected_px) -> np.ndarray:
    """Whether discs of radius ``found_px`` can be those of a ball expected at ``expected_px`` (broadcast).

    Sizes that are not positive (a detector that gives none reports 0) or not finite tell nothing: they fit.
    """
    found_px, expected_px = np.asarray(found_px, dtype=np.float64), np.asarray(expected_px, dtype=np.float64)
    known = np.isfinite(found_px) & np.isfinite(expected_px) & (found_px > 0) & (expected_px > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return ~known | (np.abs(found_px / expected_px - 1.0) <= _RADIUS_TOLERANCE)


def _ball_radius_mm(point, chosen, detections, angles, geometry) -> float:
    """A ball's radius (mm) from the discs ``chosen`` for it: the median of their radii scaled to its depth."""
    views = [v for v, k in enumerate(chosen) if k >= 0]
    found = np.array([detections[v][chosen[v], 2] for v in views])
    scale = _disc_radius_px(np.repeat(point[None], len(views), 0), 1.0, angles[views], geometry)
    return float(np.median(found / scale))


def _tolerance_px(points: np.ndarray, geometry: Geometry, error_rad: float, radius_px: float) -> np.ndarray:
    """How far a ball at ``points`` may lie from its nominal-angle projection: the angle error's sweep plus a margin."""
    rho = np.hypot(points[:, 0], points[:, 2])
    return geometry.magnification * rho * error_rad / min(geometry.pixel_pitch_u_mm, geometry.pixel_pitch_v_mm) \
        + 0.5 * radius_px + 2.0


def _support(point: np.ndarray, detections, angles, geometry, error_rad, radius_px, claimed,
             radius_mm: float | None = None) -> list[int]:
    """Per view, the detection nearest where ``point`` projects, if within tolerance and unclaimed (-1: none).

    With ``radius_mm``, only discs of the size a ball of that radius has there count.
    """
    points = np.repeat(point[None], len(angles), 0)
    uv = _project(points, angles, geometry, _nominal_detector(geometry))
    tol = _tolerance_px(point[None], geometry, error_rad, radius_px)[0]
    expected = None if radius_mm is None else _disc_radius_px(points, radius_mm, angles, geometry)
    chosen = []
    for view, found in enumerate(detections):
        if len(found) == 0:
            chosen.append(-1)
            continue
        distance = np.hypot(*(found[:, :2] - uv[view]).T)
        distance[claimed[view]] = np.inf
        if expected is not None:
            distance[~_radius_fits(found[:, 2], expected[view])] = np.inf
        best = int(np.argmin(distance))
        chosen.append(best if distance[best] <= tol else -1)
    return chosen


def _refine_point(point, chosen, detections, angles, geometry) -> np.ndarray:
    """Least squares of one ball's centre on its detections (nominal angles, nominal detector)."""
    from ctpipe.solve.camera import projection_jacobians

    views = [v for v, k in enumerate(chosen) if k >= 0]
    observed = np.array([detections[v][chosen[v], :2] for v in views])
    for _ in range(10):
        uv, _, d_point, _ = projection_jacobians(np.repeat(point[None], len(views), 0), angles[views], geometry)
        residual = (observed - uv).reshape(-1)
        jac = d_point.reshape(-1, 3)
        step, *_ = np.linalg.lstsq(jac, residual, rcond=None)
        point = point + step
        if np.linalg.norm(step) < 1e-6:
            break
    return point


#: Views balls are triangulated between and first scored on: at most this many, spread over the scan.
_ANCHOR_VIEWS = 24
#: A candidate whose orbit is smaller on the detector than this fraction of a disc's radius barely moves
#: through the turn: a holder's end or another stationary part on the axis, which fixes no angle.
_MIN_ORBIT_RADII = 0.5


def _min_orbit_mm(radius_px: float, geometry: Geometry) -> float:
    """The smallest distance from the axis (mm) of a ball that moves: :data:`_MIN_ORBIT_RADII` of a disc's radius."""
    return _MIN_ORBIT_RADII * radius_px * min(geometry.pixel_pitch_u_mm, geometry.pixel_pitch_v_mm) \
        / geometry.magnification


def _find_balls(detections, angles, geometry, error_rad, radius_px, min_views) -> tuple[np.ndarray, np.ndarray]:
    """Balls as 3-D points supported by detections in ``min_views`` views or more (step 1 of the module).

    Candidates are triangulated between up to :data:`_ANCHOR_VIEWS` views spread over the scan,
    merged where they fall within half a ball's radius of each other, and scored on those views
    at once; the best are then followed through every view, best first, on the discs of the
    ball's own size (:data:`_RADIUS_TOLERANCE`: not a merged pair). Returns the balls (B, 3) and
    their radii (B,), mm.
    """
    V = len(angles)
    anchors = np.unique(np.linspace(0, V - 1, min(V, _ANCHOR_VIEWS)).round().astype(int))
    reach_mm = 0.5 * geometry.detector_cols * geometry.pixel_pitch_u_mm / geometry.magnification
    height_mm = 0.5 * geometry.detector_rows * geometry.pixel_pitch_v_mm / geometry.magnification
    pitch = min(geometry.pixel_pitch_u_mm, geometry.pixel_pitch_v_mm)
    orbit_mm = _min_orbit_mm(radius_px, geometry)
    candidates = []
    for i, a in enumerate(anchors):
        for b in anchors[i + 1:]:
            if abs(math.sin(angles[b] - angles[a])) < 0.2 or len(detections[a]) == 0 or len(detections[b]) == 0:
                continue
            s1, d1 = _rays(detections[a][:, :2], angles[a], geometry)
            s2, d2 = _rays(detections[b][:, :2], angles[b], geometry)
            mid, gap = _triangulate(s1, d1, s2, d2)
            limit = _tolerance_px(mid.reshape(-1, 3), geometry, error_rad, radius_px).reshape(gap.shape)
            # A ball is in the field of view: inside the cylinder every view sees.
            rho = np.hypot(mid[..., 0], mid[..., 2])
            inside = (rho <= reach_mm) & (np.abs(mid[..., 1]) <= height_mm) & (rho >= orbit_mm)
            candidates.append(mid[(gap <= limit * pitch / geometry.magnification) & inside])
    candidates = np.concatenate(candidates) if candidates else np.zeros((0, 3))
    if not len(candidates):
        return np.zeros((0, 3)), np.zeros(0)
    # The same ball is triangulated by many pairs: one candidate per cell of half a ball's radius.
    cell_mm = max(0.5 * radius_px * pitch / geometry.magnification, 1e-6)
    _, first = np.unique(np.floor(candidates / cell_mm).astype(np.int64), axis=0, return_index=True)
    candidates = candidates[np.sort(first)]
    scores = np.zeros(len(candidates), int)
    tolerance = _tolerance_px(candidates, geometry, error_rad, radius_px)
    for view in anchors:
        found = detections[view]
        if not len(found):
            continue
        uv = _project(candidates, np.full(len(candidates), angles[view]), geometry, _nominal_detector(geometry))
        nearest = np.min(np.hypot(uv[:, None, 0] - found[None, :, 0], uv[:, None, 1] - found[None, :, 1]), axis=1)
        scores += nearest <= tolerance
    needed = max(3, int(math.ceil(min_views * len(anchors) / V)))
    claimed = [np.zeros(len(d), bool) for d in detections]
    balls, radii = [], []
    for index in np.argsort(-scores, kind="stable"):
        if scores[index] < needed:
            break
        point = candidates[index]
        if any(np.linalg.norm(point - ball) < 2.0 * cell_mm for ball in balls):
            continue
        chosen = _support(point, detections, angles, geometry, error_rad, radius_px, claimed)
        if sum(k >= 0 for k in chosen) < min_views:
            continue
        radius = _ball_radius_mm(point, chosen, detections, angles, geometry)
        chosen = _support(point, detections, angles, geometry, error_rad, radius_px, claimed, radius)
        if sum(k >= 0 for k in chosen) < min_views:
            continue
        point = _refine_point(point, chosen, detections, angles, geometry)
        if math.hypot(point[0], point[2]) < orbit_mm:
            continue
        chosen = _support(point, detections, angles, geometry, error_rad, radius_px, claimed, radius)
        if sum(k >= 0 for k in chosen) < min_views:
            continue
        balls.append(point)
        radii.append(_ball_radius_mm(point, chosen, detections, angles, geometry))
        for view, k in enumerate(chosen):
            if k >= 0:
                claimed[view][k] = True
    return np.array(balls).reshape(-1, 3), np.array(radii)


def _assign(detections, balls, radii_mm, angles, geometry, detector, tol_px) -> list[np.ndarray]:
    """Per view, the ball of every detection (-1: none): one-to-one, nearest first, within ``tol_px``, of its size."""
    from scipy.optimize import linear_sum_assignment

    assigned = []
    B = len(balls)
    for view, found in enumerate(detections):
        labels = np.full(len(found), -1)
        if len(found) and B:
            uv, expected = _view_discs(balls, radii_mm, angles[view], geometry, detector)
            cost = np.hypot(found[:, None, 0] - uv[None, :, 0], found[:, None, 1] - uv[None, :, 1])
            sized = _radius_fits(found[:, None, 2], expected[None, :])
            gated = np.where((cost <= tol_px[None, :]) & sized, cost, 1e9)
            rows, cols = linear_sum_assignment(gated)
            for r, c in zip(rows, cols):
                if gated[r, c] < 1e9:
                    labels[r] = c
        assigned.append(labels)
    return assigned


#: The step of :func:`_relocate_views`' search (rad): a ball 20 mm from the axis at magnification 6
#: moves 0.2 px per step on a 0.2 mm detector; the adjustment refines within the step.
_RELOCATE_STEP_RAD = math.radians(0.02)
#: A view's balls land on its discs within this (px) to count as found there by :func:`_relocate_views`.
_RELOCATE_REACH_PX = 3.0


def _relocate_views(detections, balls, radii_mm, angles, nominal, error_rad, geometry, detector) -> np.ndarray:
    """Each view's angle moved to where the fitted balls land on its discs, where that is clearly better.

    The assignment follows each view's current angle, so a view started far off (its nominal
    angle 1-2 deg out, several balls at one height) can settle with its discs given to the wrong
    balls, pixels off, while every other view fits to hundredths: a random layout of the mixed
    phantom's balls ended one view 1.78 deg off that way, its discs 8-13 px from their balls. With
    the balls and the detector as the other views fix them, one view's angle is a search in one
    dimension: over the nominal angle's range, in steps of :data:`_RELOCATE_STEP_RAD`, the sum over
    balls of the squared distance to the nearest disc, truncated at :data:`_RELOCATE_REACH_PX`.
    A view moves only where the best angle beats its current one by half a ball's worth of that
    sum (a view that fits is at its best already, and stays put).
    """
    offsets = _search_offsets(error_rad)
    moved = np.asarray(angles, dtype=np.float64).copy()
    for view, found in enumerate(detections):
        if not len(found):
            continue
        candidates = nominal[view] + offsets
        costs, _ = _view_cost(found, balls, radii_mm, np.append(candidates, moved[view]), geometry, detector)
        best = int(np.argmin(costs[:-1]))                           # the grid, then the current angle
        if costs[best] < costs[-1] - 0.5 * _RELOCATE_REACH_PX ** 2:
            moved[view] = candidates[best]
    return moved


def _search_offsets(error_rad: float) -> np.ndarray:
    """The offsets (rad) a view's angle is searched over from its nominal one: +-``error_rad``, in steps
    of :data:`_RELOCATE_STEP_RAD`."""
    return np.arange(-error_rad, error_rad + 0.5 * _RELOCATE_STEP_RAD, _RELOCATE_STEP_RAD)


def _view_cost(found, balls, radii_mm, candidates, geometry, detector) -> tuple[np.ndarray, np.ndarray]:
    """One view's fit at each of ``candidates`` (rad): the sum over balls of the squared distance (px^2) to the
    nearest disc, truncated at :data:`_RELOCATE_REACH_PX`, and which disc each ball lands on (-1: none within reach)."""
    B = len(balls)
    uv = ellipse_centres(np.tile(balls, (len(candidates), 1)), np.tile(radii_mm, len(candidates)),
                         np.repeat(candidates, B), geometry, *detector).reshape(len(candidates), B, 2)
    d2 = np.sum((uv[:, :, None, :] - found[None, None, :, :2]) ** 2, axis=-1)
    nearest = np.argmin(d2, axis=2)
    d2 = np.take_along_axis(d2, nearest[..., None], axis=2)[..., 0]
    reach2 = _RELOCATE_REACH_PX ** 2
    return np.sum(np.minimum(d2, reach2), axis=1), np.where(d2 <= reach2, nearest, -1)


def _ambiguous_views(detections, assigned, balls, radii_mm, angles, nominal, error_rad, geometry, detector) -> dict:
    """Views whose discs another angle in the nominal range explains as well, with other balls on them.

    A view whose only discs are of balls at one height (the rest hidden behind others, or merged)
    fits its angle with a disc given to either ball: two angles, both to hundredths of a pixel, one
    of them degrees off (in a simulated 17-view scan of seven balls at three heights, a view left
    with one disc fitted as well 1.58 deg off; a view of two or more discs, each of a ball with a
    twin on its ray a turn away, can do the same). The balls cannot tell which. Searched as
    :func:`_relocate_views` does: an angle of the grid is another explanation where balls land on
    discs ``assigned`` to other balls and none on its own, and it fits within half a ball's worth
    of the settled angle. (A step or two off, a ball of a bead cloud lands on a neighbour's disc
    while the others stay on theirs: that is the settled angle's basin, not another explanation.)
    Returns ``{view: other angle (rad)}``.
    """
    offsets = _search_offsets(error_rad)
    margin = 0.5 * _RELOCATE_REACH_PX ** 2
    ambiguous = {}
    for view, (found, labels) in enumerate(zip(detections, assigned)):
        if not len(found):
            continue
        candidates = np.append(nominal[view] + offsets, angles[view])
        costs, lands = _view_cost(found, balls, radii_mm, candidates, geometry, detector)
        owner = np.append(labels, -1)[lands]   # whose disc each ball lands on (-1: none, or a disc of no ball)
        mine = owner == np.arange(len(balls))[None, :]
        other = (np.any((owner >= 0) & ~mine, axis=1) & ~np.any(mine, axis=1))[:-1]
        close = other & (costs[:-1] <= costs[-1] + margin)
        if close.any():
            ambiguous[view] = float(candidates[np.flatnonzero(close)[np.argmin(costs[:-1][close])]])
    return ambiguous


def _hidden_within(found: np.ndarray, labels: np.ndarray, balls, radii_mm, angle: float, geometry: Geometry,
                   detector) -> np.ndarray:
    """Per disc of one view (``found``, its balls ``labels``, -1 none): whether a followed ball with no disc of its own
    in the view is projected within it (False for discs of no ball)."""
    within = np.zeros(len(found), bool)
    if np.any(labels >= 0):
        _, uv, _ = _balls_without_disc(labels, balls, radii_mm, angle, geometry, detector)
        for k in np.flatnonzero(labels >= 0):
            within[k] = bool(np.any(np.hypot(*(uv - found[k, :2]).T) < found[k, 2]))
    return within


def _balls_without_disc(labels: np.ndarray, balls, radii_mm, angle: float, geometry: Geometry,
                        detector) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The followed balls with no disc of their own in a view (``labels``: each disc's ball, -1 none), and where the
    view puts their discs (:func:`_view_discs`: centres (H, 2) and radii (H,), px)."""
    hidden = np.setdiff1d(np.arange(len(balls)), labels[labels >= 0])
    uv, r = _view_discs(balls, radii_mm, angle, geometry, detector)
    return hidden, uv[hidden], r[hidden]


def _hidden_discs_px(detections, assigned, gross, balls, radii_mm, angles, geometry: Geometry, detector,
                     shifts_px: np.ndarray | None) -> list[np.ndarray]:
    """Per view, rows ``(ball, x, y, r)`` (px, on the image as taken: the view's shift added) of the followed balls
    with no disc of their own in it (left out ones count as none) whose disc overlaps another disc of the view and
    lies on the image: :attr:`BallCalibration.hidden_px`."""
    rows, cols = geometry.shape
    out = []
    for view, (found, labels, left_out) in enumerate(zip(detections, assigned, gross)):
        hidden, uv, r = _balls_without_disc(np.where(left_out, -1, labels), balls, radii_mm, angles[view], geometry,
                                            detector)
        if not len(hidden) or not len(found):
            out.append(np.zeros((0, 4)))
            continue
        if shifts_px is not None:
            uv = uv + shifts_px[view]
        gap = np.hypot(uv[:, None, 0] - found[None, :, 0], uv[:, None, 1] - found[None, :, 1])
        keep = np.any(gap < r[:, None] + found[None, :, 2], axis=1) & np.isfinite(r) & \
            (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= cols - 1) & (uv[:, 1] <= rows - 1)
        out.append(np.column_stack([hidden[keep], uv[keep], r[keep]]).astype(np.float64))
    return out


def _leave_out_blends(gross: list, detections, assigned, off_px: np.ndarray, blend_px: float, view_of, ball_of,
                      index_of, balls, radii_mm, angles, geometry, detector, min_views: int) -> int:
    """Mark in ``gross`` the discs off their ball by more than ``blend_px`` within which a followed ball that has no
    disc of its own in the view is projected (:func:`_hidden_within`): the detector found the two as one. They are
    marked where the view's other discs fit (their lower median within :data:`_LOST_VIEW_PX`), each where its ball
    keeps ``min_views``. Returns how many it marked.

    Two balls nearly behind one another (their projections 6-40 px apart, 80 px across) can be found as one disc,
    placed between them or on the nearer's rim bent by the farther's attenuation: within the assignment's reach and
    size check, 0.8-4.7 px off the ball it is given to, and kept by :func:`_leave_out_gross` where it is below its 2 px
    or one of two discs in its view. In simulated hardened scans of solid balls at 20 views
    (``benchmarks/bench_ball_phantom_mixed.py --solid --saturation 0.9 --views 20``, seeds 1703 and 1871) such a disc
    was the only other disc of a view with one good one, and the jackknife refused the scan (left out the good ball,
    the view moved 0.08-0.6 deg). A ball hidden within a disc is not enough by itself: the detector places most of the
    discs a hidden ball overlaps (flagged overlapping) within hundredths of a pixel, the pair 35-55 px apart. Nor is
    a view's every disc being off: marked so in a round still settling, a view of a 36-view scan (seed 1934) lost its
    two good discs, 0.003-0.07 px off, and was left with one flagged.
    """
    seen = np.bincount(ball_of, minlength=len(balls))
    marked = 0
    for v in np.unique(view_of[off_px > blend_px]):
        labels = np.where(gross[v], -1, assigned[v])   # as the next round has them
        within = _hidden_within(detections[v], labels, balls, radii_mm, angles[v], geometry, detector)
        rows = np.flatnonzero(view_of == v)
        rows = rows[labels[index_of[rows]] >= 0]
        blend = (off_px[rows] > blend_px) & within[index_of[rows]]
        # Only where the view's other discs fit (their lower median within _LOST_VIEW_PX): a view still settling has
        # them all off, and one whose balls are not followed is the verdict's lost view.
        if blend.all() or _lower_median(off_px[rows[~blend]]) > _LOST_VIEW_PX:
            continue
        for j in sorted(rows[blend], key=lambda j: -off_px[j]):
            if seen[ball_of[j]] > min_views:
                gross[v][index_of[j]] = True
                seen[ball_of[j]] -= 1
                marked += 1
    return marked


def _robust_spread_px(residual_px: np.ndarray) -> float:
    """The spread (px, one coordinate's standard deviation) of 2-D residuals (N, 2) from their median squared length.

    A ball is judged by it, not by its root mean square: a real ball given one or two wrong discs where it crosses
    another at its height (12 px off, the rest 0.01-0.05: coated seed 260 of ``benchmarks/bench_ball_phantom_mixed.py``)
    has a root mean square of 2 px and was dropped, where a chance line-up of dust misses in most views.
    ``|r|^2 / sigma^2`` is chi-square with 2 degrees of freedom, whose median is ``2 ln 2``.
    """
    return math.sqrt(float(np.median(np.sum(np.asarray(residual_px) ** 2, axis=1))) / (2.0 * math.log(2.0)))


def _lower_median(values: np.ndarray) -> float:
    """The median of ``values``, the lower of the middle two where their number is even."""
    return float(np.sort(values)[(len(values) - 1) // 2])


#: How far off the settled angles may be where dropped balls are looked for again (rad): what a ball's
#: tolerance then allows beyond its disc's half radius is a few pixels.
_READMIT_ERROR_RAD = math.radians(0.1)

#: A view most of whose discs lie more than this (px; and twenty times the views' median) from their balls
#: has its balls not followed, and the correction is not returned.
_LOST_VIEW_PX = 1.0

#: A flagged disc (overlapping another, cut by the border, across a clip edge) still places its ball:
#: in the first round at a quarter of the weight (four times the error) of a clean one, since its
#: fitted centre may be pulled; after it, at the weight each kind's own residuals give (:func:`_flag_weights`).
_FLAGGED_WEIGHT = 0.25

#: Disc flags of the ``beads`` detector: 0 clean, 1 overlapping, 2 cut by the border, 3 rim across a clip edge; and 4,
#: a hidden ball's disc placed on its rim where the balls put it (``PLACED_FLAG``: the ``ball-calibration`` refiner's
#: second look), whose rims other balls mostly cover.
_CLEAN_FLAG, PLACED_FLAG, _FLAG_KINDS = 0, 4, 5


def _ball_weights(residual_px: np.ndarray, ball_of: np.ndarray, n_balls: int) -> np.ndarray:
    """Each ball's weight: the balls' median residual spread over its own, at most 1.

    Balls of one phantom are not located equally well: a faint ball (ruby, polymer) whose rim
    crosses a holder's edge or a clipped background is off by half a pixel or more in some views
    where a steel ball is off by a few hundredths. One weight for all lets those views' angles
    follow the faint ball; each ball weighted by its own spread is the usual remedy of a bundle
    adjustment with unequal observation noise. The spread is the residuals' root mean square, not
    a robust scale: the views where a faint ball's rim is pulled are part of that ball's error,
    and a scale that looks past them (1.4826 times the median absolute residual) weighted such a
    ball as if they were not there. On the mixed ball phantom of
    ``benchmarks/bench_ball_phantom_mixed.py`` (seeds 0-2), the worst view 0.064, 0.024 and 0.027
    deg with the robust scale, 0.029, 0.024 and 0.012 with the root mean square (flagged discs
    still at a fixed quarter weight; ``docs/calibration-phantoms.md``).
    """
    spread = np.full(n_balls, np.nan)
    for b in range(n_balls):
        mine = residual_px[ball_of == b]
        if mine.size:
            spread[b] = _spread_px(mine)
    reference = float(np.nanmedian(spread)) if np.isfinite(spread).any() else 1.0
    return np.where(np.isfinite(spread), np.minimum(reference / spread, 1.0), 1.0)


def _se_weights(se_px: np.ndarray, ball_of: np.ndarray, n_balls: int) -> np.ndarray:
    """Each disc's weight from its centre's standard error (:attr:`ctpipe.data.Features.centre_se_px`): its ball's
    median standard error over its own, at most 1 (1 where not known, or where the ball has fewer than two known).

    Within a ball, the edge that places a disc is seen whole in some views and in part in others (a neighbour covers
    it, a clip cuts it and the profile inside the cut is fitted on the rays left), and the centre's error grows as
    the part shrinks: on a simulated hardened scan (solid 1202, clipped at 90 %), discs placed inside the clip's cut
    from under 70 % of their rays were 0.037 px RMS off, from 70-99 % 0.018, whole rims 0.012. The detector's
    standard error says so per disc; between balls the residuals weigh them (:func:`_ball_weights`). On 11 cached
    scans of 17-36 views (hardened solid, mixed, random and coated balls; chosen on them over a weight against every
    disc's median, which double counts the balls' own spreads) the worst view went from 0.0042-0.0141 deg (median
    0.0067) to 0.0032-0.0141 (median 0.0059), better on 7, up to 0.0013 worse on 4 (``docs/calibration-phantoms.md``).
    """
    weights = np.ones(len(se_px))
    known = np.isfinite(se_px) & (se_px > 0)
    for b in range(n_balls):
        mine = known & (ball_of == b)
        if np.count_nonzero(mine) >= 2:
            weights[mine] = np.minimum(1.0, float(np.median(se_px[mine])) / se_px[mine])
    return weights


#: A disc off its ball by more than this many robust deviations of the discs' (1.4826 times their median
#: distance, unweighted), and by more than _GROSS_PX, is a gross error (a misdetection), left out of the flags'
#: spreads: a disc pulled by a clip edge is off by tenths of a pixel (0.46-0.88 px RMS for faint balls' discs
#: across a clip edge, the discs' median a few hundredths) and still counts.
_GROSS_SCALES, _GROSS_PX = 10.0, 2.0


def _flag_weights(residual_px: np.ndarray, flag: np.ndarray, gross_px: float = np.inf) -> np.ndarray:
    """Each kind of flagged disc's weight against a clean one, indexed by the flag: the clean discs'
    residual root mean square over that kind's, at most 1 (``_FLAGGED_WEIGHT`` while either is missing).

    The rim fit places most overlapping discs as well as clean ones (a few hundredths of a pixel on
    the mixed ball phantom), so a fixed quarter weight threw away the views where three of seven
    balls overlap: on ``benchmarks/bench_ball_phantom_mixed.py`` seed 4 a view with four clean
    discs, one of them a ruby pulled 0.55 px by the clipped background, was 0.039 deg off; weighted
    by what they show, 0.015 (``docs/calibration-phantoms.md``). A disc whose rim crosses the edge
    of a clipped background (flag 3) is pulled by tenths of a pixel, an overlapping one is not: each
    kind gets the weight its own residuals earn. Discs off by more than ``gross_px`` (a misdetection:
    :data:`_GROSS_SCALES`, :data:`_GROSS_PX`) are not counted: one disc 3.6 px off among fifty whose
    median is 0.06 px made the kind's spread 0.52 px and its weight a fiftieth (a simulated scan of
    seven coated balls, where every view whose discs were all of that kind then read as barely pinned).
    """
    weights = np.ones(_FLAG_KINDS)
    off_px = np.hypot(*residual_px.T) if residual_px.ndim > 1 else np.abs(residual_px)
    flag = np.where(off_px <= gross_px, flag, -1)        # a gross error counts for no kind
    clean = flag == _CLEAN_FLAG
    for kind in range(1, _FLAG_KINDS):
        mine = flag == kind
        weights[kind] = (min(1.0, _spread_px(residual_px[clean]) / _spread_px(residual_px[mine]))
                         if mine.any() and clean.any() else _FLAGGED_WEIGHT)
    return weights


def _leave_out_gross(gross: list, off_px: np.ndarray, gross_px: float, view_of: np.ndarray, ball_of: np.ndarray,
                     index_of: np.ndarray, min_views: int) -> int:
    """Mark in ``gross`` (per view, per disc index) the discs off their ball by more than ``gross_px`` (a settled
    round's unweighted distances ``off_px``), where their view's and their ball's discs otherwise fit (their lower
    medians within :data:`_LOST_VIEW_PX`), the grossest first, as long as the view keeps two discs and the ball
    ``min_views`` (what the adjustment needs of them): the rounds after leave them out. Returns how many it marked
    (where the last round marked some, one more is made without them).

    Two or three balls at one height, their projections a few tens of pixels apart, are found as one disc, 10-13 px
    from each, within the assignment's reach (a quarter of a radius) and its size check (the merged disc 5 % larger).
    Such discs held in the fit even at a robust loss's small weight: on a simulated scan of seven coated balls within
    3.4 mm of one height (``benchmarks/bench_ball_phantom_mixed.py --coated --seeds 702``, 17 views) they made four
    balls' residuals 1.7-2.2 px and every view's standard error 0.15-0.87 deg, and the scan was refused with every
    other disc within 0.15 px of its ball; left out (6 of 100), 0.0091 deg at most. Never a view's or a ball's
    discs at large: a view whose discs mostly miss is one the balls are not followed in (the verdict's lost view),
    not a view of gross errors.
    """
    view_typical = {v: _lower_median(off_px[view_of == v]) for v in np.unique(view_of)}
    ball_typical = {b: _lower_median(off_px[ball_of == b]) for b in np.unique(ball_of)}
    view_left = dict(zip(*np.unique(view_of, return_counts=True)))
    ball_left = dict(zip(*np.unique(ball_of, return_counts=True)))
    marked = 0
    for j in sorted(np.flatnonzero(off_px > gross_px), key=lambda j: -off_px[j]):
        v, b = view_of[j], ball_of[j]
        if view_typical[v] <= _LOST_VIEW_PX and ball_typical[b] <= _LOST_VIEW_PX and view_left[v] > 2 and \
                ball_left[b] > min_views:
            gross[v][index_of[j]] = True
            view_left[v] -= 1
            ball_left[b] -= 1
            marked += 1
    return marked


def _first_flag_weights() -> np.ndarray:
    """The flags' weights before any residual is seen: a clean disc 1, every flagged kind ``_FLAGGED_WEIGHT``."""
    return np.r_[1.0, np.full(_FLAG_KINDS - 1, _FLAGGED_WEIGHT)]


def _spread_px(residual_px: np.ndarray) -> float:
    """The root mean square of some residuals (px), at least 1e-3 px (a weight's floor)."""
    return max(float(np.sqrt(np.mean(residual_px ** 2))), 1e-3)


@dataclass
class _Fit:
    angles: np.ndarray
    balls: np.ndarray
    detector: np.ndarray           # u0, v0, tilt_rad, axis offset mm, source to detector mm
    residual: np.ndarray           # (M, 2) px
    jac: np.ndarray | None
    free_views: np.ndarray
    n_params: int
    cut_px: np.ndarray | None = None   # (B,) each ball's rim cut by the clip (px), NaN where not fitted
    shifts_px: np.ndarray | None = None   # (V, 2) each view's shift (px), where fitted
    shift_columns: slice = field(default_factory=lambda: slice(0, 0))   # the shifts' unknowns in ``jac``
    n_gauge: int = 0                   # gauge rows after the discs' in ``jac``, each giving one unknown back
    overlap_pull_px: float = math.nan  # how far a disc is pushed from a neighbour covering all of it (px), if fitted
    n_det: int = 0                     # the detector's unknowns fitted, the last in ``jac``
    lag_pull_px: np.ndarray | None = None   # (B,) each ball's discs' pull against the lag's direction (px), if fitted
    spot_share: float = math.nan       # the source spot's share of the views' shifts (0-1), where they are fitted


#: The robust loss once a round has settled the angles from the nominal ones (the first round, and the first after a
#: ball is dropped, use Huber's: a redescending loss from a start pixels off would count every disc as an outlier).
_SETTLED_LOSS = "cauchy"

#: The gauge row's weight, pixels per radian of the free views' mean turn (which nothing else fixes).
_GAUGE_PX_PER_RAD = 1e3

#: The shift gauge rows' weight, per pixel of the free views' mean shift (which the detector's axis column and
#: principal row fix otherwise).
_SHIFT_GAUGE_WEIGHT = 1e3

#: The views' shifts are fitted only where each is pinned to this (px, its standard error) or better. Seven balls at
#: one height (a coated scan whose three heights fell within 3.4 mm) fitted shifts of 2-3 px with standard errors of
#: 0.9-4 px, each view's shift trading with its angle, and the scan was refused; where the projections drift
#: (simulated walks of 0.02-0.1 px a view, jumps of 0.2-0.5 px) the shifts' standard errors were 0.006-0.015 px.
_MAX_SHIFT_SE_PX = 0.1

#: The views' shifts are tried only on scans of this many views or fewer: with them the adjustment's Jacobian is
#: solved dense (:func:`_adjust`), and a drifted 360-view scan of seven balls took 81 s to calibrate on 2 cores
#: (13 s without the shifts); the cost grows as the views' cube.
_MAX_SHIFT_VIEWS = 400

#: A rim cut ``d`` px deep on the rays of :attr:`~ctpipe.data.Features.clipped_side` ``s`` (the mean
#: over all rays of the cut rays' outward directions) pulls a circle fitted to it by ``-2 d s``: to
#: first order, least squares of a circle with its rim points uniform in angle (``J^T J`` is
#: ``diag(N/2, N/2, N)`` in the centre and the radius).
_CUT_PULL = 2.0
#: The deepest a clip may cut a ball's rim, as a share of the ball's radius on the detector. The clip
#: only takes rim away (a depth of 0 or more), and even a polymer ball's (0.02/mm, 2.5 mm) rim is cut
#: 11 px of 72 by a clip at 95 % of the open beam. Unbounded, the depth of a "ball" that is not one
#: (a holder's end on the axis, followed through the views) came out at -124 px, absorbing its misfit.
_MAX_CUT_FRACTION = 0.25


@dataclass(frozen=True, eq=False)
class _Discs:
    """The discs assigned to balls, a row each: the centre found (M, 2), its weight, its view and its ball, the side
    a clip cuts its rim on (M, 2: :attr:`~ctpipe.data.Features.clipped_side`), the radius of the edge that
    placed it over its disc's (1 for the rim, less for a shell's inside), how the other balls' discs overlap it
    (M, 2: :func:`_overlaps`) and the matrix its error is taken through before its weight, where its scatter
    along that overlap is modelled (M, 2, 2: :func:`_overlap_whitening`; None: the identity); where a detector's lag
    is tested, the unit vector towards where its ball was the view before (M, 2: :func:`_lag_directions`)."""

    xy: np.ndarray
    weight: np.ndarray
    view_of: np.ndarray
    ball_of: np.ndarray
    side: np.ndarray
    edge: np.ndarray
    overlap: np.ndarray
    whiten: np.ndarray | None = None
    lag: np.ndarray | None = None

    def of_balls(self, keep_ball: np.ndarray) -> "_Discs":
        """The discs of the balls where ``keep_ball`` (bool, per ball) holds, those balls numbered anew."""
        keep = keep_ball[self.ball_of]
        renumber = np.cumsum(keep_ball) - 1
        return _Discs(self.xy[keep], self.weight[keep], self.view_of[keep], renumber[self.ball_of[keep]],
                      self.side[keep], self.edge[keep], self.overlap[keep],
                      None if self.whiten is None else self.whiten[keep],
                      None if self.lag is None else self.lag[keep])


#: The adjustment's Jacobian is handed to scipy dense (exact trust-region steps) up to this many entries (8 MB: a
#: step's SVD a fraction of a second), sparse beyond (lsmr steps; :func:`_adjust`).
_DENSE_JACOBIAN_ENTRIES = 1_000_000

#: Forward differences' relative step: the square root of the machine epsilon, times the larger of 1 and the
#: unknown, as ``scipy.optimize.least_squares`` takes it ('2-point').
_FD_STEP = math.sqrt(float(np.finfo(np.float64).eps))


def _column_groups(rows: np.ndarray, cols: np.ndarray, n_rows: int, n_cols: int) -> np.ndarray:
    """Each column's group, columns of a group sharing no row (``rows``, ``cols``: the Jacobian's structure): they
    are stepped together by forward differences. Greedy, in the columns' order (Curtis, Powell and Reid 1974)."""
    groups = np.full(n_cols, -1)
    taken: list[np.ndarray] = []
    order = np.argsort(cols, kind="stable")
    starts = np.searchsorted(cols[order], np.arange(n_cols + 1))
    for j in range(n_cols):
        mine = rows[order[starts[j]:starts[j + 1]]]
        for g, used in enumerate(taken):
            if not used[mine].any():
                break
        else:
            g = len(taken)
            taken.append(np.zeros(n_rows, bool))
        taken[g][mine] = True
        groups[j] = g
    return groups


def _forward_differences(fun, x: np.ndarray, f0: np.ndarray, rows: np.ndarray, cols: np.ndarray, groups: np.ndarray,
                         lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """The Jacobian's values at ``(rows, cols)`` by forward differences of ``fun`` from ``f0 = fun(x)``, a group of
    columns stepped at a time, each by :data:`_FD_STEP` and turned back where a bound stops it (scipy's
    ``approx_derivative``, '2-point', whose values these are)."""
    step = _FD_STEP * np.where(x >= 0, 1.0, -1.0) * np.maximum(1.0, np.abs(x))
    below, above = x - lower, upper - x
    outside = (x + step < lower) | (x + step > upper)
    fits = np.abs(step) <= np.maximum(below, above)
    step = np.where(outside & fits, -step, step)
    step = np.where(fits, step, np.where(above >= below, above, -below))
    values = np.empty(len(rows))
    of_group = groups[cols]
    for g in range(int(groups.max(initial=-1)) + 1):
        stepped = np.where(groups == g, x + step, x)
        here = of_group == g
        values[here] = (fun(stepped)[rows[here]] - f0[rows[here]]) / (stepped - x)[cols[here]]
    return values


def _adjust(discs: _Discs, radii_mm, angles, balls, detector, geometry, *, free_views, fit_angles=True,
            fit_detector=True, scale_px: float = 1.0, loss: str = "huber", cut_px=None, shifts_px=None,
            fit_pose: bool = False) -> _Fit:
    """Bundle adjustment of the free views' angles, the balls and the detector on the discs.

    The detector's unknowns are the axis column, the principal row and the tilt; with ``fit_pose``, the axis's offset
    from the source's perpendicular and the source-to-detector distance too (else held where ``detector`` has them).

    The gauge (a common turn of every view turns only the phantom) is one more residual: the free
    views' mean angle held where it starts. No view is held: with one view held and a robust
    loss, the others turned away from it by 0.16 deg and its discs counted as outliers.

    Each ball with a disc cut on one side (``discs.side``) gets one more unknown, how deep the clip cuts its rim
    (``cut_px``, its start; NaN for the others; within 0 and :data:`_MAX_CUT_FRACTION` of its radius), and a
    disc's fitted centre is taken as pulled by ``-2 cut side`` (:data:`_CUT_PULL`).

    Where other balls' discs overlap some discs (``discs.overlap``), one more unknown, the overlap pull ``p`` (px, from
    0): a disc's fitted centre is taken as pushed by ``-p overlap`` (:func:`_overlaps`).

    Given ``discs.lag`` (:func:`_lag_directions`), one more unknown a ball with such discs, ``g`` (px): its discs'
    fitted centres are taken as pushed by ``-g lag`` (:func:`_lag_test`).

    Given ``shifts_px`` (V, 2: their start), every free view's projection is shifted by its own ``(du, dv)`` px
    besides, a source spot or a detector that drifts. Two more gauge rows (weighed :data:`_SHIFT_GAUGE_WEIGHT`)
    hold where they start the free views' mean shift, which the axis column and the principal row would otherwise
    share. The columns' once-a-turn part (``du`` along ``cos`` and ``sin`` of the angle) is left free: a common
    translation of the balls explains it only to within the cone's magnification across the phantom's depth, and
    held at its start as a gauge, a drift's (1 px on a 17-view coated scan) went into the angles, 0.021 deg, where
    left free they were within 0.0033 deg (:func:`_shift_se_px` leaves it out of the shifts' standard errors). One
    more unknown, the source spot's share of the shifts (0-1, from 0): a spot's move shifts a disc by ``(SDD / z - 1)
    / (SDD / SOD - 1)`` times the axis's image, ``z`` its ball's distance from the source, a detector's every disc
    alike (:attr:`BallCalibration.drift_spot_share`).
    """
    from scipy import sparse
    from scipy.optimize import least_squares

    observed, weight, view_of, ball_of = discs.xy, discs.weight, discs.view_of, discs.ball_of
    side, edge = discs.side, discs.edge
    B = len(balls)
    n_free = len(free_views) if fit_angles else 0
    n_det = (_DETECTOR_UNKNOWNS if fit_pose else _PLANE_UNKNOWNS) if fit_detector else 0
    one_sided = np.any(side != 0.0, axis=1)
    cut_balls = np.flatnonzero(np.bincount(ball_of[one_sided], minlength=B) > 0) if B else np.zeros(0, int)
    cut_start = np.zeros(B) if cut_px is None else np.nan_to_num(np.asarray(cut_px, dtype=np.float64), nan=0.0)
    n_cut = len(cut_balls)
    cut_column = np.full(B, -1)
    cut_column[cut_balls] = np.arange(n_cut)
    shifted = np.asarray(free_views) if shifts_px is not None and len(free_views) >= 2 else np.zeros(0, int)
    n_shift = len(shifted)
    first_shift = n_free + 3 * B + n_cut
    overlapped = np.any(discs.overlap != 0.0, axis=1)
    n_pull = 1 if overlapped.any() else 0
    n_spot = 1 if n_shift else 0                 # the source spot's share of the drift, after the shifts
    spot_at = first_shift + 2 * n_shift
    pull_at = spot_at + n_spot                   # the overlap pull's unknown, the lag's pulls, then the detector's
    lagged = np.zeros(len(overlapped), bool) if discs.lag is None else np.any(discs.lag != 0.0, axis=1)
    lag_balls = np.flatnonzero(np.bincount(ball_of[lagged], minlength=B) > 0) if B else np.zeros(0, int)
    n_lag = len(lag_balls)
    lag_column = np.full(B, -1)
    lag_column[lag_balls] = np.arange(n_lag)
    lag_at = pull_at + n_pull
    det_at = lag_at + n_lag

    def unpack(x):
        a = angles.copy()
        if n_free:
            a[free_views] = x[:n_free]
        p = x[n_free:n_free + 3 * B].reshape(B, 3)
        c = np.zeros(B)
        c[cut_balls] = x[n_free + 3 * B:first_shift]
        t = np.zeros((len(angles), 2)) if shifts_px is None else np.array(shifts_px, dtype=np.float64)
        t[shifted] = x[shift_unknowns].reshape(-1, 2)
        d = np.concatenate([x[det_at:], detector[n_det:]]) if n_det else detector
        g = np.zeros(B)
        g[lag_balls] = x[lag_at:det_at]
        return a, p, c, t, d, (x[pull_at] if n_pull else 0.0), g, (x[spot_at] if n_spot else 0.0)

    start_mean = float(np.mean(angles[free_views])) if n_free else 0.0
    # The shifts' gauges, over their unknowns (du, dv of each shifted view in turn): their mean (the detector's u0 and
    # v0 otherwise).
    shift_gauge = np.zeros((2, 2 * n_shift))
    shift_gauge[0, 0::2], shift_gauge[1, 1::2] = 1.0, 1.0
    shift_gauge /= max(n_shift, 1)
    shift_unknowns = slice(first_shift, first_shift + 2 * n_shift)
    start_gauge = shift_gauge @ np.asarray(shifts_px, dtype=np.float64)[shifted].reshape(-1) if n_shift else None

    def gauges(x):
        """The gauge rows: the free views' mean angle, and where shifts are fitted their mean."""
        rows = [_GAUGE_PX_PER_RAD * (float(np.mean(x[:n_free])) - start_mean)] if n_free else []
        if n_shift:
            rows += list(_SHIFT_GAUGE_WEIGHT * (shift_gauge @ x[shift_unknowns] - start_gauge))
        return rows

    def residuals(x, gauge=True):
        a, p, c, t, d, pull, lag, spot = unpack(x)
        uv = ellipse_centres(p[ball_of], radii_mm[ball_of] * edge, a[view_of], geometry, *d)
        # Where the disc's centre would be, uncut, uncovered and without the detector's lag.
        seen = observed + _CUT_PULL * c[ball_of, None] * side + pull * discs.overlap
        if n_lag:
            seen = seen + lag[ball_of, None] * discs.lag
        moved = t[view_of]
        if n_spot:
            # A source spot's move shifts a disc by more the nearer its ball is to the source: the axis's image by
            # ``t``, a ball at depth ``z`` from the source by ``t (SDD / z - 1) / (SDD / SOD - 1)``.
            sdd = d[4]   # the detector's distance, fitted with the pose
            parallax = (sdd / _depth_mm(p[ball_of], a[view_of], geometry) - 1.0) / (
                sdd / geometry.source_to_object_mm - 1.0)
            moved = moved * (1.0 + spot * (parallax - 1.0))[:, None]
        off = uv + moved - seen
        if discs.whiten is not None:
            off = np.einsum("mij,mj->mi", discs.whiten, off)
        r = (off * weight[:, None]).reshape(-1)
        return np.append(r, gauges(x)) if gauge else r

    x0 = np.concatenate([angles[free_views] if n_free else [], balls.reshape(-1), cut_start[cut_balls],
                         np.asarray(shifts_px, dtype=np.float64)[shifted].reshape(-1) if n_shift else [],
                         [0.0] * n_spot, [0.0] * n_pull, [0.0] * n_lag, detector[:n_det]])
    # The Jacobian's structure: each observation sees its view's angle, its ball, its ball's cut, the overlap pull
    # where another disc overlaps it, and the detector.
    M = len(observed)
    disc = np.arange(M)
    column = np.full(len(angles), -1)
    column[free_views[:n_free]] = np.arange(n_free)
    angle_of = column[view_of]
    seen = [(disc[angle_of >= 0], angle_of[angle_of >= 0])]
    seen += [(disc, n_free + 3 * ball_of + j) for j in range(3)]
    seen.append((disc[one_sided], n_free + 3 * B + cut_column[ball_of[one_sided]]))
    seen.append((disc[overlapped], np.full(int(np.sum(overlapped)), pull_at)) if n_pull else (disc[:0], disc[:0]))
    seen.append((disc[lagged], lag_at + lag_column[ball_of[lagged]]) if n_lag else (disc[:0], disc[:0]))
    seen += [(disc, np.full(M, det_at + j)) for j in range(n_det)]
    rows = np.concatenate([np.concatenate([2 * m, 2 * m + 1]) for m, _ in seen])
    cols = np.concatenate([np.concatenate([k, k]) for _, k in seen])
    if n_shift:
        # A view's shift moves its discs' u (the first column of its pair) and v (the second) alone.
        shift_column = np.full(len(angles), -1)
        shift_column[shifted] = first_shift + 2 * np.arange(n_shift)
        mine = disc[shift_column[view_of] >= 0]
        rows = np.concatenate([rows, 2 * mine, 2 * mine + 1])
        cols = np.concatenate([cols, shift_column[view_of[mine]], shift_column[view_of[mine]] + 1])
        # The spot's share moves both coordinates of every shifted view's discs.
        rows = np.concatenate([rows, 2 * mine, 2 * mine + 1])
        cols = np.concatenate([cols, np.full(2 * len(mine), spot_at)])
    # The gauge rows (after the discs'): the free views' mean angle, then the shifts' mean (du, dv); their slopes
    # constant.
    gauge_rows = [np.full(n_free, 2 * M)] if n_free else []
    gauge_cols = [np.arange(n_free)] if n_free else []
    gauge_slope = [np.full(n_free, _GAUGE_PX_PER_RAD / n_free)] if n_free else []
    for row in shift_gauge if n_shift else []:
        used = np.flatnonzero(row)
        gauge_rows.append(np.full(len(used), 2 * M + len(gauge_rows)))
        gauge_cols.append(first_shift + used)
        gauge_slope.append(_SHIFT_GAUGE_WEIGHT * row[used])
    n_gauge = len(gauge_rows)
    gauge_rows, gauge_cols, gauge_slope = (np.concatenate(g) if g else np.zeros(0, int if k < 2 else float)
                                           for k, g in enumerate((gauge_rows, gauge_cols, gauge_slope)))
    lower, upper = np.full(len(x0), -np.inf), np.full(len(x0), np.inf)
    depth = slice(n_free + 3 * B, n_free + 3 * B + n_cut)
    lower[depth] = 0.0
    lower[spot_at:pull_at], upper[spot_at:pull_at] = 0.0, 1.0
    upper[depth] = _MAX_CUT_FRACTION * radii_mm[cut_balls] * geometry.magnification / min(
        geometry.pixel_pitch_u_mm, geometry.pixel_pitch_v_mm)
    x0[depth] = np.clip(x0[depth], lower[depth], upper[depth])
    groups = _column_groups(rows, cols, 2 * M, len(x0))
    last = {}
    discs_only = functools.partial(residuals, gauge=False)

    def objective(x):
        """The residuals scipy minimises, the discs' kept for the Jacobian at the same point (scipy asks for it
        where it last evaluated them)."""
        out = residuals(x)
        last["x"], last["discs"] = x.copy(), out[:2 * M]
        return out

    def jacobian(x):
        """Forward differences on the discs' rows, columns that share none stepped together, and the gauge row's
        constant slope. Handed the structure instead (``jac_sparsity``), scipy steps each view's angle on its own,
        the gauge row joining them all: forty evaluations of the residuals a Jacobian where this takes eight."""
        f0 = last["discs"] if "x" in last and np.array_equal(last["x"], x) else discs_only(x)
        values = _forward_differences(discs_only, x, f0, rows, cols, groups, lower, upper)
        jac = sparse.csr_matrix((np.concatenate([values, gauge_slope]), (np.concatenate([rows, gauge_rows]),
                                 np.concatenate([cols, gauge_cols]))), shape=(2 * M + n_gauge, len(x)))
        return jac.toarray() if dense else jac

    # A small Jacobian is handed dense, and scipy's trf then takes exact trust-region steps (an SVD a step), where on
    # the sparse one its inexact steps (lsmr) ran most fits to max_nfev (200): on 18 cached scans of 17-36 views
    # (hardened solid, mixed, random and coated balls) a calibration took 125-271 evaluations of the residuals in all
    # against 519-3402, 2-9 times faster, with the same verdicts and every scan's worst view within 3e-5 deg of
    # before. With the views' shifts it is handed dense always: trf on the sparse one stopped at 200 evaluations with a
    # drift of 0.5 px fitted as 0.04 (a cut depth at its bound holds its scaled steps back). Those fits were dogbox's
    # until the shifts' once-a-turn part was fitted (:func:`_shift_se_px`), which left them nearly degenerate with a
    # translation of the balls: dogbox then ran half of them to 200 evaluations (on six drifted scans cached, 1400-1600
    # in all for a calibration of 17-24 views), where trf converges in 12-90 (350-630 in all), the same verdicts and
    # every view within 0.0006 deg of dogbox's. Dogbox had also ended a shifts' adjustment at its first step where a
    # cut depth started 1e-37 px above its bound (it takes a bound as active only where the start is on it).
    dense = bool(n_shift) or (2 * M + n_gauge) * len(x0) <= _DENSE_JACOBIAN_ENTRIES

    solved = least_squares(objective, x0, jac=jacobian, bounds=(lower, upper), method="trf", loss=loss,
                           f_scale=scale_px, x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200)
    a, p, c, t, d, pull, lag, spot = unpack(solved.x)
    cut = np.full(B, np.nan)
    cut[cut_balls] = c[cut_balls]
    return _Fit(a, p, np.asarray(d, dtype=np.float64), residuals(solved.x, gauge=False).reshape(-1, 2),
                solved.jac.toarray() if hasattr(solved.jac, "toarray") else solved.jac,
                np.asarray(free_views), len(x0), cut, None if shifts_px is None else t, shift_unknowns, n_gauge,
                float(pull) if n_pull else math.nan, n_det, lag if n_lag else None, float(spot) if n_spot else math.nan)


#: A view's correction may exceed the nominal angles' stated error by this many of the largest standard error of the
#: views' angles before the balls are taken as not followed (the check is for corrections degrees beyond it).
_MOVED_SES = 3.0

#: The jackknife over the balls leaves out one group of balls at a time: each ball its own group up to this many
#: groups, balls dealt into this many groups beyond (a bead cloud of 30).
_JACKKNIFE_GROUPS = 10

#: A jackknife refit whose discs left in a view fix its angle to no better than this many times the error allowed is
#: not counted for that view (:func:`_jackknife_se`). Between the two lie the refits that still test the discs they
#: left out: on the scans this was judged on (simulated; hardened solid 1723, 1934, 2002, 2105, the coated harsh-clip
#: scan of ``tests/solve/data``), the discs left fixed such views to 0.024-0.033 deg, where the jackknife catches a
#: biased disc (a coated view 0.066 deg off), or to 0.45-3.0 deg, where its moves (0.07-0.14 deg) were noise.
_UNCOUNTED_TIMES = 10.0


def _jackknife_se(discs: _Discs, radii_mm, angles, balls, detector, geometry, *, free_views, fit_detector, scale_px,
                  loss, cut_px, shifts_px=None, se_deg=None, fit_pose: bool = False,
                  allowed_deg: float = np.inf) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, np.ndarray]:
    """Each view's angle's standard error by the delete-a-group jackknife over the balls (deg; NaN where not free or
    where one ball's disc alone pins it), and how many refits adjusted it; then the fitted detector's (u0 px, v0 px,
    tilt deg; NaN where it is not fitted) by the same refits, and how many there were; then, per group and view,
    whether the view rests on that group's discs (``(G, V)``).

    The adjustment is made again with each group of balls left out, from its solution; each
    refit is put in the full fit's frame (their common turn, the median over the views both adjust, removed),
    and ``sqrt((G - 1) / G * sum (a_g - mean a)^2)`` over the ``G`` refits that adjust the view is
    its standard error (Efron and Tibshirani, "An Introduction to the Bootstrap", 1993, ch. 11).
    Where balls are biased each in its own way, as a clip cutting their rims unevenly, their
    angles disagree beyond what the residuals' spread says, and this shows it.

    Where a group holds all but a share ``s`` of a view's information (:func:`_kept_information`), the discs left fix
    the angle to ``se_deg / sqrt(s)`` only. Beyond ``allowed_deg``, or where the refit cannot adjust the view at all
    (with the views' own shifts, a view of two discs left one), the view rests on that group's discs, which nothing
    checks to what is allowed: the caller holds them to what a view of one disc is held to. Beyond
    :data:`_UNCOUNTED_TIMES` that, the refit is not counted for the view: its move is the weak discs' noise. On a
    simulated hardened scan of 36 views (solid 2002) one ball held all but 0.0001 of a view's information, and
    without it the view's two other balls (each across a clip's edge in many views) fixed it to 0.5 deg and moved it
    0.139 deg, a jackknife standard error of 0.119 deg for a view 0.002 deg off, and the scan was refused.
    (Hinkley, "Jackknifing in unbalanced situations", Technometrics 19, 1977, weighs each part left out by its
    leverage for the same reason.)
    """
    B, V = len(balls), len(angles)
    groups = _jackknife_groups(B)
    G = int(groups.max()) + 1
    refits = np.full((G, V), np.nan)
    others_deg = np.zeros((G, V))     # how well each refit's discs alone fix each view's angle (deg)
    if se_deg is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            others_deg = np.asarray(se_deg)[None, :] / np.sqrt(_kept_information(
                discs, groups, G, radii_mm, angles, balls, detector, geometry))
    rests = others_deg > allowed_deg
    uncounted = others_deg > _UNCOUNTED_TIMES * allowed_deg
    detectors = np.full((G, _DETECTOR_UNKNOWNS), np.nan)
    for k in range(G):
        keep_ball = groups != k
        left = discs.of_balls(keep_ball)
        if keep_ball.sum() < 2 or not len(left.xy):
            continue
        counts = np.bincount(left.view_of, minlength=V)
        # A view keeps its angle on one disc left; with its own shift too it needs two (three unknowns).
        free = np.intersect1d(free_views, np.flatnonzero(counts >= (1 if shifts_px is None else 2)))
        # A view the refit cannot adjust at all (its discs left too few for its unknowns) rests on the group's.
        rests[k, np.setdiff1d(free_views, free)] = True
        if len(free) < 2:
            continue
        refit = _adjust(left, radii_mm[keep_ball], angles, balls[keep_ball], detector, geometry, free_views=free,
                        fit_detector=fit_detector, scale_px=scale_px, loss=loss, cut_px=np.asarray(cut_px)[keep_ball],
                        shifts_px=shifts_px, fit_pose=fit_pose)
        # The refit's common turn by the median: its gauge holds the views' mean, so a view the refit loses (its one
        # good disc left out, a merged pair's disc left to pin it) would move every other view by its share.
        refits[k, free] = refit.angles[free] - np.median(refit.angles[free] - angles[free])
        refits[k, uncounted[k]] = np.nan
        if fit_detector:
            detectors[k] = refit.detector * _DETECTOR_UNITS
    se, n = np.full(V, np.nan), np.zeros(V, dtype=int)
    balls_seen = np.bincount(discs.view_of, minlength=V)   # a ball's one disc a view
    for v in free_views:
        if balls_seen[v] < 2:
            continue   # one ball's: every refit that adjusts it keeps the same disc, and agrees by construction
        a = refits[:, v][np.isfinite(refits[:, v])]
        n[v] = len(a)
        if len(a) >= 2:
            se[v] = math.degrees(math.sqrt((len(a) - 1) / len(a) * float(np.sum((a - a.mean()) ** 2))))
    refitted = detectors[np.all(np.isfinite(detectors), axis=1)]
    detector_se = np.full(_DETECTOR_UNKNOWNS, np.nan)
    if len(refitted) >= 2:
        detector_se = np.sqrt((len(refitted) - 1) / len(refitted) * np.sum((refitted - refitted.mean(axis=0)) ** 2,
                                                                           axis=0))
        if not fit_pose:
            detector_se[_PLANE_UNKNOWNS:] = np.nan   # held, not fitted
    rests &= (np.isin(np.arange(V), free_views) & (balls_seen >= 2))[None, :]
    return se, n, detector_se, len(refitted), rests


def _jackknife_groups(n_balls: int) -> np.ndarray:
    """The jackknife's group of each ball: its own up to :data:`_JACKKNIFE_GROUPS` balls, dealt into that many
    beyond."""
    return np.arange(n_balls) % min(n_balls, _JACKKNIFE_GROUPS)


#: The flags of a disc a view may rest on: clean, or overlapping another disc (placed by the rim fit within a few
#: hundredths of a pixel, as a clean one: on two simulated hardened scans of 36 views, solid 1934 and 2002, the
#: followed balls' overlapping discs were 0.023-0.038 px RMS from their true ellipse centres and the clean ones
#: 0.012-0.023, but for the two balls whose rims cross the clip's edge in many views); not one cut by the border or
#: across the clip's edge (tenths of a pixel).
_RESTING_FLAGS = (_CLEAN_FLAG, 1)

#: What a disc's flag says of it, for the flags a view may not rest on.
_FLAG_SAYS = {2: "is cut by the border", 3: "has its rim across a clip's edge",
              PLACED_FLAG: "was placed only where the balls put it, within another ball's disc"}


def _resting_views(rests: np.ndarray, discs: _Discs, flagged: np.ndarray, index_of: np.ndarray, placed, assigned,
                   balls, radii_mm, angles, geometry: Geometry, detector) -> tuple[np.ndarray, dict]:
    """The views that rest on one group's discs (``rests``, from :func:`_jackknife_se`) where each of those is clean
    or overlaps another disc only (:data:`_RESTING_FLAGS`) and no followed ball hides within it
    (:func:`_hidden_within`), and, for the others, ``{view: (ball, what is wrong with its disc)}``. A view of one disc
    is held to the same rule but for the overlap: there, what its disc overlaps is no other followed ball's disc."""
    groups = _jackknife_groups(len(balls))
    resting, unclean = [], {}
    for v in np.flatnonzero(rests.any(axis=0)):
        mine = np.flatnonzero((discs.view_of == v) & rests[groups[discs.ball_of], v])
        hidden = _hidden_within(placed[v], assigned[v], balls, radii_mm, angles[v], geometry, detector)
        faults = [(int(discs.ball_of[j]), "hides another followed ball" if hidden[index_of[j]] else
                   _FLAG_SAYS[int(flagged[j])])
                  for j in mine if hidden[index_of[j]] or flagged[j] not in _RESTING_FLAGS]
        if faults:
            unclean[int(v)] = faults[0]
        else:
            resting.append(int(v))
    return np.array(resting, dtype=int), unclean


def _kept_information(discs: _Discs, groups: np.ndarray, G: int, radii_mm, angles, balls, detector,
                      geometry: Geometry) -> np.ndarray:
    """Per group of balls and view, the share of the view's angle's information its discs but that group's hold
    (``(G, V)``; 1 where the view has none): each disc's squared slope on its view's angle (px per rad, the other
    unknowns held) times its weight squared. The weights are the discs' own (their ball's spread, their flag's,
    their standard error's), not the robust loss's: a disc the loss weighs down because it disagrees with the view's
    others would make the view look as if it rested on them, and the jackknife would stop checking it where it
    should look hardest. (On the scans :data:`_UNCOUNTED_TIMES` was judged on, either gives the same verdicts.)"""
    V = len(angles)
    share = np.ones((G, V))
    if not len(discs.xy):
        return share
    step = 1e-6
    size = radii_mm[discs.ball_of] * discs.edge
    slope = (ellipse_centres(balls[discs.ball_of], size, angles[discs.view_of] + step, geometry, *detector)
             - ellipse_centres(balls[discs.ball_of], size, angles[discs.view_of], geometry, *detector)) / step
    if discs.whiten is not None:
        slope = np.einsum("mij,mj->mi", discs.whiten, slope)
    info = np.sum(slope ** 2, axis=1) * discs.weight ** 2
    total = np.bincount(discs.view_of, info, minlength=V)
    for k in range(G):
        left = groups[discs.ball_of] != k
        kept = np.bincount(discs.view_of[left], info[left], minlength=V)
        share[k] = np.divide(kept, total, out=np.ones(V), where=total > 0)
    return share


def _overlaps(view_of, ball_of, balls, radii_mm, angles, geometry: Geometry, detector) -> np.ndarray:
    """Per disc, how the other followed balls' discs overlap it in its view (M, 2): the sum over them of the share of
    its area each covers (:func:`_lens_share`) times the unit vector towards its centre, where the balls project.

    A disc another ball's disc overlaps is found pushed away from that ball, by more the more of it the other covers:
    the rim fit (:func:`ctpipe.features.edge_centres`) drops the arc the other covers, but the rays near where the two
    rims cross read both balls' line integrals, which add, and their steepest fall lies outside the covered one's rim.
    By symmetry about the line joining the two centres, the push lies along it. On 13 simulated hardened scans of
    solid balls (16-36 views, clipped at 90-95 %; the seen scans of ``docs/calibration-phantoms.md``), the discs of
    the clean and overlapping kinds with one neighbour overlapping them, against their true ellipse centres, by how
    deep the neighbour reaches into them (in radii):

    ==============  ======  =======  =======  =======  =======  =======
    depth (radii)   < 0.1   0.1-0.3  0.3-0.5  0.5-0.8  0.8-1.2  1.2-2.1
    towards it, px  -0.001  -0.000   -0.002   -0.014   -0.027   -0.044
    across it, px   0.014   0.010    0.017    0.009    0.009    0.009
    ==============  ======  =======  =======  =======  =======  =======

    (the mean of the error towards the neighbour, and the RMS across).
    The share of the disc the other covers grows so (0.04, 0.10, 0.21, 0.39 and 0.78 of it at depths of 0.2, 0.4,
    0.65, 1.0 and 1.65 radii): a pull of 0.06 px a whole disc would be -0.002, -0.006, -0.013, -0.023 and -0.047 px.
    The pull is not the same on every scan (the blur, the balls' contrast, the clip), so it is fitted (:func:`_adjust`).
    """
    out = np.zeros((len(view_of), 2))
    for v in np.unique(view_of):
        mine = np.flatnonzero(view_of == v)
        uv, r = _view_discs(balls, radii_mm, angles[v], geometry, detector)
        gap = uv[None, :, :] - uv[ball_of[mine], None, :]            # (discs, balls, 2): towards each ball
        d = np.hypot(gap[..., 0], gap[..., 1])
        share = _lens_share(r[ball_of[mine], None], r[None, :], d)
        share[np.arange(len(mine)), ball_of[mine]] = 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            toward = np.where(d[..., None] > 0, gap / d[..., None], 0.0)
        out[mine] = np.sum(np.nan_to_num(share)[..., None] * toward, axis=1)
    return out


def _lag_directions(view_of, ball_of, balls, radii_mm, angles, geometry: Geometry, detector) -> np.ndarray:
    """Per disc, the unit vector from where its ball projects to where it projected in the view before (M, 2); zero in
    the first view, and where the ball moved less than a pixel.

    A detector's afterglow (lag) carries a share of each frame's signal into the next: every ball's disc of the view
    before is there again, faint, a step behind. The views are taken in the order given, the order they were
    recorded in.
    """
    out = np.zeros((len(view_of), 2))
    mine = np.flatnonzero(view_of > 0)
    points, radii = balls[ball_of[mine]], radii_mm[ball_of[mine]]
    step = (_project(points, angles[view_of[mine] - 1], geometry, detector, radii)
            - _project(points, angles[view_of[mine]], geometry, detector, radii))
    d = np.hypot(step[:, 0], step[:, 1])
    out[mine] = np.where(d[:, None] >= 1.0, step / np.maximum(d, 1.0)[:, None], 0.0)
    return out


def _overlap_scatter_px(residual_px: np.ndarray, overlap: np.ndarray, flagged: np.ndarray,
                        counted: np.ndarray) -> tuple[float, float]:
    """How far discs scatter along the balls that overlap them, per share covered (px), and the clean discs' spread.

    Returns ``tau`` and ``clean``: the discs other balls overlap (``overlap``, :func:`_overlaps`) have residuals
    whose squares exceed, along the overlap's direction, those across it by ``tau^2 s^2`` (``s`` the share covered,
    the overlap's length), summed over the discs (a moment estimate; 0 where across exceeds along, or fewer than
    ten such discs); ``clean`` is the root mean square of the clean discs no other overlaps (all discs' where there
    are none). ``counted`` leaves out the gross errors.
    """
    s = np.hypot(*overlap.T)
    clean = (flagged == _CLEAN_FLAG) & counted & (s == 0)
    clean_px = _spread_px(residual_px[clean] if clean.any() else residual_px[counted])
    mine = (s > 0) & counted
    if np.count_nonzero(mine) < 10:
        return 0.0, clean_px
    u = overlap[mine] / s[mine, None]
    along = np.sum(residual_px[mine] * u, axis=1)
    across = residual_px[mine, 1] * u[:, 0] - residual_px[mine, 0] * u[:, 1]
    excess = (np.sum(along ** 2) - np.sum(across ** 2)) / np.sum(s[mine] ** 2)
    return math.sqrt(max(float(excess), 0.0)), clean_px


#: The overlaps' scatter before any residual is seen (:func:`_overlap_scatter_px`'s ``tau`` and ``clean``, px):
#: none, so every disc is weighed alike along and across.
_NO_SCATTER = (0.0, 1.0)


def _overlap_whitening(overlap: np.ndarray, weight: np.ndarray, tau_px: float, clean_px: float) -> np.ndarray | None:
    """Per disc, the matrix its error is taken through before its weight (M, 2, 2), or None where nothing scatters.

    A disc other balls overlap scatters along the overlap's direction ``u`` by ``tau s`` (px; ``s`` the share
    covered, :func:`_overlap_scatter_px`) beyond its own spread ``clean / weight``: its error's covariance is
    ``sd^2 (I + k u u^T)`` with ``k = (tau s / sd)^2``, and ``(I + k u u^T)^(-1/2) = I + (1 / sqrt(1 + k) - 1) u u^T``
    weighs the disc's error along the overlap as what it is (generalised least squares), across it as before.

    The scatter grows with how much of the disc the others cover, where the push (:func:`_overlaps`) is its
    mean: on the 13 seen hardened scans (as there), the discs' error towards a neighbour reaching 0.5-0.8, 0.8-1.2 and
    1.2-2.1 radii into them had standard deviations of 0.018, 0.022 and 0.096 px about its mean, across it 0.009. Two
    or three balls crowded within 50 px of each other set the worst views: in a 36-view scan drawn after the push was
    modelled (seed 2512, told angles off by up to 2 deg), view 22's discs 0.08-0.17 px off, each pushed by two
    neighbours, left it 0.0159 deg off (0.0256 without the push) at 2.8 standard errors, kept; weighed so, 0.0071
    (``docs/calibration-phantoms.md``).
    """
    s = np.hypot(*overlap.T)
    some = (s > 0) & (tau_px > 0)
    if not some.any():
        return None
    whiten = np.tile(np.eye(2), (len(overlap), 1, 1))
    u = overlap[some] / s[some, None]
    sd = clean_px / np.maximum(weight[some], 1e-12)
    k = (tau_px * s[some] / sd) ** 2
    whiten[some] += (1.0 / np.sqrt(1.0 + k) - 1.0)[:, None, None] * (u[:, :, None] * u[:, None, :])
    return whiten


def _lens_share(r1, r2, d):
    """The share of a disc of radius ``r1`` that a disc of radius ``r2`` whose centre lies ``d`` away covers
    (broadcast): the lens of two circles over ``pi r1^2``, 0 where they do not meet."""
    r1, r2, d = np.broadcast_arrays(np.asarray(r1, float), np.asarray(r2, float), np.asarray(d, float))
    with np.errstate(divide="ignore", invalid="ignore"):
        a1 = r1 ** 2 * np.arccos(np.clip((d ** 2 + r1 ** 2 - r2 ** 2) / (2 * d * r1), -1.0, 1.0))
        a2 = r2 ** 2 * np.arccos(np.clip((d ** 2 + r2 ** 2 - r1 ** 2) / (2 * d * r2), -1.0, 1.0))
        k = 0.5 * np.sqrt(np.clip((-d + r1 + r2) * (d + r1 - r2) * (d - r1 + r2) * (d + r1 + r2), 0.0, None))
        lens = (a1 + a2 - k) / (np.pi * r1 ** 2)
        within = np.minimum(r1, r2) ** 2 / r1 ** 2
    return np.where(d >= r1 + r2, 0.0, np.where(d <= np.abs(r1 - r2), within, lens))


def _edge_ratio(row: np.ndarray) -> float:
    """The radius of the edge a disc's centre was placed on over the disc's own (1 where either is not known)."""
    if row[6] > 0 and row[2] > 0 and math.isfinite(row[6]) and math.isfinite(row[2]):
        return float(row[6] / row[2])
    return 1.0


def _columns(found) -> np.ndarray:
    """One view's detections as (N, 8): centre x, y, radius, flag, the clipped side (zeros where not given), the
    radius of the edge the centre was placed on (the disc's radius where not given) and the centre's standard error
    (NaN where not given)."""
    found = np.asarray(found, dtype=np.float64)
    if found.size == 0:
        return np.zeros((0, 8))
    if found.ndim != 2 or found.shape[1] not in (4, 6, 7, 8):
        raise InputError(f"detections: each view's an array of shape (N, 4), (N, 6), (N, 7) or (N, 8), "
                         f"got {found.shape}")
    if found.shape[1] == 4:
        found = np.column_stack([found, np.zeros((len(found), 2))])
    if found.shape[1] == 6:
        found = np.column_stack([found, found[:, 2]])
    return found if found.shape[1] == 8 else np.column_stack([found, np.full(len(found), np.nan)])


def calibrate_balls(detections, geometry: Geometry, nominal_angles_deg, *, max_error_deg: float = 2.0,
                    fit_detector: bool = True, p_value: float = 1e-3, rounds: int = 3,
                    max_angle_se_deg: float = 0.02, fit_shifts: bool | None = None) -> BallCalibration:
    """Every view's angle and the detector from the balls of a ball phantom (see the module docstring).

    Parameters
    ----------
    detections : sequence of ndarray of shape (N_k, 4), (N_k, 6), (N_k, 7) or (N_k, 8)
        Per view, every disc found: ``x=col, y=row`` of its centre (px), its radius (px) and a flag
        (0 clean, 1 overlapping another disc, 2 cut by the border, 3 its rim across the edge of a
        clipped background), as the ``beads`` detector reports them, or 4 (:data:`PLACED_FLAG`: a hidden ball's
        disc placed where the balls put it); any other flag (-1, the ``class_id`` of keypoints without one) counts as
        clean, any above 4 as 4. Two more columns, where given:
        the side a clipped background cuts the disc's rim on (:attr:`ctpipe.data.Features.clipped_side`),
        from which the pull of each ball's cut rim is fitted with the rest. A seventh, where given: the
        radius (px) of the circle the centre is that of (:attr:`ctpipe.data.Features.centre_edge_px`: a
        hollow or coated ball's shell's inside); its centre is modelled as the ellipse centre of a sphere
        that much smaller than the ball (:func:`ellipse_centres`). An eighth: the centre's standard error (px,
        :attr:`ctpipe.data.Features.centre_se_px`; NaN where not known), by which each disc is weighed against its
        ball's others (:func:`_se_weights`).
    geometry : Geometry
        The scanner's nominal geometry.
    nominal_angles_deg : array_like of shape (V,)
        The angles the stage was commanded to.
    max_error_deg : float
        The largest error a nominal angle may have: what the balls are looked for within, and
        the most a view may be corrected by.
    fit_detector : bool
        Fit the axis column, the principal row and the detector tilt with the angles.
    p_value : float
        The corrected angles are kept where the F test's p-value is below this.
    rounds : int
        Alternations of assignment and adjustment.
    max_angle_se_deg : float
        The corrected angles are kept only where every view's standard error is within this: a
        view whose balls move along its rays, or whose discs are few, is not pinned by them.
    fit_shifts : bool or None
        Fit every view's projection's own shift (a drifting source spot or detector) with the rest: where the balls
        show it (None: an F test of the shifts, at ``p_value``, once the first round has settled the angles, over every
        disc and again without each view's worst (:func:`_but_the_worst`), and each view's shift pinned to
        :data:`_MAX_SHIFT_SE_PX`; on scans of up to :data:`_MAX_SHIFT_VIEWS` views), never
        (False), or from the first round on (True: on 31 cached drift-free scans it refused 10 and kept four more
        0.0106-0.0165 deg off, against none refused and those four within 0.0049-0.0086 with None).
    """
    nominal = np.asarray(nominal_angles_deg, dtype=np.float64)
    V = len(nominal)
    if len(detections) != V:
        raise InputError(f"detections: one array per view ({V}), got {len(detections)}")
    detections = [_columns(d) for d in detections]
    theta0 = np.deg2rad(nominal)
    error_rad = math.radians(max_error_deg)
    radii_px = np.concatenate([d[:, 2] for d in detections])
    if len(radii_px) == 0:
        raise InputError("no balls were found in any view")
    radius_px = float(np.median(radii_px))
    min_views = max(3, int(math.ceil(0.4 * V)))
    balls, radii_mm = _find_balls(detections, theta0, geometry, error_rad, radius_px, min_views)
    if len(balls) < 2:
        raise InputError(f"found {len(balls)} ball(s) followed through {min_views} or more of the {V} views; a "
                         f"calibration needs two or more (are these balls, and the nominal angles within "
                         f"{max_error_deg:g} deg?)")
    pitch = min(geometry.pixel_pitch_u_mm, geometry.pixel_pitch_v_mm)
    reach_mm = 0.5 * geometry.detector_cols * geometry.pixel_pitch_u_mm / geometry.magnification
    orbit_mm = _min_orbit_mm(radius_px, geometry)
    detector = _nominal_detector(geometry)
    angles = theta0.copy()
    tol = _tolerance_px(balls, geometry, error_rad, radius_px)
    fit = None
    scale_px = 1.0      # the loss's scale: a pixel at first, then three robust deviations of the residuals
    ball_weight = np.ones(len(balls))   # each ball's weight from its own residuals' spread, after the first round
    cut_px = np.zeros(len(balls))       # how deep a clipped background cuts each ball's rim, fitted with the rest
    flag_weight = _first_flag_weights()
    scatter = _NO_SCATTER               # how discs scatter along what overlaps them, and clean ones (px)
    loss = "huber"
    start_angles, start_detector, start_balls = theta0.copy(), detector.copy(), balls.copy()
    dropped = False
    gross = [np.zeros(len(found), bool) for found in detections]   # discs left out as gross errors
    shifting = fit_shifts is True       # whether each view's shift is fitted (from the start, or once shown)
    shifts = np.zeros((V, 2))           # each view's shift (px), where fitted
    # Tested once, where the caller did not decide and the views are few enough for the dense solve the shifts need
    # (:data:`_MAX_SHIFT_VIEWS`).
    shift_p, shift_tested = math.nan, fit_shifts is not None or V > _MAX_SHIFT_VIEWS
    start_shifts = (shifting, shifts.copy(), shift_p, shift_tested)   # what a dropped ball takes the rounds back to
    # The axis's offset from the source's perpendicular and the detector's distance: fitted from the round where an F
    # test of them shows them (the unknowns beyond :data:`_PLANE_UNKNOWNS`), tested once the first round has settled
    # the angles.
    posing, pose_p, pose_tested = False, math.nan, not fit_detector
    start_pose = (posing, pose_p, pose_tested)
    for readmitted in (False, True):
        done = again = 0
        while done < rounds:   # a round that drops a ball does not count (at most all but two are dropped)
            placed = _shifted(detections, shifts)   # each view's discs where an unshifted projection puts them
            if fit is not None:
                angles = _relocate_views(placed, balls, radii_mm, angles, theta0, error_rad, geometry, detector)
            assigned = _assign(placed, balls, radii_mm, angles, geometry, detector, tol)
            for labels, left_out in zip(assigned, gross):
                labels[left_out] = -1
            # A view with one disc: is another followed ball hidden within it (found as one with it)?
            hides = np.array([np.sum(labels >= 0) == 1 and bool(np.any(_hidden_within(
                found, labels, balls, radii_mm, angles[view], geometry, detector))) for view, (found, labels)
                in enumerate(zip(placed, assigned))])
            view_of, ball_of, observed, disc_px, flagged, side, edge, index_of = [], [], [], [], [], [], [], []
            disc_se = []
            for view, (found, labels) in enumerate(zip(detections, assigned)):
                for k in np.flatnonzero(labels >= 0):
                    view_of.append(view), ball_of.append(labels[k]), observed.append(found[k, :2])
                    disc_px.append(found[k, 2]), flagged.append(found[k, 3]), side.append(found[k, 4:6])
                    edge.append(_edge_ratio(found[k])), index_of.append(k), disc_se.append(found[k, 7])
            view_of, ball_of = np.array(view_of, dtype=int), np.array(ball_of, dtype=int)
            observed, side = np.array(observed).reshape(-1, 2), np.array(side).reshape(-1, 2)
            edge = np.array(edge, dtype=np.float64)
            # Flags beyond these (another detector's -1, a NaN) count as clean; above 4 as 4.
            flagged = np.clip(np.nan_to_num(np.array(flagged), nan=0.0), 0, _FLAG_KINDS - 1).astype(int)
            weight = flag_weight[flagged] * ball_weight[ball_of] * _se_weights(np.array(disc_se), ball_of, len(balls))
            counts = np.bincount(view_of, minlength=V)
            # A view's angle is adjusted on two discs or more, or on one where that disc is clean (no neighbour, clip
            # or border on its rim), no followed ball hides within it, and the view's shift is not fitted (three
            # unknowns). Nothing checks such a view but its disc's residuals and its standard error: the verdict
            # names it.
            clean_in_view = np.zeros(V, bool)
            clean_in_view[view_of[flagged == _CLEAN_FLAG]] = True
            free_views = np.flatnonzero((counts >= 2) | ((counts == 1) & clean_in_view & ~hides & (not shifting)))
            radii_mm = np.array([np.median(np.array(disc_px)[ball_of == b]) * pitch for b in range(len(balls))])
            z = np.array([np.median(np.sin(angles[view_of[ball_of == b]]) * balls[b, 0]
                                    + np.cos(angles[view_of[ball_of == b]]) * balls[b, 2]) for b in range(len(balls))])
            radii_mm = radii_mm * (z + geometry.source_to_object_mm) / geometry.source_to_detector_mm
            overlap = _overlaps(view_of, ball_of, balls, radii_mm, angles, geometry, detector)
            whiten, fit_scatter_px = _overlap_whitening(overlap, weight, *scatter), scatter[0]
            discs = _Discs(observed, weight, view_of, ball_of, side, edge, overlap, whiten)
            fit = _adjust(discs, radii_mm, angles, balls, detector, geometry, free_views=free_views,
                          fit_detector=fit_detector, scale_px=scale_px, loss=loss, cut_px=cut_px,
                          shifts_px=shifts if shifting else None, fit_pose=posing)
            if not posing and loss == _SETTLED_LOSS and not pose_tested:
                # Once the angles have settled: does the scanner's pose differ from its file's beyond noise?
                trial = _adjust_from(fit, discs, radii_mm, geometry, free_views=free_views, fit_detector=fit_detector,
                                     scale_px=scale_px, loss=loss, shifts_px=shifts if shifting else None,
                                     fit_pose=True)
                pose_p, pose_tested = _f_test(fit, trial)[1], True
                if pose_p < p_value:
                    fit, posing = trial, True
                    if done == rounds - 1:
                        again += 1   # one more round, assigned with the pose
                        done -= 1
            if fit_shifts is None and not shifting and loss == _SETTLED_LOSS and not shift_tested:
                # Once the angles have settled: do the views' projections shift, each its own way?
                trial = _adjust_from(fit, discs, radii_mm, geometry, free_views=free_views, fit_detector=fit_detector,
                                     scale_px=scale_px, loss=loss, shifts_px=np.zeros((V, 2)), fit_pose=posing)
                # A drift moves every disc of a view: tested over all of them, and again without each view's worst
                # (:func:`_but_the_worst`), which a shift also takes up where a neighbour pulled it.
                shift_p = max(_f_test(fit, trial)[1], _f_test(fit, trial, _but_the_worst(fit.residual, view_of))[1])
                shift_tested = True
                if shift_p < p_value and _shift_se_px(trial) <= _MAX_SHIFT_SE_PX:
                    fit, shifting = trial, True
                    # The pose, tested before with the drift in the residuals, is tested again with the shifts: a
                    # drift of a pixel or two had hidden a 0.5 mm offset of the axis (F test p 0.2 and 1.0) that then
                    # went into the angles (0.016-0.030 deg).
                    pose_tested = posing or not fit_detector
                    if done == rounds - 1:
                        again += 1   # one more round, assigned with the shifts
                        done -= 1
            fit_loss = loss   # the nominal fit below is made with the loss of the fit it is tested against
            angles, balls, detector, cut_px = fit.angles, fit.balls, fit.detector, fit.cut_px
            if shifting:
                shifts = fit.shifts_px
            rms = float(np.sqrt(np.mean(fit.residual ** 2)))
            # A "ball" that fits far worse than the others in most of its views (its residuals' robust spread), or is
            # seen in too few views, is not one (dust that lined up by chance, a merged pair): it is dropped and the
            # adjustment made again. Judged without the weights, which would otherwise hide how badly it fits: a faint
            # ball whose discs are mostly flagged across a clip edge is judged by how far they are off, not by their
            # weight.
            unweighted = fit.residual / weight[:, None]   # also what the next round's weights are set from
            if whiten is not None:
                unweighted = np.linalg.solve(whiten, unweighted[..., None])[..., 0]
            per_ball = np.array([_robust_spread_px(unweighted[ball_of == b]) if np.any(ball_of == b) else np.inf
                                 for b in range(len(balls))])
            seen = np.bincount(ball_of, minlength=len(balls))
            good = (per_ball <= max(5.0 * float(np.median(per_ball)), 1.0)) & (seen >= min_views) & \
                np.all(np.isfinite(balls), axis=1) & (np.hypot(balls[:, 0], balls[:, 2]) <= 2.0 * reach_mm) & \
                (np.hypot(balls[:, 0], balls[:, 2]) >= orbit_mm)
            if not good.all() and good.sum() >= 2:
                # The rounds begin again without it, from the start: the angles, the detector and the balls as they
                # were before it bent them, and the start's tolerance. (The fitted balls kept with the start's
                # detector missed their discs by as much as the fit had moved the detector: 38 px, beyond the
                # tolerance tightened to what the fit explained, and no disc was assigned again.)
                balls, radii_mm, ball_weight = start_balls[good], radii_mm[good], ball_weight[good]
                start_balls = balls.copy()
                tol = _tolerance_px(balls, geometry, error_rad, radius_px)
                cut_px = np.zeros(len(balls))
                flag_weight = _first_flag_weights()   # their residuals held the dropped ball's discs
                scatter = _NO_SCATTER                 # and so did the overlaps' scatter
                gross = [np.zeros(len(found), bool) for found in detections]
                angles, detector = start_angles.copy(), start_detector.copy()   # as it bent them
                shifting, shifts, shift_p, shift_tested = start_shifts
                shifts = shifts.copy()
                posing, pose_p, pose_tested = start_pose
                dropped = True
                loss = "huber"
                continue
            done += 1
            # Tighter for the next assignment: what the fit explains, plus room for a poorly fitted ball.
            tol = np.full(len(balls), max(6.0 * rms + 1.0, 0.25 * radius_px))
            # A disc pulled by a neighbour or by dust is off by tenths of a pixel where the others are
            # off by hundredths: the loss's scale at three robust deviations lets it count less than quadratically.
            scale_px = max(3.0 * 1.4826 * float(np.median(np.abs(fit.residual))), 0.1)
            ball_weight = _ball_weights(unweighted, ball_of, len(balls))
            off_px = np.hypot(*unweighted.T)
            # The gross errors' bar; without its floor, the blends' (:func:`_leave_out_blends`: those seen were
            # 0.8-4.7 px off, where the discs' robust deviation was hundredths of a pixel).
            blend_px = _GROSS_SCALES * 1.4826 * float(np.median(off_px))
            gross_px = max(_GROSS_PX, blend_px)
            flag_weight = _flag_weights(unweighted, flagged, gross_px)
            scatter = _overlap_scatter_px(unweighted, overlap, flagged, off_px <= gross_px)
            index_of = np.array(index_of, dtype=int)
            marked = _leave_out_gross(gross, off_px, gross_px, view_of, ball_of, index_of, min_views)
            marked += _leave_out_blends(gross, placed, assigned, off_px, blend_px, view_of, ball_of, index_of, balls,
                                        radii_mm, angles, geometry, detector, min_views)
            if marked and done == rounds and again < rounds:
                done, again = done - 1, again + 1   # the adjustment is made again without the discs just left out
            loss = _SETTLED_LOSS
        if readmitted or not dropped:
            break
        # Balls dropped while the angles were still the nominal ones (their discs given to a neighbour at
        # the same height, pixels off) are looked for again among the discs left over, the angles settled.
        leftover = [found[labels < 0] for found, labels in zip(_shifted(detections, shifts), assigned)]
        settled = dataclasses.replace(geometry, u0_px=float(detector[0]), v0_px=float(detector[1]))
        more, more_radii_mm = _find_balls(leftover, angles, settled, _READMIT_ERROR_RAD, radius_px, min_views)
        if not len(more):
            break
        balls = np.vstack([balls, more])
        tol = np.append(tol, np.full(len(more), tol.max()))
        radii_mm = np.append(radii_mm, more_radii_mm)
        ball_weight, cut_px = np.append(ball_weight, np.ones(len(more))), np.append(cut_px, np.zeros(len(more)))
        start_angles, start_detector, start_balls = angles.copy(), detector.copy(), balls.copy()
        start_shifts = (shifting, shifts.copy(), shift_p, shift_tested)
        start_pose = (posing, pose_p, pose_tested)
        loss = "huber"
    view_shifts = shifts if shifting else None
    nominal_fit = _adjust(discs, radii_mm, theta0, balls, detector, geometry, free_views=free_views, fit_angles=False,
                          fit_detector=fit_detector, scale_px=scale_px, loss=fit_loss, cut_px=cut_px,
                          shifts_px=view_shifts, fit_pose=posing)
    # The gauge row takes one unknown back: the angles add len(free_views) - 1 over the nominal fit.
    extra = len(free_views) - 1
    f_stat, p = _f_test(nominal_fit, fit)
    # Standard errors: the Gauss-Newton covariance of the angles, scaled by the residual variance.
    se = np.full(V, np.nan)
    cov = _covariance(fit) if extra > 0 else None
    if cov is not None:
        se[free_views] = np.rad2deg(np.sqrt(np.clip(np.diag(cov)[:len(free_views)], 0, None)))
    lag_p, lag_pull, lag_move = _lag_test(fit, discs, radii_mm, free_views, geometry, fit_detector=fit_detector,
                                          scale_px=scale_px, loss=fit_loss, shifts_px=view_shifts, fit_pose=posing)
    lag_view = int(np.nanargmax(lag_move)) if np.any(np.isfinite(lag_move)) else None
    lag_most = math.nan if lag_view is None else float(lag_move[lag_view])
    # Shown where the test says so and the pulls, fitted, move some view's angle by a share of what is allowed.
    lag_shown = bool(lag_p < p_value and lag_most > _LAG_MOVE_SHARE * max_angle_se_deg)
    # The balls must agree on each view's angle: the Gauss-Newton errors take the residuals as independent, and a
    # bias a ball's discs share (a rim the clip cuts less where something below the clip lies behind it) is not.
    jack_se, jack_n = np.full(V, np.nan), np.zeros(V, dtype=int)
    detector_jack_se, detector_jack_n = np.full(_DETECTOR_UNKNOWNS, np.nan), 0
    rests = np.zeros((1, V), bool)
    if len(free_views) and extra > 0:
        jack_se, jack_n, detector_jack_se, detector_jack_n, rests = _jackknife_se(
            discs, radii_mm, angles, balls, detector, geometry, free_views=free_views, fit_detector=fit_detector,
            scale_px=scale_px, loss=fit_loss, cut_px=cut_px, shifts_px=view_shifts, se_deg=se,
            allowed_deg=max_angle_se_deg, fit_pose=posing)
    # A view resting on one ball's disc (the other balls' discs in it do not fix it): as a view of one disc, that disc
    # must be whole (clean, or overlapping another), with no other followed ball within it.
    resting, unclean = _resting_views(rests, discs, np.asarray(flagged), np.asarray(index_of), placed, assigned,
                                      balls, radii_mm, angles, geometry, detector)
    # A view one ball's disc pins has no jackknife: its error is taken as the others' are found, their jackknife over
    # their Gauss-Newton error (the median ratio, at least 1), since a disc's bias is not in its view's residuals.
    lone = np.intersect1d(free_views, np.flatnonzero(counts == 1))
    single = np.union1d(lone, resting)
    checked = np.setdiff1d(np.flatnonzero((jack_n >= 2) & np.isfinite(jack_se) & (se > 0)), resting)
    if len(single) and len(checked):
        se[single] *= max(1.0, float(np.median(jack_se[checked] / se[checked])))
    disagree = np.flatnonzero((jack_n >= 2) & _beyond_allowed(jack_se, jack_n, max_angle_se_deg, p_value))
    corrected = np.rad2deg(angles)
    change = corrected - nominal
    # A common turn is no correction: the views' corrections less the common turn that makes the
    # largest of them smallest (half their range). Taken from the median instead, nominal angles each
    # within 2 deg of the truth (a correction spanning up to 4 deg) were refused at 2.79 deg.
    moved = 0.5 * float(np.max(change) - np.min(change))
    # What the balls disagree on, view by view: the larger of the jackknife's and the fit's standard errors.
    spread = np.fmax(jack_se, se)
    spread_dof = np.where(jack_se >= se, jack_n - 1.0, np.inf)
    chi_change, dof_change, p_change, rms_change = _beyond_disagreement(change, spread, spread_dof)
    within_disagreement = not p_change < p_value
    rms = float(np.sqrt(np.mean(fit.residual ** 2)))
    nominal_rms = float(np.sqrt(np.mean(nominal_fit.residual ** 2)))
    # A view whose discs mostly miss their balls has them assigned wrongly (its angle settled far off): the
    # residual sum can still be far below the nominal angles', and the F test pass, with that view degrees off.
    # Judged on the last round's unweighted residuals, by the lower median: most of the view's discs miss (of
    # two, both), not one garbage disc of two or four.
    miss_px = np.array([_lower_median(np.hypot(*unweighted[view_of == v].T)) for v in free_views])
    lost = np.flatnonzero(miss_px > max(_LOST_VIEW_PX, 20.0 * float(np.median(miss_px)))) if len(miss_px) else []
    # A view with no disc of the followed balls, or one that is flagged or hides another ball, was never adjusted: its
    # angle is where the search or a round with balls since dropped left it, which the balls no longer support (a
    # simulated scan of seven balls at three heights, most views' discs merged, ended two views 1.1 and 1.6 deg off
    # so).
    unfixed = np.setdiff1d(np.arange(V), free_views)
    one_view = False        # refused for some views' angles only: the balls follow, and the correction fits them
    if not math.isfinite(p):
        kept, reason = False, "too few balls in too few views to test the correction"
    elif len(unfixed):
        view = int(unfixed[0])
        kept, reason = False, (f"view {view} shows {int(counts[view])} disc(s) of the {len(balls)} balls followed: the "
                               f"balls do not fix its angle ({len(unfixed)} view(s) so)"
                               + ("; one disc pins a view only where it is clean and no other followed ball lies "
                                  "within it" if counts[view] == 1 else ""))
    elif len(lost):
        worst = int(lost[np.argmax(miss_px[lost])])
        typical = float(np.median(miss_px))
        kept, reason = False, (f"view {int(free_views[worst])}'s discs lie a median {miss_px[worst]:.1f} px from their "
                               f"balls, the views' median {typical:.3f} px: the balls are not followed there "
                               f"({len(lost)} view(s) so)")
    elif not np.all(np.isfinite(se)):
        kept, reason = False, "the views' standard errors could not be computed (the adjustment is singular)"
    elif np.max(se) > max_angle_se_deg:
        view = int(np.argmax(se))
        one_view = True
        kept, reason = False, (f"view {view}'s angle is fixed to {se[view]:.3f} deg (standard error) only, more than "
                               f"the {max_angle_se_deg:g} deg allowed: its balls barely pin it "
                               f"({int(np.sum(se > max_angle_se_deg))} view(s) so)")
    elif len(disagree):
        view = int(disagree[np.argmax(jack_se[disagree])])
        one_view = True
        kept, reason = False, (f"the balls disagree on view {view}'s angle: left out one at a time, they move it by a "
                               f"standard error of {jack_se[view]:.3f} deg, beyond the {max_angle_se_deg:g} deg "
                               f"allowed (chi-square p < {p_value:g}; {len(disagree)} view(s) so)")
    elif lag_shown and lag_most > max_angle_se_deg:
        view = lag_view
        one_view = True
        kept, reason = False, (f"the balls' discs are pulled towards where they were the view before, as a detector's "
                               f"lag pulls them (F test p {lag_p:.2g}), and with those pulls fitted view {view} moves "
                               f"by {lag_most:.3f} deg, more than the {max_angle_se_deg:g} deg allowed: the "
                               f"balls do not fix the angles to that")
    elif unclean:
        view, (ball, why) = next(iter(unclean.items()))
        one_view = True
        kept, reason = False, (f"view {view}'s angle rests on ball {ball}'s disc, which {why}: without it the view's "
                               f"other discs do not fix the angle to {max_angle_se_deg:g} deg, and nothing checks "
                               f"that disc ({len(unclean)} view(s) so)")
    # Every view is free here (the unfixed ones were refused above).
    elif ambiguous := _ambiguous_views(_shifted(detections, shifts), assigned, balls, radii_mm, angles, theta0,
                                       error_rad, geometry, detector):
        view, other = min(ambiguous.items(), key=lambda item: abs(item[1] - angles[item[0]]))
        kept, reason = False, (f"view {view}'s discs fit its balls as well at {math.degrees(other):.2f} deg as at "
                               f"{corrected[view]:.2f} deg, with other balls on them: the balls do not fix its angle "
                               f"({len(ambiguous)} view(s) so)")
    # A correction as large as the stated error is allowed, give or take what the views' angles are known to: nominal
    # angles 2 deg off either way were refused where the estimate put the half range 2.0002 deg (a simulated hardened
    # scan, seed 2512 of ``benchmarks/bench_ball_phantom_mixed.py --max-error-deg 2``; standard errors up to 0.006 deg).
    elif moved > max_error_deg + _MOVED_SES * float(np.max(se)):
        kept, reason = False, (f"a view moved {moved:.2f} deg from the views' common turn, more than the nominal "
                               f"angles' error allows ({max_error_deg:g} deg, and {_MOVED_SES:g} standard errors): the "
                               f"balls are not followed reliably")
    elif p >= p_value:
        kept, reason = False, (f"the corrected angles explain the balls no better than the nominal ones beyond noise "
                               f"(reprojection RMS {rms:.3f} px against {nominal_rms:.3f} px; F test p {p:.2g})")
    elif within_disagreement:
        kept, reason = False, (f"the corrections are no larger than the balls' disagreement on the views' angles "
                               f"(standard errors up to {float(np.nanmax(spread)):.4f} deg, left out a ball at a "
                               f"time): {rms_change:.4f} deg RMS, the common turn taken out (chi-square "
                               f"{chi_change:.1f} on {dof_change} degrees of freedom, p {p_change:.2g}; the F test's "
                               f"p {p:.2g} takes the discs' errors as independent)")
    else:
        kept, reason = True, (f"the corrected angles explain the balls better: reprojection RMS {rms:.3f} px against "
                              f"{nominal_rms:.3f} px with the nominal ones (F test p {p:.2g})"
                              + (f"; view(s) {', '.join(str(int(v)) for v in lone)} pinned by one clean disc each, "
                                 f"which no other ball checks (standard error up to {np.max(se[lone]):.4f} deg)"
                                 if len(lone) else "")
                              + (f"; view(s) {', '.join(str(int(v)) for v in resting)} resting on a disc that their "
                                 f"other discs do not check to {max_angle_se_deg:g} deg (standard error up to "
                                 f"{np.max(se[resting]):.4f} deg)" if len(resting) else ""))
    ball_rms = np.array([np.sqrt(np.mean(fit.residual[ball_of == b] ** 2)) if np.any(ball_of == b) else np.nan
                         for b in range(len(balls))])
    returned, returned_cov = (fit, cov) if kept else (nominal_fit, _covariance(nominal_fit) if fit_detector else None)
    nominal_as_good = math.isfinite(p) and (p >= p_value or within_disagreement) and not len(lost)
    detector_kept, detector_reason = _detector_verdict(
        returned, kept, fit_detector, p_value, nominal_as_good=nominal_as_good,
        scan_fit=lambda: _adjust(discs, radii_mm, theta0, nominal_fit.balls,
                                 _nominal_detector(geometry), geometry, free_views=free_views,
                                 fit_angles=False, fit_detector=False, scale_px=scale_px, loss=fit_loss,
                                 cut_px=nominal_fit.cut_px, shifts_px=nominal_fit.shifts_px))
    detector_fit, detector_cov = returned, returned_cov
    if one_view and fit_detector and not nominal_as_good and p < p_value:
        detector_kept, detector_reason = _refused_angles_detector(_detector_se(cov, fit.n_det), detector_jack_se,
                                                                  detector_jack_n,
                                                                  p_value)
        if detector_kept:
            detector_fit, detector_cov = fit, cov
    detector = detector_fit.detector
    # The shifts go out where every view is fixed and each shift pinned: into the geometry a user reconstructs with,
    # fitted with its detector.
    pinned = detector_fit.shifts_px is not None and _shift_se_px(detector_fit, detector_cov) <= _MAX_SHIFT_SE_PX
    shifts_out = detector_fit.shifts_px.copy() if pinned and not len(unfixed) and not len(lost) else None
    return BallCalibration(angles_deg=corrected if kept else nominal.copy(), corrected_deg=corrected,
                           angle_se_deg=se, kept=kept, reason=reason, balls_mm=balls, u0_px=float(detector[0]),
                           v0_px=float(detector[1]), tilt_deg=math.degrees(detector[2]),
                           axis_offset_mm=float(detector[3]), source_to_detector_mm=float(detector[4]), rms_px=rms,
                           nominal_rms_px=nominal_rms, ball_rms_px=ball_rms, f_statistic=float(f_stat), p_value=p,
                           observations=int(len(observed)), shell_observations=int(np.sum(edge < 1.0)),
                           left_out=int(sum(int(np.sum(out)) for out in gross)),
                           assigned=assigned, ball_cut_px=cut_px,
                           detector_se=_detector_se(detector_cov if fit_detector else None, detector_fit.n_det),
                           pose_p_value=pose_p,
                           angle_jackknife_se_deg=jack_se, detector_kept=detector_kept,
                           detector_reason=detector_reason, correction_p_value=p_change,
                           view_shifts_px=shifts_out, shift_p_value=shift_p,
                           drift_spot_share=detector_fit.spot_share if shifts_out is not None else math.nan,
                           hidden_px=_hidden_discs_px(detections, assigned, gross, balls, radii_mm, angles, geometry,
                                                      detector, view_shifts), overlap_pull_px=fit.overlap_pull_px,
                           overlap_scatter_px=fit_scatter_px if math.isfinite(fit.overlap_pull_px) else math.nan,
                           lag_pull_px=lag_pull, lag_p_value=lag_p, lag_shown=lag_shown,
                           lag_move_deg=lag_most)


#: A detector's lag is said where its test's F test is below the calibration's ``p_value`` and the pulls, fitted, move
#: some view's angle by more than this share of ``max_angle_se_deg`` (0.005 deg at the default 0.02). The F test
#: alone also shows pulls too small to matter: a hardened scan of 36 views with no lag (solid 3112 of
#: ``benchmarks/bench_ball_phantom_mixed.py``) had p 7e-9, pulls up to 0.064 px, and moves up to 0.0021 deg; with 3 and
#: 5 % lag (solid 3104, kept 0.0138 and 0.0167 deg off) the moves were 0.0054 and 0.0106 deg, and on the scans whose
#: lag left them within 0.01 deg (the mixed phantom with 5 %, coated balls with 8 %) 0.0041 and 0.0019. Chosen on
#: those seen scans.
_LAG_MOVE_SHARE = 0.25


def _adjust_from(fit: _Fit, discs: _Discs, radii_mm, geometry: Geometry, **adjust) -> _Fit:
    """:func:`_adjust` again from ``fit``'s solution (its angles, balls, detector and cut depths), with ``adjust``'s
    changes: a larger model tried against it (the scanner's pose, the views' shifts, the lag's pulls)."""
    return _adjust(discs, radii_mm, fit.angles, fit.balls, fit.detector, geometry, cut_px=fit.cut_px, **adjust)


def _lag_test(fit: _Fit, discs: _Discs, radii_mm, free_views, geometry: Geometry,
              **adjust) -> tuple[float, np.ndarray, np.ndarray]:
    """Are the discs pulled towards where their balls were the view before, as a detector's lag pulls them? The F test
    of ``fit`` against the same adjustment with one more unknown a ball, how far its discs are pulled so
    (:func:`_lag_directions`), those pulls (px, towards the view before) and how far they move each view's angle
    (deg, the common turn taken out; NaN where not free): ``(p, pulls, moves)``, NaN where it cannot be tested. Only
    tested: the angles are ``fit``'s.

    Lag (afterglow) leaves a share of each frame's signal in the next, so every disc of the view before is there
    again, faint. Under a clipped background it moves a faint ball's rim most: inside the view before's disc the
    ghost takes light away, outside it the rim reads as it is, so the clip cuts the rim on the side the ball moves
    towards deeper than on the side it came from, and the disc is found pulled back along its way, by about the same
    whatever the step (simulated hardened scans with 3-5 % lag, ``benchmarks/bench_ball_phantom_mixed.py
    --lag-fraction``: a clipped aluminium ball's discs 0.27-0.41 px back at steps of 0.08-0.76 of its diameter, the
    faint polymer balls' 0.5-2.7 px, a dense ball's a few hundredths; ``docs/calibration-phantoms.md``). Fitted, the
    pulls take up some of it (a hardened scan with 3 % lag: its worst view 0.0138 -> 0.0104 deg) and cost elsewhere
    (the mixed phantom with 5 %: 0.0081 -> 0.0108 deg, the faint balls' pulls trading with the angles), so they are
    reported, not fitted.
    """
    lag = _lag_directions(discs.view_of, discs.ball_of, fit.balls, radii_mm, fit.angles, geometry, fit.detector)
    trial = _adjust_from(fit, dataclasses.replace(discs, lag=lag), radii_mm, geometry, free_views=free_views, **adjust)
    move = np.full(len(fit.angles), np.nan)
    if trial.lag_pull_px is None:
        return math.nan, np.full(len(fit.balls), np.nan), move
    if len(free_views):
        turn = trial.angles[free_views] - fit.angles[free_views]
        move[free_views] = np.rad2deg(np.abs(turn - np.median(turn)))
    return _f_test(fit, trial)[1], -trial.lag_pull_px, move


def _shifted(detections, shifts_px: np.ndarray) -> list[np.ndarray]:
    """Each view's detections with its shift taken off their centres: where an unshifted projection puts them."""
    if not np.any(shifts_px):
        return detections
    moved = []
    for found, shift in zip(detections, shifts_px):
        found = found.copy()
        found[:, :2] -= shift
        moved.append(found)
    return moved


def _f_test(fit: _Fit, larger: _Fit, kept: np.ndarray | None = None) -> tuple[float, float]:
    """The F test of ``larger`` (more unknowns, ``fit`` nested in it) against ``fit``: ``(F, p-value)``, NaN where it
    cannot be computed. The extra unknowns are counted less the gauge rows on either side. Given ``kept`` (a mask
    over the discs), on those discs' residuals alone."""
    from scipy import stats

    chi, _ = _chi_dof(fit, kept)
    chi_larger, dof = _chi_dof(larger, kept)
    extra = (larger.n_params - larger.n_gauge) - (fit.n_params - fit.n_gauge)
    if dof <= 0 or extra <= 0 or chi_larger <= 0:
        return math.nan, math.nan
    f_stat = ((chi - chi_larger) / extra) / (chi_larger / dof)
    return f_stat, float(stats.f.sf(f_stat, extra, dof))


def _shift_se_px(fit: _Fit, cov: np.ndarray | None = None) -> float:
    """The largest standard error (px) of a fit's views' shifts less their columns' once-a-turn part, from its
    covariance ``cov`` (computed where not given); infinite where it cannot be computed.

    The once-a-turn part trades with a common translation of the balls, which explains it to within the cone's
    magnification across the phantom's depth: fitted (:func:`_adjust`), it is pinned far less than each view's own
    shift, and counted in, it would have every drift's shifts refused. What the bar asks is each view's own shift
    pinned; what the trade costs the angles, their standard errors say."""
    cov = _covariance(fit) if cov is None else cov
    if cov is None or fit.shift_columns.stop <= fit.shift_columns.start:
        return math.inf
    turn = fit.angles[fit.free_views]
    once = np.zeros((2 * len(turn), 2))
    once[0::2, 0], once[0::2, 1] = np.cos(turn), np.sin(turn)
    basis, _ = np.linalg.qr(once)
    less = np.eye(len(once)) - basis @ basis.T
    shifts_cov = less @ cov[fit.shift_columns, fit.shift_columns] @ less.T
    return float(np.sqrt(np.max(np.clip(np.diag(shifts_cov), 0.0, None))))


def _chi_dof(fit: _Fit, kept: np.ndarray | None = None) -> tuple[float, int]:
    """A fit's residual sum of squares and its degrees of freedom (each gauge row gives one unknown back), over the
    discs ``kept`` where given."""
    residual = fit.residual if kept is None else fit.residual[kept]
    return float(np.sum(residual ** 2)), int(residual.size - (fit.n_params - fit.n_gauge))


def _but_the_worst(residual: np.ndarray, view_of: np.ndarray) -> np.ndarray:
    """A mask over the discs leaving out each view's worst-fitted one (its largest residual), in views of three or
    more, and every disc of a view of fewer: the discs a drift must still show in before the views' shifts are
    fitted.

    A view of two discs with a shift of its own has one number to spare (four, less its angle and shift), so its
    shift takes up a disc pulled off as readily as a drift: a merged pair's disc 4 px off, in the one view of two
    discs on a drift-free synthetic scan of 20 views, showed as a drift (p 3e-25 with that view's discs kept), and
    fitted, the shifts left the view 0.82 deg off. Without that view: p 1.

    A view's shift also takes up a single disc that something pulled. On a simulated scan of nine balls placed at
    random (24 views, the clip at 80 %; ``tests/solve/data/random_layout_1103.npz``) a steel ball's disc half
    covered by a polymer ball the clip hid was 0.24 px off in two views, every other disc of theirs within 0.03 px:
    the F test over every disc took the shifts (p 6e-33; those two discs were 85 % of what they explained) and
    both views came out 0.017 deg off, kept, where without shifts they are within 0.004. Without each view's worst
    disc the shifts fitted the rest worse (residual sum of squares 0.0066 -> 0.0155; p 1). Where the projections
    drift, every disc shows it: on five drifted coated scans (a walk of 0.01-0.1 px a view, jumps of 0.2-0.5 px) the
    rest's sum fell 4-130 fold, p 8e-19 or less, and every view's median disc fitted better
    (``docs/calibration-phantoms.md``, "Projections that drift")."""
    kept = np.ones(len(residual), bool)
    size = np.sum(residual ** 2, axis=1)
    for view in np.unique(view_of):
        mine = np.flatnonzero(view_of == view)
        if len(mine) >= 3:
            kept[mine[np.argmax(size[mine])]] = False
        else:
            kept[mine] = False
    return kept


def _covariance(fit: _Fit) -> np.ndarray | None:
    """The Gauss-Newton covariance of a fit's unknowns, scaled by its residual variance; None without degrees of
    freedom or where it cannot be computed."""
    chi, dof = _chi_dof(fit)
    if fit.jac is None or dof <= 0:
        return None
    try:
        return np.linalg.pinv(fit.jac.T @ fit.jac) * (chi / dof)
    except np.linalg.LinAlgError:
        return None


#: A fitted detector ``(u0, v0, tilt, axis offset, source to detector)`` (px, px, rad, mm, mm) times this is in the
#: units it is reported in (px, px, deg, mm, mm).
_DETECTOR_UNITS = np.array([1.0, 1.0, math.degrees(1.0), 1.0, 1.0])


def _beyond_allowed(jackknife_se, refits, allowed, p_value: float) -> np.ndarray:
    """Where a jackknife's standard error over ``refits`` refits is beyond ``allowed`` by more than its own spread: its
    variance is about chi-square with one fewer degrees of freedom than the refits, so it exceeds the bar where that
    chi-square does at ``p_value``. False where the standard error is NaN."""
    from scipy import stats

    refits = np.asarray(refits)
    with np.errstate(invalid="ignore"):
        return (refits - 1) * (np.asarray(jackknife_se) / allowed) ** 2 > stats.chi2.isf(p_value,
                                                                                        np.maximum(refits - 1, 1))


#: The most a detector fitted with angles that are not returned may be unsure of (px for the axis column and the
#: principal row, deg for the tilt; a standard error): half what issue 34 asks the geometry to be within (0.1 px,
#: 0.01 deg), so that it is within that at two standard errors.
_MAX_DETECTOR_SE = np.array([0.05, 0.05, 0.005])


def _refused_angles_detector(fit_se: np.ndarray, jackknife_se: np.ndarray, refits: int,
                             p_value: float) -> tuple[bool, str]:
    """Whether the detector fitted with the corrected angles is given though the angles are not, and why.

    Where the corrected angles are refused for some views alone (a view its balls barely pin, or on which they
    disagree), the balls still follow, the correction explains them beyond noise, and the detector is fitted on every
    view: one view's angle moves it little, and the nominal angles, off by the stage's error, would move it more (a
    simulated 36-view hardened scan, seed 2105 of ``benchmarks/bench_ball_phantom_mixed.py``: the axis column 0.26 px
    off with them). It is given where its standard errors, by the residuals (``fit_se``) and by the jackknife over the
    balls (``jackknife_se`` over ``refits``), are within :data:`_MAX_DETECTOR_SE`, the jackknife's by the views' own
    test (:func:`_beyond_allowed`): those of the axis column, the principal row and the tilt, which the geometry takes.
    """
    names = ("axis column", "principal row", "tilt")
    # What the geometry a user reconstructs with takes (the axis offset and the distance are reported alone).
    fit_se, jackknife_se = fit_se[:len(names)], jackknife_se[:len(names)]
    spread = np.fmax(fit_se, jackknife_se)
    if refits < 2 or not np.all(np.isfinite(spread)):
        return False, "not given: the detector fitted with the corrected angles, which are not returned, is not checked"
    beyond = (fit_se > _MAX_DETECTOR_SE) | _beyond_allowed(jackknife_se, refits, _MAX_DETECTOR_SE, p_value)
    said = (f"the balls fix its axis column to {spread[0]:.3f} px, its principal row to {spread[1]:.3f} px and its "
            f"tilt to {spread[2]:.4f} deg (the larger of the fit's and the jackknife's standard errors over "
            f"{refits} refits)")
    if beyond.any():
        over = " and ".join(f"{name} beyond the {allowed:g} {unit}" for name, allowed, unit, b in
                            zip(names, _MAX_DETECTOR_SE, ("px", "px", "deg"), beyond) if b)
        return False, (f"not given: fitted with the corrected angles, which are not returned, {said}; its {over} "
                       f"allowed (the fit's standard error, or the jackknife's by more than its own spread)")
    return True, (f"fitted with the corrected angles, which are not returned (some views' angles are not fixed: "
                  f"above); {said}, within the {_MAX_DETECTOR_SE[0]:g} px and {_MAX_DETECTOR_SE[2]:g} deg allowed")


def _detector_se(cov: np.ndarray | None, n_det: int) -> np.ndarray:
    """Standard errors of the detector (u0 px, v0 px, tilt deg, axis offset mm, source to detector mm), a fitted
    detector's ``n_det`` unknowns being the last of ``cov`` (:func:`_covariance`); NaN without one, and for those not
    fitted."""
    se = np.full(_DETECTOR_UNKNOWNS, np.nan)
    if cov is not None and n_det:
        se[:n_det] = np.sqrt(np.clip(np.diag(cov)[-n_det:], 0.0, None)) * _DETECTOR_UNITS[:n_det]
    return se


def _beyond_disagreement(change_deg: np.ndarray, spread_deg: np.ndarray,
                         spread_dof: np.ndarray | None = None) -> tuple[float, int, float, float]:
    """Whether the views' corrections ``change_deg`` stand out from the balls' disagreement on them: ``(chi-square,
    degrees of freedom, p-value, RMS)`` of the corrections less their common turn (weighted), over ``spread_deg``
    per view (views where it is not finite are left out). Were the nominal angles right, the corrections would be
    noise of that spread: chi-square with one fewer degree of freedom than the views. NaN where fewer than two views
    count.

    ``spread_dof`` gives the degrees of freedom each view's spread is estimated with (infinite where it is known): a
    jackknife's over ``G`` refits has ``G - 1`` (as :func:`_jackknife_se`'s own test takes it), so the view's
    correction over it is Student's t, not normal (Efron and Tibshirani 1993, ch. 11), and is counted as the normal
    deviate of the same tail probability: over six balls' spread a correction 7 times it is as likely as a normal
    one 3.3 times. Told its true angles, a hardened scan's corrections (solid 1202, what its discs share) stood out
    at p 3.8e-4 taken as normal, 1.3e-3 so, and the nominal angles came back (``docs/calibration-phantoms.md``).
    """
    from scipy import stats

    counted = np.isfinite(change_deg) & np.isfinite(spread_deg) & (spread_deg > 0)
    if np.count_nonzero(counted) < 2:
        return math.nan, 0, math.nan, math.nan
    weight = 1.0 / spread_deg[counted] ** 2
    change = change_deg[counted]
    change = change - np.sum(weight * change) / np.sum(weight)
    z = np.abs(change) / spread_deg[counted]
    if spread_dof is not None:
        dof_view = np.asarray(spread_dof, dtype=np.float64)[counted]
        student = np.isfinite(dof_view) & (dof_view >= 1)
        # A tail too far out to represent (a correction far beyond any doubt) keeps its own deviate.
        z[student] = np.minimum(z[student], stats.norm.isf(stats.t.sf(z[student], dof_view[student])))
    chi = float(np.sum(z ** 2))
    dof = int(np.count_nonzero(counted)) - 1
    return chi, dof, float(stats.chi2.sf(chi, dof)), float(np.sqrt(np.mean(change ** 2)))


def _detector_verdict(returned: _Fit, kept: bool, fit_detector: bool, p_value: float, *, nominal_as_good: bool,
                      scan_fit) -> tuple[bool, str]:
    """Whether the detector fitted with the returned angles is the one to use, and why (module docstring, step 4).

    ``scan_fit`` makes the fit with the scan's own detector and the nominal angles, only when it is needed.
    """
    if not fit_detector:
        return False, "the detector was not fitted"
    if kept:
        return True, "fitted with the corrected angles"
    if not nominal_as_good:
        return False, ("not given: the nominal angles are returned without explaining the balls as well as the "
                       "corrected ones, so no detector is fitted to the angles returned")
    chi, dof = _chi_dof(returned)
    if dof <= 0 or chi <= 0:
        return False, "not given: too few discs to test the fitted detector"
    scan = scan_fit()
    rms = math.sqrt(chi / returned.residual.size)
    rms_scan = math.sqrt(float(np.sum(scan.residual ** 2)) / scan.residual.size)
    _, p = _f_test(scan, returned)    # the detector's unknowns
    if p < p_value:
        return True, (f"with the nominal angles, the fitted detector explains the balls better than the scan's: "
                      f"reprojection RMS {rms:.3f} px against {rms_scan:.3f} px (F test p {p:.2g})")
    return False, (f"the scan's detector: the fitted one explains the balls no better beyond noise (reprojection RMS "
                   f"{rms:.3f} px against {rms_scan:.3f} px; F test p {p:.2g})")
