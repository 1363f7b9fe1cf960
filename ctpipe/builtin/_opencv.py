"""The only module that calls OpenCV.

OpenCV 5 moved AKAZE, BRISK and KAZE to ``cv2.xfeatures2d`` and refuses SURF in the PyPI
wheels; keeping every ``cv2`` call here means such moves are absorbed in one place.
"""

from __future__ import annotations

import cv2
import numpy as np

from ctpipe.errors import ConfigError, InputError

__all__ = ["available_detectors", "detect_and_compute", "knn_match", "essential_pose", "version"]

_NORMS = {cv2.NORM_L2: "L2", cv2.NORM_L1: "L1", cv2.NORM_HAMMING: "HAMMING", cv2.NORM_HAMMING2: "HAMMING2"}
_NORM_CODES = {name: code for code, name in _NORMS.items()}

_DIFFUSIVITY = {"pm_g1": 0, "pm_g2": 1, "weickert": 2, "charbonnier": 3}
_AKAZE_DESCRIPTOR = {"kaze": 3, "kaze_upright": 2, "mldb": 5, "mldb_upright": 4}
_ORB_SCORE = {"harris": 0, "fast": 1}


_FACTORIES = {"sift": "SIFT_create", "orb": "ORB_create", "akaze": "AKAZE_create", "brisk": "BRISK_create",
              "kaze": "KAZE_create"}


def version() -> str:
    return cv2.__version__


def _factory(kind: str):
    """The ``*_create`` function for ``kind`` wherever this build keeps it, or None.

    OpenCV 4 has AKAZE, BRISK and KAZE in ``cv2``, OpenCV 5 contrib in ``cv2.xfeatures2d``, and a
    plain (non-contrib) OpenCV 5 wheel installed over the contrib one has them in neither. The main
    namespace comes first: OpenCV 5 keeps a deprecated ``xfeatures2d.SIFT_create`` shim that warns.
    """
    name = _FACTORIES[kind]
    for module in (cv2, getattr(cv2, "xfeatures2d", None)):
        factory = getattr(module, name, None)
        if factory is not None:
            return factory
    return None


def available_detectors() -> list[str]:
    """The OpenCV detectors this cv2 build can create."""
    return [kind for kind in _FACTORIES if _factory(kind) is not None]


def _create(kind: str, p: dict):
    if kind not in _FACTORIES:
        raise ValueError(f"unknown OpenCV detector {kind!r}; known: {', '.join(_FACTORIES)}")
    create = _factory(kind)
    if create is None:
        raise RuntimeError(f"this OpenCV build ({cv2.__version__}) has no {_FACTORIES[kind]}; "
                           "install opencv-contrib-python-headless and not opencv-python beside it")
    if kind == "sift":
        return create(nfeatures=p["n_features"], nOctaveLayers=p["n_octave_layers"],
                      contrastThreshold=p["contrast_threshold"], edgeThreshold=p["edge_threshold"], sigma=p["sigma"])
    if kind == "orb":
        return create(nfeatures=p["n_features"], scaleFactor=p["scale_factor"], nlevels=p["n_levels"],
                      edgeThreshold=p["edge_threshold"], firstLevel=p["first_level"], WTA_K=p["wta_k"],
                      scoreType=_ORB_SCORE[p["score_type"]], patchSize=p["patch_size"],
                      fastThreshold=p["fast_threshold"])
    if kind == "akaze":
        return create(descriptor_type=_AKAZE_DESCRIPTOR[p["descriptor_type"]], descriptor_size=p["descriptor_size"],
                      descriptor_channels=p["descriptor_channels"], threshold=p["threshold"],
                      nOctaves=p["n_octaves"], nOctaveLayers=p["n_octave_layers"],
                      diffusivity=_DIFFUSIVITY[p["diffusivity"]])
    if kind == "brisk":
        return create(thresh=p["thresh"], octaves=p["octaves"], patternScale=p["pattern_scale"])
    if kind == "kaze":
        return create(extended=p["extended"], upright=p["upright"], threshold=p["threshold"],
                      nOctaves=p["n_octaves"], nOctaveLayers=p["n_octave_layers"],
                      diffusivity=_DIFFUSIVITY[p["diffusivity"]])
    raise AssertionError(kind)


def set_num_threads(n: int) -> None:
    """Threads OpenCV may use (benchmarks pin it to 1 to compare single-thread speed)."""
    cv2.setNumThreads(int(n))


def raw_detect_and_compute(kind: str, params: dict):
    """A function ``image_u8 -> (keypoints, descriptors)`` calling OpenCV directly.

    For benchmarks that time OpenCV itself, without the conversion to plain arrays that
    :func:`detect_and_compute` adds.
    """
    detector = _create(kind, params)
    return lambda image_u8: detector.detectAndCompute(image_u8, None)


def detect_and_compute(kind: str, params: dict, image_u8: np.ndarray) -> dict:
    """Run an OpenCV feature detector and return plain arrays.

    Returns a dict with ``xy`` (N, 2), ``size``, ``angle_deg`` (NaN where OpenCV stores -1),
    ``response``, ``octave`` (SIFT's packed octave decoded to the plain index), ``class_id``,
    ``descriptors`` and ``norm`` (from the detector's ``defaultNorm()``).
    """
    detector = _create(kind, params)
    try:
        keypoints, descriptors = detector.detectAndCompute(image_u8, None)
    except cv2.error as error:
        raise _detect_error(kind, params, image_u8, error) from None
    norm = _NORMS[detector.defaultNorm()]
    n = len(keypoints)
    if descriptors is None:
        width = detector.descriptorSize() if n == 0 else 0
        descriptors = np.zeros((0, width), dtype=np.uint8 if norm.startswith("HAMMING") else np.float32)
    if kind == "sift" and descriptors.dtype == np.float32 and _whole_bytes(descriptors):
        # OpenCV quantises SIFT's descriptors to bytes (saturate_cast<uchar>) and returns them
        # as floats: kept as the bytes they are, a quarter of the memory (checked, never assumed).
        descriptors = descriptors.astype(np.uint8)
    octave = np.array([k.octave for k in keypoints], dtype=np.int64)
    if kind == "sift":
        octave = octave & 255
        octave = np.where(octave >= 128, octave - 256, octave)
    angle = np.array([k.angle for k in keypoints], dtype=np.float32)
    return {
        "xy": np.array([k.pt for k in keypoints], dtype=np.float32).reshape(n, 2),
        "size": np.array([k.size for k in keypoints], dtype=np.float32),
        "angle_deg": np.where(angle < 0, np.nan, angle % 360.0).astype(np.float32),
        "response": np.array([k.response for k in keypoints], dtype=np.float32),
        "octave": octave,
        "class_id": np.array([k.class_id for k in keypoints], dtype=np.int64),
        "descriptors": descriptors,
        "norm": norm,
    }


def _whole_bytes(values: np.ndarray) -> bool:
    """Whether every value is a whole number from 0 to 255 (so uint8 holds it exactly)."""
    return bool(np.all((values >= 0) & (values <= 255) & (values == np.floor(values))))


def _detect_error(kind: str, params: dict, image_u8: np.ndarray, error: cv2.error) -> Exception:
    """One line for an OpenCV assertion or allocation failure in a detector.

    OpenCV asserts instead of returning nothing on images too small for its pyramid (ORB on
    1 x 1, BRISK on 2 x 2), but also on parameters that only fail on some images (a pyramid
    deeper than the image, a huge upsampling). Which one the user should change is found out by
    running OpenCV's defaults on the same image: if they work, the parameters are the cause.
    """
    reason = (getattr(error, "err", "") or str(error)).strip().splitlines()[-1]
    rows, cols = image_u8.shape[:2]
    try:
        cv2_defaults = _factory(kind)()
        cv2_defaults.detectAndCompute(image_u8, None)
    except cv2.error:
        return InputError(f"image: {kind} cannot run on a {rows} x {cols} image (OpenCV: {reason}); "
                          "give it a larger image")
    changed = ", ".join(f"{k}={v!r}" for k, v in params.items())
    return ConfigError(f"detector: {kind} with {changed} fails on this {rows} x {cols} image although OpenCV's "
                       f"defaults run (OpenCV: {reason}); bring the pyramid or size parameters closer to their defaults")


def knn_match(descriptors_a: np.ndarray, descriptors_b: np.ndarray, norm: str, k: int, *, flann: bool = False,
              flann_trees: int = 4, flann_checks: int = 64, lsh_tables: int = 6, lsh_key_size: int = 12,
              lsh_probes: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """k nearest neighbours in ``b`` of every descriptor of ``a``.

    Brute force with ``norm``, or FLANN (a randomised KD-tree forest for float descriptors,
    LSH for binary ones). Returns ``index`` and ``distance`` of shape (N_a, k); missing
    neighbours (fewer than k candidates, or LSH buckets that came back short) are -1 / inf.
    """
    n_a = len(descriptors_a)
    index = np.full((n_a, k), -1, dtype=np.int64)
    distance = np.full((n_a, k), np.inf, dtype=np.float32)
    if n_a == 0 or len(descriptors_b) == 0:
        return index, distance
    if not norm.startswith("HAMMING"):  # float or whole-number uint8 descriptors: OpenCV wants one float type
        descriptors_a = np.asarray(descriptors_a, dtype=np.float32)
        descriptors_b = np.asarray(descriptors_b, dtype=np.float32)
    if flann:
        if norm.startswith("HAMMING"):
            index_params = dict(algorithm=6, table_number=lsh_tables, key_size=lsh_key_size, multi_probe_level=lsh_probes)
        else:
            index_params = dict(algorithm=1, trees=flann_trees)
        matcher = cv2.FlannBasedMatcher(index_params, dict(checks=flann_checks))
    else:
        matcher = cv2.BFMatcher(_NORM_CODES[norm], crossCheck=False)
    for row, neighbours in enumerate(matcher.knnMatch(descriptors_a, descriptors_b, k=min(k, len(descriptors_b)))):
        for col, m in enumerate(neighbours[:k]):
            index[row, col] = m.trainIdx
            distance[row, col] = m.distance
    return index, distance


_ESSENTIAL_METHODS = {"ransac": cv2.RANSAC, "lmeds": cv2.LMEDS, "usac-default": cv2.USAC_DEFAULT,
                      "usac-accurate": cv2.USAC_ACCURATE, "usac-magsac": cv2.USAC_MAGSAC}


def essential_pose(q_a: np.ndarray, q_b: np.ndarray, *, method: str, probability: float, threshold: float,
                   max_iters: int, seed: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Five-point essential matrix + chirality check on normalised coordinates.

    ``cv2.findEssentialMat`` with the identity camera matrix, then ``cv2.recoverPose``.
    OpenCV's RANSAC draws from its global RNG, which is seeded with ``seed`` first.

    Returns
    -------
    (R, inlier_mask) or None
        ``R`` (3, 3) maps view-a to view-b camera coordinates (``X_b = R X_a + t``);
        ``None`` when OpenCV finds no essential matrix.
    """
    cv2.setRNGSeed(int(seed))
    camera = np.eye(3)
    q_a = np.ascontiguousarray(q_a, dtype=np.float64)
    q_b = np.ascontiguousarray(q_b, dtype=np.float64)
    essential, mask = cv2.findEssentialMat(q_a, q_b, camera, method=_ESSENTIAL_METHODS[method],
                                           prob=probability, threshold=threshold, maxIters=max_iters)
    if essential is None or essential.shape[0] < 3 or mask is None:
        return None
    # findEssentialMat may return several stacked 3x3 solutions; the first is its best.
    _, rotation, _, pose_mask = cv2.recoverPose(essential[:3], q_a, q_b, camera, mask=mask.copy())
    return rotation, pose_mask.ravel() > 0
