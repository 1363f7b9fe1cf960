"""Shared fixtures: a small bead scan rendered analytically with known angles."""

from __future__ import annotations

import numpy as np
import pytest

from bead_rendering import render_beads
from ctpipe.geometry import Geometry


@pytest.fixture(scope="session")
def bead_scan():
    """(projections, geometry, true angles in degrees) of 200 beads, 5 views with uneven steps.

    A wide cone (half-angle ~12 deg): the angle one correspondence fixes has an error of about
    2 da / b, so narrow cones need many more keypoints than a test image of 256^2 has.
    """
    geometry = Geometry(source_to_object_mm=250.0, source_to_detector_mm=500.0, detector_cols=256,
                        detector_rows=256, pixel_pitch_u_mm=0.8, pixel_pitch_v_mm=0.8)
    rng = np.random.default_rng(3)
    n = 200
    r = 40.0 * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    centres = np.stack([r * np.cos(phi), rng.uniform(-40, 40, n), r * np.sin(phi)], axis=1)
    radii = rng.uniform(0.8, 2.0, n)
    angles = np.array([0.0, 2.0, 3.5, 6.5, 8.0])
    return render_beads(geometry, angles, centres, radii), geometry, angles
