"""The pipeline: projections + geometry + view pairs -> per-pair and per-view angles."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ctpipe._checks import short_repr
from ctpipe.config import PipelineConfig, build_stage, load_yaml, parse_geometry, parse_pipeline
from ctpipe.data import Features, ScanObservations, ScanSolution
from ctpipe.errors import EstimationError, InputError
from ctpipe.execution import Executor, ThreadExecutor
from ctpipe.geometry import Geometry
from ctpipe.images import check_image
from ctpipe.io.scans import StackReference, ViewStack
from ctpipe.plugins import get_registry
from ctpipe.registry import StageRegistry
from ctpipe.solve.graph import view_pairs
from ctpipe.stages import Detector, Estimator, Matcher, Refiner

__all__ = ["Pipeline", "ScanResult", "consecutive_pairs"]

#: Most memory the static background's median may take: 90 views of 512^2, 32 of 2,048^2.
_BACKGROUND_BYTES = 512 * 2**20


def consecutive_pairs(n_views: int, baselines: tuple[int, ...] = (1,)) -> np.ndarray:
    """View pairs ``(i, i + k)`` for every baseline ``k``, shape (P, 2)."""
    pairs = [(i, i + k) for k in baselines for i in range(n_views - k)]
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


@dataclass(frozen=True, eq=False)
class ScanResult:
    """What a pipeline run returns.

    Attributes
    ----------
    pairs : ndarray of shape (P, 2), int64
    pair_angles_deg : ndarray of shape (P,)
        Refined angle of each pair, NaN where it failed.
    pair_inlier_masks : tuple of ndarray of shape (M_k,), bool
    n_matches, n_inliers : ndarray of shape (P,), int64
    residuals : ndarray of shape (P,)
        RMS Sampson distance of each pair's inliers, normalised units.
    pair_status : tuple of str
        ``"ok"`` or why the pair failed.
    angles_deg : ndarray of shape (V,)
        Angle of every view relative to view 0, chained from the pairs; NaN where a view is
        not connected to view 0 by successful pairs.
    n_keypoints : ndarray of shape (V,), int64
    timings_s : dict
    refiner_info : dict
        What the refiner reported (see :attr:`ctpipe.data.ScanSolution.info`).
    static_background_removed : bool
        Whether features were detected on the views less the scan's static part.
    """

    pairs: np.ndarray
    pair_angles_deg: np.ndarray
    pair_inlier_masks: tuple[np.ndarray, ...]
    n_matches: np.ndarray
    n_inliers: np.ndarray
    residuals: np.ndarray
    pair_status: tuple[str, ...]
    angles_deg: np.ndarray
    n_keypoints: np.ndarray
    timings_s: dict[str, float]
    refiner_info: dict[str, Any] = field(default_factory=dict)
    static_background_removed: bool = False

    def to_dict(self) -> dict[str, Any]:
        return {
            "angles_deg": self.angles_deg,
            "n_keypoints": self.n_keypoints,
            "pairs": [
                {"views": [int(i), int(j)], "angle_deg": a, "n_matches": m, "n_inliers": n, "residual": r, "status": s}
                for (i, j), a, m, n, r, s in zip(self.pairs, self.pair_angles_deg, self.n_matches, self.n_inliers,
                                                  self.residuals, self.pair_status)
            ],
            "timings_s": self.timings_s,
            "refiner": self.refiner_info,
            "static_background_removed": self.static_background_removed,
        }


@dataclass(frozen=True)
class Pipeline:
    """Detector -> matcher -> estimator -> refiner over a whole scan.

    Build one from stage objects, or with :meth:`from_config` from a YAML file or mapping.
    """

    detector: Detector
    matcher: Matcher
    estimator: Estimator
    refiner: Refiner
    baselines: tuple[int, ...] = (1,)
    seed: int | None = 0
    loop_closure: bool = True
    static_background: str = "auto"

    def __post_init__(self) -> None:
        for name, kind in (("detector", Detector), ("matcher", Matcher), ("estimator", Estimator), ("refiner", Refiner)):
            stage = getattr(self, name)
            if not isinstance(stage, kind):
                raise InputError(f"{name}: must be a ctpipe {kind.__name__} stage (e.g. from the registry or "
                                 f"Pipeline.from_config), got {type(stage).__name__} {short_repr(stage)}")
        if self.static_background not in ("auto", "on", "off"):
            raise InputError(f"static_background: must be one of 'auto', 'on', 'off', got {self.static_background!r}")

    @classmethod
    def from_config(cls, config: PipelineConfig | Mapping | str | Path | None = None, *,
                    registry: StageRegistry | None = None) -> "Pipeline":
        """A pipeline from a validated config, a mapping, or a YAML file path (None: defaults)."""
        registry = registry or get_registry()
        if isinstance(config, (str, Path)):
            config = parse_pipeline(load_yaml(config), registry, path="pipeline")
        elif not isinstance(config, PipelineConfig):
            config = parse_pipeline(config, registry)
        return cls(*(build_stage(getattr(config, kind), registry) for kind in ("detector", "matcher", "estimator", "refiner")),
                   baselines=config.baselines, seed=config.seed, loop_closure=config.loop_closure,
                   static_background=config.static_background)

    def detect(self, projections: np.ndarray, *, background: np.ndarray | None = None,
               progress: Callable[[int], None] | None = None, executor: Executor | None = None) -> tuple[Features, ...]:
        """Features of every view, on ``view - background`` if given (one task per view, see :meth:`run`)."""
        with _executor(executor) as run_on:
            source = run_on.scatter(_shippable(projections))
            tasks = [run_on.submit(_detect_view, self.detector, source, background, index, name="detect")
                     for index in range(len(projections))]
            return tuple(run_on.gather(tasks, progress=progress))

    def run(self, projections: np.ndarray, geometry: Geometry, *, nominal_angles_deg=None,
            pairs: np.ndarray | None = None, progress: Callable[[int], None] | None = None,
            executor: Executor | None = None) -> ScanResult:
        """Estimate the angle of every view of a scan: :meth:`observe`, then :meth:`refine`.

        Parameters
        ----------
        projections : ndarray of shape (V, rows, cols), or ViewStack
            uint8 or float images (float: e.g. ``-log`` line integrals); no NaN. A
            :class:`ctpipe.io.scans.ViewStack` (what :func:`ctpipe.io.open_scan` gives) is read
            one view at a time and never held whole.
        geometry : Geometry or mapping
            Must match the projections' (rows, cols). A mapping of the :class:`Geometry`
            fields is validated as a geometry YAML is (:func:`ctpipe.config.parse_geometry`).
        nominal_angles_deg : array_like of shape (V,), optional
            The commanded angles. They tell a full turn (whose seam is then paired too, see
            :func:`ctpipe.solve.view_pairs`) and give whole-scan refiners their start.
        pairs : ndarray of shape (P, 2), optional
            View pairs to estimate; default ``(i, i + k)`` for the configured baselines.
        progress : callable, optional
            ``progress(n)`` as ``n`` more views have their features.
        executor : ctpipe.execution.Executor, optional
            Where the tasks run: detection one task per view, matching and estimation one task
            per chunk of pairs, and the refiner as one task. Default a
            :class:`~ctpipe.execution.ThreadExecutor` over this process's cores; a
            :class:`~ctpipe.execution.DaskExecutor` runs them on a cluster, whose workers
            read a scan opened from disk themselves. Every pair has its own seed, so the
            angles are the same bit for bit wherever they run.

        Raises
        ------
        InputError
            Wrong shapes/dtypes, NaN pixels, pairs out of range.
        EstimationError
            When not a single pair could be estimated.
        """
        with _executor(executor) as run_on:
            observations, placed = self._observe(projections, geometry, nominal_angles_deg, pairs, progress, run_on)
            return self._refine(observations, run_on, placed)

    def observe(self, projections: np.ndarray, geometry: Geometry, *, nominal_angles_deg=None,
                pairs: np.ndarray | None = None, progress: Callable[[int], None] | None = None,
                executor: Executor | None = None) -> ScanObservations:
        """Detect, match and estimate every pair: what a refiner works from (arguments as :meth:`run`).

        Several refiners can then be compared on the same observations with :meth:`refine`.
        """
        return self._observe(projections, geometry, nominal_angles_deg, pairs, progress, executor)[0]

    def _observe(self, projections, geometry, nominal_angles_deg, pairs, progress,
                 executor) -> tuple[ScanObservations, "_Placed"]:
        """:meth:`observe`, and where its projections and features are on the executor (for the refiner's task)."""
        geometry = _check_geometry(geometry)
        projections = _check_projections(projections, geometry)
        n_views = len(projections)
        nominal = None if nominal_angles_deg is None else _check_nominal(nominal_angles_deg, n_views)
        if pairs is None:
            pairs = view_pairs(n_views, self.baselines, nominal, loop_closure=self.loop_closure)
        else:
            pairs = _check_pairs(pairs, n_views)
        if len(pairs) == 0:
            raise InputError(f"no view pairs: {n_views} views with baselines {list(self.baselines)}")
        with _executor(executor) as run_on:
            timings = {}
            start = time.perf_counter()
            # A scan from disk travels as its path: each worker reads the views it detects on.
            source = run_on.scatter(_shippable(projections))
            views = self._background_views(projections, nominal)
            background = None if views is None else run_on.submit(_median_background, source, views,
                                                                   name="background")
            detected = [run_on.submit(_detect_view, self.detector, source, background, index, name="detect")
                        for index in range(n_views)]
            features = tuple(run_on.gather(detected, progress=progress))
            timings["detect"] = time.perf_counter() - start

            # Chunks of pairs, a few per worker; each task gets the features of its own views only.
            chunks = np.array_split(np.arange(len(pairs)), min(len(pairs), 4 * run_on.workers))
            start = time.perf_counter()
            tasks = []
            for chunk in chunks:
                used, local = np.unique(pairs[chunk], return_inverse=True)
                tasks.append(run_on.submit(_match_pairs, self.matcher, geometry, [detected[v] for v in used],
                                           local.reshape(-1, 2), name="match"))
            matched = [m for chunk in run_on.gather(tasks) for m in chunk]
            matches = tuple(m for m, _, _ in matched)
            points_a = tuple(q_a for _, q_a, _ in matched)
            points_b = tuple(q_b for _, _, q_b in matched)
            timings["match"] = time.perf_counter() - start

            start = time.perf_counter()
            # Each chunk's points are where its matching task left them: nothing goes back out.
            seeds = np.random.SeedSequence(self.seed).spawn(len(pairs))
            tasks = [run_on.submit(_estimate_pairs, self.estimator, matched_chunk, [seeds[k] for k in chunk],
                                   name="estimate") for matched_chunk, chunk in zip(tasks, chunks)]
            estimates = tuple(e for chunk in run_on.gather(tasks) for e in chunk)
            timings["estimate"] = time.perf_counter() - start
        observations = ScanObservations(geometry=geometry, n_views=n_views, features=features, pairs=pairs,
                                        matches=matches, points_a=points_a, points_b=points_b, estimates=estimates,
                                        nominal_angles_deg=nominal, projections=projections, timings_s=timings,
                                        static_background_removed=views is not None)
        return observations, _Placed(source, detected)

    def refine(self, observations: ScanObservations, *, executor: Executor | None = None) -> ScanResult:
        """Per-view angles from :meth:`observe`'s observations with this pipeline's refiner.

        With an ``executor`` the refiner runs as one of its tasks (on a cluster: on a worker,
        which reads the projections it needs itself); without, here.
        """
        return self._refine(observations, executor, None)

    def _refine(self, observations: ScanObservations, executor: Executor | None, placed: "_Placed | None") -> ScanResult:
        timings = dict(observations.timings_s)
        start = time.perf_counter()
        # The refiner's generator is the last of len(pairs) + 1 children, as it always was.
        seed = np.random.SeedSequence(self.seed).spawn(len(observations.pairs) + 1)[-1]
        if executor is None:
            solution = self.refiner.refine(observations, rng=np.random.default_rng(seed))
        else:
            # The features and projections already where the tasks run are passed as handles, not sent again.
            if placed is not None:
                source, features = placed
                observations_out = dataclasses.replace(observations, projections=None, features=())
            else:
                projections = observations.projections
                source = None if projections is None else executor.scatter(_shippable(projections))
                features, observations_out = None, dataclasses.replace(observations, projections=None)
            task = executor.submit(_refine_task, self.refiner, observations_out, source, features, seed, name="refine")
            solution, = executor.gather([task])
        timings["refine"] = time.perf_counter() - start

        refined, matches, features = solution.pair_estimates, observations.matches, observations.features
        if not any(refined):
            counts = ", ".join(f"view {v}: {len(f)}" for v, f in enumerate(features[:6]))
            raise EstimationError(
                f"no view pair could be estimated (first pair: {refined[0]}); keypoints per view: {counts}"
                f"{', ...' if observations.n_views > 6 else ''}")
        return ScanResult(
            pairs=observations.pairs,
            pair_angles_deg=np.array([np.rad2deg(e.angle_rad) if e else np.nan for e in refined]),
            pair_inlier_masks=tuple(e.inlier_mask if e else np.zeros(len(m), bool) for e, m in zip(refined, matches)),
            n_matches=np.array([len(m) for m in matches], dtype=np.int64),
            n_inliers=np.array([e.n_inliers if e else 0 for e in refined], dtype=np.int64),
            residuals=np.array([e.residual if e else np.nan for e in refined]),
            pair_status=tuple("ok" if e else str(e) for e in refined),
            angles_deg=np.rad2deg(solution.angles_rad),
            n_keypoints=np.array([len(f) for f in features], dtype=np.int64),
            timings_s=timings,
            refiner_info=dict(solution.info),
            static_background_removed=observations.static_background_removed,
        )

    def _background_views(self, projections, nominal: np.ndarray | None) -> np.ndarray | None:
        """Which views make the static background to remove before detection, or None (see ``static_background``).

        The background is the per-pixel median over (up to 90, and at most ``_BACKGROUND_BYTES``
        of) evenly spread views, read one at a time when the projections are a ViewStack: what
        every view shares, i.e. the rotationally symmetric part of the object (container, matrix,
        detector pattern). Features sitting on that static profile are localised a few percent
        short of their motion, which biases every pair angle low (docs/wholescan.md). ``auto``
        removes it when the nominal angles show the views spread over at least 180 deg, so that
        features move across the image and the median is theirs in no view.
        """
        if self.static_background == "off":
            return None
        if self.static_background == "auto":
            if nominal is None or len(nominal) < 16:
                return None
            step = float(np.median(np.abs(np.diff(nominal))))
            if float(np.ptp(nominal)) + step < 180.0:
                return None
        # Up to 90 views, fewer on a detector so large that 90 would take more than _BACKGROUND_BYTES.
        rows, cols = projections.shape[1:]
        count = int(min(len(projections), 90, max(16, _BACKGROUND_BYTES // (rows * cols * 4))))
        return np.unique(np.linspace(0, len(projections) - 1, count).round().astype(int))


# Tasks: module-level functions, so that a worker process finds them by name.

def _shippable(projections):
    """What a task gets for the projections: a scan from disk by reference, anything else as it is."""
    reference = projections.reference() if isinstance(projections, ViewStack) else None
    return projections if reference is None else reference


def _views(source):
    return source.open() if isinstance(source, StackReference) else source


def _median_background(source, views: np.ndarray) -> np.ndarray:
    return np.median(np.asarray(_views(source)[views], dtype=np.float32), axis=0)


def _detect_view(detector: Detector, source, background: np.ndarray | None, index: int) -> Features:
    image = _views(source)[index]
    return detector.detect(image if background is None else image - background)


def _match_pairs(matcher: Matcher, geometry: Geometry, features: list[Features], pairs: np.ndarray) -> list:
    """(matches, first view's points, second view's points) of each pair; ``pairs`` index ``features``."""
    out = []
    for i, j in pairs:
        m = matcher.match(features[i], features[j])
        out.append((m, geometry.pixels_to_normalised(features[i].xy[m.index_ab[:, 0]]),
                    geometry.pixels_to_normalised(features[j].xy[m.index_ab[:, 1]])))
    return out


def _estimate_pairs(estimator: Estimator, matched: list, seeds: list) -> list:
    """Estimates of ``_match_pairs``'s output, pair ``k`` with its own generator ``seeds[k]``."""
    return [estimator.estimate(q_a, q_b, rng=np.random.default_rng(s)) for (_, q_a, q_b), s in zip(matched, seeds)]


def _refine_task(refiner: Refiner, observations: ScanObservations, source, features: list | None,
                 seed) -> ScanSolution:
    changes = {} if features is None else {"features": tuple(features)}
    if source is not None:
        changes["projections"] = _views(source)
    return refiner.refine(dataclasses.replace(observations, **changes), rng=np.random.default_rng(seed))


class _Placed(NamedTuple):
    """Where a run's inputs already are on its executor: the projections' handle, one handle per view's features."""

    source: Any
    features: list


class _executor:
    """The caller's executor as it is, or a thread pool for the block."""

    def __init__(self, executor: Executor | None) -> None:
        if executor is not None and not isinstance(executor, Executor):
            raise InputError(f"executor: must be a ctpipe.execution.Executor (ThreadExecutor or DaskExecutor), "
                             f"got {type(executor).__name__}")
        self.given, self.own = executor, None

    def __enter__(self) -> Executor:
        if self.given is not None:
            return self.given
        self.own = ThreadExecutor()
        return self.own

    def __exit__(self, *exc) -> None:
        if self.own is not None:
            self.own.close()


def _check_geometry(geometry) -> Geometry:
    if isinstance(geometry, Geometry):
        return geometry
    if isinstance(geometry, Mapping):
        return parse_geometry(geometry)
    raise InputError(f"geometry: must be a ctpipe.geometry.Geometry (or a mapping of its fields), "
                     f"got {type(geometry).__name__} {short_repr(geometry)}")


def _check_projections(projections, geometry: Geometry) -> np.ndarray | ViewStack:
    if isinstance(projections, ViewStack):
        # Read lazily: each view is checked as it is read.
        if len(projections) < 2:
            raise InputError(f"projections need at least 2 views to estimate an angle, got {len(projections)}")
        if projections.shape[1:] != geometry.shape:
            raise InputError(f"projections have (rows, cols) = {projections.shape[1:]} but the geometry says "
                             f"{geometry.shape} (detector_rows, detector_cols)")
        return projections
    projections = np.asarray(projections)
    if projections.ndim != 3:
        raise InputError(f"projections must be a 3-D array (views, rows, cols), got shape {projections.shape}")
    if len(projections) < 2:
        raise InputError(f"projections need at least 2 views to estimate an angle, got {len(projections)}")
    if projections.shape[1:] != geometry.shape:
        raise InputError(f"projections have (rows, cols) = {projections.shape[1:]} but the geometry says "
                         f"{geometry.shape} (detector_rows, detector_cols)")
    check_image(projections.reshape(-1, projections.shape[-1]), name="projections")
    return projections


def _check_nominal(nominal_angles_deg, n_views: int) -> np.ndarray:
    nominal = np.asarray(nominal_angles_deg)
    if nominal.shape != (n_views,) or not np.issubdtype(nominal.dtype, np.number) or np.iscomplexobj(nominal):
        raise InputError(f"nominal_angles_deg: must be {n_views} real numbers, one per view, got shape "
                         f"{nominal.shape} and dtype {nominal.dtype}")
    nominal = nominal.astype(np.float64)
    if not np.all(np.isfinite(nominal)):
        raise InputError("nominal_angles_deg: must be finite, got NaN or infinite values")
    nominal.flags.writeable = False
    return nominal


def _check_pairs(pairs, n_views: int) -> np.ndarray:
    pairs = np.asarray(pairs)
    if pairs.ndim != 2 or pairs.shape[1] != 2 or not np.issubdtype(pairs.dtype, np.integer):
        raise InputError(f"pairs must be an integer array of shape (P, 2), got {pairs.dtype} {pairs.shape}")
    if pairs.size and (pairs.min() < 0 or pairs.max() >= n_views):
        raise InputError(f"pairs must index views 0..{n_views - 1}, got indices {pairs.min()}..{pairs.max()}")
    if np.any(pairs[:, 0] == pairs[:, 1]):
        raise InputError("pairs must join two different views, got a pair (i, i)")
    return pairs.astype(np.int64)
