"""Frozen containers passed between pipeline stages.

Arrays inside are never modified by a stage; a stage returns new containers.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ctpipe.errors import InputError
from ctpipe.geometry import Geometry
from ctpipe.model import FailedEstimation

__all__ = ["Features", "Matches", "PairEstimate", "ScanObservations", "ScanSolution", "DESCRIPTOR_NORMS"]

#: Norms a matcher may be asked to use, named as OpenCV names them (``NORM_L2`` ...).
DESCRIPTOR_NORMS = ("L2", "L1", "HAMMING", "HAMMING2")


@dataclass(frozen=True, eq=False)
class Features:
    """Keypoints and descriptors of one image.

    Keypoints are ordered by ``response``, strongest first (ties: smaller y, then smaller x),
    whichever detector made them.

    Attributes
    ----------
    xy : ndarray of shape (N, 2), float32
        Position (x=col, y=row) in pixels, OpenCV's convention (pixel centres at integers).
    size : ndarray of shape (N,), float32
        Diameter of the meaningful neighbourhood, pixels.
    angle_deg : ndarray of shape (N,), float32
        Orientation in degrees in [0, 360); NaN where the detector assigns none.
    response : ndarray of shape (N,), float32
        Detector strength.
    octave : ndarray of shape (N,), int32
        Pyramid octave the keypoint was found in (0 where not applicable).
    class_id : ndarray of shape (N,), int32
        Detector-specific class (SURF: sign of the Hessian trace); -1 where not applicable.
    descriptors : ndarray of shape (N, D)
        For ``L2``/``L1`` norms float32, or uint8 when every value is a whole number from 0
        to 255 (SIFT's are: the same distances in a quarter of the memory, which at 2,000 views
        of 1,600 keypoints is 1.2 GB less); packed uint8 bits for ``HAMMING``/``HAMMING2``.
        Matchers compare float and uint8 descriptors of one norm alike.
    norm : str
        Distance the descriptors are compared with, one of ``DESCRIPTOR_NORMS``.
    clipped_side : ndarray of shape (N, 2), float32, or None
        For discs whose rim a clipped background cuts (the ``beads`` detector): the mean, over
        the rays cast from the disc's centre, of the outward direction (x, y) of those whose
        outside is the clip's plateau; 0 where none or all are, or where the disc does not cross the clip's edge
        (not flagged 3) or was placed inside the cut. The fitted centre of a rim cut
        ``d`` px deep there is pulled by about ``-2 d`` times it
        (:func:`ctpipe.solve.balls.calibrate_balls` fits ``d`` per ball). None for other detectors.
    centre_edge_px : ndarray of shape (N,), float32, or None
        For discs (the ``beads`` detector's rim method): the radius (px) of the circle whose centre ``xy`` is, the
        outer rim's (``size / 2``) or, for a hollow or coated ball, its shell's inner edge, which a clip, a holder
        or a neighbour beyond the rim does not move (:mod:`ctpipe.features.ball_edges`). The calibration models the
        projected centre of a sphere of that radius. None for other detectors.
    centre_se_px : ndarray of shape (N,), float32, or None
        For discs (the ``beads`` detector's rim method): the standard error (px) of the centre from the edge that
        placed it, which grows as less of that edge is seen (a neighbour, the clip); NaN where no edge placed it.
        The calibration weighs each disc by it against its ball's other discs. None for other detectors.
    """

    xy: np.ndarray
    size: np.ndarray
    angle_deg: np.ndarray
    response: np.ndarray
    octave: np.ndarray
    class_id: np.ndarray
    descriptors: np.ndarray
    norm: str
    clipped_side: np.ndarray | None = None
    centre_edge_px: np.ndarray | None = None
    centre_se_px: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.xy)
        if self.xy.shape != (n, 2):
            raise InputError(f"Features.xy must have shape (N, 2), got {self.xy.shape}")
        for name in ("size", "angle_deg", "response", "octave", "class_id"):
            if getattr(self, name).shape != (n,):
                raise InputError(f"Features.{name} must have shape ({n},), got {getattr(self, name).shape}")
        if self.descriptors.ndim != 2 or len(self.descriptors) != n:
            raise InputError(f"Features.descriptors must have shape ({n}, D), got {self.descriptors.shape}")
        if self.norm not in DESCRIPTOR_NORMS:
            raise InputError(f"Features.norm must be one of {', '.join(DESCRIPTOR_NORMS)}, got {self.norm!r}")
        binary = self.norm.startswith("HAMMING")
        if binary and self.descriptors.dtype != np.uint8:
            raise InputError(f"Features with norm {self.norm} need uint8 descriptors, got {self.descriptors.dtype}")
        if not binary and self.descriptors.dtype not in (np.float32, np.uint8):
            raise InputError(f"Features with norm {self.norm} need float32 (or whole-number uint8) descriptors, "
                             f"got {self.descriptors.dtype}")
        if self.clipped_side is not None and self.clipped_side.shape != (n, 2):
            raise InputError(f"Features.clipped_side must have shape ({n}, 2), got {self.clipped_side.shape}")
        for name in ("centre_edge_px", "centre_se_px"):
            array = getattr(self, name)
            if array is not None and array.shape != (n,):
                raise InputError(f"Features.{name} must have shape ({n},), got {array.shape}")
        for array in (self.xy, self.size, self.angle_deg, self.response, self.octave, self.class_id, self.descriptors,
                      self.clipped_side, self.centre_edge_px, self.centre_se_px):
            if array is not None:
                array.flags.writeable = False

    def __len__(self) -> int:
        return len(self.xy)

    @property
    def has_descriptors(self) -> bool:
        """False for features whose descriptors were dropped (:meth:`without_descriptors`)."""
        return self.descriptors.shape[1] > 0 or len(self) == 0

    def without_descriptors(self) -> "Features":
        """The same keypoints with descriptors of width 0: what is kept once the pairs are matched.

        Matchers refuse such features (:class:`~ctpipe.errors.InputError`); keypoints, their
        positions and counts are all a refiner that does not compare descriptors reads.
        """
        return dataclasses.replace(self, descriptors=np.empty((len(self), 0), dtype=self.descriptors.dtype))

    @classmethod
    def build(cls, *, xy, size, angle_deg, response, octave=None, class_id=None, descriptors, norm,
              clipped_side=None, centre_edge_px=None, centre_se_px=None) -> "Features":
        """Normalise dtypes and apply the ordering rule; detectors construct through this."""
        xy = np.asarray(xy, dtype=np.float32).reshape(-1, 2)
        n = len(xy)
        response = np.asarray(response, dtype=np.float32).reshape(n)
        order = np.lexsort((xy[:, 0], xy[:, 1], -response)) if n else np.arange(0)
        descriptors = np.asarray(descriptors)
        if n == 0:
            descriptors = descriptors.reshape(0, descriptors.shape[1] if descriptors.ndim == 2 else 0)
        dtype = np.uint8 if norm.startswith("HAMMING") or descriptors.dtype == np.uint8 else np.float32

        def per_disc(values):
            """An optional float32 value per feature, in the features' order."""
            return None if values is None else np.asarray(values, dtype=np.float32).reshape(n)[order]

        return cls(
            xy=np.ascontiguousarray(xy[order]),
            size=np.asarray(size, dtype=np.float32).reshape(n)[order],
            angle_deg=np.asarray(angle_deg, dtype=np.float32).reshape(n)[order],
            response=response[order],
            octave=(np.zeros(n) if octave is None else np.asarray(octave)).astype(np.int32).reshape(n)[order],
            class_id=(np.full(n, -1) if class_id is None else np.asarray(class_id)).astype(np.int32).reshape(n)[order],
            descriptors=np.ascontiguousarray(descriptors[order].astype(dtype, copy=False)),
            norm=norm,
            clipped_side=(None if clipped_side is None else
                          np.ascontiguousarray(np.asarray(clipped_side, dtype=np.float32).reshape(n, 2)[order])),
            centre_edge_px=per_disc(centre_edge_px),
            centre_se_px=per_disc(centre_se_px),
        )


@dataclass(frozen=True, eq=False)
class Matches:
    """Putative correspondences between two feature sets.

    Attributes
    ----------
    index_ab : ndarray of shape (M, 2), int64
        Row ``k`` pairs keypoint ``index_ab[k, 0]`` of the first view with ``index_ab[k, 1]``
        of the second.
    distance : ndarray of shape (M,), float32
        Descriptor distance of each match.
    """

    index_ab: np.ndarray
    distance: np.ndarray

    def __len__(self) -> int:
        return len(self.index_ab)


@dataclass(frozen=True, eq=False)
class PairEstimate:
    """An estimator's answer for one view pair.

    Attributes
    ----------
    angle_rad : float
        Turntable angle from the first to the second view.
    inlier_mask : ndarray of shape (M,), bool
        Which correspondences support the angle.
    residual : float
        RMS Sampson distance of the inliers, normalised units.
    """

    angle_rad: float
    inlier_mask: np.ndarray
    residual: float

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inlier_mask))

    @property
    def angle_deg(self) -> float:
        return float(np.rad2deg(self.angle_rad))


@dataclass(frozen=True, eq=False)
class ScanObservations:
    """Everything a refiner sees: the whole scan, not one pair.

    Attributes
    ----------
    geometry : Geometry
    n_views : int
    features : tuple of Features, one per view
        Without descriptors (:meth:`Features.without_descriptors`) where the pipeline's refiner
        does not read them.
    pairs : ndarray of shape (P, 2), int64
        View indices ``(i, j)`` of each estimated pair.
    matches : tuple of Matches, one per pair
    points_a, points_b : tuple of ndarray of shape (M_k, 2)
        Normalised coordinates of each pair's matches in its first and second view.
    estimates : tuple of PairEstimate or FailedEstimation, one per pair
    nominal_angles_deg : ndarray of shape (V,), float64, or None
        The angles the stage was commanded to (a starting point, and what tells a full turn,
        whose seam pairs close the loop); None when unknown.
    projections : ndarray of shape (V, rows, cols) or None
        The images the features came from, for refiners that work on pixels (projection
        matching); never modified.
    timings_s : dict
        Seconds spent detecting, matching and estimating.
    static_background_removed : bool
        Whether features were detected on the views less the scan's static part.
    detect_binning : int
        The binning of the views the features were detected on (keypoints are in the full
        views' pixels either way; see ``Pipeline.detect_binning``).
    """

    geometry: Geometry
    n_views: int
    features: tuple[Features, ...]
    pairs: np.ndarray
    matches: tuple[Matches, ...]
    points_a: tuple[np.ndarray, ...]
    points_b: tuple[np.ndarray, ...]
    estimates: tuple[PairEstimate | FailedEstimation, ...]
    nominal_angles_deg: np.ndarray | None = None
    projections: np.ndarray | None = None
    timings_s: dict[str, float] = field(default_factory=dict)
    static_background_removed: bool = False
    detect_binning: int = 1


@dataclass(frozen=True, eq=False)
class ScanSolution:
    """A refiner's answer for the whole scan.

    Attributes
    ----------
    angles_rad : ndarray of shape (V,)
        Angle of every view relative to view 0 (``angles_rad[0] == 0``); NaN for views not
        connected to view 0 by successful pairs.
    pair_estimates : tuple of PairEstimate or FailedEstimation, one per pair
        The (refined) per-pair answers.
    info : dict
        What the refiner wants a user to see (counts, costs, iterations): plain JSON values.
    u0_px, v0_px : float or None
        The detector's principal point (``u0_px``: the centre of rotation's column) where the
        refiner estimated it; None where it kept the input geometry's.
    tilt_deg : float or None
        The detector's in-plane tilt, degrees, where the refiner estimated it; None otherwise.
    angle_se_deg : ndarray of shape (V,) or None
        Standard error of every view's angle, degrees, where the refiner can tell (e.g. the
        curvature of projection matching's fit); None otherwise.
    view_shifts_px : ndarray of shape (V, 2) or None
        Each view's own shift of the projection ``(du, dv)`` in pixels (a drifting source spot or
        detector: the view's principal point is ``(u0_px + du, v0_px + dv)``), where the refiner
        estimated it; None otherwise.
    source_to_detector_mm : float or None
        The source-to-detector distance, where the refiner estimated it (at the input geometry's source-to-object
        distance: the ball calibration); None otherwise.
    axis_offset_mm : float or None
        How far the rotation axis lies off the source's perpendicular to the detector, along the columns, at the axis
        (mm), where the refiner estimated it; ``(u0_px, v0_px)`` is then where the axis's point level with the source
        projects (:func:`ctpipe.solve.balls.ellipse_centres`). None otherwise.
    drift_spot_share : float or None
        How much of :attr:`view_shifts_px` the source spot made (0: the detector moved, 1: the spot did), where the
        refiner told them apart (the ball calibration, by the parallax across its balls' depths); None: the
        detector's.
    """

    angles_rad: np.ndarray
    pair_estimates: tuple[PairEstimate | FailedEstimation, ...]
    info: dict[str, Any] = field(default_factory=dict)
    u0_px: float | None = None
    v0_px: float | None = None
    tilt_deg: float | None = None
    angle_se_deg: np.ndarray | None = None
    view_shifts_px: np.ndarray | None = None
    source_to_detector_mm: float | None = None
    axis_offset_mm: float | None = None
    drift_spot_share: float | None = None
