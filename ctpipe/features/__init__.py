"""Feature extraction: the image processing that turns one projection into keypoints.

Plain functions on arrays, no stages and no configuration: SURF as OpenCV computes it
(:mod:`ctpipe.features.surf`: integral image, fast-Hessian keypoints, orientations and
descriptors in numba) and the ball finder of calibration phantoms (:mod:`ctpipe.features.balls`:
noise and defects, scale-space candidates, sub-pixel fits of a blurred disc model, crowds of
overlapping balls). The detector stages of :mod:`ctpipe.builtin` are thin adapters that call
these functions and pack their output as :class:`ctpipe.data.Features`; a new detector's
numerics belong here, its stage there.
"""

from __future__ import annotations

from ctpipe.features.balls import despike, find_balls, noise_sigma, render_ball_model
from ctpipe.features.surf import compute_surf, fast_hessian, integral_image, surf_descriptors

__all__ = [
    "compute_surf", "fast_hessian", "integral_image", "surf_descriptors",
    "find_balls", "noise_sigma", "despike", "render_ball_model",
]
