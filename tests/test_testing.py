"""ctpipe.testing's ball-phantom helpers against geometry worked out by hand."""

import numpy as np
import pytest

from ctpipe.errors import InputError
from ctpipe.geometry import Geometry
from ctpipe.sim.phantoms import parse_phantom
from ctpipe.testing import overlapping_spheres, phantom_spheres

GEOMETRY = Geometry(source_to_object_mm=250.0, source_to_detector_mm=500.0, detector_cols=128, detector_rows=96,
                    pixel_pitch_u_mm=0.4, pixel_pitch_v_mm=0.2)


def test_balls_side_by_side_overlap_exactly_when_closer_than_a_diameter():
    """At angle 0, balls at (+-a, 0, 0) project to +-a SDD / SOD with radii r SDD / SOD: they
    overlap iff a < r; at 90 deg they lie on the central ray and always overlap."""
    for a, expected in ((0.99, True), (1.01, False)):
        centres = np.array([[-a, 0.0, 0.0], [a, 0.0, 0.0]])
        pairs = overlapping_spheres(centres, [1.0, 1.0], GEOMETRY, [0.0, 90.0])
        assert [len(p) for p in pairs] == [int(expected), 1]
        if expected:
            np.testing.assert_array_equal(pairs[0], [[0, 1]])


def test_nearer_balls_look_larger():
    """A ball nearer the source is magnified more: radius 1 at depth -50 (SDD / 200) and radius 1
    at depth +50 (SDD / 300), stacked vertically, overlap iff their centres' gap on the detector is
    below 500 / 200 + 500 / 300 mm."""
    limit = 500.0 / 200.0 + 500.0 / 300.0
    for gap, expected in ((limit - 0.01, 1), (limit + 0.01, 0)):
        # Ball 0 at y0 = 0 in front; ball 1 at depth +50 and height y with y * 500 / 300 = gap.
        centres = np.array([[0.0, 0.0, -50.0], [0.0, gap * 300.0 / 500.0, 50.0]])
        assert len(overlapping_spheres(centres, [1.0, 1.0], GEOMETRY, [0.0])[0]) == expected


def test_phantom_spheres_keeps_positive_round_ellipsoids_only():
    phantom = parse_phantom({"objects": [
        {"cylinder": {"radius_mm": 10, "height_mm": 10, "density_per_mm": 0.01}},
        {"sphere": {"centre_mm": [1, 2, 3], "radius_mm": 1.5, "density_per_mm": 0.5}},
        {"sphere": {"centre_mm": [-1, 0, 0], "radius_mm": 1.0, "density_per_mm": -0.01}},   # a pore
        {"ellipsoid": {"semi_axes_mm": [1, 2, 1], "density_per_mm": 0.5}},
    ]})
    centres, radii = phantom_spheres(phantom)
    np.testing.assert_array_equal(centres, [[1, 2, 3]])
    np.testing.assert_array_equal(radii, [1.5])


def test_overlapping_spheres_names_bad_shapes():
    with pytest.raises(InputError, match=r"centres_mm, radii_mm: must have shapes \(N, 3\) and \(N,\)"):
        overlapping_spheres(np.zeros((3, 2)), np.ones(3), GEOMETRY, [0.0])
