"""The projection-matching refiner: feature angles first, then every view against the reconstruction."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ctpipe.data import ScanObservations, ScanSolution
from ctpipe.errors import ConfigError
from ctpipe.hookspecs import hookimpl
from ctpipe.geometry import Geometry
from ctpipe.recon.feldkamp import FILTERS, bin_detector, binned_geometry
from ctpipe.solve.graph import solve_view_graph
from ctpipe.solve.reprojection import (HELD_OUT_Z, consistency_costs, matching_levels, projection_matching,
                                       static_part_applies)
from ctpipe.stages import Refiner, StageSpec, param

__all__ = ["ProjectionMatchingRefiner"]

Filter = Literal[FILTERS]  # type: ignore[valid-type]


def _fill(angles_deg: np.ndarray, nominal_deg: np.ndarray | None) -> tuple[np.ndarray, int]:
    """Views without a start angle take the nominal one (shifted onto the others), else a neighbour's."""
    missing = ~np.isfinite(angles_deg)
    if not missing.any():
        return angles_deg, 0
    if not (~missing).any():
        return (np.zeros_like(angles_deg) if nominal_deg is None else nominal_deg - nominal_deg[0]), int(missing.sum())
    if nominal_deg is not None:
        offset = float(np.median(angles_deg[~missing] - nominal_deg[~missing]))
        return np.where(missing, nominal_deg + offset, angles_deg), int(missing.sum())
    views = np.arange(len(angles_deg))
    return np.interp(views, views[~missing], angles_deg[~missing]), int(missing.sum())


def _binned_views(projections, geometry: Geometry, factor: int) -> tuple[np.ndarray, Geometry, bool]:
    """The projections binned by ``factor``, read and binned one view at a time, and whether that is a copy.

    A :class:`~ctpipe.io.scans.ViewStack` is never held whole: only the binned copy is, which at
    the default levels is at most 256^2 pixels a view whatever the detector size. A copy is
    ours to spend (:func:`projection_matching`'s ``overwrite``); the caller's array is not.
    """
    if factor == 1 and isinstance(projections, np.ndarray):
        views = projections.astype(np.float32, copy=False)   # nothing to bin, nothing to stream
        return views, geometry, views is not projections
    coarse = binned_geometry(geometry, factor)
    out = np.empty((len(projections), coarse.detector_rows, coarse.detector_cols), np.float32)
    for index in range(len(projections)):
        out[index] = bin_detector(np.asarray(projections[index], dtype=np.float32)[None], geometry, factor)[0][0]
    return out, coarse, True


@dataclass(frozen=True)
class ProjectionMatchingRefiner(Refiner):
    """Whole-scan angles: features give the start, projection matching against the scan's own FDK pins every view.

    The start (``view-graph``: the pair estimates refit and solved robustly on the view graph
    with loop closure; ``nominal``; or any refiner, e.g. ``{name: bundle-adjustment,
    loss_scale_px: 0.7}``, built through the registry) has the capture range for slips of degrees; matching
    each view against the reprojection of a reconstruction from all views then removes the drift
    a chain of pairs accumulates (:mod:`ctpipe.solve.reprojection`), with the centre of rotation's
    column and the detector's tilt (``detector``) and what does not turn taken out (``static``).
    With ``select``, matching starts from whichever of the start and the nominal angles explains
    the projections better (a reconstruct-and-reproject residual, each on the detector aligned to
    it where ``detector``: :func:`~ctpipe.solve.reprojection.consistency_costs`), and the matched
    angles are returned only where they predict views held out of the reference better than the
    nominal angles do, beyond noise (:func:`~ctpipe.solve.reprojection.held_out_scores`; a reference built from
    wrong angles bends towards them, so its own residual cannot judge them), so a scan the
    matching cannot handle keeps its nominal angles; the evidence goes to the gate.
    With ``shifts`` each view's detector shift is fitted with its angle, so a detector or source
    that drifts during the scan is not taken for angle errors; the shifts are in
    ``info["matching"]["shifts_px"]``.
    Needs the projections (``ScanObservations.projections``); without them it returns the start.
    """

    start: Refiner | StageSpec | Literal["view-graph", "nominal"] = param(
        "view-graph", stage="refiner",
        doc="where matching starts: 'view-graph' (the pair estimates refit on their inliers and solved robustly on the "
            "view graph, weighted by inliers: least-squares with weighting: inliers), 'nominal' (the nominal angles; "
            "without them the view graph), or a refiner's angles, named like a pipeline's refiner (a bare name takes "
            "its defaults)")
    level_px: tuple[int, ...] = param((128, 256), doc="detector size (pixels a side) each level is binned to, coarse "
                                      "to fine", ge=16, le=8192)
    binning: tuple[int, ...] | None = param(None, doc="explicit binning factor of each level (null: from level_px)",
                                            ge=1, le=64)
    iterations: tuple[int, ...] = param((3, 2), doc="reconstruct-and-match rounds at each level", ge=0, le=50)
    band_low_px: float = param(0.7, doc="fine edge of the band-pass (Gaussian sigma, binned pixels)", ge=0, le=16)
    band_high_px: float = param(4.0, doc="coarse edge of the band-pass (Gaussian sigma, binned pixels)", gt=0, le=64)
    max_voxels: int = param(192, doc="largest edge of the reconstruction grid", ge=16, le=1024)
    filter: Filter = param("ram-lak", doc="FDK ramp-filter window for the reference volume")
    max_step_deg: float | None = param(None, doc="largest change of one view's angle per step (null: what the band "
                                       "holds linear at each level: its coarse scale over the grid's edge)",
                                       gt=0, le=45)
    shifts: bool = param(True, doc="fit each view's detector shift (a drifting detector or source) with its angle, so "
                         "the drift is not taken for angle errors")
    detector: bool = param(True, doc="fit the centre of rotation's column and the detector's in-plane tilt with the "
                           "angles (reported in the refined geometry)")
    static: bool = param(True, doc="match the views less their static part (what does not turn with the sample: the "
                         "views' mean on a full turn, their per-pixel median on a short scan), where 16 views or "
                         "more span 180 deg or more")
    select: bool = param(True, doc="start matching from whichever of the start and the nominal angles fits the "
                         "projections better (each on the detector aligned to it, with detector), and return the "
                         "matched angles only where they predict views held out of the reference better than the "
                         "nominal ones, beyond noise")
    min_views: int = param(32, doc="fewest views worth reconstructing a reference from; fewer keep the start",
                           ge=8, le=100000)

    def __post_init__(self) -> None:
        super().__post_init__()
        n_levels = len(self.level_px if self.binning is None else self.binning)
        if n_levels != len(self.iterations):
            raise ConfigError(f"ProjectionMatchingRefiner.iterations: must give one count per level "
                              f"({n_levels}), got {list(self.iterations)}")
        if not self.band_low_px < self.band_high_px:
            raise ConfigError(f"ProjectionMatchingRefiner.band_low_px: must be below band_high_px "
                              f"({self.band_high_px:g}), got {self.band_low_px:g}")

    @property
    def reads_descriptors(self) -> bool:
        """Matching reads pixels; only a refiner given as the start may read descriptors."""
        return isinstance(self.start, Refiner) and self.start.reads_descriptors

    def refine(self, observations: ScanObservations, *, rng: np.random.Generator) -> ScanSolution:
        start = self.start
        if isinstance(start, StageSpec):
            raise ConfigError(f"ProjectionMatchingRefiner.start: refiner {start.name!r} is only named, not built; build "
                              "this stage through a registry (ctpipe.config.build_stage, Pipeline.from_config) or pass "
                              "a refiner stage")
        nominal = observations.nominal_angles_deg
        if start == "nominal" and nominal is not None:
            start_solution = ScanSolution(np.deg2rad(nominal - nominal[0]), observations.estimates,
                                          {"refiner": "nominal"})
        elif isinstance(start, str):
            start_solution = solve_view_graph(observations, weighting="inliers")
        else:
            start_solution = start.refine(observations, rng=rng)
        info = {"start": start if isinstance(start, str) else type(start).__name__,
                "start_info": dict(start_solution.info)}
        start_deg, n_filled = _fill(np.rad2deg(start_solution.angles_rad), nominal)
        info["views_filled"] = n_filled
        projections = observations.projections
        rows, cols = observations.geometry.shape
        levels = matching_levels((rows, cols), self.iterations, level_px=self.level_px, binning=self.binning)
        skip = ("skipped: no projections to match" if projections is None else
                f"skipped: every level leaves fewer than 16 pixels of the {rows} x {cols} detector" if not levels else
                f"skipped: {observations.n_views} views are too few to reconstruct a reference from (min_views "
                f"{self.min_views})" if observations.n_views < self.min_views else "")
        if skip:
            info["matching"] = skip
            return ScanSolution(np.deg2rad(start_deg - start_deg[0]), start_solution.pair_estimates, info)
        # Match in the frame of the nominal angles, where the volume sits as the user expects.
        if nominal is not None:
            start_deg = start_deg + float(np.median(nominal - start_deg))
        begin = time.perf_counter()
        # Bin once by what every level shares, view by view: the levels then bin that copy further.
        prebin = math.gcd(*(b for b, _ in levels))
        projections, geometry, owned = _binned_views(projections, observations.geometry, prebin)
        levels = [(b // prebin, n) for b, n in levels]
        band = (self.band_low_px, self.band_high_px)
        static = self.static and static_part_applies(start_deg if nominal is None else nominal)
        info["static_removed"] = bool(static)
        costs = {}
        candidates = {"start": start_deg}
        if nominal is not None:
            candidates["nominal"] = np.asarray(nominal, dtype=np.float64)
        def cost_the_rest() -> None:
            """Consistency cost of every candidate not costed yet, in one reconstruct-and-reproject pass."""
            costs.update(consistency_costs(projections, geometry,
                                           {name: a for name, a in candidates.items() if name not in costs},
                                           binning=levels[0][0], band_px=band, max_voxels=self.max_voxels,
                                           filter=self.filter, static=static, detector=self.detector))

        if self.select and len(candidates) > 1:
            # Match from whichever explains the projections better: a feature start that went
            # astray (too few features, a degenerate object) must not be the one refined.
            cost_the_rest()
        origin = min(candidates, key=lambda name: (costs.get(name, 0.0), name != "start"))
        # The matched angles are judged against the others on views left out of the reference
        # they are compared with (a reference bends towards the angles it is built from).
        # (The nominal angles only, or the start without them: a start the matching began from
        # and improved on is not worth another pair of reconstructions in the held-out test.)
        compare = ({"nominal": candidates["nominal"]} if "nominal" in candidates else
                   {"start": candidates["start"]}) if self.select else None
        result = projection_matching(projections, geometry, candidates[origin],
                                     binning=[b for b, _ in levels], iterations=[n for _, n in levels], band_px=band,
                                     max_voxels=self.max_voxels, filter=self.filter, max_step_deg=self.max_step_deg,
                                     shifts=self.shifts, detector=self.detector, static=static, compare=compare,
                                     overwrite=owned)   # the binned copy is not read again here
        info["matching"] = {"from": origin, "levels": [{"binning": b * prebin, "iterations": n} for b, n in levels],
                            "history": [{**h, "binning": h["binning"] * prebin,
                                         **({"shift_rms_px": h["shift_rms_px"] * prebin} if "shift_rms_px" in h else {})}
                                        for h in result.history],
                            "stopped": result.stopped}
        shifts_px = None if result.shifts_px is None else result.shifts_px * prebin
        if shifts_px is not None:
            # Each view's detector shift, in the scan's own pixels (columns, rows), without the
            # common and once-per-turn part an object's place on the table explains.
            info["matching"]["shifts_px"] = shifts_px.round(4).tolist()
            info["matching"]["shift_rms_px"] = float(np.sqrt(np.mean(shifts_px ** 2)))
        chosen, angles = "matched", result.angles_deg
        if result.held_out is not None:
            candidates["matched"] = result.angles_deg
            scores = result.held_out
            reference = next(iter(compare))
            # The lowest held-out cost, but nothing over the reference (the nominal angles) unless
            # it predicts the held-out views better beyond their noise.
            best = min(scores, key=lambda name: (scores[name].cost, name != "matched"))
            chosen = best if best == reference or scores[best].z < -HELD_OUT_Z else reference
            angles = candidates[chosen]
            info["held_out"] = {name: score.to_dict() for name, score in scores.items()}
            if result.held_out_slow_even is not None:
                # The slow-even band of the matched correction on its own: what the gate decides
                # that band by where the held-out views vouch for the whole beyond doubt.
                info["held_out_slow_even"] = {name: score.to_dict()
                                              for name, score in result.held_out_slow_even.items()}
            info["matching"]["held_out_binning"] = result.held_out_binning * prebin
            info["consistency_cost"] = {name: score.cost for name, score in scores.items()}
        info["matching"]["seconds"] = time.perf_counter() - begin
        info["chosen"] = chosen
        geometry_found = {}
        if result.axis_offset_px is not None:
            info["matching"]["axis_offset_px"] = result.axis_offset_px * prebin
            info["matching"]["tilt_deg"] = result.tilt_deg
            if chosen == "matched":
                # The geometry the matched angles were found with: the axis column and the tilt.
                geometry_found = {"u0_px": observations.geometry.u0_px + result.axis_offset_px * prebin,
                                  "tilt_deg": result.tilt_deg}
        return ScanSolution(np.deg2rad(angles - angles[0]), start_solution.pair_estimates, info,
                            angle_se_deg=result.angle_se_deg if chosen == "matched" else None, **geometry_found)


@hookimpl
def ctpipe_register_stages(registry) -> None:
    registry.add_refiner("projection-matching", ProjectionMatchingRefiner)
