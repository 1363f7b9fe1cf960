"""Reconstruction: the voxel grid and FDK filtered backprojection for arbitrary angles.

:mod:`~ctpipe.recon.volume` defines the grid every volume in ctpipe lives on (axes, voxel size,
where the turntable axis is); :mod:`~ctpipe.recon.feldkamp` reconstructs a circular cone-beam
scan on it from line integrals at any set of angles, full or short scan (Parker weights), with
rows extended past the detector's edges for objects wider than the field of view, and
bins detectors for coarser, faster reconstructions. The forward projectors that go the other
way are the simulator's (:mod:`ctpipe.sim.projectors`).
"""

from ctpipe.recon.feldkamp import (FILTERS, TRUNCATION, bin_detector, binned_geometry, covers_full_circle, fdk,
                                   is_truncated, parker_weights, ramp_filter, short_scan_minimum_deg, view_weights)
from ctpipe.recon.volume import VolumeGrid

__all__ = ["VolumeGrid", "fdk", "FILTERS", "TRUNCATION", "is_truncated", "ramp_filter", "view_weights", "parker_weights",
           "covers_full_circle", "short_scan_minimum_deg", "bin_detector", "binned_geometry"]
