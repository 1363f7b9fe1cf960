"""``ctpipe validate``: a simulated scan with known angle errors, scored end to end.

One run:

1. projects the phantom at the *true* angles (nominal angles plus jitter) and, as a
   reference, at the nominal angles without jitter; both through the same acquisition model;
2. runs the pipeline on the jittered projections and scores its angles against the truth
   (per view and per pair, the paper's table);
3. reconstructs the jittered scan three times with FDK: with the nominal, the estimated and
   the true angles; and the reference scan with its own (nominal = true) angles;
4. scores the three reconstructions inside the object's support against the phantom
   voxelised on the same grid, and against the reference reconstruction (which isolates the
   geometric error from discretisation), and reports the recovery
   ``(PSNR_est - PSNR_nominal) / (PSNR_true - PSNR_nominal)``, negative when the correction hurts.

The per-view angle errors are reported for the nominal angles, the pipeline's angles
(``estimated``) and ``pair-chained``: the consecutive pair angles summed along the scan by plain
least squares without loop closure, what a pair-by-pair method gives, so a report shows what
the whole-scan refiner gains.

Whatever angles the pipeline returns (NaN views, a diverged span, views out of order), the
run reconstructs and reports: views without an angle take their nominal one, the estimated
angles are reconstructed with the nominal scan's full/short-scan decision, a reconstruction
FDK refuses is scored as failed, and the verdict says what went wrong. Settings FDK or the
simulation would refuse late are refused before the first projection (:func:`check_experiment`).

An experiment file::

    phantom: granular                 # a built-in name or a phantom YAML path
    scan: {...}                       # a scan spec (see ctpipe.sim.scan_spec), or a path to one
    pipeline: null                    # null: the default pipeline; a path or a mapping
    reconstruction:
      grid_size: 160                  # voxels per edge of the cubic grid around the object
      voxel_size_mm: null             # null: the object's extent / grid_size
      filter: hann                    # one of ctpipe.recon.feldkamp.FILTERS
      detector_binning: 2             # average b x b pixels before FDK (grid resolution)
    seed: 0

The built-in default is ``ctpipe/evaluate/validate.yaml``.
"""

from __future__ import annotations

import math
import platform
import time
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from ctpipe._shared.resources import FLOAT32, check_fits, memory_guard
from ctpipe.config import PipelineConfig, check_keys, load_yaml, parse_pipeline
from ctpipe.errors import ConfigError, InputError, ResourceError
from ctpipe.recon.feldkamp import bin_detector, binned_geometry
from ctpipe.recon.volume import VolumeGrid
from ctpipe.registry import StageRegistry
from ctpipe.stages import ParamSpec, check_value

__all__ = ["ValidateSettings", "load_validate_settings", "parse_validate", "check_experiment", "run_validate",
           "SimulatedExperiment", "simulate_experiment", "score_pipeline",
           "ValidateReport", "write_validate_outputs", "bin_detector", "binned_geometry", "pair_chained_deg",
           "estimate_problems"]

#: Per-view angle sets of the report, in the order they are printed.
VIEW_LABELS = ("nominal", "pair-chained", "estimated")

Progress = Callable[[str, int], Any]


@dataclass(frozen=True)
class ReconstructionSettings:
    grid_size: int = 160
    voxel_size_mm: float | None = None
    filter: str = "hann"
    detector_binning: int = 2


@dataclass(frozen=True)
class ValidateSettings:
    """A validated experiment (see the module docstring)."""

    phantom_ref: str
    phantom: Any
    scan: Any
    pipeline: PipelineConfig
    reconstruction: ReconstructionSettings = field(default_factory=ReconstructionSettings)
    seed: int = 0
    source: str = "built-in default"

    def to_dict(self) -> dict:
        return {"phantom": self.phantom_ref, "scan": self.scan.to_dict(), "pipeline": self.pipeline.to_dict(),
                "reconstruction": dict(vars(self.reconstruction)), "seed": self.seed, "source": self.source}


def _resolve(base_dir: Path | None, value: str) -> Path:
    path = Path(value)
    return path if path.is_absolute() or base_dir is None else base_dir / path


def parse_validate(mapping: Any, registry: StageRegistry, *, base_dir: Path | None = None, path: str = "experiment",
                   source: str = "") -> ValidateSettings:
    """Validate an experiment mapping; relative file names resolve against ``base_dir``."""
    from ctpipe.recon.feldkamp import FILTERS
    from ctpipe.sim.phantoms import load_phantom
    from ctpipe.sim.scan_spec import load_scan_spec, parse_scan_spec

    check_keys(mapping, path, allowed=("phantom", "scan", "pipeline", "reconstruction", "seed"),
               required=("phantom", "scan"))
    phantom_ref = mapping["phantom"]
    if not isinstance(phantom_ref, str):
        raise ConfigError(f"{path}.phantom: must be a built-in phantom name or a YAML path, got {phantom_ref!r}")
    looks_like_file = phantom_ref.endswith((".yaml", ".yml")) or "/" in phantom_ref
    phantom = load_phantom(str(_resolve(base_dir, phantom_ref)) if looks_like_file else phantom_ref)

    scan = mapping["scan"]
    if isinstance(scan, str):
        scan = load_scan_spec(_resolve(base_dir, scan))
    else:
        scan = parse_scan_spec(scan, path=f"{path}.scan")

    pipeline = mapping.get("pipeline")
    if isinstance(pipeline, str):
        pipeline_path = _resolve(base_dir, pipeline)
        pipeline = parse_pipeline(load_yaml(pipeline_path), registry, path=str(pipeline_path))
    else:
        pipeline = parse_pipeline(pipeline, registry, path=f"{path}.pipeline")

    recon = check_keys(mapping.get("reconstruction", {}) or {}, f"{path}.reconstruction",
                       allowed=("grid_size", "voxel_size_mm", "filter", "detector_binning"))
    specs = {
        "grid_size": ParamSpec("grid_size", int, 160, "", ge=8, le=1024),
        "voxel_size_mm": ParamSpec("voxel_size_mm", float | None, None, "", gt=0),
        "filter": ParamSpec("filter", str, "hann", ""),
        "detector_binning": ParamSpec("detector_binning", int, 2, "", ge=1, le=16),
    }
    values = {key: check_value(spec, recon.get(key, spec.default), f"{path}.reconstruction.{key}")
              for key, spec in specs.items()}
    if values["filter"] not in FILTERS:
        raise ConfigError(f"{path}.reconstruction.filter: unknown filter {values['filter']!r}; allowed: {', '.join(FILTERS)}")
    if values["voxel_size_mm"] is not None:
        values["voxel_size_mm"] = float(values["voxel_size_mm"])
    geometry = scan.geometry
    if geometry.detector_cols % values["detector_binning"] or geometry.detector_rows % values["detector_binning"]:
        raise ConfigError(f"{path}.reconstruction.detector_binning: must divide the detector size "
                          f"{geometry.detector_cols} x {geometry.detector_rows}, got {values['detector_binning']}")
    seed = check_value(ParamSpec("seed", int, 0, "", ge=0), mapping.get("seed", 0), f"{path}.seed")
    settings = ValidateSettings(phantom_ref=phantom_ref, phantom=phantom, scan=scan, pipeline=pipeline,
                                reconstruction=ReconstructionSettings(**values), seed=seed, source=source)
    check_experiment(settings, path=path)
    return settings


def check_experiment(settings: ValidateSettings, *, path: str = "experiment") -> None:
    """Refuse, in milliseconds, what the simulation, the pipeline or FDK would only refuse late.

    Checks that the jitter can be drawn for this many views (a ``jumps.count`` needs more
    views), that the pipeline has view pairs to estimate, that a short scan (nominal angles not
    covering a full circle) spans at least 180 deg + the fan angle of the reconstruction's
    (binned) detector, also once jittered with the experiment's seed, and that the grid has
    voxels inside the object.

    Also refuses, before anything is allocated, a run whose two simulated scans and volumes
    cannot fit in the memory available, or whose two simulations would take too long
    (:func:`ctpipe.sim.simulator.check_simulation_work`).

    Raises
    ------
    ConfigError
        One line naming the YAML path, the value and what is allowed.
    ctpipe._shared.resources.ResourceError
        The run needs more memory than is available, or more work than ctpipe takes on in a
        simulation (the message names the sizes and what to lower).
    """
    from ctpipe.evaluate.scoring import support_mask
    from ctpipe.recon.feldkamp import covers_full_circle, short_scan_minimum_deg
    from ctpipe.sim.simulator import check_simulation_work
    from ctpipe.solve.graph import view_pairs

    scan = settings.scan
    what, n_bytes, of, hint = _run_size(settings, path)
    check_fits(what, n_bytes, of=of, hint=hint)
    try:
        check_simulation_work(settings.phantom, scan, scans=2)
    except ResourceError as exc:
        raise ResourceError(f"{path}: {exc}") from None
    nominal = scan.nominal_angles_deg()
    try:
        # simulate() draws the jitter first from default_rng(seed): these are the true angles.
        truth = nominal + scan.jitter.sample(nominal, np.random.default_rng(settings.seed))
    except InputError as exc:
        raise ConfigError(f"{path}.scan.jitter: cannot be drawn for {scan.n_views} views: {exc}") from None
    pipeline = settings.pipeline
    if scan.n_views < 2 or not len(view_pairs(scan.n_views, pipeline.baselines, nominal,
                                              loop_closure=pipeline.loop_closure)):
        raise ConfigError(f"{path}.scan.angles.n_views: the pipeline needs view pairs; baselines "
                          f"{list(pipeline.baselines)} need more than {max(pipeline.baselines)} views, got {scan.n_views}")
    geometry = binned_geometry(scan.geometry, settings.reconstruction.detector_binning)
    if not covers_full_circle(nominal):
        minimum = short_scan_minimum_deg(geometry)
        span = float(np.ptp(nominal))
        if span < minimum - _SPAN_TOLERANCE_DEG:
            raise ConfigError(f"{path}.scan.angles.range_deg: a short scan must span at least {minimum:.2f} deg "
                              f"(180 + fan angle {minimum - 180.0:.2f} deg of this geometry), got {span:g} deg")
        if float(np.ptp(truth)) < minimum - _SPAN_TOLERANCE_DEG:
            raise ConfigError(f"{path}.scan.jitter: the jittered angles (seed {settings.seed}) span "
                              f"{float(np.ptp(truth)):.2f} deg, less than the {minimum:.2f} deg a short scan needs "
                              f"(180 + fan angle); widen {path}.scan.angles.range_deg")
    phantom = settings.phantom
    try:
        support_mask(_grid(settings), phantom.radius_mm, phantom.half_height_mm, margin_voxels=2.0)
    except InputError as exc:
        raise ConfigError(f"{path}.reconstruction.voxel_size_mm: the grid misses the object: {exc}") from None


_SPAN_TOLERANCE_DEG = 1e-6
#: Volumes of the grid a run holds at its peak: the phantom's, the reference, nominal, estimated
#: and true reconstructions, and FDK's accumulator with its transposed copy.
_PEAK_VOLUMES = 7


def _run_size(settings: ValidateSettings, path: str) -> tuple[str, int, str, str]:
    """What a run allocates at its peak, in words and bytes: two simulated scans and the volumes."""
    from ctpipe.sim.simulator import simulation_bytes

    scan, n = settings.scan, settings.reconstruction.grid_size
    volumes = _PEAK_VOLUMES * n**3 * FLOAT32
    what = (f"{path}: simulating 2 scans of {scan.n_views} views of {scan.geometry.detector_rows} x "
            f"{scan.geometry.detector_cols} and reconstructing on a {n}^3 grid")
    hint = (f"lower {path}.scan.angles.n_views, the detector size in {path}.scan.geometry or "
            f"{path}.reconstruction.grid_size")
    return what, simulation_bytes(scan, scans=2) + volumes, "float32", hint


def load_validate_settings(path: str | Path | None, registry: StageRegistry) -> ValidateSettings:
    """Settings from an experiment YAML, or the built-in default when ``path`` is None."""
    if path is None:
        text = resources.files("ctpipe.evaluate").joinpath("validate.yaml").read_text(encoding="utf-8")
        return parse_validate(load_yaml("validate.yaml", text=text), registry, source="built-in default")
    path = Path(path)
    return parse_validate(load_yaml(path), registry, base_dir=path.parent, path=str(path), source=str(path))


def pair_chained_deg(pairs, pair_angles_deg, nominal_angles_deg) -> np.ndarray:
    """View angles (degrees, view 0 = 0) from the consecutive pairs ``(i, i + 1)`` alone, chained.

    Plain least squares on a chain is the running sum of the pair angles; no other baseline and
    no seam pair (loop closure) enters. Views after a failed pair get NaN.

    Parameters
    ----------
    pairs : ndarray of shape (P, 2), int
    pair_angles_deg : ndarray of shape (P,)
        As the pipeline returns them, in (-180, 180]; unwrapped here against the nominal angles.
    nominal_angles_deg : ndarray of shape (V,)
    """
    from ctpipe.solve.graph import chain_pair_angles, unwrap_pair_angles_deg

    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    nominal = np.asarray(nominal_angles_deg, dtype=np.float64)
    consecutive = pairs[:, 1] - pairs[:, 0] == 1
    angles = unwrap_pair_angles_deg(pairs[consecutive], np.asarray(pair_angles_deg)[consecutive], nominal)
    return np.rad2deg(chain_pair_angles(len(nominal), pairs[consecutive], np.deg2rad(angles)))


def estimate_problems(estimated_deg, true_deg, range_deg: float) -> list[str]:
    """What is wrong with a set of estimated view angles, in words; empty when nothing stands out.

    Looks at views without an angle, the span of the estimated angles against the true one
    (off by more than a typical step and 1 deg: drift; by more than 10 % of the scan range:
    divergence), and consecutive views whose order disagrees with the truth.

    Parameters
    ----------
    estimated_deg : ndarray of shape (V,)
        Relative to view 0, NaN where not estimated.
    true_deg : ndarray of shape (V,)
    range_deg : float
        The scan's nominal range (360 for a full turn).
    """
    estimated = np.asarray(estimated_deg, dtype=np.float64)
    truth = np.asarray(true_deg, dtype=np.float64)
    n = estimated.size
    known = np.isfinite(estimated)
    if known.sum() <= 1:
        return [f"the pipeline estimated no view angle ({n - int(known.sum())} of {n} views without one): "
                "the estimated reconstruction uses the nominal angles"]
    problems = []
    if not known.all():
        problems.append(f"{n - int(known.sum())} of {n} views have no estimated angle and keep their nominal one")
    span, true_span = float(np.ptp(estimated[known])), float(np.ptp(truth[known]))
    step = float(np.median(np.abs(np.diff(truth)))) if n > 1 else 0.0
    if abs(span - true_span) > max(step, 1.0):
        how = "the estimate diverged" if abs(span - true_span) > 0.1 * range_deg else \
            f"the estimate drifts by {span - true_span:+.2f} deg over the scan"
        problems.append(f"the estimated angles span {span:.0f} deg over a {range_deg:g} deg scan (the true angles "
                        f"span {true_span:.1f} deg): {how}")
    both = known[1:] & known[:-1]
    turn, true_turn = np.diff(estimated)[both], np.diff(truth)[both]
    wrong = int(np.count_nonzero(np.sign(turn) != np.sign(true_turn)))
    if wrong:
        problems.append(f"{wrong} of {int(both.sum())} consecutive view pairs turn the wrong way against the truth: "
                        "the estimate reorders views")
    return problems


def _grid(settings: ValidateSettings) -> VolumeGrid:
    phantom, recon = settings.phantom, settings.reconstruction
    extent = 2.0 * max(phantom.radius_mm, phantom.half_height_mm)
    voxel = recon.voxel_size_mm or extent * 1.04 / recon.grid_size
    return VolumeGrid.cube(recon.grid_size, voxel)


@dataclass
class ValidateReport:
    """Everything ``ctpipe validate`` measured; :meth:`to_dict` is ``report.json``."""

    settings: ValidateSettings
    grid: VolumeGrid
    nominal_deg: np.ndarray
    true_deg: np.ndarray
    estimated_deg: np.ndarray
    pipeline_result: Any
    volumes: dict[str, np.ndarray]
    phantom_volume: np.ndarray
    reference_volume: np.ndarray
    metrics: dict[str, dict[str, dict[str, float]]]
    recovery: dict[str, float]
    angle_tables: dict[str, dict[str, Any]]
    view_errors: dict[str, np.ndarray]
    timings_s: dict[str, float]
    notes: list[str]
    problems: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)

    def summary_lines(self) -> list[str]:
        """A short plain-text account: the angle tables, the reconstruction scores, the verdict."""
        lines = []
        t = self.angle_tables
        lines.append("angle error per view (deg, common offset removed):")
        for label in [label for label in (*VIEW_LABELS, "before the gate") if label in t["views"]]:
            s = t["views"][label]
            lines.append(f"  {label:<12}  {s['estimated']}/{s['total']} views  RMS {s['rms_deg']:.4f}  "
                         f"MAE {s['mae_deg']:.4f}  median {s['median_deg']:.4f}  max {s['max_deg']:.4f}")
        s = t["pairs"]["estimated"]
        lines.append(f"angle error per pair (deg): {s['estimated']}/{s['total']} pairs  MAE {s['mae_deg']:.4f}  "
                     f"std {s['std_deg']:.4f}  min {s['min_deg']:.4f}  q25 {s['q25_deg']:.4f}  "
                     f"median {s['median_deg']:.4f}  q75 {s['q75_deg']:.4f}  max {s['max_deg']:.4f}")
        for reference in ("phantom", "reference"):
            lines.append(f"reconstruction vs {'the voxelised phantom' if reference == 'phantom' else 'the jitter-free scan'}"
                         " (inside the support):")
            for label in ("nominal", "estimated", "true"):
                m = self.metrics[reference][label]
                if label in self.failed:
                    lines.append(f"  {label:<9}  failed: {self.failed[label]}")
                    continue
                lines.append(f"  {label:<9}  PSNR {m['psnr_db']:6.2f} dB  SSIM {m['ssim']:.4f}  "
                             f"relative RMSE {m['relative_rmse']:.4f}")
            lines.append(f"  recovery {self.recovery[reference]:+.3f}")
        gate = self.pipeline_result.gate
        if gate is not None:
            lines.append(f"gate: {gate.chosen if gate.decided else 'undecided, ' + gate.chosen}: {gate.reason}")
        coverage = self.se_coverage
        if coverage is not None:
            lines.append(f"standard errors: {coverage['within']}/{coverage['views']} views "
                         f"({coverage['fraction']:.0%}) within two of the truth; median {coverage['median_se_deg']:.4f} deg")
        lines.append(self.verdict())
        lines.extend(self.notes)
        return lines

    @property
    def se_coverage(self) -> dict[str, Any] | None:
        """How the returned angles' standard errors cover their true errors (:func:`~ctpipe.evaluate.scoring.se_coverage`)."""
        from ctpipe.evaluate.scoring import se_coverage

        se = self.pipeline_result.angle_se_deg
        return None if se is None else se_coverage(self.view_errors["estimated"], se)

    def verdict(self) -> str:
        """One sentence: is the jitter visible, and did the estimated angles help or hurt?

        Judged against the jitter-free scan, which isolates the geometric error.
        """
        m = self.metrics["reference"]
        visible = m["true"]["psnr_db"] - m["nominal"]["psnr_db"]
        gain = m["estimated"]["psnr_db"] - m["nominal"]["psnr_db"]
        wrong = "" if not self.problems else "; what went wrong: " + "; ".join(self.problems)
        if "estimated" in self.failed:
            head = (f"the jitter is visible (true angles {visible:+.2f} dB over the nominal ones)" if visible > 0 else
                    f"the jitter is not visible at this grid (true angles {visible:+.2f} dB against the nominal ones)")
            return (f"verdict: {head}; the estimated angles could not be reconstructed "
                    f"({self.failed['estimated']}){wrong}")
        if not visible > 0:
            return (f"verdict: the jitter is not visible at this grid (true angles {visible:+.2f} dB against the "
                    f"nominal ones); the experiment cannot judge the correction{wrong}")
        effect = "improve on" if gain > 0 else "are worse than"
        return (f"verdict: the jitter is visible (true angles {visible:+.2f} dB over the nominal ones); the estimated "
                f"angles {effect} the nominal ones by {abs(gain):.2f} dB, recovering "
                f"{100.0 * self.recovery['reference']:.0f} % of what the true angles gain{wrong}")

    def to_dict(self) -> dict[str, Any]:
        import numba
        import scipy
        import skimage

        from ctpipe._version import __version__
        from ctpipe.builtin import _opencv

        result = self.pipeline_result
        return {
            "settings": self.settings.to_dict(),
            "grid": self.grid.to_dict(),
            "angle_errors": self.angle_tables,
            "reconstruction": {"metrics": self.metrics, "recovery": self.recovery, "failed": self.failed},
            "pipeline": {"n_pairs": int(len(result.pairs)), "pairs_ok": int(sum(s == "ok" for s in result.pair_status)),
                         "median_inliers": float(np.median(result.n_inliers)),
                         "median_matches": float(np.median(result.n_matches)),
                         "median_keypoints": float(np.median(result.n_keypoints)),
                         "timings_s": result.timings_s, "refiner": result.refiner_info,
                         "gate": None if result.gate is None else result.gate.to_dict()},
            "se_coverage": self.se_coverage,
            "estimate_problems": self.problems,
            "timings_s": self.timings_s,
            "verdict": self.verdict(),
            "notes": self.notes,
            "versions": {"ctpipe": __version__, "python": platform.python_version(), "numpy": np.__version__,
                         "scipy": scipy.__version__, "numba": numba.__version__, "opencv": _opencv.version(),
                         "scikit-image": skimage.__version__, "machine": platform.machine()},
        }


def run_validate(settings: ValidateSettings, registry: StageRegistry, *,
                 progress: Callable[[str, int], Any] | None = None) -> ValidateReport:
    """Run the experiment; ``progress(step, total)`` returns a context manager yielding an ``advance(n)``.

    Raises
    ------
    ConfigError
        Settings the simulation or FDK would refuse (:func:`check_experiment`).
    ctpipe._shared.resources.ResourceError
        The run cannot fit in the memory available: refused before the first projection.
    """
    check_experiment(settings)
    what, n_bytes, of, hint = _run_size(settings, "experiment")
    with memory_guard(what, n_bytes, of=of, hint=hint):
        return _run_validate(settings, registry, progress)


@dataclass
class SimulatedExperiment:
    """What every pipeline scored on one experiment shares (:func:`simulate_experiment`).

    The jittered scan (and its views binned for FDK), the jittered scan reconstructed with the
    nominal and the true angles, the reconstruction of the jitter-free reference scan, the
    voxelised phantom, and the scores of the nominal and true reconstructions against both
    (``metrics[reference][label]``). ``experiment compare`` makes one per scenario and scores
    every pipeline on it (:func:`score_pipeline`), so the pipelines see the same projections.
    """

    settings: ValidateSettings
    jittered: Any
    grid: VolumeGrid
    binned: np.ndarray
    binned_geometry: Any
    short_scan: bool
    volumes: dict[str, np.ndarray]
    reference_volume: np.ndarray
    phantom_volume: np.ndarray
    mask: np.ndarray
    metrics: dict[str, dict[str, dict[str, float]]]
    timings_s: dict[str, float]


def simulate_experiment(settings: ValidateSettings, *, progress: Progress | None = None) -> SimulatedExperiment:
    """Simulate the experiment's scans and reconstruct what does not depend on the pipeline.

    Raises as :func:`run_validate` does; the memory check covers one pipeline's run on top.
    """
    check_experiment(settings)
    what, n_bytes, of, hint = _run_size(settings, "experiment")
    with memory_guard(what, n_bytes, of=of, hint=hint):
        return _simulate(settings, progress)


def _bar(progress: Progress | None, step: str, total: int):
    return progress(step, total) if progress is not None else nullcontext(None)


def _simulate(settings: ValidateSettings, progress: Progress | None) -> SimulatedExperiment:
    from ctpipe.recon.feldkamp import covers_full_circle, fdk
    from ctpipe.evaluate.scoring import align_offset, support_mask, volume_metrics
    from ctpipe.sim.simulator import simulate, voxelise_phantom

    timings: dict[str, float] = {}
    rng = np.random.default_rng(settings.seed)
    scan, phantom = settings.scan, settings.phantom
    geometry = scan.geometry
    n_views = scan.n_views

    start = time.perf_counter()
    with _bar(progress, "projecting (jittered scan)", n_views) as advance:
        jittered = simulate(phantom, scan, rng=rng, progress=advance)
    with _bar(progress, "projecting (jitter-free reference)", n_views) as advance:
        reference_scan = simulate(phantom, scan, rng=rng, jitter=False, progress=advance)
    timings["simulate"] = time.perf_counter() - start
    nominal, truth = jittered.nominal_angles_deg, jittered.true_angles_deg

    grid = _grid(settings)
    binning = settings.reconstruction.detector_binning
    start = time.perf_counter()
    projections, recon_geometry = bin_detector(jittered.projections, geometry, binning)
    reference_projections, _ = bin_detector(reference_scan.projections, geometry, binning)
    nominal_aligned, _ = align_offset(nominal, truth)
    # Every angle set is weighted as the nominal scan is (full or Parker short scan): a diverged
    # estimate spanning more than a turn must not switch the estimated reconstruction's weighting.
    short_scan = not covers_full_circle(nominal)
    volumes = {}
    with _bar(progress, "reconstructing (FDK x 3)", 3 * n_views) as advance:
        for label, angles in (("nominal", nominal_aligned), ("true", truth)):
            volumes[label] = fdk(projections, recon_geometry, angles, grid, filter=settings.reconstruction.filter,
                                 short_scan=short_scan, progress=advance)
        reference_volume = fdk(reference_projections, recon_geometry, reference_scan.true_angles_deg, grid,
                               filter=settings.reconstruction.filter, short_scan=short_scan, progress=advance)
    timings["reconstruct"] = time.perf_counter() - start
    start = time.perf_counter()
    phantom_volume = voxelise_phantom(phantom, grid)
    mask = support_mask(grid, phantom.radius_mm, phantom.half_height_mm, margin_voxels=2.0)
    metrics = {name: {label: volume_metrics(volume, target, mask) for label, volume in volumes.items()}
               for name, target in (("phantom", phantom_volume), ("reference", reference_volume))}
    timings["score"] = time.perf_counter() - start
    return SimulatedExperiment(settings=settings, jittered=jittered, grid=grid, binned=projections,
                               binned_geometry=recon_geometry, short_scan=short_scan, volumes=volumes,
                               reference_volume=reference_volume, phantom_volume=phantom_volume, mask=mask,
                               metrics=metrics, timings_s=timings)


def _run_validate(settings: ValidateSettings, registry: StageRegistry, progress) -> ValidateReport:
    return score_pipeline(_simulate(settings, progress), settings.pipeline, registry, progress=progress)


def score_pipeline(simulated: SimulatedExperiment, pipeline_config: PipelineConfig, registry: StageRegistry, *,
                   progress: Progress | None = None, pipeline_run: Callable[..., Any] | None = None) -> ValidateReport:
    """Run one pipeline on a :class:`SimulatedExperiment` and score it as ``ctpipe validate`` does.

    ``pipeline_run(pipeline, projections, geometry, nominal_angles_deg, advance)`` replaces
    ``pipeline.run`` (``experiment compare`` runs the stages one by one to measure each).
    """
    from ctpipe.pipeline import Pipeline
    from ctpipe.recon.feldkamp import fdk, short_scan_minimum_deg
    from ctpipe.evaluate.scoring import (align_offset, error_table, pair_errors_deg, recovery, view_errors_deg,
                                         volume_metrics)

    settings = replace(simulated.settings, pipeline=pipeline_config)
    scan = settings.scan
    geometry = scan.geometry
    n_views = scan.n_views
    jittered = simulated.jittered
    timings = {"simulate": simulated.timings_s["simulate"]}
    notes: list[str] = []
    nominal, truth = jittered.nominal_angles_deg, jittered.true_angles_deg

    start = time.perf_counter()
    pipeline = Pipeline.from_config(pipeline_config, registry=registry)
    with _bar(progress, "estimating angles (detect)", n_views) as advance:
        if pipeline_run is None:
            result = pipeline.run(jittered.projections, geometry, nominal_angles_deg=nominal, progress=advance)
        else:
            result = pipeline_run(pipeline, jittered.projections, geometry, nominal, advance)
    timings["estimate"] = time.perf_counter() - start

    estimated_rel = result.angles_deg
    estimated, n_filled = align_offset(estimated_rel, truth, fallback_deg=nominal)
    if n_filled:
        notes.append(f"{n_filled} views were not connected to view 0 by estimated pairs; they keep their nominal angle")
    problems = estimate_problems(estimated_rel, truth, scan.angles.range_deg)
    gate = result.gate
    if gate is not None and gate.chosen != "estimate":
        returned = "the nominal angles" if gate.chosen == "nominal" else f"only the {gate.chosen} of the correction"
        problems.insert(0, f"the gate returned {returned}: {gate.reason}")
    chosen = result.refiner_info.get("chosen")
    if chosen in ("nominal", "start"):
        problems.insert(0, f"the refiner kept the {'nominal' if chosen == 'nominal' else 'feature-based start'} "
                           "angles: projection matching explained the projections no better")
    view_errors = {"nominal": view_errors_deg(nominal, truth),
                   "pair-chained": view_errors_deg(pair_chained_deg(result.pairs, result.pair_angles_deg, nominal),
                                                   truth),
                   "estimated": view_errors_deg(estimated_rel, truth)}
    if gate is not None and gate.chosen != "estimate":
        # What the gate held back: the refiner's angles, scored as if they had been returned.
        view_errors["before the gate"] = view_errors_deg(gate.estimate_deg, truth)
    pair_truth_errors = pair_errors_deg(result.pairs, result.pair_angles_deg, truth)
    nominal_pairs = nominal[result.pairs[:, 1]] - nominal[result.pairs[:, 0]]
    angle_tables = {
        "views": {label: error_table(errors) for label, errors in view_errors.items()},
        "pairs": {"estimated": error_table(pair_truth_errors),
                  "nominal": error_table(pair_errors_deg(result.pairs, nominal_pairs, truth))},
    }

    grid = simulated.grid
    start = time.perf_counter()
    volumes, failed = {"nominal": simulated.volumes["nominal"]}, {}
    minimum = short_scan_minimum_deg(simulated.binned_geometry)
    span = float(np.ptp(estimated))
    with _bar(progress, "reconstructing (FDK, estimated angles)", n_views) as advance:
        if simulated.short_scan and span < minimum - _SPAN_TOLERANCE_DEG:
            # Said in the experiment's terms: FDK's own advice (an argument) means nothing in YAML.
            failed["estimated"] = (f"the estimated angles span {span:.2f} deg, less than the {minimum:.2f} deg "
                                   f"(180 + fan angle) a short scan of this geometry needs; widen "
                                   f"scan.angles.range_deg in the experiment to leave a margin")
        else:
            try:
                volumes["estimated"] = fdk(simulated.binned, simulated.binned_geometry, estimated, grid,
                                           filter=settings.reconstruction.filter, short_scan=simulated.short_scan,
                                           progress=advance)
            except InputError as exc:
                failed["estimated"] = f"FDK refused the estimated angles: {exc}"
    volumes["true"] = simulated.volumes["true"]
    timings["reconstruct"] = simulated.timings_s["reconstruct"] + time.perf_counter() - start

    start = time.perf_counter()
    unscored = {"rmse": math.nan, "relative_rmse": math.nan, "psnr_db": math.nan, "ssim": math.nan}
    metrics = {}
    for name, target in (("phantom", simulated.phantom_volume), ("reference", simulated.reference_volume)):
        shared = simulated.metrics[name]
        estimated_metrics = (volume_metrics(volumes["estimated"], target, simulated.mask) if "estimated" in volumes
                             else dict(unscored))
        metrics[name] = {"nominal": dict(shared["nominal"]), "estimated": estimated_metrics,
                         "true": dict(shared["true"])}
    gains = {ref: recovery(m["estimated"]["psnr_db"], m["nominal"]["psnr_db"], m["true"]["psnr_db"])
             for ref, m in metrics.items()}
    timings["score"] = simulated.timings_s["score"] + time.perf_counter() - start
    for ref, m in metrics.items():
        if not m["true"]["psnr_db"] > m["nominal"]["psnr_db"]:
            notes.append(f"against the {ref}, the true angles do not reconstruct better than the nominal ones: the "
                         "jitter is not visible at this grid; recovery is undefined")
    return ValidateReport(settings=settings, grid=grid, nominal_deg=nominal, true_deg=truth, estimated_deg=estimated,
                          pipeline_result=result, volumes=volumes, phantom_volume=simulated.phantom_volume,
                          reference_volume=simulated.reference_volume, metrics=metrics, recovery=gains,
                          angle_tables=angle_tables, view_errors=view_errors, timings_s=timings, notes=notes,
                          problems=problems, failed=failed)


def write_validate_outputs(report: ValidateReport, out: str | Path) -> list[Path]:
    """``report.json``, ``angles.csv``, ``slices.png``, ``angle_errors.png`` in ``out``.

    Everything is rendered before the first file is written; each file is renamed into place.
    """
    from ctpipe.evaluate.report import angle_errors_png, slices_png
    from ctpipe.io.outputs import atomic_write, write_csv, write_json

    out = Path(out)
    grid = report.grid
    # An axial slice a third of the way up and the vertical slice through the axis: off-centre
    # features smear along arcs when the angles are wrong.
    labels = {"nominal": "nominal angles", "estimated": "estimated angles", "true": "true angles"}
    volumes = {labels[k]: v for k, v in report.volumes.items()}
    slices = slices_png(volumes, report.phantom_volume, axial_index=grid.n_y // 3, vertical_index=grid.n_z // 2,
                        title="FDK of the jittered scan; columns: phantom, " + ", ".join(volumes)
                        + ("" if not report.failed else f" ({', '.join(report.failed)} failed)"))
    errors = angle_errors_png({"nominal angles": report.view_errors["nominal"],
                               "pair-chained (consecutive pairs, no loop closure)": report.view_errors["pair-chained"],
                               "estimated angles (whole-scan refiner)": report.view_errors["estimated"]},
                              title="per-view angle error against the truth",
                              scale_to=("nominal angles", "estimated angles (whole-scan refiner)"))
    rows = [[v, n, t, e, en, ee, ec] for v, (n, t, e, en, ee, ec) in enumerate(zip(
        report.nominal_deg, report.true_deg, report.pipeline_result.angles_deg, report.view_errors["nominal"],
        report.view_errors["estimated"], report.view_errors["pair-chained"]))]
    return [
        write_json(out / "report.json", report.to_dict()),
        write_csv(out / "angles.csv", ["view", "nominal_deg", "true_deg", "estimated_relative_deg",
                                       "nominal_error_deg", "estimated_error_deg", "pair_chained_error_deg"], rows),
        atomic_write(out / "slices.png", lambda h: h.write(slices)),
        atomic_write(out / "angle_errors.png", lambda h: h.write(errors)),
    ]
