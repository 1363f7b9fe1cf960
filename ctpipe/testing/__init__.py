"""What tests and benchmarks share: stage conformance checks and a closed-form reference phantom.

Conformance checks every stage must pass; third-party plugins can run them in their tests:

>>> from ctpipe.testing import check_stage
>>> check_stage(MyDetector())          # raises AssertionError with what broke

:func:`render_balls` renders projections of calibration balls (sub-pixel centres and radii
known exactly) with detector blur and photon noise, for the ``beads`` detector.

The ellipsoid phantom (:data:`ELLIPSOIDS`) has exact line integrals in closed form
(:func:`project_ellipsoids`, numpy only, independent of ctpipe's projectors) and an exact
voxel density (:func:`phantom_volume`): the reference FDK and the projectors are tested and
benchmarked against.

Ball phantoms (``ball-bar``, ``bead-cloud-*``): :func:`phantom_spheres` lists their balls and
:func:`overlapping_spheres` says, view by view, which pairs of balls overlap on the detector.

Vendor scans, written as the scanners leave them, for the readers of :mod:`ctpipe.io` to be
tested and benchmarked on: :func:`write_nikon` (Nikon / X-Tek, module
:mod:`ctpipe.testing.nikon`), :func:`write_zeiss` (Zeiss Xradia ``.txrm``,
:mod:`ctpipe.testing.zeiss`, an OLE compound file written by :func:`write_compound_file` of
:mod:`ctpipe.testing.ole`), :func:`write_bruker` (Bruker SkyScan, :mod:`ctpipe.testing.bruker`)
and :func:`write_waygate` (GE / Waygate datos|x, :mod:`ctpipe.testing.waygate`). Each takes a
geometry, the nominal and recorded angles and raw counts with flats and darks. They are
imported on first use, so importing ``ctpipe.testing`` imports no scan format. The corrected
angle logs ``ctpipe estimate`` writes for users stay with their readers
(``ctpipe.io.nikon.write_nikon_angles``, ``ctpipe.io.waygate.write_waygate_angles``).
"""

from __future__ import annotations

from ctpipe._shared.lazy import lazy_exports

import numpy as np
from scipy import ndimage

from ctpipe.data import Features, Matches, PairEstimate, ScanObservations, ScanSolution
from ctpipe.errors import InputError
from ctpipe.evaluate.synthetic import make_correspondences
from ctpipe.geometry import Geometry
from ctpipe.model import FailedEstimation, rotation_matrix
from ctpipe.recon.volume import VolumeGrid
from ctpipe.stages import Detector, Estimator, Matcher, Refiner, Stage

__all__ = ["check_stage", "check_detector", "check_matcher", "check_estimator", "check_refiner", "check_pickles", "textured_image",
           "render_balls", "ELLIPSOIDS", "MARGIN_MM", "project_ellipsoids", "phantom_volume", "relative_rmse",
           "phantom_spheres", "overlapping_spheres",
           "write_nikon", "write_zeiss", "write_bruker", "write_waygate", "write_compound_file"]

#: The vendor scan writers, name -> the module of ctpipe.testing that defines it (imported on first use).
_WRITERS = {"write_nikon": "nikon", "write_zeiss": "zeiss", "write_bruker": "bruker", "write_waygate": "waygate",
            "write_compound_file": "ole"}


__getattr__, __dir__ = lazy_exports(__name__, _WRITERS)


def textured_image(shape: tuple[int, int] = (256, 256), seed: int = 0) -> np.ndarray:
    """A deterministic float32 image of overlapping blobs and edges, rich in keypoints."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float32)
    image = np.zeros(shape, np.float32)
    for _ in range(60):
        r0, c0 = rng.uniform(0, shape[0]), rng.uniform(0, shape[1])
        radius = rng.uniform(3, 14)
        image += rng.uniform(0.3, 1.0) * (((rows - r0) ** 2 + (cols - c0) ** 2) < radius ** 2)
    return image


def render_balls(shape: tuple[int, int], centres_xy, radii_px, *, peak=1.0, blur_sigma_px: float = 0.7,
                 photons: float | None = None, intensities: bool = False, background=0.0,
                 rng: np.random.Generator | int | None = None, supersample: int = 5) -> np.ndarray:
    """Projections of balls: chord profiles ``peak sqrt(1 - d^2 / r^2)``, blurred and pixel-integrated.

    The sharp line integrals (balls plus ``background``) are sampled on a grid ``supersample``
    times finer than the pixels; photons are attenuated as ``exp(-p)`` there (where balls
    overlap their line integrals add, so their transmissions multiply), blurred by a Gaussian
    detector PSF and averaged over each pixel, then counted.

    Parameters
    ----------
    shape : (rows, cols)
    centres_xy : array_like of shape (N, 2)
        Ball centres (x=col, y=row) in pixels, pixel centres at integers.
    radii_px : array_like of shape (N,) or float
        Projected ball radii, pixels.
    peak : array_like of shape (N,) or float
        Line integral through each ball's centre (``2 r mu``), dimensionless.
    blur_sigma_px : float
        Standard deviation of the Gaussian detector PSF, pixels (0: pixel integration only).
    photons : float or None
        Unattenuated photons per pixel; None for no noise.
    intensities : bool
        Return transmitted photons (``photons`` or 1 per unattenuated pixel) rather than line
        integrals ``-log(counts / photons)``.
    background : float or ndarray of shape ``shape``
        Line integral of everything else, added to the balls' before attenuation.
    rng : numpy.random.Generator, int or None
        Source of the Poisson noise.
    supersample : int
        Sub-samples per pixel along each axis.

    Returns
    -------
    ndarray of shape ``shape``, float64
        Line integrals, or transmitted counts when ``intensities``. Without noise and without
        ``intensities`` and ``photons`` the line integrals are blurred linearly (no ``exp``).
    """
    rows, cols = shape
    centres = np.asarray(centres_xy, dtype=np.float64).reshape(-1, 2)
    radii = np.broadcast_to(np.asarray(radii_px, dtype=np.float64), (len(centres),))
    peaks = np.broadcast_to(np.asarray(peak, dtype=np.float64), (len(centres),))
    ss = int(supersample)
    fine = np.zeros((rows * ss, cols * ss))
    for (cx, cy), radius, height in zip(centres, radii, peaks):
        # Fine sample k sits at (k + 1/2) / ss - 1/2 px; only the ball's bounding box is touched.
        x_lo = max(int(np.floor((cx - radius + 0.5) * ss)), 0)
        x_hi = min(int(np.ceil((cx + radius + 0.5) * ss)) + 1, cols * ss)
        y_lo = max(int(np.floor((cy - radius + 0.5) * ss)), 0)
        y_hi = min(int(np.ceil((cy + radius + 0.5) * ss)) + 1, rows * ss)
        if x_lo >= x_hi or y_lo >= y_hi:
            continue
        xs = (np.arange(x_lo, x_hi) + 0.5) / ss - 0.5
        ys = (np.arange(y_lo, y_hi) + 0.5) / ss - 0.5
        d2 = ((xs[None, :] - cx) ** 2 + (ys[:, None] - cy) ** 2) / radius**2
        fine[y_lo:y_hi, x_lo:x_hi] += height * np.sqrt(np.clip(1.0 - d2, 0.0, None))
    background = np.asarray(background, dtype=np.float64)
    if background.ndim == 2:
        background = np.repeat(np.repeat(background, ss, axis=0), ss, axis=1)
    fine += background
    attenuate = intensities or photons is not None
    if attenuate:
        fine = np.exp(-fine)
    if blur_sigma_px > 0:
        fine = ndimage.gaussian_filter(fine, blur_sigma_px * ss, mode="nearest", truncate=5.0)
    image = fine.reshape(rows, ss, cols, ss).mean(axis=(1, 3))
    if photons is None:
        return image
    counts = np.random.default_rng(rng).poisson(photons * image).astype(np.float64)
    if intensities:
        return counts
    return -np.log(np.maximum(counts, 0.5) / photons)


def _raises_input_error(call, what: str) -> None:
    try:
        call()
    except InputError:
        return
    raise AssertionError(f"{what} must raise ctpipe.errors.InputError")


def check_detector(detector: Detector) -> Features:
    """Shapes, dtypes, ordering, determinism, no mutation, and clear errors on bad images."""
    image = textured_image()
    before = image.copy()
    features = detector.detect(image)
    assert isinstance(features, Features), f"detect() must return Features, got {type(features).__name__}"
    assert np.array_equal(image, before), "detect() modified its input image"
    n = len(features)
    assert n > 0, "no keypoints on a textured test image"
    assert features.xy.dtype == np.float32 and features.xy.shape == (n, 2)
    assert np.all((features.xy >= -0.5) & (features.xy <= np.array(image.shape[::-1]) - 0.5)), "keypoint outside image"
    assert np.all(np.diff(features.response) <= 0), "keypoints must be ordered by response, strongest first"
    finite = np.isfinite(features.angle_deg)
    assert np.all((features.angle_deg[finite] >= 0) & (features.angle_deg[finite] < 360)), "angle_deg outside [0, 360)"
    again = detector.detect(image)
    assert np.array_equal(features.xy, again.xy) and np.array_equal(features.descriptors, again.descriptors), \
        "detect() is not deterministic"
    empty = detector.detect(np.zeros((64, 64), np.float32))
    assert isinstance(empty, Features) and len(empty) == 0 and empty.descriptors.ndim == 2
    _raises_input_error(lambda: detector.detect(np.zeros((8, 8, 3), np.float32)), "a 3-D image")
    _raises_input_error(lambda: detector.detect(np.full((32, 32), np.nan, np.float32)), "an image of NaN")
    _raises_input_error(lambda: detector.detect(np.zeros((0, 0), np.float32)), "an empty image")
    return features


def check_matcher(matcher: Matcher, features: Features | None = None) -> Matches:
    """Matching a feature set with itself pairs (almost) every keypoint with itself."""
    if features is None:
        from ctpipe.builtin.opencv_detectors import SiftDetector

        features = SiftDetector().detect(textured_image())
    matches = matcher.match(features, features)
    assert isinstance(matches, Matches)
    assert matches.index_ab.dtype == np.int64 and matches.index_ab.shape == (len(matches), 2)
    assert matches.distance.shape == (len(matches),)
    if len(matches):
        assert matches.index_ab.min() >= 0 and matches.index_ab.max() < len(features)
    # Every keypoint should find itself; a matcher that proposes several candidates per keypoint
    # (all-pairs, for identical objects) may propose others too.
    found = set(matches.index_ab[matches.index_ab[:, 0] == matches.index_ab[:, 1], 0].tolist())
    recall = len(found) / max(len(features), 1)
    assert recall > 0.9, f"only {recall:.0%} of keypoints are matched with themselves"
    return matches


def check_estimator(estimator: Estimator, *, tolerance_deg: float = 0.05) -> None:
    """Recovers +alpha as +alpha (and -alpha as -alpha), fails cleanly on no data."""
    for alpha_deg in (5.0, -5.0, 40.0):
        rng = np.random.default_rng(7)
        q_a, q_b, _ = make_correspondences(np.deg2rad(alpha_deg), rng, n_inliers=60, n_outliers=0, sigma=1e-6)
        before = (q_a.copy(), q_b.copy())
        result = estimator.estimate(q_a, q_b, rng=np.random.default_rng(0))
        assert np.array_equal(q_a, before[0]) and np.array_equal(q_b, before[1]), "estimate() modified its input"
        assert isinstance(result, PairEstimate), f"no estimate on clean data at {alpha_deg} deg: {result}"
        assert abs(result.angle_deg - alpha_deg) < tolerance_deg, \
            f"estimated {result.angle_deg:.4f} deg for a rotation of {alpha_deg} deg"
        assert result.inlier_mask.dtype == bool and result.inlier_mask.shape == (len(q_a),)
    failed = estimator.estimate(np.zeros((0, 2)), np.zeros((0, 2)), rng=np.random.default_rng(0))
    assert isinstance(failed, FailedEstimation) and not failed and str(failed), "no data must give a FailedEstimation"


def check_refiner(refiner: Refiner) -> ScanSolution:
    """Consecutive pair estimates of known angles chain into the right per-view angles."""
    geometry = Geometry(500.0, 1000.0, 256, 256, 0.4, 0.4)
    steps_deg = np.array([1.0, 1.5, -0.5, 2.0])
    truth = np.concatenate([[0.0], np.cumsum(steps_deg)])
    points_a, points_b, estimates, matches = [], [], [], []
    for k, step in enumerate(steps_deg):
        q_a, q_b, _ = make_correspondences(np.deg2rad(step), np.random.default_rng(k), n_inliers=40, n_outliers=0,
                                           sigma=0.0)
        points_a.append(q_a)
        points_b.append(q_b)
        estimates.append(PairEstimate(float(np.deg2rad(step)), np.ones(len(q_a), bool), 0.0))
        matches.append(Matches(np.stack([np.arange(len(q_a))] * 2, axis=1).astype(np.int64),
                               np.zeros(len(q_a), np.float32)))
    observations = ScanObservations(
        geometry=geometry, n_views=len(truth), features=(), pairs=np.stack([np.arange(4), np.arange(1, 5)], axis=1),
        matches=tuple(matches), points_a=tuple(points_a), points_b=tuple(points_b), estimates=tuple(estimates))
    solution = refiner.refine(observations, rng=np.random.default_rng(0))
    assert isinstance(solution, ScanSolution)
    assert solution.angles_rad.shape == (len(truth),) and solution.angles_rad[0] == 0.0
    np.testing.assert_allclose(np.rad2deg(solution.angles_rad), truth, atol=1e-6)
    return solution


def check_stage(stage: Stage) -> None:
    """Run the conformance check that fits the stage's kind, then :func:`check_pickles`."""
    checks = {"detector": check_detector, "matcher": check_matcher, "estimator": check_estimator,
              "refiner": check_refiner}
    checks[stage.kind](stage)
    check_pickles(stage)


def check_pickles(stage: Stage) -> None:
    """The stage survives ``pickle`` (as a Dask cluster ships it to its workers) and works the same after.

    Checked on a stage that has already run once, so a cache built on first use (an OpenCV
    object, a compiled kernel) must not break pickling either.
    """
    import pickle

    try:
        copy = pickle.loads(pickle.dumps(stage))
    except Exception as exc:
        raise AssertionError(f"{type(stage).__name__} does not pickle ({type(exc).__name__}: {exc}); a cluster "
                             f"ships stages to its workers by pickle") from exc
    assert type(copy) is type(stage), f"unpickled as {type(copy).__name__}, not {type(stage).__name__}"
    if stage.kind == "detector":
        image = textured_image()
        a, b = stage.detect(image), copy.detect(image)
        assert np.array_equal(a.xy, b.xy) and np.array_equal(a.descriptors, b.descriptors), \
            "the unpickled detector finds other keypoints"
    elif stage.kind == "matcher":
        from ctpipe.builtin.opencv_detectors import SiftDetector

        features = SiftDetector().detect(textured_image())
        assert np.array_equal(stage.match(features, features).index_ab, copy.match(features, features).index_ab), \
            "the unpickled matcher matches otherwise"
    elif stage.kind == "estimator":
        q_a, q_b, _ = make_correspondences(np.deg2rad(3.0), np.random.default_rng(3), n_inliers=40, n_outliers=10,
                                           sigma=1e-4)
        a = stage.estimate(q_a, q_b, rng=np.random.default_rng(1))
        b = copy.estimate(q_a, q_b, rng=np.random.default_rng(1))
        assert bool(a) == bool(b) and (not a or a.angle_rad == b.angle_rad), "the unpickled estimator answers otherwise"
    elif stage.kind == "refiner":
        np.testing.assert_array_equal(check_refiner(copy).angles_rad, check_refiner(stage).angles_rad,
                                      err_msg="the unpickled refiner answers otherwise")


# ---------------------------------------------------------------------------------------------
# Reference phantom

#: Distance from every ellipsoid surface beyond which :func:`phantom_volume`'s interior starts.
MARGIN_MM = 1.0


def _rot_y(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])


def _rot_x(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)], [0.0, np.sin(a), np.cos(a)]])


#: (centre_mm, semi-axes_mm, rotation, density_per_mm); densities add. Off-centre in z and tilted,
# so that a mirrored reconstruction (what negated angles give) is clearly wrong.
ELLIPSOIDS = [
    ((0.0, 0.0, 0.0), (14.0, 13.0, 13.0), np.eye(3), 0.02),
    ((-4.0, -3.0, 5.0), (4.0, 5.0, 3.0), _rot_y(30.0), 0.015),
    ((5.0, 4.0, -4.0), (3.5, 3.0, 5.0), _rot_x(20.0) @ _rot_y(-25.0), -0.01),
    ((2.0, -5.0, 6.0), (2.5, 2.5, 2.5), np.eye(3), 0.03),
]


def project_ellipsoids(geometry: Geometry, angles_deg, phantom=ELLIPSOIDS) -> np.ndarray:
    """Exact line integrals, float32 (V, rows, cols).

    In each view, the ray of pixel (col, row) leaves the source (camera origin) along
    ``d = ((col - u0) pu / SDD, (row - v0) pv / SDD, 1)``; the ellipsoid centred at ``c`` with
    axes ``A = R(theta) Q`` in the camera frame is ``|diag(1/a) A^T (X - c)| <= 1``. With
    ``X = t d`` that is a quadratic in ``t``; its root gap times ``|d|`` is the chord.
    """
    rows, cols = np.mgrid[0:geometry.detector_rows, 0:geometry.detector_cols].astype(np.float64)
    d = np.stack([(cols - geometry.u0_px) * geometry.pixel_pitch_u_mm / geometry.source_to_detector_mm,
                  (rows - geometry.v0_px) * geometry.pixel_pitch_v_mm / geometry.source_to_detector_mm,
                  np.ones_like(cols)], axis=-1).reshape(-1, 3)
    d_norm = np.linalg.norm(d, axis=1)
    out = np.zeros((len(angles_deg), geometry.detector_rows * geometry.detector_cols))
    for k, angle in enumerate(angles_deg):
        rot = rotation_matrix(np.deg2rad(angle))
        for centre, semi, q, density in phantom:
            axes = rot @ q
            c_cam = rot @ np.asarray(centre) + [0.0, 0.0, geometry.source_to_object_mm]
            p0 = (axes.T @ -c_cam) / np.asarray(semi)
            dl = (d @ axes) / np.asarray(semi)
            a = np.einsum("ij,ij->i", dl, dl)
            b = 2.0 * dl @ p0
            disc = b * b - 4.0 * a * (p0 @ p0 - 1.0)
            out[k] += density * d_norm * np.sqrt(np.clip(disc, 0.0, None)) / a
    return out.reshape(len(angles_deg), geometry.detector_rows, geometry.detector_cols).astype(np.float32)


def phantom_volume(grid: VolumeGrid, phantom=ELLIPSOIDS) -> tuple[np.ndarray, np.ndarray]:
    """Density at voxel centres (grid.shape) and the interior mask (``MARGIN_MM`` from every surface)."""
    y, z, x = np.meshgrid(grid.axis_mm("y"), grid.axis_mm("z"), grid.axis_mm("x"), indexing="ij")
    points = np.stack([x, y, z], axis=-1)
    volume = np.zeros(grid.shape)
    interior = np.ones(grid.shape, dtype=bool)
    for i, (centre, semi, q, density) in enumerate(phantom):
        local = ((points - centre) @ q) / np.asarray(semi)
        radius = np.linalg.norm(local, axis=-1)
        volume += density * (radius <= 1.0)
        # |grad radius| <= 1 / min(semi), so |1 - radius| min(semi) bounds the distance to the surface.
        interior &= np.abs(1.0 - radius) * min(semi) >= MARGIN_MM
        if i == 0:
            interior &= radius < 1.0
    return volume.astype(np.float32), interior


def relative_rmse(volume: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    err = volume[mask].astype(np.float64) - truth[mask]
    return float(np.sqrt(np.mean(err**2)) / np.sqrt(np.mean(truth[mask].astype(np.float64) ** 2)))


# ---------------------------------------------------------------------------------------------
# Ball phantoms


def phantom_spheres(phantom) -> tuple[np.ndarray, np.ndarray]:
    """The balls of a primitive phantom: its ellipsoids with three equal semi-axes and density > 0.

    Parameters
    ----------
    phantom : ctpipe.sim.phantoms.Phantom
        A primitive phantom (``sphere`` objects, or ``beads``; pores, of negative density, are left out).

    Returns
    -------
    centres_mm : ndarray of shape (N, 3)
        Object-frame ``(x, y, z)``, mm.
    radii_mm : ndarray of shape (N,)
    """
    from ctpipe.sim.primitives import KINDS

    p = phantom.primitives
    if p is None:
        raise InputError(f"phantom: {phantom.name!r} is a voxel phantom; spheres need a primitive one")
    half = p.half_size_mm
    round_ = (p.kind == KINDS.index("ellipsoid")) & np.all(np.isclose(half, half[:, :1]), axis=1)
    balls = round_ & (p.density_per_mm > 0)
    return p.centre_mm[balls].copy(), half[balls, 0].copy()


def overlapping_spheres(centres_mm, radii_mm, geometry: Geometry, angles_deg) -> list[np.ndarray]:
    """Per view, the pairs of balls whose images overlap on the detector.

    Two balls overlap in a view when their projected centres
    (:func:`ctpipe.solve.camera.project_points`) are closer on the detector than the sum of their
    projected radii, ``radius_mm x SDD / depth``; the depth is read off the projection itself (a
    point ``radius_mm`` below the centre lands ``radius_mm x SDD / depth`` lower on the detector).
    Distances are compared in mm on the detector, so non-square pixels count right.

    Parameters
    ----------
    centres_mm : ndarray of shape (N, 3)
    radii_mm : ndarray of shape (N,)
    geometry : Geometry
    angles_deg : ndarray of shape (V,)
        Turntable angles of the views, degrees.

    Returns
    -------
    list of V ndarrays of shape (K, 2), int64
        Ball index pairs ``(i, j)``, ``i < j``, overlapping in each view (K = 0 when none do).
    """
    from ctpipe.solve.camera import project_points

    centres = np.asarray(centres_mm, dtype=np.float64)
    radii = np.asarray(radii_mm, dtype=np.float64)
    angles = np.deg2rad(np.asarray(angles_deg, dtype=np.float64))
    if centres.ndim != 2 or centres.shape[1] != 3 or radii.shape != (len(centres),):
        raise InputError(f"centres_mm, radii_mm: must have shapes (N, 3) and (N,), got {centres.shape} and "
                         f"{radii.shape}")
    n = len(centres)
    pitch = np.array([geometry.pixel_pitch_u_mm, geometry.pixel_pitch_v_mm])
    below = centres + radii[:, None] * np.array([0.0, 1.0, 0.0])
    i, j = np.triu_indices(n, k=1)
    pairs = []
    for angle in angles:
        at = np.full(n, angle)
        centre_px = project_points(centres, at, geometry)
        radius_mm = np.abs(project_points(below, at, geometry)[:, 1] - centre_px[:, 1]) * pitch[1]
        centre_det = centre_px * pitch
        distance = np.linalg.norm(centre_det[i] - centre_det[j], axis=1)
        hit = distance < radius_mm[i] + radius_mm[j]
        pairs.append(np.stack([i[hit], j[hit]], axis=1).astype(np.int64))
    return pairs
