"""ctpipe's own stages: detectors, matchers, estimators and refiners, each module a plugin.

Every module here is listed in :data:`ctpipe.plugins.BUILTIN_PLUGINS` and registers its stages
through the same hook third-party plugins implement, so the built-in stages are found by name
(``surf``, ``beads``, ``ransac-1pt``, ``projection-matching``, ...) exactly as theirs are. The
classes can also be built directly from Python. Every ``cv2`` call is in
:mod:`~ctpipe.builtin._opencv`, the adapter that absorbs OpenCV's version differences. The
refiners are thin stages over the solvers of :mod:`ctpipe.solve`.
"""

from ctpipe.builtin.beads import BeadDetector
from ctpipe.builtin.bundle import BundleAdjustmentRefiner
from ctpipe.builtin.estimators import HistogramEstimator, MedianEstimator, OpenCV5ptEstimator, Ransac1ptEstimator
from ctpipe.builtin.matchers import BruteForceMatcher, FlannMatcher
from ctpipe.builtin.opencv_detectors import AkazeDetector, BriskDetector, KazeDetector, OrbDetector, SiftDetector
from ctpipe.builtin.projection_matching import ProjectionMatchingRefiner
from ctpipe.builtin.refiners import LeastSquaresRefiner
from ctpipe.builtin.surf import SurfDetector

__all__ = ["SurfDetector", "BeadDetector", "SiftDetector", "OrbDetector", "AkazeDetector", "BriskDetector",
           "KazeDetector", "BruteForceMatcher", "FlannMatcher", "Ransac1ptEstimator", "HistogramEstimator",
           "MedianEstimator", "OpenCV5ptEstimator", "LeastSquaresRefiner", "BundleAdjustmentRefiner",
           "ProjectionMatchingRefiner"]
