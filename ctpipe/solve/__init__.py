"""Whole-scan solving: the view graph, feature tracks, bundle adjustment and projection matching.

Pair estimates tie two views each; the functions here turn all of a scan's evidence into one
consistent set of per-view angles. :mod:`ctpipe.solve.graph` holds the view graph (which pairs
to estimate, loop closure on full turns, unwrapping pair angles against the nominal ones) and
solves it for per-view angles, plainly or with a robust loss.
"""

from ctpipe.solve.graph import (LOSSES, PairGraphSolution, chain_pair_angles, covers_full_turn, solve_pair_graph,
                                unwrap_pair_angles_deg, view_pairs)

__all__ = ["covers_full_turn", "unwrap_pair_angles_deg", "view_pairs", "chain_pair_angles", "solve_pair_graph",
           "PairGraphSolution", "LOSSES"]
