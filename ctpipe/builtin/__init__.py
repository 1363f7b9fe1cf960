"""ctpipe's own stages: detectors, matchers, estimators and refiners, each module a plugin.

Every module here is listed in :data:`ctpipe.plugins.BUILTIN_PLUGINS` and registers its stages
through the same hook third-party plugins implement, so the built-in stages are found by name
(``surf``, ``beads``, ``ransac-1pt``, ``projection-matching``, ...) exactly as theirs are. The
classes can also be built directly from Python. Every ``cv2`` call is in
:mod:`~ctpipe.builtin._opencv`, the adapter that absorbs OpenCV's version differences. The
stages are thin: the feature numerics are in :mod:`ctpipe.features`, the solvers in
:mod:`ctpipe.solve`. No module here imports another's stages (a stage that needs another, such
as projection matching's start, gets it from the registry).

The modules are imported on first use of a name, so that ``--block-plugin`` keeps a module
(and what it imports, e.g. OpenCV) out of the process.
"""

from __future__ import annotations

from ctpipe._shared.lazy import lazy_exports

#: Public name -> the module of this package that defines it.
_EXPORTS = {
    "SurfDetector": "surf", "BeadDetector": "beads",
    "SiftDetector": "opencv_detectors", "OrbDetector": "opencv_detectors", "AkazeDetector": "opencv_detectors",
    "BriskDetector": "opencv_detectors", "KazeDetector": "opencv_detectors",
    "BruteForceMatcher": "matchers", "FlannMatcher": "matchers",
    "Ransac1ptEstimator": "estimators", "HistogramEstimator": "estimators", "MedianEstimator": "estimators",
    "OpenCV5ptEstimator": "estimators",
    "LeastSquaresRefiner": "refiners", "BundleAdjustmentRefiner": "bundle",
    "ProjectionMatchingRefiner": "projection_matching", "BallCalibrationRefiner": "ball_calibration",
}

__all__ = list(_EXPORTS)


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
