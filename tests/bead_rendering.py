"""Line integrals through spheres, rendered analytically: the bead scans of the tests."""

from __future__ import annotations

import numpy as np

from ctpipe.geometry import Geometry
from ctpipe.model import rotation_matrix


def render_beads(geometry: Geometry, angles_deg, centres_mm: np.ndarray, radii_mm: np.ndarray) -> np.ndarray:
    """Line integrals through spheres (chord length 2 sqrt(r^2 - d^2)), one view per angle.

    Each sphere is rendered at its own magnification (its centre's depth); good enough for
    features to be detected where the sphere centres project. Returns float32 (V, rows, cols).
    """
    rows, cols = np.mgrid[0:geometry.detector_rows, 0:geometry.detector_cols].astype(np.float64)
    views = []
    for angle in angles_deg:
        camera = centres_mm @ rotation_matrix(np.deg2rad(angle)).T + [0.0, 0.0, geometry.source_to_object_mm]
        image = np.zeros(geometry.shape)
        for (x, y, z), radius in zip(camera, radii_mm):
            u, v = geometry.normalised_to_pixels(np.array([[x / z, y / z]]))[0]
            scale = geometry.source_to_detector_mm / z / geometry.pixel_pitch_u_mm
            d2 = ((cols - u) ** 2 + (rows - v) ** 2) / scale**2
            image += 2.0 * np.sqrt(np.clip(radius**2 - d2, 0.0, None))
        views.append(image)
    return np.asarray(views, dtype=np.float32)
