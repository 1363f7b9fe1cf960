"""Detectors wrapping OpenCV's SIFT, ORB, AKAZE, BRISK and KAZE.

Parameter names are OpenCV's, in snake case (``nOctaveLayers`` -> ``n_octave_layers``), with
OpenCV's defaults. Float images are mapped to uint8 by :func:`ctpipe.images.to_uint8`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ctpipe.builtin import _opencv
from ctpipe.data import Features
from ctpipe.errors import ConfigError
from ctpipe.hookspecs import hookimpl
from ctpipe.images import to_uint8
from ctpipe.stages import Detector, param


class _OpenCVDetector(Detector):
    _opencv_name = ""
    # Multi-scale keypoints (scale-space or image pyramids): a binned view keeps them.
    working_resolution = True

    def detect(self, image: np.ndarray) -> Features:
        return Features.build(**_opencv.detect_and_compute(self._opencv_name, self.params(), to_uint8(image)))


@dataclass(frozen=True)
class SiftDetector(_OpenCVDetector):
    """SIFT keypoints and 128-float descriptors (OpenCV)."""

    _opencv_name = "sift"
    n_features: int = param(0, doc="keep the n best keypoints (0: all)", ge=0, le=1_000_000)
    n_octave_layers: int = param(3, doc="layers per octave", ge=1, le=16)
    contrast_threshold: float = param(0.04, doc="reject weak extrema in low-contrast regions", ge=0, le=10)
    edge_threshold: float = param(10.0, doc="reject edge-like extrema", gt=0, le=1000)
    sigma: float = param(1.6, doc="Gaussian sigma at octave 0", gt=0, le=16)


@dataclass(frozen=True)
class OrbDetector(_OpenCVDetector):
    """ORB: oriented FAST keypoints with rotated BRIEF binary descriptors (OpenCV)."""

    _opencv_name = "orb"
    n_features: int = param(500, doc="maximum number of keypoints", ge=1, le=1_000_000)
    scale_factor: float = param(1.2, doc="pyramid decimation ratio", gt=1, le=4)
    n_levels: int = param(8, doc="pyramid levels", ge=1, le=32)
    edge_threshold: int = param(31, doc="border where no keypoints are detected, px", ge=0, le=1024)
    first_level: int = param(0, doc="pyramid level of the source image", ge=0, le=31)
    wta_k: int = param(2, doc="points per BRIEF comparison (2, 3 or 4)", ge=2, le=4)
    score_type: Literal["harris", "fast"] = param("harris", doc="keypoint ranking score")
    patch_size: int = param(31, doc="oriented BRIEF patch size, px", ge=2, le=1024)
    fast_threshold: int = param(20, doc="FAST threshold", ge=0, le=255)

    def __post_init__(self) -> None:
        super().__post_init__()
        # first_level > 0 upsamples the image by scale_factor ** first_level before the pyramid.
        if self.scale_factor ** self.first_level > 16:
            raise ConfigError(f"OrbDetector.first_level: scale_factor ** first_level (the upsampling of the image) "
                              f"must be <= 16, got {self.scale_factor:g} ** {self.first_level}")


_Diffusivity = Literal["pm_g1", "pm_g2", "weickert", "charbonnier"]


@dataclass(frozen=True)
class AkazeDetector(_OpenCVDetector):
    """AKAZE: nonlinear-scale-space keypoints with binary MLDB descriptors (OpenCV)."""

    _opencv_name = "akaze"
    descriptor_type: Literal["mldb", "mldb_upright", "kaze", "kaze_upright"] = param("mldb", doc="descriptor kind")
    descriptor_size: int = param(0, doc="descriptor bits (0: full)", ge=0, le=486)
    descriptor_channels: int = param(3, doc="channels in the descriptor (1, 2 or 3)", ge=1, le=3)
    threshold: float = param(0.001, doc="detector response threshold", gt=0, le=1)
    n_octaves: int = param(4, doc="maximum octave evolution", ge=1, le=8)
    n_octave_layers: int = param(4, doc="sublevels per octave", ge=1, le=8)
    diffusivity: _Diffusivity = param("pm_g2", doc="diffusivity function")

    def __post_init__(self) -> None:
        super().__post_init__()
        full = 162 * self.descriptor_channels  # OpenCV's MLDB: 162 bits per channel
        if self.descriptor_size > full:
            raise ConfigError(f"AkazeDetector.descriptor_size: must be <= {full} (162 bits per channel) with "
                              f"descriptor_channels={self.descriptor_channels}, got {self.descriptor_size}")


@dataclass(frozen=True)
class BriskDetector(_OpenCVDetector):
    """BRISK: scale-space AGAST keypoints with binary descriptors (OpenCV)."""

    _opencv_name = "brisk"
    thresh: int = param(30, doc="AGAST detection threshold", ge=0, le=255)
    octaves: int = param(3, doc="detection octaves (0: single scale)", ge=0, le=8)
    pattern_scale: float = param(1.0, doc="scale of the sampling pattern", gt=0, le=16)


@dataclass(frozen=True)
class KazeDetector(_OpenCVDetector):
    """KAZE: nonlinear-scale-space keypoints with float descriptors (OpenCV)."""

    _opencv_name = "kaze"
    extended: bool = param(False, doc="128-float descriptors instead of 64")
    upright: bool = param(False, doc="skip orientation (faster, not rotation invariant)")
    threshold: float = param(0.001, doc="detector response threshold", gt=0, le=1)
    n_octaves: int = param(4, doc="maximum octave evolution", ge=1, le=8)
    n_octave_layers: int = param(4, doc="sublevels per octave", ge=1, le=8)
    diffusivity: _Diffusivity = param("pm_g2", doc="diffusivity function")


@hookimpl
def ctpipe_register_stages(registry) -> None:
    # Only what this cv2 build can create: a plain opencv-python wheel installed over the contrib
    # one (mbirjax pulls it in) drops AKAZE, BRISK and KAZE, and a stage that cannot run is not offered.
    available = set(_opencv.available_detectors())
    for cls in (SiftDetector, OrbDetector, AkazeDetector, BriskDetector, KazeDetector):
        if cls._opencv_name in available:
            registry.add_detector(cls._opencv_name, cls)
