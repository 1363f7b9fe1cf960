"""Scenario sweeps: many ``ctpipe validate`` runs drawn from distributions, scored in one table.

A sweep is a YAML file::

    n: 30                     # scenarios drawn (``--n`` overrides)
    seed: 0                   # scenario k is drawn from numpy's default_rng([seed, k])
    base:                     # a ``ctpipe validate`` experiment (phantom, scan, pipeline, ...)
      phantom: granular
      scan: {geometry: {...}, angles: {n_views: 180}, noise: {...}}
      reconstruction: {grid_size: 96}
    draw:                     # dotted key of the experiment -> one distribution
      scan.angles.n_views: {log_integer: [24, 480]}
      scan.angles.range_deg: {choice: [360.0, 250.0], weights: [3, 1]}
      scan.geometry.source_to_object_mm: {uniform: [90.0, 260.0]}
      scan.jitter: {choice: [[{gaussian: {sigma_deg: 0.2}}], [{random_walk: {step_sigma_deg: 0.02}}]]}

Every key of the experiment can be drawn, including sections the simulator gains later, so the
sweep's reach grows with the simulator's without a change here. Distributions: ``choice``
(optionally ``weights``), ``uniform`` and ``loguniform`` over ``[low, high]``, ``integer``
and ``log_integer`` (inclusive). Scenario ``k`` depends only on ``seed`` and ``k``, so any row
is re-run alone: its whole experiment is written to ``scenarios/NNN.yaml``, which ``ctpipe
validate scenarios/NNN.yaml`` runs again.

Each scenario runs as ``ctpipe validate`` would, as a task on the execution layer (a thread
pool, or Dask workers), and becomes one row: its draw, the nominal and estimated per-view RMS
angle errors (views the pipeline gave no angle count at their nominal one, as they are
reconstructed; ``views_estimated`` says how many had one) and the refiner's own before the
gate (``ungated_rms_deg``), the PSNR gains of the estimated angles over the nominal ones
against the jitter-free scan and the phantom, how much the true angles gain (``visible_db``),
the recoveries, what the refiner kept and what the gate returned (:mod:`ctpipe.solve.gate`),
seconds.
A scenario is *worse than nominal* when its per-view RMS is above the nominal angles', or its
reconstruction falls more than :data:`WORSE_DB` below theirs against the phantom, or against the
jitter-free scan by more than the true angles' own reconstruction does. A scenario that the experiment refuses or that fails is a row with its
reason, never the end of the sweep.
"""

from __future__ import annotations

import copy
import math
import re
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources as importlib_resources
from pathlib import Path
from typing import Any

import numpy as np

from ctpipe.config import check_keys, load_yaml
from ctpipe.errors import ConfigError, CtpipeError
from ctpipe.registry import StageRegistry

__all__ = ["SweepSettings", "SweepReport", "DISTRIBUTIONS", "parse_sweep", "load_sweep_settings", "draw_scenario",
           "run_scenario", "report_row", "failure_reason", "run_sweep", "write_sweep_outputs", "worse_than_nominal"]

#: The distributions a ``draw`` entry may name.
DISTRIBUTIONS = ("choice", "uniform", "loguniform", "integer", "log_integer")
#: Most scenarios a sweep draws.
MAX_SCENARIOS = 10_000
_KEY = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")
#: The columns of ``sweep.csv`` after the drawn keys.
COLUMNS = ("scenario", "status", "nominal_rms_deg", "estimated_rms_deg", "views_estimated", "ungated_rms_deg",
           "worse_than_nominal", "gain_db", "gain_phantom_db", "visible_db", "recovery_reference", "recovery_phantom",
           "refiner_kept", "gate", "se_views", "se_within_2", "seconds", "reason")
#: How far below the nominal angles' PSNR a reconstruction may fall and still count as no worse (dB).
WORSE_DB = 0.05
#: The true angles must gain this much PSNR over the nominal ones (against the jitter-free scan) for
#: a scenario's recovery to count in the median: below it the jitter is not visible (dB).
VISIBLE_DB = 0.5


@dataclass(frozen=True)
class _Draw:
    key: str
    kind: str
    values: tuple
    weights: tuple[float, ...] | None = None

    def sample(self, rng: np.random.Generator) -> Any:
        if self.kind == "choice":
            p = None if self.weights is None else np.asarray(self.weights) / sum(self.weights)
            return copy.deepcopy(self.values[int(rng.choice(len(self.values), p=p))])
        low, high = self.values
        if self.kind == "uniform":
            return float(rng.uniform(low, high))
        if self.kind == "loguniform":
            return float(math.exp(rng.uniform(math.log(low), math.log(high))))
        if self.kind == "integer":
            return int(rng.integers(low, high + 1))
        return int(min(high, max(low, round(math.exp(rng.uniform(math.log(low), math.log(high)))))))

    def to_dict(self) -> dict:
        out: dict[str, Any] = {self.kind: list(self.values)}
        if self.weights is not None:
            out["weights"] = list(self.weights)
        return out


@dataclass(frozen=True)
class SweepSettings:
    """A validated sweep (see the module docstring)."""

    n: int
    seed: int
    base: Mapping[str, Any]
    draws: tuple[_Draw, ...]
    source: str = "built-in sweep"

    def to_dict(self) -> dict:
        return {"n": self.n, "seed": self.seed, "base": copy.deepcopy(dict(self.base)),
                "draw": {d.key: d.to_dict() for d in self.draws}, "source": self.source}


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{where}: must be a finite number, got {value!r}")
    return float(value)


def _parse_draw(key: Any, spec: Any, path: str) -> _Draw:
    where = f"{path}.{key}"
    if not isinstance(key, str) or not _KEY.match(key):
        raise ConfigError(f"{path}: a key must be a dotted experiment key such as scan.angles.n_views, got {key!r}")
    if key.split(".")[0] not in ("phantom", "scan", "pipeline", "reconstruction", "seed"):
        raise ConfigError(f"{where}: must start with phantom, scan, pipeline, reconstruction or seed")
    if not isinstance(spec, Mapping):
        raise ConfigError(f"{where}: must be one distribution, e.g. {{uniform: [1, 2]}} ({', '.join(DISTRIBUTIONS)})")
    kinds = [k for k in spec if k in DISTRIBUTIONS]
    extra = [k for k in spec if k not in DISTRIBUTIONS and k != "weights"]
    if len(kinds) != 1 or extra:
        raise ConfigError(f"{where}: give exactly one of {', '.join(DISTRIBUTIONS)} (and weights with choice), "
                          f"got {', '.join(map(str, spec)) or 'nothing'}")
    kind = kinds[0]
    values = spec[kind]
    if kind == "choice":
        if not isinstance(values, list) or not values:
            raise ConfigError(f"{where}.choice: must be a non-empty list of values")
        weights = spec.get("weights")
        if weights is not None:
            if not isinstance(weights, list) or len(weights) != len(values):
                raise ConfigError(f"{where}.weights: must be a list of {len(values)} numbers, one per choice")
            weights = tuple(_number(w, f"{where}.weights") for w in weights)
            if any(w < 0 for w in weights) or not sum(weights) > 0:
                raise ConfigError(f"{where}.weights: must be >= 0 with a positive sum, got {list(weights)}")
        return _Draw(key, kind, tuple(values), weights)
    if "weights" in spec:
        raise ConfigError(f"{where}.weights: only choice takes weights")
    if not isinstance(values, list) or len(values) != 2:
        raise ConfigError(f"{where}.{kind}: must be [low, high], got {values!r}")
    low, high = (_number(v, f"{where}.{kind}") for v in values)
    if kind in ("integer", "log_integer"):
        if low != int(low) or high != int(high):
            raise ConfigError(f"{where}.{kind}: bounds must be whole numbers, got {values!r}")
        low, high = int(low), int(high)
    if not low <= high:
        raise ConfigError(f"{where}.{kind}: low must not exceed high, got {values!r}")
    if kind in ("loguniform", "log_integer") and not low > 0:
        raise ConfigError(f"{where}.{kind}: bounds must be > 0, got {values!r}")
    return _Draw(key, kind, (low, high))


def parse_sweep(mapping: Any, registry: StageRegistry, *, path: str = "sweep", source: str = "") -> SweepSettings:
    """Validate a sweep mapping: its keys, its distributions, and its base experiment."""
    from ctpipe.evaluate.validate import parse_validate

    check_keys(mapping, path, allowed=("n", "seed", "base", "draw"), required=("base", "draw"))
    n = mapping.get("n", 30)
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_SCENARIOS:
        raise ConfigError(f"{path}.n: must be a whole number from 1 to {MAX_SCENARIOS}, got {n!r}")
    seed = mapping.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"{path}.seed: must be a whole number >= 0, got {seed!r}")
    base = mapping["base"]
    if not isinstance(base, Mapping):
        raise ConfigError(f"{path}.base: must be a validate experiment (phantom, scan, ...), got {base!r}")
    parse_validate(base, registry, path=f"{path}.base")
    draw = mapping["draw"]
    if not isinstance(draw, Mapping) or not draw:
        raise ConfigError(f"{path}.draw: must map experiment keys to distributions, e.g. "
                          f"scan.angles.n_views: {{log_integer: [24, 480]}}")
    draws = tuple(_parse_draw(key, spec, f"{path}.draw") for key, spec in draw.items())
    return SweepSettings(n=n, seed=seed, base=copy.deepcopy(dict(base)), draws=draws, source=source or "built-in sweep")


def load_sweep_settings(path: str | Path | None, registry: StageRegistry) -> SweepSettings:
    """A sweep YAML file, or the built-in ``ctpipe/evaluate/sweep.yaml`` for None."""
    if path is None:
        text = importlib_resources.files("ctpipe.evaluate").joinpath("sweep.yaml").read_text(encoding="utf-8")
        return parse_sweep(load_yaml("sweep.yaml", text=text), registry, source="built-in sweep")
    return parse_sweep(load_yaml(path), registry, path=str(path), source=str(path))


def _set(mapping: dict, key: str, value: Any) -> None:
    *parents, last = key.split(".")
    node = mapping
    for part in parents:
        child = node.get(part)
        if not isinstance(child, dict):
            child = {}
            node[part] = child
        node = child
    node[last] = value


def draw_scenario(settings: SweepSettings, index: int) -> tuple[dict, dict]:
    """Scenario ``index``: its validate experiment and the values drawn, from ``default_rng([seed, index])``."""
    rng = np.random.default_rng([settings.seed, index])
    experiment = copy.deepcopy(dict(settings.base))
    drawn = {}
    for draw in settings.draws:
        value = draw.sample(rng)
        _set(experiment, draw.key, value)
        drawn[draw.key] = value
    if not any(d.key == "seed" for d in settings.draws):
        experiment["seed"] = int(rng.integers(2**31 - 1))
    return experiment, drawn


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return (text[0] if text else type(exc).__name__)[:300]


def failure_reason(exc: Exception) -> str:
    """A failed row's reason in one line: the user's error as it is, a bug with its type."""
    if isinstance(exc, CtpipeError):
        return _one_line(exc)
    if isinstance(exc, MemoryError):
        return "out of memory"
    return f"{type(exc).__name__}: {_one_line(exc)}"


def run_scenario(experiment: Mapping[str, Any], blocked: Sequence[str] = ()) -> dict:
    """Run one scenario as ``ctpipe validate`` would; the result row's measured columns.

    A task of the execution layer (it runs on a Dask worker as well as in a thread). Whatever
    goes wrong becomes ``status: failed`` with the reason in one line, so one scenario never
    ends a sweep; only an interrupt does.
    """
    from ctpipe.evaluate.validate import parse_validate, run_validate
    from ctpipe.plugins import get_registry

    start = time.perf_counter()
    row: dict[str, Any] = {"status": "failed"}
    try:
        registry = get_registry(blocked=tuple(blocked))
        report = run_validate(parse_validate(experiment, registry, path="scenario"), registry)
    except Exception as exc:  # a bug in one scenario must not end the others; its row says what it was
        row["reason"] = failure_reason(exc)
    else:
        row.update(report_row(report))
    row["seconds"] = time.perf_counter() - start
    return row


def report_row(report) -> dict:
    """The measured columns of one scored run (a :class:`~ctpipe.evaluate.validate.ValidateReport`), ``status: ok``."""
    from ctpipe.evaluate.scoring import view_errors_deg

    views = report.angle_tables["views"]
    failed = report.failed

    def gain(reference: str, label: str = "estimated") -> float | None:
        if label in failed or "nominal" in failed:
            return None
        metrics = report.metrics[reference]
        return float(metrics[label]["psnr_db"] - metrics["nominal"]["psnr_db"])

    gains = (gain("reference"), gain("phantom"))
    nominal_rms, estimated_rms = float(views["nominal"]["rms_deg"]), float(views["estimated"]["rms_deg"])
    if views["estimated"]["estimated"] < views["estimated"]["total"]:
        # Views the pipeline gave no angle keep their nominal one, in the reconstruction as here: the
        # RMS of the angles the user gets, not of the few estimated (one view alone would score 0).
        errors = view_errors_deg(report.estimated_deg, report.true_deg)
        estimated_rms = float(np.sqrt(np.mean(errors ** 2)))
    gate = report.pipeline_result.gate
    coverage = report.se_coverage or {"views": 0, "within": 0}
    return {
        "status": "ok",
        "nominal_rms_deg": nominal_rms,
        "estimated_rms_deg": estimated_rms,
        "views_estimated": int(views["estimated"]["estimated"]),
        # The refiner's angles before the gate: how close the estimate came, where the gate held it back.
        "ungated_rms_deg": float(views.get("before the gate", views["estimated"])["rms_deg"]),
        "gain_db": gains[0],
        "gain_phantom_db": gains[1],
        "visible_db": gain("reference", "true"),
        "worse_than_nominal": None if None in gains else worse_than_nominal(
            estimated_rms, nominal_rms, gains[0], gains[1], gain("reference", "true")),
        "recovery_reference": float(report.recovery["reference"]),
        "recovery_phantom": float(report.recovery["phantom"]),
        "refiner_kept": report.pipeline_result.refiner_info.get("chosen", ""),
        "gate": "" if gate is None else gate.chosen if gate.decided else f"undecided: {gate.chosen}",
        "se_views": coverage["views"],
        "se_within_2": coverage["within"],
        "reason": "; ".join(report.problems),
    }


def worse_than_nominal(estimated_rms_deg: float, nominal_rms_deg: float, gain_db: float, gain_phantom_db: float,
                       visible_db: float | None) -> bool:
    """Whether a scenario's returned angles are worse than its nominal ones.

    Their per-view RMS above the nominal angles' (by more than rounding: angles returned as
    nominal give the nominal RMS to ~1e-15), or their reconstruction more than :data:`WORSE_DB`
    below the nominal one's against the phantom (``gain_phantom_db``), or against the jitter-free
    scan (``gain_db``) by more than the true angles' reconstruction falls below it there
    (``visible_db`` when negative). On a sparse scan the regular nominal angles share the
    jitter-free scan's streak pattern, and the true angles reconstruct up to 5.8 dB below them
    against it (scenario 6 of the built-in sweep), so without that allowance any correction,
    a perfect one included, would count as worse.
    """
    allowance = min(visible_db if visible_db is not None and math.isfinite(visible_db) else 0.0, 0.0)
    return bool(estimated_rms_deg > nominal_rms_deg + 1e-9 or gain_phantom_db < -WORSE_DB
                or gain_db < allowance - WORSE_DB)


@dataclass
class SweepReport:
    """The rows of a sweep, in scenario order, and its settings."""

    settings: SweepSettings
    rows: list[dict] = field(default_factory=list)
    experiments: list[dict] = field(default_factory=list)
    wall_s: float = 0.0

    def summary(self) -> dict:
        ok = [r for r in self.rows if r["status"] == "ok"]
        worse = [r for r in ok if r.get("worse_than_nominal")]

        def median(key: str) -> float | None:
            values = [r[key] for r in ok if r.get(key) is not None and np.isfinite(r[key])]
            return float(np.median(values)) if values else None

        visible = [r["recovery_reference"] for r in ok if (r.get("visible_db") or 0.0) >= VISIBLE_DB
                   and np.isfinite(r["recovery_reference"])]
        se_views = sum(r.get("se_views") or 0 for r in ok)
        se_within = sum(r.get("se_within_2") or 0 for r in ok)
        # What the gate did to the refiner's answer: held a closer one back, or kept a worse one out.
        gated = [r for r in ok if r.get("ungated_rms_deg") is not None and np.isfinite(r["ungated_rms_deg"])]
        held_back = [r for r in gated if r["estimated_rms_deg"] > 1.01 * r["ungated_rms_deg"]]
        kept_out = [r for r in gated if r["ungated_rms_deg"] > r["nominal_rms_deg"] + 1e-9
                    and r["estimated_rms_deg"] < r["ungated_rms_deg"]]
        return {"scenarios": len(self.rows), "ok": len(ok), "failed": len(self.rows) - len(ok),
                "worse_than_nominal": len(worse),
                "median_nominal_rms_deg": median("nominal_rms_deg"),
                "median_estimated_rms_deg": median("estimated_rms_deg"),
                "median_recovery_reference": median("recovery_reference"),
                "visible": len(visible),
                "median_recovery_visible": float(np.median(visible)) if visible else None,
                "se_views": se_views, "se_within_2": se_within,
                "se_coverage": se_within / se_views if se_views else None,
                "gate_held_back": len(held_back), "gate_kept_out": len(kept_out),
                "wall_s": self.wall_s}

    def summary_line(self) -> str:
        s = self.summary()

        def fmt(value, spec):
            return "n/a" if value is None else format(value, spec)

        return (f"{s['scenarios']} scenarios: {s['worse_than_nominal']} worse than the nominal angles, "
                f"{s['failed']} failed; median per-view RMS {fmt(s['median_estimated_rms_deg'], '.4f')} deg "
                f"(nominal {fmt(s['median_nominal_rms_deg'], '.4f')}); median recovery "
                f"{fmt(s['median_recovery_reference'], '.3f')} ({fmt(s['median_recovery_visible'], '.3f')} over the "
                f"{s['visible']} with visible jitter); {fmt(s['se_coverage'], '.1%')} of {s['se_views']} views within two "
                f"standard errors of the truth; the gate held back a closer answer on {s['gate_held_back']} and kept a "
                f"worse one out on {s['gate_kept_out']}; {s['wall_s']:.0f} s")

    def table_rows(self) -> list[dict]:
        """One flat row per scenario: the drawn keys, then :data:`COLUMNS`."""
        keys = [d.key for d in self.settings.draws]
        out = []
        for row in self.rows:
            flat = {key: row["drawn"].get(key) for key in keys}
            flat.update({column: row.get(column) for column in COLUMNS})
            out.append(flat)
        return out


def run_sweep(settings: SweepSettings, *, n: int | None = None, executor=None, blocked: Sequence[str] = (),
              progress: Callable[[int], Any] | None = None) -> SweepReport:
    """Draw ``n`` (default ``settings.n``) scenarios and run each as a task on ``executor``.

    With no executor the scenarios run one after another in this process (each already uses
    every core through numba and OpenCV); a :class:`~ctpipe.execution.DaskExecutor` spreads them
    over a cluster.
    """
    from ctpipe.execution import ThreadExecutor

    count = settings.n if n is None else int(n)
    if not 1 <= count <= MAX_SCENARIOS:
        raise ConfigError(f"--n: must be from 1 to {MAX_SCENARIOS}, got {count}")
    report = SweepReport(settings)
    draws = [draw_scenario(settings, k) for k in range(count)]
    report.experiments = [experiment for experiment, _ in draws]
    start = time.perf_counter()
    own = executor is None
    executor = executor or ThreadExecutor(1)
    try:
        handles = [executor.submit(run_scenario, experiment, tuple(blocked), name=f"scenario-{k:03d}")
                   for k, (experiment, _) in enumerate(draws)]
        results = executor.gather(handles, progress=progress)
    finally:
        if own:
            executor.close()
    report.wall_s = time.perf_counter() - start
    report.rows = [{"scenario": k, "drawn": drawn, **result} for k, ((_, drawn), result) in enumerate(zip(draws, results))]
    return report


def write_sweep_outputs(report: SweepReport, out: str | Path) -> list[Path]:
    """``sweep.csv``, ``sweep.json``, ``sweep.png`` and ``scenarios/NNN.yaml`` in ``out`` (a staged folder)."""
    import yaml

    from ctpipe.io.outputs import to_jsonable, write_csv, write_json

    out = Path(out)
    rows = report.table_rows()
    columns = list(rows[0]) if rows else [d.key for d in report.settings.draws] + list(COLUMNS)
    written = [write_csv(out / "sweep.csv", columns, [[_cell(r[c]) for c in columns] for r in rows]),
               write_json(out / "sweep.json", to_jsonable({"settings": report.settings.to_dict(),
                                                           "summary": report.summary(), "rows": report.rows}))]
    scenarios = out / "scenarios"
    scenarios.mkdir(parents=True, exist_ok=True)
    for k, experiment in enumerate(report.experiments):
        path = scenarios / f"{k:03d}.yaml"
        path.write_text(f"# scenario {k} of {report.settings.source} (seed {report.settings.seed}); re-run alone "
                        f"with: ctpipe validate {path.name}\n" + yaml.safe_dump(to_jsonable(experiment), sort_keys=False),
                        encoding="utf-8")
        written.append(path)
    written.append(_plot(report, out / "sweep.png"))
    return written


def _cell(value: Any) -> Any:
    if isinstance(value, (list, dict)):
        import json

        return json.dumps(value, separators=(",", ":"))
    return "" if value is None else value


def _plot(report: SweepReport, path: Path) -> Path:
    """Estimated against nominal per-view RMS (below the diagonal: better), and the recoveries."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in report.rows if r["status"] == "ok"]
    fig, (left, right) = plt.subplots(1, 2, figsize=(11.0, 4.8))
    if ok:
        nominal = np.array([r["nominal_rms_deg"] for r in ok])
        estimated = np.array([r["estimated_rms_deg"] for r in ok])
        worse = np.array([bool(r.get("worse_than_nominal")) for r in ok])
        low = max(1e-4, float(min(nominal.min(), estimated.min())) / 1.5)
        high = float(max(nominal.max(), estimated.max())) * 1.5
        left.plot([low, high], [low, high], color="0.6", lw=1)
        left.scatter(nominal[~worse], estimated[~worse], color="#2f7d32", label="reconstruction better")
        left.scatter(nominal[worse], estimated[worse], color="#c62828", marker="x", s=60,
                     label="reconstruction worse than nominal")
        for r in ok:
            left.annotate(str(r["scenario"]), (r["nominal_rms_deg"], r["estimated_rms_deg"]), fontsize=7,
                          xytext=(3, 3), textcoords="offset points")
        left.set(xscale="log", yscale="log", xlim=(low, high), ylim=(low, high))
        left.legend(fontsize=8, loc="upper left")
        recoveries = np.array([r["recovery_reference"] for r in ok if np.isfinite(r["recovery_reference"])])
        if recoveries.size:
            right.hist(np.clip(recoveries, -1.0, 1.5), bins=20, color="#2f5597")
        right.axvline(0.0, color="0.4", lw=1)
    failed = len(report.rows) - len(ok)
    left.set(xlabel="nominal angles: per-view RMS error (deg)", ylabel="estimated angles: per-view RMS error (deg)",
             title="each scenario (below the diagonal: closer to the truth)")
    right.set(xlabel="recovery against the jitter-free scan (1: all the true angles gain; < 0: worse)",
              ylabel="scenarios", title=f"recovery ({failed} failed, not shown)")
    fig.suptitle(report.summary_line(), fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
