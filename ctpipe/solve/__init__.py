"""Whole-scan solving: the view graph, feature tracks, bundle adjustment and projection matching.

Pair estimates tie two views each; the functions here turn all of a scan's evidence into one
consistent set of per-view angles. :mod:`ctpipe.solve.graph` holds the view graph (which pairs
to estimate, loop closure on full turns, unwrapping pair angles against the nominal ones).
"""

from ctpipe.solve.graph import covers_full_turn, unwrap_pair_angles_deg, view_pairs

__all__ = ["covers_full_turn", "unwrap_pair_angles_deg", "view_pairs"]
