"""The small simulated scan the conjugate-ray and gate tests share, and its variants."""

from __future__ import annotations

import copy

import numpy as np

from ctpipe.sim.phantoms import load_phantom
from ctpipe.sim.scan_spec import parse_scan_spec
from ctpipe.sim.simulator import simulate

#: 180 views of 128^2 over a full turn, 0.3 deg Gaussian jitter, 1e5 photons a pixel.
SCAN = {
    "geometry": {"source_to_object_mm": 130.0, "source_to_detector_mm": 300.0, "detector_cols": 128,
                 "detector_rows": 128, "pixel_pitch_u_mm": 1.6, "pixel_pitch_v_mm": 1.6},
    "angles": {"n_views": 180, "range_deg": 360.0},
    "jitter": [{"gaussian": {"sigma_deg": 0.3}}],
    "noise": {"photons_per_pixel": 100000, "flat_frames": 4, "dark_frames": 2, "dark_counts": 100},
    "projector": {"kind": "analytic", "supersample": 1, "blur_px": 0.5},
    "seed": 1,
}


def simulate_scan(phantom: str = "bead-cylinder", **changes):
    """:data:`SCAN` of ``phantom`` with dotted keys changed (``**{"angles.range_deg": 250.0}``)."""
    spec = copy.deepcopy(SCAN)
    for key, value in changes.items():
        node = spec
        *parents, last = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[last] = value
    return simulate(load_phantom(phantom), parse_scan_spec(spec), rng=np.random.default_rng(5))
