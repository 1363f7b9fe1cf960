"""scikit-image keypoint detectors as ctpipe detector stages.

This plugin registers three detectors through the ``ctpipe`` entry-point group:

``skimage-sift``
    :class:`skimage.feature.SIFT`, 128-float descriptors compared with ``L2``.
``skimage-orb``
    :class:`skimage.feature.ORB`, 256-bit rBRIEF descriptors compared with ``HAMMING``.
``skimage-censure``
    :class:`skimage.feature.CENSURE` keypoints with :class:`skimage.feature.BRIEF`
    descriptors compared with ``HAMMING``.

Parameter names are scikit-image's, with its defaults, except where one stage wraps two
scikit-image objects (see :class:`SkimageCensureDetector`).

Image conversion
----------------
Every detector validates its input with :func:`ctpipe.images.check_image` (so a 3-D, empty,
non-numeric or NaN image raises :class:`ctpipe.errors.InputError` exactly as the built-in
detectors do) and then maps it linearly from its own [min, max] to float64 in [0, 1]. The
thresholds (``c_dog``, ``fast_threshold``, ``non_max_threshold``) therefore apply to the
image's contrast whatever its dtype or units: a uint8 image is stretched too, unlike
``skimage.util.img_as_float``. A constant image has no contrast and gives no keypoints.

Coordinates
-----------
Keypoints are returned in ctpipe's convention, ``xy = (col, row)`` with pixel centres at
integers. scikit-image reports positions found on resampled images as if resampling kept
the pixel corners fixed; the stages below map them back exactly (see each class).

Angles
------
``angle_deg`` is measured from +x (columns) towards +y (rows, downwards), in [0, 360) degrees,
the convention of OpenCV's ORB.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from skimage.feature import BRIEF, CENSURE, ORB, SIFT

from ctpipe.data import Features
from ctpipe.errors import ConfigError
from ctpipe.hookspecs import hookimpl
from ctpipe.images import check_image
from ctpipe.stages import Detector, param

__all__ = [
    "SkimageSiftDetector",
    "SkimageOrbDetector",
    "SkimageCensureDetector",
    "to_unit_float",
    "ctpipe_register_stages",
]

#: scikit-image's ORB samples its rBRIEF tests in a 31 x 31 patch, like OpenCV's default.
ORB_PATCH_SIZE = 31

#: scikit-image's SIFT keeps octaves at least this many pixels wide (``size_min``).
_SIFT_MIN_OCTAVE_SIZE = 12

#: FAST compares a pixel with a circle of radius 3, so ORB needs 7 pixels across.
_FAST_DIAMETER = 7


def to_unit_float(image) -> np.ndarray | None:
    """Validate ``image`` and map it linearly to float64 in [0, 1].

    Parameters
    ----------
    image : array_like of shape (rows, cols)
        Integer or float image, no NaN or inf.

    Returns
    -------
    ndarray of shape (rows, cols), float64, or None
        ``(image - min) / (max - min)``, a new array; ``None`` for a constant image, which
        has no contrast and so no keypoints.

    Raises
    ------
    ctpipe.errors.InputError
        From :func:`ctpipe.images.check_image`: not 2-D, empty, not numeric, NaN or inf.
    """
    image = check_image(image)
    low, high = image.min(), image.max()
    if high <= low:
        return None
    # astype copies, so the caller's array is never written to.
    unit = image.astype(np.float64)
    unit -= float(low)
    unit /= float(high) - float(low)
    return unit


def _empty(width: int, norm: str) -> Features:
    """Features without keypoints whose descriptors still have the detector's width."""
    dtype = np.uint8 if norm.startswith("HAMMING") else np.float32
    return Features.build(xy=np.zeros((0, 2)), size=(), angle_deg=(), response=(),
                          descriptors=np.zeros((0, width), dtype=dtype), norm=norm)


def _found_nothing(exc: RuntimeError) -> bool:
    """True for the RuntimeError SIFT and ORB raise when not one keypoint survives."""
    return "found no features" in str(exc)


def _degrees(radians: np.ndarray) -> np.ndarray:
    """Radians to float32 degrees in [0, 360)."""
    degrees = (np.rad2deg(np.asarray(radians, dtype=np.float64)) % 360.0).astype(np.float32)
    # Tiny negative angles wrap to 360.0 after % and float32 rounding; 360 is 0.
    degrees[degrees >= 360.0] = 0.0
    return degrees


def _sampled_gaussian(offsets: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian weights at ``offsets`` (pixels), normalised to sum to one."""
    weights = np.exp(-0.5 * (offsets / sigma) ** 2)
    return weights / weights.sum()


def _dog_response(image: np.ndarray, rc: np.ndarray, sigmas: np.ndarray, ratio: float,
                  sigma_in: float) -> np.ndarray:
    """|DoG| of ``image`` at each keypoint's position and scale.

    The difference of Gaussians of blur ``sigma * ratio`` and ``sigma`` (total blur, the input
    being assumed blurred by ``sigma_in``), evaluated at the subpixel position ``rc`` with
    mirrored borders: the quantity SIFT thresholds with ``c_dog``, in the same units.
    """
    response = np.zeros(len(rc))
    if len(rc) == 0:
        return response
    # Clamp so a sampled Gaussian never becomes narrower than a pixel can represent.
    blur_low = np.maximum(np.sqrt(np.maximum(sigmas**2 - sigma_in**2, 0.0)), 0.25)
    blur_high = np.maximum(np.sqrt(np.maximum((sigmas * ratio) ** 2 - sigma_in**2, 0.0)), 0.25)
    radius = np.ceil(4.0 * blur_high).astype(int) + 1
    pad = int(radius.max()) + 1
    padded = np.pad(image, pad, mode="symmetric")  # numpy's "symmetric" is scipy's "reflect"
    for k, ((row, col), r) in enumerate(zip(rc + pad, radius)):
        rows = np.arange(int(row) - r, int(row) + r + 2)
        cols = np.arange(int(col) - r, int(col) + r + 2)
        patch = padded[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
        high = _sampled_gaussian(rows - row, blur_high[k]) @ patch @ _sampled_gaussian(cols - col, blur_high[k])
        low = _sampled_gaussian(rows - row, blur_low[k]) @ patch @ _sampled_gaussian(cols - col, blur_low[k])
        response[k] = abs(high - low)
    return response


@dataclass(frozen=True)
class SkimageSiftDetector(Detector):
    """SIFT keypoints and 128-float descriptors (scikit-image).

    Wraps :class:`skimage.feature.SIFT`; the parameters are its own, with its defaults.
    The image is first mapped to float64 in [0, 1] by :func:`to_unit_float`.

    Returned :class:`~ctpipe.data.Features`:

    xy
        ``SIFT.positions`` (row, col) swapped to (col, row) and shifted by
        ``0.5 / upsampling - 0.5`` px: scikit-image places the pixels of its upsampled seed
        image at ``k / upsampling`` whereas bilinear upsampling puts them at
        ``(k + 0.5) / upsampling - 0.5`` (-0.25 px for the default ``upsampling=2``).
    size
        ``2 * SIFT.sigmas``, the diameter OpenCV's SIFT reports (its ``size`` is twice the
        keypoint's scale-space sigma), in input pixels.
    angle_deg
        ``SIFT.orientations`` is measured from +row towards +col, and half a histogram bin
        too far (scikit-image centres bin ``m`` at ``m * 2 pi / n_bins`` but reads a peak
        there as ``(m + 0.5) * 2 pi / n_bins``: +5 deg by default). Converted to degrees from
        +x towards +y without that bias: ``(90 - degrees(orientation - pi / n_bins)) mod 360``.
    response
        scikit-image does not expose the DoG value it thresholds, so it is recomputed
        (:func:`_dog_response`): ``|G(k sigma) - G(sigma)|`` of the unit image at the
        keypoint's subpixel position, with ``k = 2 ** (1 / n_scales)``. This is the quantity
        scikit-image compares with ``c_dog`` (there on its resampled octaves), in the same
        units.
    octave
        ``SIFT.octaves - log2(upsampling)``, OpenCV's numbering: 0 is the input resolution,
        -1 the 2x upsampled seed image.
    descriptors
        ``SIFT.descriptors`` (uint8, ``n_hist**2 * n_ori`` wide) as float32, norm ``L2``.

    An image narrower than ``12 / upsampling`` pixels (scikit-image's smallest octave) or
    without contrast gives no keypoints.
    """

    upsampling: Literal[1, 2, 4] = param(2, doc="upscale the image by 1, 2 or 4 before detection")
    n_octaves: int = param(8, doc="maximum number of octaves (reduced to keep 12 px at the coarsest)", ge=1,
                           le=16)
    n_scales: int = param(3, doc="scales per octave", ge=1, le=16)
    sigma_min: float = param(1.6, doc="blur of the seed image, upsampled pixels (must be >= sigma_in * upsampling)",
                             gt=0, le=16)
    sigma_in: float = param(0.5, doc="assumed blur of the input image, px", ge=0, le=16)
    c_dog: float = param(0.04 / 3, doc="DoG contrast threshold, unit-image intensity (rescaled by skimage "
                                       "when n_scales != 3)", ge=0, le=1)
    c_edge: float = param(10.0, doc="edgeness threshold (ratio of principal curvatures)", gt=0, le=1000)
    n_bins: int = param(36, doc="bins of the orientation histogram", ge=8, le=360)
    lambda_ori: float = param(1.5, doc="orientation window: Gaussian weight of std lambda_ori * sigma", gt=0, le=16)
    c_max: float = param(0.8, doc="secondary orientation peaks above c_max * highest make extra keypoints", gt=0, le=1)
    lambda_descr: float = param(6.0, doc="descriptor window: Gaussian weight of std lambda_descr * sigma", gt=0, le=64)
    n_hist: int = param(4, doc="descriptor grid is n_hist x n_hist histograms", ge=1, le=16)
    n_ori: int = param(8, doc="orientation bins per descriptor histogram", ge=1, le=64)

    def __post_init__(self) -> None:
        super().__post_init__()
        # skimage blurs the seed by sqrt((sigma_min / upsampling)^2 - sigma_in^2): NaN otherwise.
        if self.sigma_min < self.sigma_in * self.upsampling:
            raise ConfigError(
                f"{type(self).__name__}.sigma_min: must be >= sigma_in * upsampling "
                f"({self.sigma_in:g} * {self.upsampling} = {self.sigma_in * self.upsampling:g}), got {self.sigma_min!r}")

    @property
    def descriptor_width(self) -> int:
        """Floats per descriptor, ``n_hist**2 * n_ori``."""
        return self.n_hist**2 * self.n_ori

    def detect(self, image: np.ndarray) -> Features:
        """Detect SIFT keypoints and compute their descriptors.

        Parameters
        ----------
        image : ndarray of shape (rows, cols)
            Integer or float image; mapped to [0, 1] by its own min and max.

        Returns
        -------
        Features
            float32 descriptors with norm ``L2``; empty if nothing is found.

        Raises
        ------
        ctpipe.errors.InputError
            If ``image`` is not a usable 2-D picture.
        """
        unit = to_unit_float(image)
        if unit is None or min(unit.shape) * self.upsampling < _SIFT_MIN_OCTAVE_SIZE:
            return _empty(self.descriptor_width, "L2")
        sift = SIFT(**self.params())
        try:
            sift.detect_and_extract(unit)
        except RuntimeError as exc:
            if _found_nothing(exc):
                return _empty(self.descriptor_width, "L2")
            raise
        rc = sift.positions + (0.5 / self.upsampling - 0.5)
        sigmas = np.asarray(sift.sigmas, dtype=np.float64)
        return Features.build(
            xy=rc[:, ::-1],
            size=2.0 * sigmas,
            # skimage centres orientation bin m at m * width but reads peaks as (m + 0.5) * width.
            angle_deg=_degrees(np.pi / 2 - (np.asarray(sift.orientations) - np.pi / self.n_bins)),
            response=_dog_response(unit, rc, sigmas, 2.0 ** (1.0 / self.n_scales), self.sigma_in),
            octave=np.asarray(sift.octaves) - int(math.log2(self.upsampling)),
            descriptors=np.asarray(sift.descriptors, dtype=np.float32),
            norm="L2",
        )


def _pyramid_shapes(shape: tuple[int, int], downscale: float, n_levels: int) -> np.ndarray:
    """(rows, cols) of every level of ``skimage.transform.pyramid_gaussian``, shape (n_levels, 2)."""
    shapes = [tuple(shape)]
    for _ in range(n_levels - 1):
        shapes.append(tuple(math.ceil(d / float(downscale)) for d in shapes[-1]))
    return np.array(shapes, dtype=np.float64)


@dataclass(frozen=True)
class SkimageOrbDetector(Detector):
    """ORB: oriented FAST keypoints with rotated BRIEF binary descriptors (scikit-image).

    Wraps :class:`skimage.feature.ORB`; the parameters are its own, with its defaults.
    The image is first mapped to float64 in [0, 1] by :func:`to_unit_float`, so
    ``fast_threshold`` is a fraction of the image's contrast.

    Returned :class:`~ctpipe.data.Features`:

    xy
        The pyramid-level pixel ``p`` of each keypoint mapped to the input image as
        ``(p + 0.5) * shape_0 / shape_level - 0.5`` per axis, which is how
        ``skimage.transform.resize`` samples. (``ORB.keypoints`` is ``p * downscale**level``,
        off by up to a few pixels on coarse levels because level shapes are rounded up.)
    size
        ``31 * ORB.scales``: the side of the 31 x 31 rBRIEF patch at the keypoint's level,
        OpenCV's ORB ``size`` with its default ``patchSize``.
    angle_deg
        ``ORB.orientations`` (intensity centroid, from +x towards +y) in degrees.
    response
        ``ORB.responses``, the Harris corner measure at the keypoint.
    octave
        The pyramid level, ``log(scale) / log(downscale)``.
    descriptors
        The 256 boolean tests packed with ``np.packbits(axis=1)`` to uint8 (N, 32), norm
        ``HAMMING``.

    An image narrower than 7 pixels (the FAST circle) or without contrast gives no keypoints.
    """

    n_keypoints: int = param(500, doc="keep the n keypoints of highest Harris response", ge=1,
                                 le=1_000_000)
    fast_n: int = param(9, doc="contiguous FAST circle pixels (of 16) that must differ", ge=1, le=16)
    fast_threshold: float = param(0.08, doc="FAST intensity threshold, fraction of the image contrast", ge=0, le=1)
    harris_k: float = param(0.04, doc="Harris sensitivity k (corners ranked by det - k trace^2)", ge=0, le=0.25)
    downscale: float = param(1.2, doc="pyramid downscale factor", gt=1, le=4)
    n_scales: int = param(8, doc="pyramid levels", ge=1, le=32)

    def detect(self, image: np.ndarray) -> Features:
        """Detect oriented FAST keypoints and compute their rBRIEF descriptors.

        Parameters
        ----------
        image : ndarray of shape (rows, cols)
            Integer or float image; mapped to [0, 1] by its own min and max.

        Returns
        -------
        Features
            Packed uint8 descriptors (N, 32) with norm ``HAMMING``; empty if nothing is found.

        Raises
        ------
        ctpipe.errors.InputError
            If ``image`` is not a usable 2-D picture.
        """
        unit = to_unit_float(image)
        width = 256 // 8
        # skimage's ORB squeezes its input, so a single-row image would stop being 2-D.
        if unit is None or min(unit.shape) < _FAST_DIAMETER:
            return _empty(width, "HAMMING")
        orb = ORB(**self.params())
        try:
            orb.detect_and_extract(unit)
        except RuntimeError as exc:
            if _found_nothing(exc):
                return _empty(width, "HAMMING")
            raise
        if len(orb.keypoints) == 0:
            return _empty(width, "HAMMING")
        scales = np.asarray(orb.scales, dtype=np.float64)
        level = np.rint(np.log(scales) / math.log(self.downscale)).astype(np.int64)
        level_rc = np.rint(np.asarray(orb.keypoints, dtype=np.float64) / scales[:, None])
        shapes = _pyramid_shapes(unit.shape, self.downscale, self.n_scales)
        rc = (level_rc + 0.5) * (shapes[0] / shapes[level]) - 0.5
        return Features.build(
            xy=rc[:, ::-1],
            size=ORB_PATCH_SIZE * scales,
            angle_deg=_degrees(orb.orientations),
            response=orb.responses,
            octave=level,
            descriptors=np.packbits(np.asarray(orb.descriptors, dtype=bool), axis=1),
            norm="HAMMING",
        )


#: Largest ``max_scale`` each CENSURE filter has sizes for in scikit-image (DoB: any).
_CENSURE_MAX_SCALE = {"Octagon": 11, "STAR": 12}


def _dob_response(image: np.ndarray, rc: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """|Difference of boxes| of ``image`` at integer keypoints ``rc`` and CENSURE scales ``n``.

    Mean of the ring between the (4n+1)^2 and the (2n+1)^2 box minus the mean of the inner box,
    from an integral image with mirrored borders: CENSURE's DoB filter, zero on flat regions.
    """
    if len(rc) == 0:
        return np.zeros(0)
    pad = 2 * int(scales.max()) + 1
    padded = np.pad(image, pad, mode="symmetric")
    integral = np.zeros((padded.shape[0] + 1, padded.shape[1] + 1))
    integral[1:, 1:] = padded.cumsum(axis=0).cumsum(axis=1)
    rows = rc[:, 0].astype(np.int64) + pad
    cols = rc[:, 1].astype(np.int64) + pad

    def box_sum(half: np.ndarray) -> np.ndarray:
        r0, r1, c0, c1 = rows - half, rows + half + 1, cols - half, cols + half + 1
        return integral[r1, c1] - integral[r0, c1] - integral[r1, c0] + integral[r0, c0]

    inner, outer = box_sum(scales), box_sum(2 * scales)
    inner_mean = inner / (2 * scales + 1) ** 2
    ring_mean = (outer - inner) / (12 * scales**2 + 4 * scales)
    return np.abs(ring_mean - inner_mean)


@dataclass(frozen=True)
class SkimageCensureDetector(Detector):
    """CENSURE keypoints with BRIEF binary descriptors (scikit-image).

    Wraps :class:`skimage.feature.CENSURE` (``min_scale``, ``max_scale``, ``mode``,
    ``non_max_threshold``, ``line_threshold``) and :class:`skimage.feature.BRIEF`
    (``descriptor_size``, ``patch_size``, ``brief_mode`` -- BRIEF's ``mode`` --, ``sigma``, and
    ``seed`` passed as BRIEF's ``rng``), with their defaults. The image is first mapped to
    float64 in [0, 1] by :func:`to_unit_float`.

    scikit-image's CENSURE only keeps extrema whose filter response is positive, i.e. dark blobs
    on a brighter surround. ``polarity`` chooses which blobs to find: ``"both"`` (the
    default, as in the CENSURE paper and OpenCV's STAR) also runs it on the inverted image,
    whose response is exactly the negated one.

    Returned :class:`~ctpipe.data.Features`:

    xy
        ``CENSURE.keypoints`` (integer row, col) as (col, row).
    size
        ``4 n + 1`` for CENSURE scale ``n``: the side of the outer box of the DoB filter (the
        Octagon and STAR filters of the same scale are about as wide).
    angle_deg
        NaN: neither CENSURE nor BRIEF assigns an orientation.
    response
        CENSURE keeps its filter response internal, so it is recomputed as the absolute
        difference-of-boxes response at the keypoint's scale (:func:`_dob_response`): exactly
        CENSURE's own for ``mode="DoB"``, a box approximation of the Octagon or STAR filter
        otherwise.
    octave
        0 (CENSURE filters the full-resolution image at every scale).
    class_id
        -1.
    descriptors
        BRIEF's ``descriptor_size`` boolean tests packed to uint8 (N, descriptor_size / 8), norm
        ``HAMMING``. BRIEF drops keypoints closer than ``patch_size // 2`` to the border;
        only keypoints that have a descriptor are returned.

    The sampling pattern depends only on ``seed``, so all views share it; descriptors from
    different seeds cannot be matched.
    """

    min_scale: int = param(1, doc="smallest CENSURE filter scale (keypoints start at min_scale + 1)", ge=1,
                           le=32)
    max_scale: int = param(7, doc="largest CENSURE filter scale (keypoints end at max_scale - 1)", ge=3,
                           le=64)
    mode: Literal["DoB", "Octagon", "STAR"] = param("DoB", doc="bi-level filter shape")
    non_max_threshold: float = param(0.15, doc="minimum filter response, unit-image intensity", ge=0,
                                     le=1000)
    line_threshold: float = param(10.0, doc="reject points whose ratio of principal curvatures exceeds this", gt=0,
                                    le=1000)
    polarity: Literal["both", "dark", "bright"] = param("both", doc="blobs to find: dark, bright or both")
    descriptor_size: Literal[128, 256, 512] = param(256, doc="BRIEF bits per descriptor")
    patch_size: int = param(49, doc="BRIEF patch side, px (keypoints within patch_size // 2 of the border dropped)",
                            ge=5, le=1024)
    brief_mode: Literal["normal", "uniform"] = param("normal", doc="BRIEF sampling distribution of the test pairs")
    sigma: float = param(1.0, doc="Gaussian blur before the BRIEF tests, px", ge=0, le=16)
    seed: int = param(1, doc="seed of BRIEF's sampling pattern (must be equal for views to match)", ge=0,
                     le=2**32 - 1)

    def __post_init__(self) -> None:
        super().__post_init__()
        name = type(self).__name__
        if self.max_scale - self.min_scale < 2:
            raise ConfigError(f"{name}.max_scale: must be >= min_scale + 2 = {self.min_scale + 2} "
                              f"(CENSURE needs three scales), got {self.max_scale!r}")
        limit = _CENSURE_MAX_SCALE.get(self.mode)
        if limit is not None and self.max_scale > limit:
            raise ConfigError(f"{name}.max_scale: must be <= {limit} for mode {self.mode!r}, got {self.max_scale!r}")

    def _censure(self, unit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) keypoints and scales of the requested polarity."""
        images = {"dark": (unit,), "bright": (1.0 - unit,), "both": (unit, 1.0 - unit)}[self.polarity]
        keypoints, scales = [np.zeros((0, 2), dtype=np.int64)], [np.zeros(0, dtype=np.int64)]
        for picture in images:
            censure = CENSURE(min_scale=self.min_scale, max_scale=self.max_scale, mode=self.mode,
                              non_max_threshold=self.non_max_threshold, line_threshold=self.line_threshold)
            censure.detect(picture)
            keypoints.append(np.asarray(censure.keypoints, dtype=np.int64).reshape(-1, 2))
            scales.append(np.asarray(censure.scales, dtype=np.int64).reshape(-1))
        return np.concatenate(keypoints), np.concatenate(scales)

    def detect(self, image: np.ndarray) -> Features:
        """Detect CENSURE keypoints and compute their BRIEF descriptors.

        Parameters
        ----------
        image : ndarray of shape (rows, cols)
            Integer or float image; mapped to [0, 1] by its own min and max.

        Returns
        -------
        Features
            Packed uint8 descriptors (N, descriptor_size / 8) with norm ``HAMMING``; empty if
            nothing is found.

        Raises
        ------
        ctpipe.errors.InputError
            If ``image`` is not a usable 2-D picture.
        """
        unit = to_unit_float(image)
        width = self.descriptor_size // 8
        # BRIEF keeps rows and cols in [patch_size // 2, shape - patch_size // 2]: none fit here.
        if unit is None or min(unit.shape) < 2 * (self.patch_size // 2):
            return _empty(width, "HAMMING")
        keypoints, scales = self._censure(unit)
        brief = BRIEF(descriptor_size=self.descriptor_size, patch_size=self.patch_size, mode=self.brief_mode,
                      sigma=self.sigma, rng=self.seed)
        brief.extract(unit, keypoints)
        keep = np.asarray(brief.mask, dtype=bool)
        keypoints, scales = keypoints[keep], scales[keep]
        descriptors = np.asarray(brief.descriptors, dtype=bool).reshape(len(keypoints), self.descriptor_size)
        return Features.build(
            xy=keypoints[:, ::-1],
            size=4 * scales + 1,
            angle_deg=np.full(len(keypoints), np.nan),
            response=_dob_response(unit, keypoints, scales),
            descriptors=np.packbits(descriptors, axis=1),
            norm="HAMMING",
        )


@hookimpl
def ctpipe_register_stages(registry) -> None:
    """Register the scikit-image detectors.

    Parameters
    ----------
    registry : ctpipe.registry.StageRegistrar
        The registrar ctpipe hands to this plugin.
    """
    registry.add_detector("skimage-sift", SkimageSiftDetector)
    registry.add_detector("skimage-orb", SkimageOrbDetector)
    registry.add_detector("skimage-censure", SkimageCensureDetector)
