"""Whole-scan solving: the view graph, feature tracks, bundle adjustment and projection matching.

Pair estimates tie two views each; the functions here turn all of a scan's evidence into one
consistent set of per-view angles. :mod:`~ctpipe.solve.graph` holds the view graph (which pairs
to estimate, loop closure on full turns, unwrapping pair angles against the nominal ones) and
solves it, plainly or with a robust loss (:mod:`~ctpipe.solve.losses`, the one definition of the
robust losses every solver uses); :mod:`~ctpipe.solve.pairs` packages pair estimates;
:mod:`~ctpipe.solve.tracks` and
:mod:`~ctpipe.solve.bundle` follow features over the scan and adjust every view angle and a 3-D
point per track, through the camera model of :mod:`~ctpipe.solve.camera`;
:mod:`~ctpipe.solve.reprojection` matches every view against the reprojection of the scan's own
reconstruction (projection matching); :mod:`~ctpipe.solve.conjugate` checks a set of angles
against the projections alone, by the rays that two views half a turn apart both measure, and
:mod:`~ctpipe.solve.gate` returns corrected angles only where that check shows them better, band by
band (:mod:`~ctpipe.solve.bands`);
:mod:`~ctpipe.solve.balls` calibrates a ball phantom's angles and detector from all views at once. :mod:`~ctpipe.solve.simulated` draws observations of
known points for testing the solvers without images. ``docs/wholescan.md`` has the methods and
figures; the refiner stages that call these are in :mod:`ctpipe.builtin`.
"""

from ctpipe.solve.balls import PLACED_FLAG, BallCalibration, calibrate_balls, ellipse_centres
from ctpipe.solve.bundle import BundleResult, BundleSettings, BundleSolution, bundle_adjust, solve_bundle
from ctpipe.solve.camera import pixels_to_rays, project_points
from ctpipe.solve.conjugate import (ConjugateRayScore, conjugate_pairs, conjugate_ray_costs, conjugate_ray_mismatch,
                                     midplane_row, midplane_rows, turning_part)
from ctpipe.solve.bands import BANDS, split_bands
from ctpipe.solve.gate import GateDecision, cannot_tell, gate_angles, needed_z
from ctpipe.solve.graph import (PairGraphSolution, chain_pair_angles, covers_full_turn, solve_pair_graph,
                                solve_view_graph, turn_pairs, unwrap_pair_angles_deg, view_pairs)
from ctpipe.solve.losses import LOSSES, check_loss, robust_loss, robust_weight
from ctpipe.solve.pairs import one_to_one, pair_estimate
from ctpipe.solve.reprojection import (HELD_OUT_DECISIVE_Z, HELD_OUT_Z, HeldOutScore, ProjectionMatchingResult,
                                       consistency_costs, held_out_decisive, held_out_scores, matching_levels,
                                       projection_matching, slow_even_band_scores, static_part, static_part_applies,
                                       step_cap_deg)
from ctpipe.solve.simulated import SyntheticScan, synthetic_scan
from ctpipe.solve.tracks import Tracks, build_tracks, extend_tracks, static_tracks, triangulate_tracks

__all__ = ["covers_full_turn", "turn_pairs", "unwrap_pair_angles_deg", "view_pairs", "chain_pair_angles", "solve_pair_graph",
           "PairGraphSolution", "solve_view_graph", "LOSSES", "check_loss", "robust_loss", "robust_weight", "pair_estimate",
           "one_to_one", "Tracks", "build_tracks", "extend_tracks", "static_tracks",
           "triangulate_tracks", "bundle_adjust", "solve_bundle", "BundleResult", "BundleSettings", "BundleSolution",
           "projection_matching", "consistency_costs", "matching_levels", "ProjectionMatchingResult",
           "HELD_OUT_Z", "HELD_OUT_DECISIVE_Z", "HeldOutScore", "held_out_scores", "held_out_decisive",
           "slow_even_band_scores",
           "static_part", "static_part_applies", "step_cap_deg",
           "project_points", "pixels_to_rays", "synthetic_scan", "SyntheticScan", "midplane_rows", "midplane_row", "conjugate_pairs",
           "conjugate_ray_mismatch", "conjugate_ray_costs", "ConjugateRayScore", "turning_part",
           "gate_angles", "GateDecision",
           "split_bands", "needed_z", "cannot_tell", "BANDS", "calibrate_balls", "BallCalibration", "ellipse_centres",
           "PLACED_FLAG"]
