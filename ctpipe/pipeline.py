"""The pipeline: projections + geometry + view pairs -> per-pair and per-view angles."""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ctpipe._shared import device as gpu
from ctpipe._shared.checks import short_repr
from ctpipe._shared.resources import release_free_memory
from ctpipe.config import PipelineConfig, StageSpec, build_stage, load_yaml, parse_geometry, parse_pipeline
from ctpipe.data import Features, ScanObservations, ScanSolution
from ctpipe.errors import EstimationError, InputError
from ctpipe.execution import Executor, ProcessPool, ThreadExecutor, WorkerLost, one_blas_thread_per_task
from ctpipe.geometry import Geometry
from ctpipe.images import check_image
from ctpipe.io.corrected import cone_vectors, scanner_frame_deg
from ctpipe.io.scans import ScanFiles, StackReference, ViewStack
from ctpipe.model import wrap_deg
from ctpipe.plugins import get_registry
from ctpipe.registry import StageRegistry
from ctpipe.solve.conjugate import midplane_rows
from ctpipe.solve.bands import split_bands
from ctpipe.solve.gate import GateDecision, cannot_tell, gate_angles
from ctpipe.solve.graph import view_pairs
from ctpipe.solve.reprojection import as_line_integrals
from ctpipe.stages import Detector, Estimator, Matcher, Refiner

__all__ = ["Pipeline", "ScanResult", "RefinedGeometry", "TurnCheck", "RefinerChoice", "ClosingView", "AngleErrors",
           "difference_table"]

#: Most memory the static background's median may take: 90 views of 512^2, 32 of 2,048^2.
_BACKGROUND_BYTES = 512 * 2**20


#: What a refiner may estimate of the geometry, by the key it reports it under in its info.
REFINABLE_GEOMETRY = ("u0_px", "v0_px", "tilt_deg", "source_to_detector_mm", "axis_offset_mm")


@dataclass(frozen=True)
class RefinedGeometry:
    """The geometry a run ends with: the input one, with what the refiner estimated put in.

    Attributes
    ----------
    geometry : Geometry
        The input geometry with the principal point (``u0_px``: the centre of rotation's
        column; ``v0_px``) the refiner estimated, where it estimated it.
    tilt_deg : float
        In-plane detector tilt the refiner estimated, degrees; 0 when it estimated none.
    refined : tuple of str
        Which of ``"u0_px"``, ``"v0_px"``, ``"tilt_deg"``, ``"source_to_detector_mm"``, ``"axis_offset_mm"``,
        ``"view_shifts_px"`` the refiner estimated (bundle adjustment with ``estimate_u0``, ``estimate_v0`` or
        ``estimate_tilt``; the ball calibration); empty when ``geometry`` is the input geometry as it was.
    view_shifts_px : tuple of (float, float) per view, or None
        Each view's own shift of the projection ``(du, dv)`` (px), where the refiner estimated it
        (:attr:`ctpipe.data.ScanSolution.view_shifts_px`); a tuple, so that the geometry compares and
        hashes by value.
    axis_offset_mm : float
        How far the rotation axis lies off the source's perpendicular to the detector (mm), where the refiner
        estimated it (the ball calibration), else 0: ``(u0_px, v0_px)`` is where the axis's point level with the
        source projects. :meth:`ScanResult.cone_vectors` places the source and detector so; ctpipe's own FDK takes
        the axis on the perpendicular.
    spot_share : float
        How much of each view's shift the source spot made (:attr:`ctpipe.data.ScanSolution.drift_spot_share`;
        0: the detector's, as where the refiner did not tell): :meth:`ScanResult.cone_vectors` moves the source
        by that share and the detector by the rest.
    """

    geometry: Geometry
    tilt_deg: float = 0.0
    refined: tuple[str, ...] = ()
    view_shifts_px: tuple[tuple[float, float], ...] | None = None
    axis_offset_mm: float = 0.0
    spot_share: float = 0.0

    @classmethod
    def from_solution(cls, geometry: Geometry, solution: ScanSolution) -> "RefinedGeometry":
        """The geometry a refiner's solution estimated (its typed ``u0_px``, ``v0_px``, ``tilt_deg``,
        ``source_to_detector_mm``, ``axis_offset_mm``)."""
        refined = tuple(k for k in REFINABLE_GEOMETRY if getattr(solution, k) is not None)
        corrected = dataclasses.replace(geometry, **{k: float(getattr(solution, k))
                                                     for k in ("u0_px", "v0_px", "source_to_detector_mm")
                                                     if k in refined})
        offset = solution.axis_offset_mm
        tilt = solution.tilt_deg
        shifts = solution.view_shifts_px
        share = 0.0
        if shifts is not None:
            shifts = tuple((float(du), float(dv)) for du, dv in np.asarray(shifts, dtype=np.float64))
            refined = (*refined, "view_shifts_px")
            share = 0.0 if solution.drift_spot_share is None else float(solution.drift_spot_share)
        return cls(corrected, 0.0 if tilt is None else float(tilt), refined, shifts,
                   0.0 if offset is None else float(offset), share)


@dataclass(frozen=True)
class TurnCheck:
    """Whether the pair angles, measured from the images alone, turn the way the nominal angles do.

    A reader whose angle sign is wrong for a scanner gives nominal steps of one sign and pair
    angles of the other; that shows here before it spoils anything downstream. It is said only
    where the pairs show it beyond chance (:attr:`reversed`): on a ball phantom the pair angles
    are the estimator's guesses on a handful of look-alike discs (a median of one inlier), as
    often of one sign as the other. On a simulated Nikon folder of the ball bar, 59 % of 32 pairs
    disagreeing told a scan whose balls the calibration followed the nominal way (to 0.005 px)
    that its sign was "probably reversed" (sign test p 0.19).

    Attributes
    ----------
    pairs : int
        Pairs with an angle and a nominal step of more than 1e-6 deg; 0 when none (the other
        fields are then None).
    agree_fraction : float or None
        Share of those pairs whose angle has the sign of its nominal step.
    median_pair_deg : float or None
        Median angle of those pairs.
    median_nominal_step_deg : float or None
        Median nominal step of those pairs, wrapped to [-180, 180).
    sign_p_value : float or None
        The sign test's: how likely as many pairs would disagree or more, were each pair's sign a
        coin's toss (one-sided binomial).
    """

    pairs: int
    agree_fraction: float | None = None
    median_pair_deg: float | None = None
    median_nominal_step_deg: float | None = None
    sign_p_value: float | None = None

    #: The sign test's level below which the pairs are taken to turn the other way: ten pairs of ten disagreeing
    #: reach it (0.5^10 = 0.00098); a scan read with the wrong sign has every informative pair disagreeing.
    P_VALUE = 1e-3

    @classmethod
    def compute(cls, pairs: np.ndarray, pair_angles_deg: np.ndarray, nominal_angles_deg: np.ndarray) -> "TurnCheck":
        """The check of ``pair_angles_deg`` (NaN: failed) against the nominal steps of ``pairs``."""
        nominal = np.asarray(nominal_angles_deg, dtype=np.float64)
        steps = wrap_deg(nominal[pairs[:, 1]] - nominal[pairs[:, 0]])
        usable = np.isfinite(pair_angles_deg) & (np.abs(steps) > 1e-6)
        if not usable.any():
            return cls(pairs=0)
        from scipy.stats import binomtest

        agree = np.sign(pair_angles_deg[usable]) == np.sign(steps[usable])
        n = int(usable.sum())
        return cls(pairs=n, agree_fraction=float(np.mean(agree)),
                   median_pair_deg=float(np.median(pair_angles_deg[usable])),
                   median_nominal_step_deg=float(np.median(steps[usable])),
                   sign_p_value=float(binomtest(int(n - agree.sum()), n, 0.5, alternative="greater").pvalue))

    @property
    def reversed(self) -> bool:
        """The images turn the other way from the nominal angles: more pairs disagree in sign than agree, beyond
        chance (the sign test's p below :attr:`P_VALUE`)."""
        return bool(self.pairs) and self.agree_fraction < 0.5 and self.sign_p_value < self.P_VALUE

    def to_dict(self) -> dict[str, Any]:
        """``{"pairs": 0}``, or every field."""
        if not self.pairs:
            return {"pairs": 0}
        return {"pairs": self.pairs, "agree_fraction": self.agree_fraction, "median_pair_deg": self.median_pair_deg,
                "median_nominal_step_deg": self.median_nominal_step_deg, "sign_p_value": self.sign_p_value}


@dataclass(frozen=True)
class RefinerChoice:
    """What a whole-scan refiner chose between, as it reported it (projection matching's gate).

    Attributes
    ----------
    start : str or None
        Where the refiner started from (projection matching: ``least-squares``,
        ``bundle-adjustment`` or ``nominal``); None when it does not say.
    matched : bool
        Whether projection matching ran.
    matched_from : str or None
        Which candidate matching started from: ``start`` or ``nominal``, the one that explained
        the projections better.
    skipped : str or None
        Why matching did not run (too few views, no projections, too small a detector).
    chosen : str or None
        The candidate whose angles were returned: ``matched``, ``start`` or ``nominal``.
    consistency_cost : dict of str to float
        Each candidate's residual on views held out of the reference they are compared with
        (:func:`ctpipe.solve.reprojection.held_out_scores`); the lowest is chosen where it beats
        the nominal angles' beyond noise (``held_out_z``); empty when the candidates were not compared.
    held_out_z : dict of str to float
        Each candidate's held-out cost against the nominal angles', in standard errors (negative:
        better); empty when the candidates were not compared.
    """

    start: str | None = None
    matched: bool = False
    matched_from: str | None = None
    skipped: str | None = None
    chosen: str | None = None
    consistency_cost: Mapping[str, float] = field(default_factory=dict)
    held_out_z: Mapping[str, float] = field(default_factory=dict)

    @classmethod
    def from_info(cls, info: Mapping[str, Any]) -> "RefinerChoice":
        """The choice a refiner's :attr:`~ctpipe.data.ScanSolution.info` reports."""
        matching = info.get("matching")
        matched = isinstance(matching, Mapping)
        return cls(start=info.get("start"), matched=matched, matched_from=matching.get("from") if matched else None,
                   skipped=matching if isinstance(matching, str) else None, chosen=info.get("chosen"),
                   consistency_cost=dict(info.get("consistency_cost") or {}),
                   held_out_z={name: score["z"] for name, score in (info.get("held_out") or {}).items()})


@dataclass(frozen=True)
class ClosingView:
    """How far a scan's closing view turned from view 0 (see :attr:`ctpipe.io.scans.ScanFiles.closing_view`).

    The closing view is view 0's pose one turn on, so its angle measured from the images says
    how far the whole scan turned.

    Attributes
    ----------
    view : int
        Its index, the last view.
    nominal_turn_deg : float
        Its nominal angle minus view 0's.
    estimated_turn_deg : float
        Its estimated angle minus view 0's, measured from the images.
    recorded_turn_deg : float or None
        The same from the scanner's angle log; None without a log.
    """

    view: int
    nominal_turn_deg: float
    estimated_turn_deg: float
    recorded_turn_deg: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass(frozen=True, eq=False)
class AngleErrors:
    """Errors of a run against known true angles (a simulation), as
    :func:`ctpipe.evaluate.scoring.score_against_truth` finds them.

    Attributes
    ----------
    true_angles_deg : ndarray of shape (V,)
    view_errors_deg : ndarray of shape (V,)
        Each view's error after the common offset; NaN where a view has no angle.
    views, pairs : dict
        :func:`ctpipe.evaluate.scoring.error_table` of the views' and the pairs' errors.
    """

    true_angles_deg: np.ndarray
    view_errors_deg: np.ndarray
    views: Mapping[str, float | int]
    pairs: Mapping[str, float | int]

    def to_dict(self) -> dict[str, Any]:
        return {"views": dict(self.views), "pairs": dict(self.pairs)}


@dataclass(frozen=True, eq=False)
class ScanResult:
    """What a pipeline run returns: the angles, the geometry it ends with, and its report.

    Attributes
    ----------
    pairs : ndarray of shape (P, 2), int64
    pair_angles_deg : ndarray of shape (P,)
        Refined angle of each pair, NaN where it failed.
    pair_inlier_masks : tuple of ndarray of shape (M_k,), bool
    n_matches, n_inliers : ndarray of shape (P,), int64
    residuals : ndarray of shape (P,)
        RMS Sampson distance of each pair's inliers, normalised units.
    pair_status : tuple of str
        ``"ok"`` or why the pair failed.
    angles_deg : ndarray of shape (V,)
        Angle of every view relative to view 0, chained from the pairs; NaN where a view is
        not connected to view 0 by successful pairs.
    n_keypoints : ndarray of shape (V,), int64
    timings_s : dict
    refiner_info : dict
        What the refiner reported, as it reported it (see :attr:`ctpipe.data.ScanSolution.info`);
        :attr:`refined_geometry` and :attr:`refiner_choice` hold what of it a user acts on.
    static_background_removed : bool
        Whether features were detected on the views less the scan's static part.
    detect_binning : int
        The binning of the views the features were detected on (1: the full views).
    geometry : Geometry or None
        The geometry the run was given.
    refined_geometry : RefinedGeometry or None
        The geometry with the principal point and detector tilt the refiner estimated, where it
        estimated them (else ``geometry`` as it was).
    refiner_choice : RefinerChoice
        What the refiner chose between (projection matching: the start, the candidate it
        matched from, the one it kept and their consistency costs).
    nominal_angles_deg : ndarray of shape (V,) or None
        The nominal angles the run was given.
    turn_check : TurnCheck or None
        Whether the images turn the way the nominal angles do; None without nominal angles.
    closing_view : ClosingView or None
        The turn measured to the scan's closing view, when the run was given a scan that has one.
    scan : ctpipe.io.scans.ScanFiles or None
        The scan the run was given (format, path, notes, the scanner's angle log), if any.
    pipeline : ctpipe.config.PipelineConfig or None
        The configuration of the pipeline that ran, when it was built from one.
    angle_errors : AngleErrors or None
        Errors against the true angles, filled by :func:`ctpipe.evaluate.scoring.score_against_truth`.
    gate : ctpipe.solve.gate.GateDecision or None
        Whether the projections showed the refiner's angles (or one band of their correction)
        better than the nominal angles, and which were returned (:mod:`ctpipe.solve.gate`);
        None when the run had no nominal angles or the pipeline's gate is off.
    angle_se_deg : ndarray of shape (V,) or None
        Standard error of every view's returned angle, degrees: the refiner's own (projection
        matching: its fit's curvature) and, where the gate kept a band of the correction out,
        that band's size (``docs/wholescan.md``); None when the refiner gives none.
    before_after : ctpipe.evaluate.preview.BeforeAfter or None
        Slices reconstructed with the nominal and the returned angles and the conjugate-ray
        measure of each, when made (``ctpipe estimate --out`` makes them; see
        :func:`ctpipe.evaluate.preview.before_after`).
    """

    pairs: np.ndarray
    pair_angles_deg: np.ndarray
    pair_inlier_masks: tuple[np.ndarray, ...]
    n_matches: np.ndarray
    n_inliers: np.ndarray
    residuals: np.ndarray
    pair_status: tuple[str, ...]
    angles_deg: np.ndarray
    n_keypoints: np.ndarray
    timings_s: dict[str, float]
    refiner_info: dict[str, Any] = field(default_factory=dict)
    static_background_removed: bool = False
    detect_binning: int = 1
    geometry: Geometry | None = None
    refined_geometry: RefinedGeometry | None = None
    refiner_choice: RefinerChoice = field(default_factory=RefinerChoice)
    nominal_angles_deg: np.ndarray | None = None
    turn_check: TurnCheck | None = None
    closing_view: ClosingView | None = None
    scan: ScanFiles | None = None
    pipeline: PipelineConfig | None = None
    angle_errors: AngleErrors | None = None
    gate: GateDecision | None = None
    angle_se_deg: np.ndarray | None = None
    before_after: Any = None

    @property
    def estimated_deg(self) -> np.ndarray:
        """:attr:`angles_deg` in the nominal angles' frame (their median offset), or as they are without them."""
        return scanner_frame_deg(self.angles_deg, self.nominal_angles_deg)

    @property
    def recorded_angles_deg(self) -> np.ndarray | None:
        """The angles the scanner logged per view (from :attr:`scan`), or None."""
        return None if self.scan is None else self.scan.recorded_angles_deg

    def to_dict(self) -> dict[str, Any]:
        """The run itself: angles, keypoints, every pair, timings, what the refiner reported."""
        return {
            "angles_deg": self.angles_deg,
            "n_keypoints": self.n_keypoints,
            "pairs": [
                {"views": [int(i), int(j)], "angle_deg": a, "n_matches": m, "n_inliers": n, "residual": r, "status": s}
                for (i, j), a, m, n, r, s in zip(self.pairs, self.pair_angles_deg, self.n_matches, self.n_inliers,
                                                  self.residuals, self.pair_status)
            ],
            "timings_s": self.timings_s,
            "refiner": self.refiner_info,
            "static_background_removed": self.static_background_removed,
            "detect_binning": self.detect_binning,
        }

    def report(self) -> dict[str, Any]:
        """What ``ctpipe estimate`` writes to result.json (and prints with ``--json``).

        The pipeline and geometry, :meth:`to_dict`, the angles in the nominal frame
        (``estimated_deg``), then as known: the scan, the nominal angles with the estimate's
        difference from them and the :attr:`turn_check`, the :attr:`closing_view`, the
        scanner's logged angles and the difference from them, the :attr:`gate`, the
        :attr:`before_after` measure, the :attr:`angle_errors`; the :attr:`refined_geometry` where the
        refiner estimated any of it (``refined_geometry``: the geometry, the tilt and which were estimated).
        Values are plain Python and numpy arrays (:func:`ctpipe.io.outputs.to_jsonable` makes
        it JSON).
        """
        estimated = self.estimated_deg
        report = {"pipeline": None if self.pipeline is None else self.pipeline.to_dict(),
                  "geometry": None if self.geometry is None else self.geometry.to_dict(), **self.to_dict(),
                  "estimated_deg": estimated}
        scan = self.scan
        if scan is not None:
            report["scan"] = {"format": scan.format, "path": str(scan.path), "notes": list(scan.notes),
                              "angle_log": None if scan.angle_log is None else str(scan.angle_log)}
            if scan.skipped_views:
                # The arrays of the report hold the other views; these are their numbers in the scan.
                report["scan"]["skipped_views"] = [{"view": k, "reason": why}
                                                   for k, why in sorted(scan.skipped_views.items())]
                report["scan"]["view_numbers"] = list(scan.view_numbers)
        nominal = self.nominal_angles_deg
        if nominal is not None:
            report["nominal_deg"] = nominal
            report["against_nominal"] = difference_table(estimated, nominal)
            report["turn_check"] = self.turn_check.to_dict()
        if self.closing_view is not None:
            report["closing_view"] = self.closing_view.to_dict()
        recorded = self.recorded_angles_deg
        if recorded is not None:
            report["recorded_deg"] = recorded
            report["against_recorded"] = difference_table(estimated, recorded)
        refined = self.refined_geometry
        if refined is not None and refined.refined:
            # What geometry_vectors.csv holds, for a lab to set beside its scanner's calibration.
            report["refined_geometry"] = {"geometry": refined.geometry.to_dict(), "tilt_deg": refined.tilt_deg,
                                          "refined": list(refined.refined)}
            if "axis_offset_mm" in refined.refined:
                report["refined_geometry"]["axis_offset_mm"] = refined.axis_offset_mm
            if refined.view_shifts_px is not None:
                report["refined_geometry"]["view_shifts_px"] = np.round(np.array(refined.view_shifts_px), 4).tolist()
                report["refined_geometry"]["drift_spot_share"] = refined.spot_share
        if self.gate is not None:
            report["gate"] = self.gate.to_dict()
        if self.angle_se_deg is not None:
            report["angle_se_deg"] = self.angle_se_deg
        if self.before_after is not None:
            report["before_after"] = self.before_after.to_dict()
        if self.angle_errors is not None:
            report["angle_errors"] = self.angle_errors.to_dict()
        return report

    def angle_columns(self) -> dict[str, np.ndarray]:
        """The per-view columns of angles.csv after its ``view`` column, by name."""
        estimated = self.estimated_deg
        columns = {"angle_deg": estimated}
        if self.angle_se_deg is not None:
            columns["se_deg"] = self.angle_se_deg
        columns["n_keypoints"] = self.n_keypoints
        nominal = self.nominal_angles_deg
        if nominal is not None:
            columns["nominal_deg"] = nominal
            columns["estimated_minus_nominal_deg"] = estimated - nominal
        recorded = self.recorded_angles_deg
        if recorded is not None:
            columns["recorded_deg"] = recorded
            columns["estimated_minus_recorded_deg"] = estimated - recorded
        gate = self.gate
        if gate is not None and gate.chosen != "estimate":
            # What the refiner said, before the gate replaced it (nominal frame, as angle_deg).
            columns["refiner_deg"] = gate.estimate_deg
        if self.angle_errors is not None:
            columns["true_deg"] = self.angle_errors.true_angles_deg
            columns["error_deg"] = self.angle_errors.view_errors_deg
        return columns

    def cone_vectors(self) -> np.ndarray:
        """ASTRA ``cone_vec`` rows of every view (:func:`ctpipe.io.corrected.cone_vectors`), shape (V, 12).

        With the :attr:`refined_geometry` and :attr:`estimated_deg`: what geometry_vectors.csv holds.
        """
        refined = self.refined_geometry
        return cone_vectors(refined.geometry, self.estimated_deg, tilt_deg=refined.tilt_deg,
                            shifts_px=refined.view_shifts_px, axis_offset_mm=refined.axis_offset_mm,
                            spot_share=refined.spot_share)

    def failed_pairs_warning(self) -> str | None:
        """One line saying how many pairs failed and why the first did, or None when none failed."""
        failed = [s for s in self.pair_status if s != "ok"]
        return f"warning: {len(failed)} pairs failed, e.g. {failed[0]}" if failed else None

    def summary(self, *, source: str | Path | None = None, written: Sequence[str] = (),
                described: bool = False) -> str:
        """One screen: what was read, how the estimate went, how far it is from the nominal and logged angles.

        What ``ctpipe estimate`` prints.

        Parameters
        ----------
        source : str or Path, optional
            The projection file, named in the first line when the run was given no scan.
        written : sequence of str
            Names of the files written, listed last.
        described : bool
            The scan was described (:meth:`ctpipe.io.scans.ScanFiles.describe`) before the run:
            do not repeat it.
        """
        g = self.geometry
        lines = []
        if self.scan is not None and not described:
            lines += self.scan.describe()
        elif self.scan is None:
            lines.append(f"projections{'' if source is None else f' {source}'}: {len(self.angles_deg)} views of "
                         f"{g.detector_rows} x {g.detector_cols} px, SOD {g.source_to_object_mm:g} mm, "
                         f"SDD {g.source_to_detector_mm:g} mm")
        if self.pipeline is not None:
            stages = self.pipeline.to_dict()
            lines.append("pipeline: " + " -> ".join(stages[k]["name"] for k in ("detector", "matcher", "estimator",
                                                                                  "refiner"))
                         + (f" (keypoints found on views binned {self.detect_binning} x {self.detect_binning})"
                            if self.detect_binning > 1 else ""))
        failed = sum(s != "ok" for s in self.pair_status)
        # The ball calibration follows every ball from the nominal angles: the pairs' guesses on look-alike discs
        # (a median of one inlier) are not what its angles rest on, and a user reading them should know.
        unused = ("; the ball calibration does not use them: it follows every ball from the nominal angles"
                  if isinstance(self.refiner_info.get("balls"), dict) else "")
        lines.append(f"pairs: {len(self.pairs) - failed}/{len(self.pairs)} estimated, median "
                     f"{np.median(self.n_inliers):.0f} inliers of {np.median(self.n_matches):.0f} matches; "
                     f"{int(np.isfinite(self.angles_deg).sum())}/{len(self.angles_deg)} views have an angle{unused}")
        choice = self.refiner_choice
        if choice.matched:
            kept = "matched" if choice.chosen is None else choice.chosen
            evidence = choice.held_out_z.get("matched")
            lines.append(f"refiner: projection matching from the {choice.matched_from} angles, kept the {kept} ones"
                         + ("" if evidence is None else f" (views held out of the reference: the matched angles "
                            f"z {evidence:+.1f} against the nominal ones)"))
        balls = self.refiner_info.get("balls")
        if isinstance(balls, dict):
            shells, left_out = balls.get("shell_observations", 0), balls.get("left_out", 0)
            notes = ([f"{shells} of the {balls['observations']} discs fitted placed on a hollow or coated ball's "
                      f"inner edge, which no clip or neighbour beyond the rim moves"] if shells else []) + \
                ([f"{left_out} disc(s) left out as gross errors, pixels off their ball where the rest of their view "
                  f"and ball fit (balls merged into one disc)"] if left_out else [])
            hidden = balls.get("hidden_discs_placed", 0)
            if hidden:
                notes.append(f"{hidden} disc(s) of balls hidden within others' placed on their rims where the balls "
                             f"put them")
            shifts, shift_p = balls.get("view_shifts_px"), balls.get("shift_p_value")
            if shifts is not None:
                shifts = np.asarray(shifts, dtype=np.float64)
                share = balls.get("drift_spot_share")   # by the parallax across the balls' depths
                moved = ("a source spot or detector that drifts" if share is None else
                         "a detector that drifts: no source spot's parallax" if share <= 0.05 else
                         "a source spot that drifts, by its parallax" if share >= 0.95 else
                         f"a drift {share:.0%} the source spot's and {1 - share:.0%} the detector's, by the parallax")
                notes.append(f"each view's projection shifted by up to {np.abs(shifts[:, 0]).max():.2f} px across and "
                             f"{np.abs(shifts[:, 1]).max():.2f} px along the axis, fitted with its angle ({moved}"
                             f"{'' if shift_p is None else f'; F test p {shift_p:.2g}'})")
            placed = f" ({'; '.join(notes)})" if notes else ""
            lines.append(f"refiner: ball calibration, {balls['balls']} balls followed through the views{placed}, "
                         f"{'the corrected angles kept' if balls['kept'] else 'the nominal angles returned'}: "
                         f"{balls['reason']}")
            if not balls["kept"] and balls.get("detector_kept"):
                lines.append(f"detector: {balls['detector_reason']}")
            if balls.get("lag_shown"):
                lines.append(_lag_warning(balls))
        gate = self.gate
        if gate is not None:
            lines.append(_gate_line(gate, measured=self.before_after is not None and bool(self.before_after.scores)))
        if self.before_after is not None:
            # A ball calibration is judged by its balls (its line above); the slices still show it. The conjugate
            # rays of a ball phantom say little: on simulated coated-ball scans of 16 and 17 views, corrected to
            # 0.003 deg, they read 5300 % and 12565 % "more" disagreement (docs/calibration-phantoms.md).
            verdict = self.before_after.verdict()
            if isinstance(balls, dict) and not self.before_after.unchanged:
                # The balls' measure first: it is the one that decides, and the one issue 34 asks to see.
                verdict = (f"before/after: the balls' reprojection RMS {balls['nominal_rms_px']:.3f} px with the "
                           f"nominal angles, {balls['rms_px']:.3f} px with the corrected ones (a ball phantom's "
                           f"measure, the one that decides); beside it (not a ball phantom's measure), "
                           + verdict.removeprefix("before/after: "))
            lines.append(verdict)
        estimated = self.estimated_deg
        for reference, label in ((self.nominal_angles_deg, "nominal angles"),
                                 (self.recorded_angles_deg, "scanner's angle log")):
            table = None if reference is None else difference_table(estimated, reference)
            if table and table.get("views"):
                lines.append(f"estimated minus {label}: RMS {table['rms_deg']:.4f} deg, max {table['max_deg']:.4f} deg "
                             f"(view {table['worst_view']}), median offset removed")
        closing = self.closing_view
        if closing is not None:
            logged = "" if closing.recorded_turn_deg is None else f", logged {closing.recorded_turn_deg:.4f}"
            lines.append(f"closing view {closing.view}: {closing.estimated_turn_deg:.4f} deg after view 0, measured "
                         f"from the images (nominal {closing.nominal_turn_deg:.4f}{logged})")
        if self.angle_errors is not None:
            table = self.angle_errors.views
            lines.append(f"against the true angles: RMS {table['rms_deg']:.4f} deg, MAE {table['mae_deg']:.4f} deg, "
                         f"max {table['max_deg']:.4f} deg ({table['estimated']}/{table['total']} views)")
        turn = self.turn_check
        if turn is not None and turn.reversed:
            lines.append(f"warning: the images turn the other way from the nominal angles ({100 * (1 - turn.agree_fraction):.0f} % "
                         f"of {turn.pairs} pairs, sign test p {turn.sign_p_value:.1g}; median pair angle "
                         f"{turn.median_pair_deg:+.3f} deg against a nominal step of "
                         f"{turn.median_nominal_step_deg:+.3f} deg): the angle sign read from this scan's files is "
                         "probably reversed for this scanner (docs/real-scans.md)")
        refined = self.refined_geometry
        if refined is not None and any(k in refined.refined for k in ("u0_px", "tilt_deg")):
            lines.append(f"geometry: u0 {refined.geometry.u0_px:.3f} px (was {g.u0_px:.3f}), v0 "
                         f"{refined.geometry.v0_px:.3f} px, detector tilt {refined.tilt_deg:.4f} deg"
                         + _detector_se_text(balls) + _ball_scanner_text(balls, g, refined))
        lines.append(f"estimated angles: {estimated[0]:.4f} .. {estimated[-1]:.4f} deg "
                     f"(in the nominal angles' frame{'' if self.nominal_angles_deg is not None else ': relative to view 0'})")
        if written:
            lines.append("written: " + ", ".join(written))
        return "\n".join(lines)


def _lag_warning(balls) -> str:
    """The summary's warning where the ball calibration's discs are pulled back along their way, as a detector's lag
    pulls them (:func:`ctpipe.solve.balls._lag_test`)."""
    pulls = np.asarray([np.nan if p is None else p for p in balls.get("lag_pull_px") or []], dtype=np.float64)
    worst = int(np.nanargmax(np.abs(pulls))) if np.any(np.isfinite(pulls)) else None
    most = "" if worst is None else f"up to {pulls[worst]:+.2f} px, ball {worst}; "
    return (f"warning: the balls' discs are pulled towards where they were the view before ({most}F test p "
            f"{balls['lag_p_value']:.2g}): the detector's lag (afterglow) carries each view into "
            f"the next, and moves most the rims a clipped background cuts, so the angles may be off by a hundredth of "
            f"a degree; discard a frame or two after each move, or let the detector settle, and scan again "
            f"(docs/calibration-phantoms.md, Limits)")


def _ball_scanner_text(balls, geometry: Geometry, refined: RefinedGeometry) -> str:
    """The ball calibration's axis offset and source-to-detector distance, as the summary's geometry line ends, and
    which of them the refined geometry took (:meth:`ctpipe.solve.balls.BallCalibration.pose_beyond_noise`), or ""."""
    if not isinstance(balls, dict) or balls.get("source_to_detector_mm") is None:
        return ""
    se, p = balls.get("detector_se") or [], balls.get("pose_p_value")
    tested = "" if p is None else f" (F test p {p:.2g})"
    if len(se) < 5 or se[3] is None or se[4] is None:
        return ("" if p is None else f"; the axis on the source's perpendicular and the detector at the scan's "
                f"distance: the balls show them no different beyond noise{tested}")
    offset, sdd = float(balls["axis_offset_mm"]), float(balls["source_to_detector_mm"])
    return (f"; the axis {offset:.3f} mm off the source's perpendicular to the detector (a detector yaw of "
            f"{math.degrees(math.asin(max(-1.0, min(1.0, offset / geometry.source_to_object_mm)))):.3f} deg), source "
            f"to detector {sdd:.2f} mm (was {geometry.source_to_detector_mm:.2f}; magnification "
            f"{sdd / geometry.source_to_object_mm:.4f}), standard errors {se[3]:.3f} mm and {se[4]:.2f} mm{tested}; "
            + _taken_text(refined))


def _taken_text(refined: RefinedGeometry) -> str:
    """Which of the axis offset and the distance the refined geometry took, in words."""
    taken = [name for key, name in (("axis_offset_mm", "the axis offset"), ("source_to_detector_mm", "the distance"))
             if key in refined.refined]
    if not taken:
        return "both within three standard errors of the scan's own, which the geometry keeps"
    left = "" if len(taken) == 2 else (", the other within three standard errors of the scan's own, which it keeps")
    return (f"{' and '.join(taken)} in the geometry written (geometry_vectors.csv{left}; ctpipe's FDK takes the "
            f"axis on the perpendicular)")


def _detector_se_text(balls) -> str:
    """The ball calibration's standard errors of u0, v0 and the tilt, as the summary's geometry line ends, or ""."""
    se = balls.get("detector_se") if isinstance(balls, dict) else None
    if not se or len(se) < 3 or any(e is None for e in se[:3]):
        return ""
    return f" (standard errors {se[0]:.3f} px, {se[1]:.3f} px, {se[2]:.4f} deg)"


def _gate_line(gate: GateDecision, *, measured: bool = False) -> str:
    """The summary's one line on whether the correction helped, by the projections alone.

    With ``measured`` (a before/after line follows with the same measure) it says only what was returned.
    """
    if not gate.decided:
        return (f"gate: {gate.reason} (the refiner's angles are in angles.csv as refiner_deg; gate: off returns "
                "them)")
    if gate.chosen == "nominal":
        return (f"gate: returned the NOMINAL angles: {gate.reason} (the refiner's angles are in angles.csv as "
                f"refiner_deg; gate: off returns them)")
    what = ("the corrected angles" if gate.chosen == "estimate" else
            f"the nominal angles corrected by the {gate.chosen} part{'s' if len(gate.bands) > 1 else ''} of the correction")
    if measured:
        return f"gate: returned {what}"
    if gate.held_out_z is not None and gate.held_out_z < -gate.z:
        return f"gate: returned {what}: {gate.reason}"
    return (f"gate: the correction helped: {what} agree {gate.improvement:.0%} better than the nominal angles with the "
            f"projections' conjugate rays (z {gate.scores['returned'].z:+.1f})")


def difference_table(estimated_deg: np.ndarray, reference_deg: np.ndarray) -> dict[str, Any]:
    """Estimated minus reference angles after their median offset: how many views, RMS, max and where.

    Returns
    -------
    dict
        ``{"views": 0}`` when no view has both; else ``views``, ``rms_deg``, ``max_deg`` and
        ``worst_view``.
    """
    difference = estimated_deg - reference_deg
    finite = np.isfinite(difference)
    if not finite.any():
        return {"views": 0}
    difference = difference - float(np.median(difference[finite]))
    worst = int(np.nanargmax(np.abs(difference)))
    return {"views": int(finite.sum()), "rms_deg": float(np.sqrt(np.mean(difference[finite] ** 2))),
            "max_deg": float(abs(difference[worst])), "worst_view": worst}


@dataclass(frozen=True)
class Pipeline:
    """Detector -> matcher -> estimator -> refiner over a whole scan.

    Build one from stage objects, or with :meth:`from_config` from a YAML file or mapping
    (which keeps the configuration in ``config``, for the report of each run).
    """

    detector: Detector
    matcher: Matcher
    estimator: Estimator
    refiner: Refiner
    baselines: tuple[int, ...] = (1,)
    seed: int | None = 0
    loop_closure: bool = True
    static_background: str = "auto"
    gate: str = "auto"
    detect_max_px: int | None = 1024
    device: str = "auto"
    config: PipelineConfig | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        for name, kind in (("detector", Detector), ("matcher", Matcher), ("estimator", Estimator), ("refiner", Refiner)):
            stage = getattr(self, name)
            if not isinstance(stage, kind):
                raise InputError(f"{name}: must be a ctpipe {kind.__name__} stage (e.g. from the registry or "
                                 f"Pipeline.from_config), got {type(stage).__name__} {short_repr(stage)}")
        if self.static_background not in ("auto", "on", "off"):
            raise InputError(f"static_background: must be one of 'auto', 'on', 'off', got {self.static_background!r}")
        if self.detect_max_px is not None and not (isinstance(self.detect_max_px, (int, np.integer))
                                                   and not isinstance(self.detect_max_px, bool)
                                                   and 64 <= self.detect_max_px <= 65536):
            raise InputError(f"detect_max_px: must be an integer from 64 to 65536 (pixels a side) or None (the full "
                             f"views), got {self.detect_max_px!r}")
        if self.device not in gpu.DEVICES:
            raise InputError(f"device: must be one of {', '.join(gpu.DEVICES)} (where the refiner's projector and "
                             f"FDK run), got {self.device!r}")
        if self.gate not in ("auto", "off"):
            raise InputError(f"gate: must be 'auto' (return corrected angles only where the projections show them "
                             f"better than the nominal ones) or 'off', got {self.gate!r}")
        # A stage built in Python may name a nested stage (ProjectionMatchingRefiner(start=
        # "bundle-adjustment")): build it through the registry here, as from_config does.
        registry = None
        for name in ("detector", "matcher", "estimator", "refiner"):
            stage = getattr(self, name)
            if any(spec.stage is not None and isinstance(getattr(stage, spec.name), StageSpec)
                   for spec in stage.parameters()):
                registry = registry or get_registry()
                object.__setattr__(self, name, build_stage(stage, registry))

    @classmethod
    def from_config(cls, config: PipelineConfig | Mapping | str | Path | None = None, *,
                    registry: StageRegistry | None = None) -> "Pipeline":
        """A pipeline from a validated config, a mapping, or a YAML file path (None: defaults)."""
        registry = registry or get_registry()
        if isinstance(config, (str, Path)):
            config = parse_pipeline(load_yaml(config), registry, path="pipeline")
        elif not isinstance(config, PipelineConfig):
            config = parse_pipeline(config, registry)
        return cls(*(build_stage(getattr(config, kind), registry) for kind in ("detector", "matcher", "estimator", "refiner")),
                   baselines=config.baselines, seed=config.seed, loop_closure=config.loop_closure,
                   static_background=config.static_background, gate=config.gate,
                   detect_max_px=config.detect_max_px, device=config.device, config=config)

    def run(self, projections: np.ndarray | ViewStack | ScanFiles, geometry: Geometry | None = None, *,
            nominal_angles_deg=None, pairs: np.ndarray | None = None, progress: Callable[[int], None] | None = None,
            executor: Executor | None = None) -> ScanResult:
        """Estimate the angle of every view of a scan: :meth:`observe`, then :meth:`refine`.

        Parameters
        ----------
        projections : ndarray of shape (V, rows, cols), ViewStack, or ScanFiles
            uint8 or float images (float: e.g. ``-log`` line integrals); no NaN. A
            :class:`ctpipe.io.scans.ViewStack` (what :func:`ctpipe.io.open_scan` gives) is read
            one view at a time and never held whole. A whole scan opened with
            :func:`ctpipe.io.open_scan` gives its projections, geometry and nominal angles, and
            the result's report also holds its format, notes, logged angles and closing view.
        geometry : Geometry or mapping
            Must match the projections' (rows, cols). A mapping of the :class:`Geometry`
            fields is validated as a geometry YAML is (:func:`ctpipe.config.parse_geometry`).
            Not with a scan, which has its own.
        nominal_angles_deg : array_like of shape (V,), optional
            The commanded angles. They tell a full turn (whose seam is then paired too, see
            :func:`ctpipe.solve.view_pairs`) and give whole-scan refiners their start.
        pairs : ndarray of shape (P, 2), optional
            View pairs to estimate; default ``(i, i + k)`` for the configured baselines.
        progress : callable, optional
            ``progress(n)`` as ``n`` more views have their features.
        executor : ctpipe.execution.Executor, optional
            Where the tasks run: detection one task per view, matching and estimation one task
            per chunk of pairs, and the refiner as one task. Default a
            :class:`~ctpipe.execution.ThreadExecutor` over this process's cores; a
            :class:`~ctpipe.execution.DaskExecutor` runs them on a cluster, whose workers
            read a scan opened from disk themselves. Every pair has its own seed, so the
            angles are the same bit for bit wherever they run.

        Returns
        -------
        ScanResult
            The angles; the geometry with what the refiner estimated of it
            (:attr:`~ScanResult.refined_geometry`); what the refiner chose; with nominal angles,
            whether the images turn their way (:attr:`~ScanResult.turn_check`); with a scan
            that has one, the turn measured to its closing view; and the report
            (:meth:`~ScanResult.report`, :meth:`~ScanResult.summary`).

        Raises
        ------
        InputError
            Wrong shapes/dtypes, NaN pixels, pairs out of range.
        EstimationError
            When not a single pair could be estimated.
        """
        scan = None
        if isinstance(projections, ScanFiles):
            scan = projections
            for name, value in (("geometry", geometry), ("nominal_angles_deg", nominal_angles_deg)):
                if value is not None:
                    raise InputError(f"{name}: a scan ({scan.format} scan {scan.path}) brings its own; give the "
                                     f"scan alone, or its projections with the {name} to use")
            projections, geometry, nominal_angles_deg = scan.projections, scan.geometry, scan.nominal_angles_deg
        elif geometry is None:
            raise InputError("geometry: missing; projections need the geometry they were taken with (or give a scan "
                             "opened with ctpipe.io.open_scan, which has its own)")
        with _executor(executor) as run_on:
            observations, placed = self._observe(projections, geometry, nominal_angles_deg, pairs, progress, run_on)
            return self._refine(observations, run_on, placed, scan)

    def observe(self, projections: np.ndarray, geometry: Geometry, *, nominal_angles_deg=None,
                pairs: np.ndarray | None = None, progress: Callable[[int], None] | None = None,
                executor: Executor | None = None) -> ScanObservations:
        """Detect, match and estimate every pair: what a refiner works from (arguments as :meth:`run`).

        Several refiners can then be compared on the same observations with :meth:`refine`. The
        features keep their descriptors only where this pipeline's refiner reads them
        (:attr:`~ctpipe.stages.Refiner.reads_descriptors`); a refiner that does refuses
        observations without them.
        """
        return self._observe(projections, geometry, nominal_angles_deg, pairs, progress, executor)[0]

    def _observe(self, projections, geometry, nominal_angles_deg, pairs, progress,
                 executor) -> tuple[ScanObservations, "_Placed"]:
        """:meth:`observe`, and where its projections and features are on the executor (for the refiner's task)."""
        geometry = _check_geometry(geometry)
        projections = _check_projections(projections, geometry)
        n_views = len(projections)
        nominal = None if nominal_angles_deg is None else _check_nominal(nominal_angles_deg, n_views)
        if pairs is None:
            pairs = view_pairs(n_views, self.baselines, nominal, loop_closure=self.loop_closure)
        else:
            pairs = _check_pairs(pairs, n_views)
        if len(pairs) == 0:
            raise InputError(f"no view pairs: {n_views} views with baselines {list(self.baselines)}")
        with _executor(executor) as run_on:
            timings = {}
            start = time.perf_counter()
            # A scan from disk travels as its path: each worker reads the views it detects on.
            source = run_on.scatter(_shippable(projections))
            views = self._background_views(projections, nominal)
            background = None if views is None else run_on.submit(_median_background, source, views,
                                                                   name="background")
            factor = self.detect_binning(geometry.shape)
            done = (_detected_on_processes(self.detector, run_on, projections, source, background, factor, progress)
                    if _detect_on_processes(self.detector, run_on, geometry.shape, factor, n_views) else {})
            # The views not detected on processes (all of them, but where a detector holds the GIL) as the executor's
            # tasks: on a cluster each view's features stay on its worker, a handle each.
            handles = {index: run_on.submit(_detect_view, self.detector, source, background, index, factor,
                                            name="detect") for index in range(n_views) if index not in done}
            done.update(zip(handles, run_on.gather(list(handles.values()), progress=progress)))
            detected = [handles.get(index, done[index]) for index in range(n_views)]
            features = tuple(done[index] for index in range(n_views))
            timings["detect"] = time.perf_counter() - start

            # Chunks of pairs, a few per worker; each task gets the features of its own views only.
            chunks = np.array_split(np.arange(len(pairs)), min(len(pairs), 4 * run_on.workers))
            start = time.perf_counter()
            tasks = []
            with one_blas_thread_per_task(run_on):
                for chunk in chunks:
                    used, local = np.unique(pairs[chunk], return_inverse=True)
                    tasks.append(run_on.submit(_match_pairs, self.matcher, geometry, [detected[v] for v in used],
                                               local.reshape(-1, 2), name="match"))
                matched = [m for chunk in run_on.gather(tasks) for m in chunk]
            matches = tuple(m for m, _, _ in matched)
            points_a = tuple(q_a for _, q_a, _ in matched)
            points_b = tuple(q_b for _, _, q_b in matched)
            timings["match"] = time.perf_counter() - start
            if not self.refiner.reads_descriptors:
                # Nothing reads the descriptors again (286 MB of SIFT's at 2,000 views of 2,048^2,
                # measured): keep the keypoints, where the tasks run too.
                detected = [run_on.submit(Features.without_descriptors, handle, name="detect") for handle in detected]
                features = tuple(run_on.gather(detected))

            start = time.perf_counter()
            # Each chunk's points are where its matching task left them: nothing goes back out.
            seeds = np.random.SeedSequence(self.seed).spawn(len(pairs))
            tasks = [run_on.submit(_estimate_pairs, self.estimator, matched_chunk, [seeds[k] for k in chunk],
                                   name="estimate") for matched_chunk, chunk in zip(tasks, chunks)]
            estimates = tuple(e for chunk in run_on.gather(tasks) for e in chunk)
            timings["estimate"] = time.perf_counter() - start
        release_free_memory()   # what the pair stages' threads freed, before the refiner allocates
        observations = ScanObservations(geometry=geometry, n_views=n_views, features=features, pairs=pairs,
                                        matches=matches, points_a=points_a, points_b=points_b, estimates=estimates,
                                        nominal_angles_deg=nominal, projections=projections, timings_s=timings,
                                        static_background_removed=views is not None, detect_binning=factor)
        return observations, _Placed(source, detected)

    def refine(self, observations: ScanObservations, *, executor: Executor | None = None) -> ScanResult:
        """Per-view angles from :meth:`observe`'s observations with this pipeline's refiner.

        With an ``executor`` the refiner runs as one of its tasks (on a cluster: on a worker,
        which reads the projections it needs itself); without, here.
        """
        return self._refine(observations, executor, None)

    def _refine(self, observations: ScanObservations, executor: Executor | None, placed: "_Placed | None",
                scan: ScanFiles | None = None) -> ScanResult:
        timings = dict(observations.timings_s)
        if self.refiner.reads_descriptors and not all(f.has_descriptors for f in observations.features):
            raise InputError(f"{type(self.refiner).__name__} reads the features' descriptors, and these observations "
                             f"were made without them (a pipeline whose refiner does not read them drops them once "
                             f"its pairs are matched); observe with this pipeline")
        start = time.perf_counter()
        # The refiner's generator is the last of len(pairs) + 1 children, as it always was.
        seed = np.random.SeedSequence(self.seed).spawn(len(observations.pairs) + 1)[-1]
        gate = self.gate == "auto" and observations.nominal_angles_deg is not None
        if executor is None:
            solution, decision = _refine_task(self.refiner, observations, None, None, seed, gate, self.device)
        else:
            # The features and projections already where the tasks run are passed as handles, not sent again.
            if placed is not None:
                source, features = placed
                observations_out = dataclasses.replace(observations, projections=None, features=())
            else:
                projections = observations.projections
                source = None if projections is None else executor.scatter(_shippable(projections))
                features, observations_out = None, dataclasses.replace(observations, projections=None)
            task = executor.submit(_refine_task, self.refiner, observations_out, source, features, seed, gate,
                                   self.device, name="refine")
            (solution, decision), = executor.gather([task])
        timings["refine"] = time.perf_counter() - start

        refined, matches, features = solution.pair_estimates, observations.matches, observations.features
        if not any(refined):
            counts = ", ".join(f"view {v}: {len(f)}" for v, f in enumerate(features[:6]))
            raise EstimationError(
                f"no view pair could be estimated (first pair: {refined[0]}); keypoints per view: {counts}"
                f"{', ...' if observations.n_views > 6 else ''}")
        pair_angles_deg = np.array([np.rad2deg(e.angle_rad) if e else np.nan for e in refined])
        angles_deg = np.rad2deg(solution.angles_rad)
        if decision is not None and decision.chosen != "estimate":
            angles_deg = decision.angles_deg - decision.angles_deg[0]
        angle_se_deg = _angle_se_deg(solution.angle_se_deg, decision, observations.nominal_angles_deg)
        info = dict(solution.info)
        nominal = observations.nominal_angles_deg
        closing = None
        if scan is not None and scan.closing_view:
            # The closing view is view 0's pose one turn on: how far it turned, measured from the images.
            recorded = scan.recorded_angles_deg
            closing = ClosingView(view=scan.n_views - 1, nominal_turn_deg=float(nominal[-1] - nominal[0]),
                                  estimated_turn_deg=float(angles_deg[-1] - angles_deg[0]),
                                  recorded_turn_deg=None if recorded is None else float(recorded[-1] - recorded[0]))
        return ScanResult(
            pairs=observations.pairs,
            pair_angles_deg=pair_angles_deg,
            pair_inlier_masks=tuple(e.inlier_mask if e else np.zeros(len(m), bool) for e, m in zip(refined, matches)),
            n_matches=np.array([len(m) for m in matches], dtype=np.int64),
            n_inliers=np.array([e.n_inliers if e else 0 for e in refined], dtype=np.int64),
            residuals=np.array([e.residual if e else np.nan for e in refined]),
            pair_status=tuple("ok" if e else str(e) for e in refined),
            angles_deg=angles_deg,
            n_keypoints=np.array([len(f) for f in features], dtype=np.int64),
            timings_s=timings,
            refiner_info=info,
            static_background_removed=observations.static_background_removed,
            detect_binning=observations.detect_binning,
            geometry=observations.geometry,
            refined_geometry=RefinedGeometry.from_solution(observations.geometry, solution),
            refiner_choice=RefinerChoice.from_info(info),
            nominal_angles_deg=nominal,
            turn_check=None if nominal is None else TurnCheck.compute(observations.pairs, pair_angles_deg, nominal),
            closing_view=closing,
            angle_se_deg=angle_se_deg,
            scan=scan,
            pipeline=self.config,
            gate=decision,
        )

    def detect_binning(self, shape: tuple[int, int]) -> int:
        """The binning of the views detection works on: 1 (the full views) unless the detector's
        keypoints hold at a working resolution (``Detector.working_resolution``) and the larger
        side of ``shape`` (rows, cols) exceeds ``detect_max_px``; then the least factor that brings
        it within. A 2,048^2 flat panel is detected at 1,024^2: about 4x faster for SIFT, and the
        refiner (projection matching) works at 256^2 at most whatever the detection did.
        """
        if self.detect_max_px is None or not self.detector.working_resolution:
            return 1
        return max(1, math.ceil(max(shape) / self.detect_max_px))

    def _background_views(self, projections, nominal: np.ndarray | None) -> np.ndarray | None:
        """Which views make the static background to remove before detection, or None (see ``static_background``).

        The background is the per-pixel median over (up to 90, and at most ``_BACKGROUND_BYTES``
        of) evenly spread views, read one at a time when the projections are a ViewStack: what
        every view shares, i.e. the rotationally symmetric part of the object (container, matrix,
        detector pattern). Features sitting on that static profile are localised a few percent
        short of their motion, which biases every pair angle low (docs/wholescan.md). ``auto``
        removes it when the nominal angles show the views spread over at least 180 deg, so that
        features move across the image and the median is theirs in no view.
        """
        if self.static_background == "off":
            return None
        if self.static_background == "auto":
            if nominal is None or len(nominal) < 16:
                return None
            step = float(np.median(np.abs(np.diff(nominal))))
            if float(np.ptp(nominal)) + step < 180.0:
                return None
        # Up to 90 views, fewer on a detector so large that 90 would take more than _BACKGROUND_BYTES.
        rows, cols = projections.shape[1:]
        count = int(min(len(projections), 90, max(16, _BACKGROUND_BYTES // (rows * cols * 4))))
        return np.unique(np.linspace(0, len(projections) - 1, count).round().astype(int))


# Tasks: module-level functions, so that a worker process finds them by name.

def _shippable(projections):
    """What a task gets for the projections: a scan from disk by reference, anything else as it is."""
    reference = projections.reference() if isinstance(projections, ViewStack) else None
    return projections if reference is None else reference


def _views(source):
    return source.open() if isinstance(source, StackReference) else source


def _median_background(source, views: np.ndarray) -> np.ndarray:
    return np.median(np.asarray(_views(source)[views], dtype=np.float32), axis=0)


def _detect_view(detector: Detector, source, background: np.ndarray | None, index: int, factor: int = 1) -> Features:
    image = _views(source)[index]
    image = image if background is None else image - background
    if factor == 1:
        return detector.detect(image)
    # Detect on the view binned factor x factor (the block means), and put the keypoints back in
    # the view's own pixels: a binned pixel's centre k is the view's (k + 0.5) factor - 0.5.
    rows, cols = (n // factor for n in image.shape)
    binned = np.asarray(image[:rows * factor, :cols * factor], dtype=np.float32).reshape(
        rows, factor, cols, factor).mean(axis=(1, 3))
    found = detector.detect(binned)
    return dataclasses.replace(found, xy=(found.xy + np.float32(0.5)) * np.float32(factor) - np.float32(0.5),
                               size=found.size * np.float32(factor))


#: Pixels of a view, as detected, from which a detector that holds the GIL runs on processes
#: (:attr:`ctpipe.stages.Detector.holds_gil`): the ball finder takes about 2 s on a 2000^2 view
#: (4 megapixels) of a ball scan, starting two processes 1.6 s (2 cores).
_PROCESS_MIN_PIXELS = 1 << 20


def _detect_on_processes(detector: Detector, run_on: Executor, shape: tuple[int, int], factor: int,
                         n_views: int) -> bool:
    """Whether to detect on worker processes rather than the executor's threads: a detector that holds the GIL, on
    threads of this process (a cluster's workers are processes already), several views of a megapixel or more, where
    processes can be started (:attr:`ctpipe.execution.ProcessPool.supported`)."""
    rows, cols = shape
    return (detector.holds_gil and ProcessPool.supported and isinstance(run_on, ThreadExecutor) and run_on.workers > 1
            and n_views > 1 and (rows // factor) * (cols // factor) >= _PROCESS_MIN_PIXELS)


class _ViewTasks(Sequence):
    """:func:`_detect_view`'s arguments per view, made as a worker process asks for them: a scan from disk goes as its
    reference (each process reads its own view), any other stack as the one view."""

    def __init__(self, detector, projections, source, background, factor):
        self.detector, self.projections, self.source = detector, projections, source
        self.background, self.factor = background, factor

    def __len__(self) -> int:
        return len(self.projections)

    def __getitem__(self, index: int) -> tuple:
        if isinstance(self.source, StackReference):
            return self.detector, self.source, self.background, index, self.factor
        return self.detector, np.asarray(self.projections[index])[None], self.background, 0, self.factor


def _detected_on_processes(detector: Detector, run_on: ThreadExecutor, projections, source, background, factor: int,
                           progress) -> dict[int, Features]:
    """``{view: features}`` detected on a :class:`~ctpipe.execution.ProcessPool` of ``run_on.workers`` processes:
    every view, or where the processes cannot run (not started, a task they cannot take, one lost mid-task) those
    done, with a warning that says why (the caller detects the views left on ``run_on``'s threads)."""
    if background is not None:
        background, = run_on.gather([background])
    tasks = _ViewTasks(detector, projections, source, background, factor)
    try:
        with ProcessPool(run_on.workers) as pool:
            return dict(enumerate(pool.map(_detect_view, tasks, progress=progress)))
    except WorkerLost as lost:
        warnings.warn(f"{lost}; detecting the views left on threads", RuntimeWarning, stacklevel=3)
        return dict(lost.done)


def _match_pairs(matcher: Matcher, geometry: Geometry, features: list[Features], pairs: np.ndarray) -> list:
    """(matches, first view's points, second view's points) of each pair; ``pairs`` index ``features``."""
    out = []
    for i, j in pairs:
        m = matcher.match(features[i], features[j])
        out.append((m, geometry.pixels_to_normalised(features[i].xy[m.index_ab[:, 0]]),
                    geometry.pixels_to_normalised(features[j].xy[m.index_ab[:, 1]])))
    return out


def _estimate_pairs(estimator: Estimator, matched: list, seeds: list) -> list:
    """Estimates of ``_match_pairs``'s output, pair ``k`` with its own generator ``seeds[k]``."""
    return [estimator.estimate(q_a, q_b, rng=np.random.default_rng(s)) for (_, q_a, q_b), s in zip(matched, seeds)]


def _refine_task(refiner: Refiner, observations: ScanObservations, source, features: list | None,
                 seed, gate: bool = False, device: str = "auto") -> tuple[ScanSolution, GateDecision | None]:
    """The refiner's solution and, with ``gate``, the gate's decision on it (where the projections are).

    ``device`` other than ``"auto"`` runs the heavy kernels there (:mod:`ctpipe.gpu`); ``"auto"``
    leaves what the process asked for (``--device``, ``CTPIPE_DEVICE``).
    """
    changes = {} if features is None else {"features": tuple(features)}
    if source is not None:
        changes["projections"] = _views(source)
    observations = dataclasses.replace(observations, **changes)
    with gpu.use(device) if device != "auto" else contextlib.nullcontext():
        solution = refiner.refine(observations, rng=np.random.default_rng(seed))
        return solution, (_gate(observations, solution) if gate else None)


def _angle_se_deg(refiner_se_deg: np.ndarray | None, gate: GateDecision | None,
                  nominal_deg: np.ndarray | None = None) -> np.ndarray | None:
    """Standard error of every returned angle: the refiner's own, and what the gate left out.

    Where the gate returned the nominal angle for a band of the correction, the returned angle is
    off by that band if the refiner was right, so the band's size adds to the error in
    quadrature: the slow bands view by view (they are smooth), the fast band by its RMS over
    the views (it says how large the jitter left in may be, not at which view). The refiner's
    own standard error (None: it gives none) covers the rest.
    """
    if refiner_se_deg is None:
        return None
    se = np.asarray(refiner_se_deg, dtype=np.float64)
    if gate is None or gate.chosen == "estimate" or nominal_deg is None:
        return se
    left_out = wrap_deg(gate.estimate_deg - gate.angles_deg)
    known = np.isfinite(left_out)
    if not known.any():
        return se
    # A view the refiner gave no angle left nothing out.
    left_out = np.where(known, wrap_deg(left_out - np.median(left_out[known])), 0.0)
    bands = split_bands(left_out, nominal_deg, gate.harmonics)
    fast = float(np.sqrt(np.mean(bands["fast"] ** 2)))
    return np.sqrt(se**2 + fast**2 + (bands["slow-odd"] + bands["slow-even"]) ** 2)


def _gate(observations: ScanObservations, solution: ScanSolution) -> GateDecision:
    """The gate on a solution: the midplane rows of the projections (as line integrals) against its angles."""
    estimate = np.rad2deg(solution.angles_rad)
    projections = observations.projections
    if projections is None:
        return cannot_tell(observations.nominal_angles_deg, estimate, "no projections to check the angles against")
    try:
        rows, slopes = midplane_rows(projections, observations.geometry, slopes=True)
    except InputError as error:
        return cannot_tell(observations.nominal_angles_deg, estimate, str(error))
    # Intensities (a bright field around a dark object) become line integrals, as projection matching takes them.
    line_integrals, converted = as_line_integrals(rows[:, None, :])
    if converted:   # d(-log I)/dv = -(dI/dv) / I
        slopes = -slopes / np.maximum(rows, 1e-30)
    chosen = solution.info.get("chosen", "")
    held_out = solution.info.get("held_out", {}).get(chosen, {})
    band = solution.info.get("held_out_slow_even", {}) if chosen == "matched" else {}
    return gate_angles(line_integrals[:, 0].astype(np.float64), observations.geometry, observations.nominal_angles_deg,
                       estimate, slopes=slopes, held_out_z=held_out.get("z"),
                       held_out_slow_even_z=band.get("band", {}).get("z"),
                       held_out_without_slow_even_z=band.get("without", {}).get("z"))


class _Placed(NamedTuple):
    """Where a run's inputs already are on its executor: the projections' handle, one handle per view's features."""

    source: Any
    features: list


class _executor:
    """The caller's executor as it is, or a thread pool for the block."""

    def __init__(self, executor: Executor | None) -> None:
        if executor is not None and not isinstance(executor, Executor):
            raise InputError(f"executor: must be a ctpipe.execution.Executor (ThreadExecutor or DaskExecutor), "
                             f"got {type(executor).__name__}")
        self.given, self.own = executor, None

    def __enter__(self) -> Executor:
        if self.given is not None:
            return self.given
        self.own = ThreadExecutor()
        return self.own

    def __exit__(self, *exc) -> None:
        if self.own is not None:
            self.own.__exit__(*exc)  # interrupted or failed: it does not wait for running tasks


def _check_geometry(geometry) -> Geometry:
    if isinstance(geometry, Geometry):
        return geometry
    if isinstance(geometry, Mapping):
        return parse_geometry(geometry)
    raise InputError(f"geometry: must be a ctpipe.geometry.Geometry (or a mapping of its fields), "
                     f"got {type(geometry).__name__} {short_repr(geometry)}")


def _check_projections(projections, geometry: Geometry) -> np.ndarray | ViewStack:
    if isinstance(projections, ViewStack):
        # Read lazily: each view is checked as it is read.
        if len(projections) < 2:
            raise InputError(f"projections need at least 2 views to estimate an angle, got {len(projections)}")
        if projections.shape[1:] != geometry.shape:
            raise InputError(f"projections have (rows, cols) = {projections.shape[1:]} but the geometry says "
                             f"{geometry.shape} (detector_rows, detector_cols)")
        return projections
    projections = np.asarray(projections)
    if projections.ndim != 3:
        raise InputError(f"projections must be a 3-D array (views, rows, cols), got shape {projections.shape}")
    if len(projections) < 2:
        raise InputError(f"projections need at least 2 views to estimate an angle, got {len(projections)}")
    if projections.shape[1:] != geometry.shape:
        raise InputError(f"projections have (rows, cols) = {projections.shape[1:]} but the geometry says "
                         f"{geometry.shape} (detector_rows, detector_cols)")
    check_image(projections.reshape(-1, projections.shape[-1]), name="projections")
    return projections


def _check_nominal(nominal_angles_deg, n_views: int) -> np.ndarray:
    nominal = np.asarray(nominal_angles_deg)
    if nominal.shape != (n_views,) or not np.issubdtype(nominal.dtype, np.number) or np.iscomplexobj(nominal):
        raise InputError(f"nominal_angles_deg: must be {n_views} real numbers, one per view, got shape "
                         f"{nominal.shape} and dtype {nominal.dtype}")
    nominal = nominal.astype(np.float64)
    if not np.all(np.isfinite(nominal)):
        raise InputError("nominal_angles_deg: must be finite, got NaN or infinite values")
    nominal.flags.writeable = False
    return nominal


def _check_pairs(pairs, n_views: int) -> np.ndarray:
    pairs = np.asarray(pairs)
    if pairs.ndim != 2 or pairs.shape[1] != 2 or not np.issubdtype(pairs.dtype, np.integer):
        raise InputError(f"pairs must be an integer array of shape (P, 2), got {pairs.dtype} {pairs.shape}")
    if pairs.size and (pairs.min() < 0 or pairs.max() >= n_views):
        raise InputError(f"pairs must index views 0..{n_views - 1}, got indices {pairs.min()}..{pairs.max()}")
    if np.any(pairs[:, 0] == pairs[:, 1]):
        raise InputError("pairs must join two different views, got a pair (i, i)")
    return pairs.astype(np.int64)
