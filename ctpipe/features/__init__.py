"""Feature extraction: the image processing that turns one projection into keypoints.

Plain functions on arrays, no stages and no configuration: SURF as OpenCV computes it
(:mod:`ctpipe.features.surf`: integral image, fast-Hessian keypoints, orientations and
descriptors in numba) and the ball finder of calibration phantoms (:mod:`ctpipe.features.balls`:
noise and defects, scale-space candidates, sub-pixel fits of a blurred disc model, crowds of
overlapping balls), and exact nearest neighbours of float descriptors both ways in one pass
(:mod:`ctpipe.features.nearest`, for matching). The detector stages of :mod:`ctpipe.builtin` are thin adapters that call
these functions and pack their output as :class:`ctpipe.data.Features`; a new detector's
numerics belong here, its stage there.
"""

from __future__ import annotations

from ctpipe._shared.lazy import lazy_exports

#: Public name -> the module of this package that defines it. Imported on first use, so that the
#: SURF detector does not load the ball finder's scipy modules (0.6 s) and the other way round.
_EXPORTS = {
    "compute_surf": "surf", "fast_hessian": "surf", "integral_image": "surf", "surf_descriptors": "surf",
    "find_balls": "balls", "noise_sigma": "balls", "despike": "balls", "render_ball_model": "balls",
    "edge_centres": "ball_edges", "bright_view": "ball_edges", "rim_seeds": "ball_edges",
    "looks_like_ball_phantom": "ball_phantom", "ball_phantom_share": "ball_phantom",
    "l2_neighbours": "nearest",
}

__all__ = list(_EXPORTS)


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
