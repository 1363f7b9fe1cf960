"""Whole-scan solving: the view graph, feature tracks, bundle adjustment and projection matching.

Pair estimates tie two views each; the functions here turn all of a scan's evidence into one
consistent set of per-view angles. :mod:`ctpipe.solve.graph` holds the view graph (which pairs
to estimate, loop closure on full turns, unwrapping pair angles against the nominal ones) and
solves it, plainly or with a robust loss; :mod:`ctpipe.solve.tracks` and
:mod:`ctpipe.solve.bundle` follow features over the scan and adjust every view angle and a 3-D
point per track; :mod:`ctpipe.solve.projection_matching` matches every view against the
reprojection of the scan's own reconstruction. ``docs/wholescan.md`` has the methods and figures.
"""

from ctpipe.solve.bundle import BundleResult, BundleSettings, BundleSolution, bundle_adjust, solve_bundle
from ctpipe.solve.graph import (LOSSES, PairGraphSolution, chain_pair_angles, covers_full_turn, solve_pair_graph,
                                unwrap_pair_angles_deg, view_pairs)
# The function projection_matching stays in its module: imported here under the module's own
# name it would shadow the submodule (``import ctpipe.solve.projection_matching as pm`` would give
# the function).
from ctpipe.solve.projection_matching import ProjectionMatchingResult, consistency_costs, matching_levels
from ctpipe.solve.tracks import Tracks, build_tracks, extend_tracks, static_tracks, triangulate_tracks

__all__ = ["covers_full_turn", "unwrap_pair_angles_deg", "view_pairs", "chain_pair_angles", "solve_pair_graph",
           "PairGraphSolution", "LOSSES", "Tracks", "build_tracks", "extend_tracks", "static_tracks",
           "triangulate_tracks", "bundle_adjust", "solve_bundle", "BundleResult", "BundleSettings", "BundleSolution",
           "consistency_costs", "matching_levels", "ProjectionMatchingResult"]
