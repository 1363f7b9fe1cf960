"""The paper's synthetic experiments: every estimator on the same random correspondences.

Three studies:

``angle``  rotation swept over (-90, 90) deg, 30 inliers + 70 outliers re-paired at random;
``near``   the same sweep, outliers a few pixels from their true partner;
``noise``  sigma swept over 1e-6..1e-3 with 100 inliers and no outliers.

Work is split into blocks of repetitions run in worker processes; every trial draws its data
from its own seed ``(seed, study, value, repetition)``, so results do not depend on the number
of workers.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from ctpipe.config import StageSpec, build_stage, check_keys, load_yaml, parse_stage
from ctpipe.errors import ConfigError
from ctpipe.evaluate.synthetic import Cylinder, make_correspondences
from ctpipe.model import wrap_deg
from ctpipe.plugins import get_registry
from ctpipe.registry import StageRegistry
from ctpipe.stages import ParamSpec, check_value

__all__ = ["SyntheticSettings", "load_synthetic_settings", "run_synthetic", "SyntheticReport", "STUDIES"]

STUDIES = ("angle", "near", "noise")


@dataclass(frozen=True)
class EstimatorEntry:
    label: str
    spec: StageSpec


@dataclass(frozen=True)
class SyntheticSettings:
    """A validated synthetic-experiment description (see ``ctpipe/evaluate/synthetic.yaml``)."""

    cylinder: Cylinder
    reps: int
    seed: int
    angles_deg: tuple[float, ...]
    n_inliers: int
    n_outliers: int
    sigma: float
    outlier_models: tuple[str, ...]
    near_px: tuple[float, float]
    noise_sigmas: tuple[float, ...]
    noise_n_inliers: int
    noise_n_outliers: int
    noise_angle_range_deg: tuple[float, float]
    estimators: tuple[EstimatorEntry, ...]


def _spec(name, annotation, **bounds) -> ParamSpec:
    return ParamSpec(name, annotation, None, "", **bounds)


def _get(mapping: Mapping, key: str, spec: ParamSpec, path: str):
    if key not in mapping:
        raise ConfigError(f"{path}.{key}: missing; it is required")
    return check_value(spec, mapping[key], f"{path}.{key}")


def _pair(mapping: Mapping, key: str, path: str, **bounds) -> tuple[float, float]:
    value = _get(mapping, key, _spec(key, tuple[float, ...], **bounds), path)
    if len(value) != 2 or not value[0] <= value[1]:
        raise ConfigError(f"{path}.{key}: must be a list [low, high] with low <= high, got {list(value)!r}")
    return tuple(float(v) for v in value)


def parse_synthetic(mapping: Any, registry: StageRegistry, path: str = "experiment") -> SyntheticSettings:
    """Validate an experiment mapping strictly; errors name the YAML path."""
    check_keys(mapping, path, allowed=("cylinder", "reps", "seed", "angle_sweep", "noise_sweep", "estimators"),
               required=("cylinder", "reps", "seed", "angle_sweep", "noise_sweep", "estimators"))
    cyl = check_keys(mapping["cylinder"], f"{path}.cylinder", allowed=("axis_distance", "height", "radius"),
                     required=("axis_distance", "height", "radius"))
    positive = _spec("", float, gt=0)
    cylinder = Cylinder(**{k: _get(cyl, k, positive, f"{path}.cylinder") for k in ("axis_distance", "height", "radius")})
    if cylinder.radius >= cylinder.axis_distance:
        raise ConfigError(f"{path}.cylinder.radius: must be < axis_distance ({cylinder.axis_distance:g}) so every "
                          f"point lies in front of the source, got {cylinder.radius:g}")
    sweep_path = f"{path}.angle_sweep"
    sweep = check_keys(mapping["angle_sweep"], sweep_path,
                       allowed=("angles_deg", "n_inliers", "n_outliers", "sigma", "outlier_models", "near_px"),
                       required=("angles_deg", "n_inliers", "n_outliers", "sigma", "outlier_models", "near_px"))
    models = _get(sweep, "outlier_models", _spec("", tuple[str, ...]), sweep_path)
    for k, model in enumerate(models):
        if model not in ("repaired", "near"):
            raise ConfigError(f"{sweep_path}.outlier_models[{k}]: must be 'repaired' or 'near', got {model!r}")
    noise_path = f"{path}.noise_sweep"
    noise = check_keys(mapping["noise_sweep"], noise_path,
                       allowed=("sigmas", "n_inliers", "n_outliers", "angle_range_deg"),
                       required=("sigmas", "n_inliers", "n_outliers", "angle_range_deg"))
    entries = mapping["estimators"]
    if not isinstance(entries, list) or not entries:
        raise ConfigError(f"{path}.estimators: must be a non-empty list of estimator mappings, got {entries!r}")
    estimators, labels = [], set()
    for k, entry in enumerate(entries):
        entry_path = f"{path}.estimators[{k}]"
        if not isinstance(entry, Mapping):
            raise ConfigError(f"{entry_path}: must be a mapping with 'name' and parameters, got {entry!r}")
        body = dict(entry)
        label = body.pop("label", body.get("name"))
        if not isinstance(label, str) or label in labels:
            raise ConfigError(f"{entry_path}.label: must be a unique string, got {label!r}")
        labels.add(label)
        estimators.append(EstimatorEntry(label, parse_stage(body, "estimator", registry, entry_path)))
    return SyntheticSettings(
        cylinder=cylinder,
        reps=_get(mapping, "reps", _spec("", int, ge=1), path),
        seed=_get(mapping, "seed", _spec("", int, ge=0), path),
        angles_deg=_get(sweep, "angles_deg", _spec("", tuple[float, ...], ge=-180, le=180), sweep_path),
        n_inliers=_get(sweep, "n_inliers", _spec("", int, ge=1), sweep_path),
        n_outliers=_get(sweep, "n_outliers", _spec("", int, ge=0), sweep_path),
        sigma=_get(sweep, "sigma", _spec("", float, ge=0), sweep_path),
        outlier_models=models,
        near_px=_pair(sweep, "near_px", sweep_path, ge=0),
        noise_sigmas=_get(noise, "sigmas", _spec("", tuple[float, ...], ge=0), noise_path),
        noise_n_inliers=_get(noise, "n_inliers", _spec("", int, ge=1), noise_path),
        noise_n_outliers=_get(noise, "n_outliers", _spec("", int, ge=0), noise_path),
        noise_angle_range_deg=_pair(noise, "angle_range_deg", noise_path, ge=-180, le=180),
        estimators=tuple(estimators),
    )


def load_synthetic_settings(path: str | Path | None = None, *, registry: StageRegistry | None = None) -> SyntheticSettings:
    """The built-in experiment (``path=None``) or one from a YAML file."""
    registry = registry or get_registry()
    if path is None:
        text = resources.files("ctpipe.evaluate").joinpath("synthetic.yaml").read_text(encoding="utf-8")
        return parse_synthetic(load_yaml("ctpipe/evaluate/synthetic.yaml", text=text), registry)
    return parse_synthetic(load_yaml(path), registry)


# --- running -------------------------------------------------------------------------------

def _studies(settings: SyntheticSettings) -> list[tuple[str, tuple[float, ...]]]:
    studies = [("angle" if model == "repaired" else "near", settings.angles_deg) for model in settings.outlier_models]
    studies.append(("noise", settings.noise_sigmas))
    return studies


_WORKER: dict[str, Any] = {}


def _init_worker(settings: SyntheticSettings, blocked: tuple[str, ...]) -> None:
    registry = get_registry(blocked=blocked)
    _WORKER["settings"] = settings
    _WORKER["estimators"] = [build_stage(e.spec, registry) for e in settings.estimators]


def _angle_error_deg(estimate_rad: float, truth_rad: float) -> float:
    return float(abs(wrap_deg(np.rad2deg(estimate_rad - truth_rad))))


def _run_block(study: str, value_index: int, reps: range, seed: int) -> tuple[str, int, np.ndarray, np.ndarray]:
    """Errors (E, len(reps)) in degrees (NaN: failure) and seconds spent per estimator (E,)."""
    settings: SyntheticSettings = _WORKER["settings"]
    estimators = _WORKER["estimators"]
    study_index = STUDIES.index(study)
    errors = np.full((len(estimators), len(reps)), np.nan)
    seconds = np.zeros(len(estimators))
    for column, rep in enumerate(reps):
        rng = np.random.default_rng([seed, study_index, value_index, rep])
        if study == "noise":
            alpha = np.deg2rad(rng.uniform(*settings.noise_angle_range_deg))
            kwargs = dict(n_inliers=settings.noise_n_inliers, n_outliers=settings.noise_n_outliers,
                          sigma=settings.noise_sigmas[value_index])
        else:
            alpha = np.deg2rad(settings.angles_deg[value_index])
            kwargs = dict(n_inliers=settings.n_inliers, n_outliers=settings.n_outliers, sigma=settings.sigma,
                          outliers="repaired" if study == "angle" else "near", near_px=settings.near_px)
        q_a, q_b, _ = make_correspondences(alpha, rng, cylinder=settings.cylinder, **kwargs)
        for row, estimator in enumerate(estimators):
            start = time.perf_counter()
            result = estimator.estimate(q_a, q_b, rng=np.random.default_rng([seed, study_index, value_index, rep, row]))
            seconds[row] += time.perf_counter() - start
            if result:
                errors[row, column] = _angle_error_deg(result.angle_rad, alpha)
    return study, value_index, errors, seconds


@dataclass(frozen=True)
class StudyResult:
    """One study: per estimator label, per swept value, the error statistics."""

    study: str
    values: tuple[float, ...]
    errors_deg: dict[str, np.ndarray]  # label -> (n_values, reps), NaN = failure
    seconds: dict[str, float]  # label -> total estimation time

    def stats(self, label: str) -> dict[str, np.ndarray]:
        errors = self.errors_deg[label]
        return {
            "mae_deg": _rows(errors, np.nanmean),
            "std_deg": _rows(errors, np.nanstd),
            "median_deg": _rows(errors, np.nanmedian),
            "max_deg": _rows(errors, np.nanmax),
            "failures": np.isnan(errors).sum(axis=1),
        }

    def ms_per_pair(self, label: str) -> float:
        return 1e3 * self.seconds[label] / self.errors_deg[label].size


def _rows(errors: np.ndarray, reduce: Callable) -> np.ndarray:
    """Reduce each row over its successes; NaN for a row where everything failed."""
    return np.array([reduce(row) if np.isfinite(row).any() else np.nan for row in errors])


@dataclass(frozen=True)
class SyntheticReport:
    settings: SyntheticSettings
    reps: int
    seed: int
    studies: dict[str, StudyResult]
    wall_s: float

    @property
    def labels(self) -> list[str]:
        return [e.label for e in self.settings.estimators]

    def summary(self) -> dict[str, Any]:
        """JSON summary; ``estimators`` holds the paper's angle sweep (re-paired outliers)."""
        def study_dict(study: StudyResult, key: str) -> dict:
            out = {}
            for label in self.labels:
                s = study.stats(label)
                out[label] = {key: list(study.values), "mae_deg": s["mae_deg"], "median_deg": s["median_deg"],
                              "max_deg": s["max_deg"], "failures": s["failures"],
                              "ms_per_pair": study.ms_per_pair(label)}
            return out

        summary: dict[str, Any] = {}
        if "angle" in self.studies:
            summary["estimators"] = study_dict(self.studies["angle"], "angles_deg")
        if "near" in self.studies:
            summary["near_outliers"] = study_dict(self.studies["near"], "angles_deg")
        summary["noise_sweep"] = study_dict(self.studies["noise"], "sigmas")
        summary["reps"] = self.reps
        summary["seed"] = self.seed
        summary["wall_s"] = self.wall_s
        summary["estimator_configs"] = {e.label: e.spec.to_dict() for e in self.settings.estimators}
        return summary


def run_synthetic(settings: SyntheticSettings, *, reps: int | None = None, seed: int | None = None,
                  jobs: int | None = None, blocked: tuple[str, ...] = (),
                  progress: Callable[[int], None] | None = None) -> SyntheticReport:
    """Run every study for every estimator of ``settings``.

    Parameters
    ----------
    reps, seed : int, optional
        Override the settings' repetitions per swept value and seed.
    jobs : int, optional
        Worker processes (default: the number of CPUs). ``1`` runs in this process.
    progress : callable, optional
        Called with the number of finished trials after every block.
    """
    reps = settings.reps if reps is None else reps
    seed = settings.seed if seed is None else seed
    jobs = jobs or os.cpu_count() or 1
    studies = _studies(settings)
    block = max(1, min(reps, 25))
    tasks = [(study, v, range(r, min(reps, r + block)), seed)
             for study, values in studies for v in range(len(values)) for r in range(0, reps, block)]
    labels = [e.label for e in settings.estimators]
    errors = {study: np.full((len(labels), len(values), reps), np.nan) for study, values in studies}
    seconds = {study: np.zeros(len(labels)) for study, _ in studies}

    def collect(task, result) -> None:
        study, v, block_reps, _ = task
        _, _, err, sec = result
        errors[study][:, v, block_reps.start:block_reps.stop] = err
        seconds[study] += sec
        if progress is not None:
            progress(len(block_reps))

    wall = time.perf_counter()
    if jobs == 1:
        _init_worker(settings, blocked)
        for task in tasks:
            collect(task, _run_block(*task))
    else:
        with ProcessPoolExecutor(max_workers=jobs, initializer=_init_worker, initargs=(settings, blocked)) as pool:
            for task, result in zip(tasks, pool.map(_run_block, *zip(*tasks))):
                collect(task, result)
    wall = time.perf_counter() - wall
    results = {
        study: StudyResult(study, values, {label: errors[study][e] for e, label in enumerate(labels)},
                           {label: float(seconds[study][e]) for e, label in enumerate(labels)})
        for study, values in studies
    }
    return SyntheticReport(settings, reps, seed, results, wall)
