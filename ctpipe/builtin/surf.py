"""The ``surf`` detector: SURF keypoints and descriptors as OpenCV's ``xfeatures2d::SURF`` computes them.

The OpenCV wheels on PyPI refuse SURF (patented, excluded from their build) and Debian's OpenCV
has no ``xfeatures2d``, yet the paper's pipeline and the results users compare with are
OpenCV's SURF. The numerics (fast Hessian, orientation, descriptors, step by step as
``modules/xfeatures2d/src/surf.cpp``) are :mod:`ctpipe.features.surf`; this module declares the
stage's parameters and packs its output as :class:`~ctpipe.data.Features`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ctpipe.data import Features
from ctpipe.features import compute_surf
from ctpipe.hookspecs import hookimpl
from ctpipe.stages import Detector, param

__all__ = ["SurfDetector", "surf"]


def surf(image, *, hessian_threshold: float = 100.0, n_octaves: int = 4, n_octave_layers: int = 3,
         extended: bool = False, upright: bool = False) -> Features:
    """SURF keypoints and descriptors of one image, as OpenCV's ``SURF_create(...).detectAndCompute``.

    Parameters
    ----------
    image : ndarray of shape (rows, cols)
        uint8, or any integer/float image (mapped linearly from its [min, max] to uint8).
    hessian_threshold : float
        Keep maxima whose Hessian determinant exceeds this (OpenCV's and the paper's 100).
    n_octaves, n_octave_layers : int
        Octaves of box-filter sizes, and the layers per octave searched for maxima.
    extended : bool
        128-float descriptors instead of 64.
    upright : bool
        Skip the orientation (angle stored as 270 deg, as OpenCV does).

    Returns
    -------
    Features
        Ordered by response, strongest first (ctpipe's rule; OpenCV breaks ties differently).

    Raises
    ------
    InputError
        Not 2-D, empty, non-numeric, or with NaN/inf pixels.
    """
    found, angles, descriptors = compute_surf(image, hessian_threshold=hessian_threshold, n_octaves=n_octaves,
                                              n_octave_layers=n_octave_layers, extended=extended, upright=upright)
    return Features.build(xy=found[:, :2], size=found[:, 2], angle_deg=angles, response=found[:, 3],
                          octave=found[:, 5].astype(np.int32), class_id=found[:, 4].astype(np.int32),
                          descriptors=descriptors, norm="L2")


@dataclass(frozen=True)
class SurfDetector(Detector):
    """SURF (Bay et al.) as OpenCV computes it: fast-Hessian keypoints, 64/128-float descriptors."""

    hessian_threshold: float = param(100.0, doc="keep maxima of the Hessian determinant above this", ge=0,
                                        le=1e9)
    n_octaves: int = param(4, doc="octaves of box-filter sizes", ge=1, le=8)
    n_octave_layers: int = param(3, doc="layers per octave searched for maxima", ge=1, le=8)
    extended: bool = param(False, doc="128-float descriptors instead of 64")
    upright: bool = param(False, doc="skip the orientation (faster, not rotation invariant; angle 270)")
    # Multi-scale (box-filter scale space): a binned view keeps its keypoints.
    working_resolution = True

    def detect(self, image: np.ndarray) -> Features:
        return surf(image, **self.params())


@hookimpl
def ctpipe_register_stages(registry) -> None:
    registry.add_detector("surf", SurfDetector)
