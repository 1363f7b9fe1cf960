"""``ctpipe experiment compare``: pipelines scored against each other, end to end, on the same scans.

Every pipeline runs on every scenario, and every scenario is simulated once and shared: the same
jittered projections, the same jitter-free reference and the same reconstructions with the
nominal and the true angles (:func:`ctpipe.evaluate.validate.simulate_experiment`). Each
(scenario, pipeline) is scored as ``ctpipe validate`` scores it
(:func:`~ctpipe.evaluate.sweep.report_row`): per-view RMS against the truth, recovery against the jitter-free scan and the phantom, the
refiner's answer before the gate, how many views lie within two standard errors of the truth,
the seconds of each stage and the memory the stages added at their peak.

The scenarios are drawn from a sweep (the built-in ``ctpipe/evaluate/sweep.yaml`` by default:
``--n`` of them at ``--seed``) or given as ``validate`` experiment files; an experiment's own
``pipeline`` is replaced by each compared one.

**Which pipeline is better, and is it beyond noise?** For every pair of pipelines, on the
scenarios where both ran (on the angles returned, and again on the refiners' own angles before
the gate, which tell detectors apart where the gate returned the nominal angles for all): on
how many the first has the lower per-view RMS, on how many the second, and on how many they
tie (equal to 1e-9 relative: both returned the nominal angles, say). Two paired tests over the
scenarios (:func:`paired_comparison`): the sign test on wins and losses
(``scipy.stats.binomtest``), and Wilcoxon's signed-rank test on the log of the RMS ratio
(``scipy.stats.wilcoxon``; the log so that a scenario with large errors does not outweigh one
with small ones). A difference is called beyond noise at a two-sided p below
:data:`ALPHA` in the signed-rank test. The same is done per scenario class (the phantom): with
a handful of scenarios per class the tests cannot reach it, and the summary says "not beyond
noise" (or "the same on every scenario", or "cannot tell" where no scenario has both).
A pipeline that failed on a scenario has no RMS there: the pair is left out of the test and
its failures are counted beside it.

Outputs: ``compare.csv`` (one row per scenario and pipeline), ``compare.json`` (the settings,
the rows, the paired tests, the summary), ``compare.png`` (per scenario and pipeline, RMS and
recovery; each pipeline against the first, scenario by scenario), ``summary.txt`` and
``scenarios/NNN.yaml`` (each scenario as a ``ctpipe validate`` experiment, to re-run one alone).

Memory is the resident memory of the process sampled every 20 ms, less what it was when the
stage began, on Linux (``/proc/self/statm``; elsewhere not measured). Where several scenarios
share a process (a Dask worker with several threads) the figures mix them.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import itertools
import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources as importlib_resources
from pathlib import Path
from typing import Any

import numpy as np

from ctpipe.config import PipelineConfig, load_yaml, parse_pipeline
from ctpipe.evaluate.sweep import VISIBLE_DB
from ctpipe.errors import ConfigError
from ctpipe.registry import StageRegistry

__all__ = ["ComparedPipeline", "CompareSettings", "CompareReport", "BUILTIN_COMPARISONS", "ALPHA", "load_pipelines",
           "builtin_pipelines", "sweep_scenarios", "file_scenarios", "run_compare_scenario", "run_compare",
           "paired_comparison", "write_compare_outputs"]

#: Two-sided p below which a paired difference is called beyond noise.
ALPHA = 0.05
#: Relative RMS difference below which two pipelines tie on a scenario.
TIE = 1e-9
#: Built-in comparisons (``--builtin NAME``): pipelines that differ in one stage only.
BUILTIN_COMPARISONS = {
    "detectors": "the paper's three detectors (SURF, ORB, SIFT) with one matcher, the 1-point RANSAC and the view graph",
    "refiners": "the default detector, matcher and estimator with each whole-scan refiner",
}
#: The stages whose seconds are columns, in order.
STAGES = ("detect", "match", "estimate", "refine", "reconstruct", "score")
#: The columns of ``compare.csv``.
COLUMNS = ("scenario", "class", "pipeline", "status", "nominal_rms_deg", "estimated_rms_deg", "views_estimated",
           "ungated_rms_deg", "worse_than_nominal", "gain_db", "gain_phantom_db", "visible_db", "recovery_reference",
           "recovery_phantom", "refiner_kept", "gate", "se_views", "se_within_2", *(f"{stage}_s" for stage in STAGES),
           "observe_peak_mb", "refine_peak_mb", "seconds", "reason")


@dataclass(frozen=True)
class ComparedPipeline:
    """One compared pipeline: its short name (unique in the comparison), where it came from, its config."""

    name: str
    source: str
    config: PipelineConfig


@dataclass(frozen=True)
class CompareSettings:
    """What ``experiment compare`` runs: the pipelines, the scenarios (label, experiment, class), where they came from."""

    pipelines: tuple[ComparedPipeline, ...]
    scenarios: tuple[tuple[str, dict, str], ...]
    source: str

    def to_dict(self) -> dict:
        return {"pipelines": [{"name": p.name, "source": p.source, "config": p.config.to_dict()}
                              for p in self.pipelines],
                "scenarios": [{"label": label, "class": kind} for label, _, kind in self.scenarios],
                "source": self.source}


def _unique_names(paths: Sequence[Path]) -> list[str]:
    """Each file's stem; where two share one, the folder too (``a/default``), then a number."""
    names = [p.stem for p in paths]
    for k, path in enumerate(paths):
        if names.count(path.stem) > 1:
            names[k] = f"{path.parent.name}/{path.stem}" if path.parent.name else path.stem
    seen: dict[str, int] = {}
    for k, name in enumerate(names):
        if names.count(name) > 1:
            seen[name] = seen.get(name, 0) + 1
            names[k] = f"{name}#{seen[name]}"
    return names


def load_pipelines(paths: Sequence[str | Path], registry: StageRegistry, *,
                   minimum: int = 2) -> tuple[ComparedPipeline, ...]:
    """The pipeline YAML files, each validated (:func:`ctpipe.config.parse_pipeline`), named by their stems.

    Raises
    ------
    ConfigError
        Fewer than ``minimum`` files, a file that is missing or not a valid pipeline.
    """
    paths = [Path(p) for p in paths]
    if len(paths) < minimum:
        got = "none" if not paths else f"only {paths[0]}"
        raise ConfigError(f"pipelines: give at least two pipeline YAML files to compare (or --builtin "
                          f"{' or '.join(BUILTIN_COMPARISONS)}), got {got}")
    names = _unique_names(paths)
    return tuple(ComparedPipeline(name, str(path), parse_pipeline(load_yaml(path), registry, path=str(path)))
                 for name, path in zip(names, paths))


def builtin_pipelines(name: str, registry: StageRegistry) -> tuple[ComparedPipeline, ...]:
    """The pipelines of a built-in comparison (:data:`BUILTIN_COMPARISONS`), from ``ctpipe/evaluate/comparisons/``."""
    if name not in BUILTIN_COMPARISONS:
        raise ConfigError(f"--builtin: unknown comparison {name!r}; allowed: {', '.join(BUILTIN_COMPARISONS)}")
    folder = importlib_resources.files("ctpipe.evaluate").joinpath("comparisons", name)
    out = []
    for entry in sorted(folder.iterdir(), key=lambda e: e.name):
        if not entry.name.endswith(".yaml"):
            continue
        mapping = load_yaml(entry.name, text=entry.read_text(encoding="utf-8"))
        out.append(ComparedPipeline(entry.name[:-len(".yaml")], f"built-in {name}/{entry.name}",
                                    parse_pipeline(mapping, registry, path=f"{name}/{entry.name}")))
    return tuple(out)


def _phantom_class(experiment: Mapping[str, Any]) -> str:
    phantom = str(experiment.get("phantom", "?"))
    return Path(phantom).stem if phantom.endswith((".yaml", ".yml")) or "/" in phantom else phantom


def sweep_scenarios(path: str | Path | None, registry: StageRegistry, *, n: int | None = None,
                    seed: int | None = None) -> tuple[tuple[tuple[str, dict, str], ...], str]:
    """``n`` scenarios drawn from a sweep (None: the built-in one) as ``experiment sweep`` draws them."""
    from ctpipe.evaluate.sweep import MAX_SCENARIOS, draw_scenario, load_sweep_settings

    settings = load_sweep_settings(path, registry)
    if seed is not None:
        settings = dataclasses.replace(settings, seed=seed)
    count = settings.n if n is None else int(n)
    if not 1 <= count <= MAX_SCENARIOS:
        raise ConfigError(f"--n: must be from 1 to {MAX_SCENARIOS}, got {count}")
    scenarios = []
    for k in range(count):
        experiment, _ = draw_scenario(settings, k)
        experiment.pop("pipeline", None)
        scenarios.append((f"{k:03d}", experiment, _phantom_class(experiment)))
    return tuple(scenarios), f"{settings.source}, seed {settings.seed}"


def file_scenarios(paths: Sequence[str | Path], registry: StageRegistry) -> tuple[tuple[str, dict, str], ...]:
    """``validate`` experiment files, each checked as ``ctpipe validate`` checks it, with paths made absolute.

    Raises
    ------
    ConfigError
        A missing or invalid file, or one the simulation or FDK would refuse (named with its path).
    """
    from ctpipe.evaluate.validate import parse_validate

    scenarios = []
    for path in map(Path, paths):
        mapping = load_yaml(path)
        if not isinstance(mapping, dict):
            raise ConfigError(f"{path}: must be a validate experiment (phantom, scan, ...), got {type(mapping).__name__}")
        experiment = copy.deepcopy(mapping)
        experiment.pop("pipeline", None)
        base = path.resolve().parent
        for key in ("phantom", "scan"):
            value = experiment.get(key)
            if isinstance(value, str) and (key == "scan" or value.endswith((".yaml", ".yml")) or "/" in value):
                experiment[key] = str(value if Path(value).is_absolute() else base / value)
        parse_validate(experiment, registry, path=str(path))
        scenarios.append((path.stem, experiment, _phantom_class(mapping)))
    if not scenarios:
        raise ConfigError("--scenario: give at least one validate experiment file")
    return tuple(scenarios)


class _PeakMemory:
    """Resident memory sampled every 20 ms on a thread; :meth:`stage` measures the peak added during a block."""

    def __init__(self) -> None:
        import os

        self._page = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 0
        self.available = Path("/proc/self/statm").exists() and self._page > 0
        self.peaks: dict[str, float] = {}

    def _rss(self) -> int:
        with open("/proc/self/statm") as statm:
            return int(statm.read().split()[1]) * self._page

    @contextlib.contextmanager
    def stage(self, name: str):
        if not self.available:
            yield
            return
        base = peak = self._rss()
        stop = threading.Event()

        def sample() -> None:
            nonlocal peak
            while not stop.wait(0.02):
                peak = max(peak, self._rss())

        thread = threading.Thread(target=sample, daemon=True, name=f"ctpipe-memory-{name}")
        thread.start()
        try:
            yield
        finally:
            stop.set()
            thread.join()
            self.peaks[name] = (max(peak, self._rss()) - base) / 2**20


def run_compare_scenario(experiment: Mapping[str, Any], pipelines: Sequence[tuple[str, dict]],
                         blocked: Sequence[str] = ()) -> list[dict]:
    """Simulate one scenario once and score every pipeline on it; one row per pipeline.

    A task of the execution layer (a thread or a Dask worker). A scenario that cannot be
    simulated gives every pipeline a failed row with its reason; a pipeline that fails, its own.
    """
    from ctpipe.evaluate.sweep import failure_reason, report_row
    from ctpipe.evaluate.validate import parse_validate, score_pipeline, simulate_experiment
    from ctpipe.plugins import get_registry

    start = time.perf_counter()
    try:
        registry = get_registry(blocked=tuple(blocked))
        simulated = simulate_experiment(parse_validate(dict(experiment), registry, path="scenario"))
    except Exception as exc:  # one scenario must not end the others; its rows say what it was
        reason = f"scenario: {failure_reason(exc)}"
        return [{"pipeline": name, "status": "failed", "reason": reason, "seconds": time.perf_counter() - start}
                for name, _ in pipelines]
    shared_s = time.perf_counter() - start
    rows = []
    for name, mapping in pipelines:
        start = time.perf_counter()
        memory = _PeakMemory()
        row: dict[str, Any] = {"pipeline": name, "status": "failed"}

        def staged(pipeline, projections, geometry, nominal, advance):
            with memory.stage("observe"):
                observations = pipeline.observe(projections, geometry, nominal_angles_deg=nominal, progress=advance)
            with memory.stage("refine"):
                return pipeline.refine(observations)

        try:
            config = parse_pipeline(mapping, registry, path=name)
            report = score_pipeline(simulated, config, registry, pipeline_run=staged)
        except Exception as exc:  # a broken pipeline is its own row; the others still run
            row["reason"] = failure_reason(exc)
        else:
            row.update(report_row(report))
            timings = report.pipeline_result.timings_s
            row.update({f"{stage}_s": timings.get(stage) for stage in ("detect", "match", "estimate", "refine")})
            row["reconstruct_s"] = report.timings_s["reconstruct"]
            row["score_s"] = report.timings_s["score"]
        row["observe_peak_mb"] = memory.peaks.get("observe")
        row["refine_peak_mb"] = memory.peaks.get("refine")
        # Each pipeline's own seconds; the shared simulation is counted in the scenario's row only once.
        row["seconds"] = time.perf_counter() - start
        row["shared_s"] = shared_s
        rows.append(row)
    return rows


def paired_comparison(first_rms: Sequence[float], second_rms: Sequence[float], *, alpha: float = ALPHA) -> dict:
    """Paired tests of two pipelines' per-view RMS on the same scenarios (lower is better).

    NaN (a failed run) leaves the scenario out. Returns the scenarios compared, the first's
    wins, the second's wins, the ties (relative difference below :data:`TIE`), the sign test's
    and the Wilcoxon signed-rank test's two-sided p on ``log(second / first)`` (ties dropped,
    exact for small counts), the median of that log ratio, and ``better``: ``"first"``,
    ``"second"`` or ``None`` (not beyond noise at ``alpha``).
    """
    from scipy import stats

    a = np.asarray(first_rms, dtype=np.float64)
    b = np.asarray(second_rms, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError(f"first_rms and second_rms must be 1-D of one length, got {a.shape} and {b.shape}")
    both = np.isfinite(a) & np.isfinite(b)
    a, b = a[both], b[both]
    tie = np.abs(a - b) <= TIE * np.maximum(np.abs(a), np.abs(b))
    floor = 1e-12
    ratio = np.log(np.maximum(b, floor) / np.maximum(a, floor))[~tie]
    first_wins, second_wins = int(np.sum(ratio > 0)), int(np.sum(ratio < 0))
    n = first_wins + second_wins
    sign_p = float(stats.binomtest(first_wins, n, 0.5).pvalue) if n else 1.0
    wilcoxon_p = float(stats.wilcoxon(ratio).pvalue) if n else 1.0
    median = float(np.median(ratio)) if n else 0.0
    better = None
    if wilcoxon_p < alpha and median != 0.0:
        better = "first" if median > 0 else "second"
    return {"scenarios": int(both.sum()), "first_wins": first_wins, "second_wins": second_wins,
            "ties": int(tie.sum()), "sign_p": sign_p, "wilcoxon_p": wilcoxon_p, "median_log_ratio": median,
            "better": better}


@dataclass
class CompareReport:
    """Every (scenario, pipeline) row, and the settings they were run with."""

    settings: CompareSettings
    rows: list[dict] = field(default_factory=list)
    wall_s: float = 0.0

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.settings.pipelines]

    def rms(self, name: str, scenarios: Sequence[str] | None = None, *, key: str = "estimated_rms_deg") -> np.ndarray:
        """The pipeline's per-view RMS per scenario (NaN where it failed): the returned angles', or
        with ``key="ungated_rms_deg"`` the refiner's own before the gate."""
        by = {(r["scenario"], r["pipeline"]): r for r in self.rows}
        labels = [label for label, _, _ in self.settings.scenarios] if scenarios is None else scenarios
        values = []
        for label in labels:
            row = by.get((label, name))
            ok = row is not None and row["status"] == "ok" and row.get(key) is not None
            values.append(float(row[key]) if ok else math.nan)
        return np.asarray(values)

    def pairs(self) -> list[dict]:
        """Every pair of pipelines, over all scenarios and per class: :func:`paired_comparison` plus failures."""
        classes = sorted({kind for _, _, kind in self.settings.scenarios})
        out = []
        for first, second in itertools.combinations(self.names, 2):
            entry = {"first": first, "second": second,
                     "failed": {name: int(np.sum(~np.isfinite(self.rms(name)))) for name in (first, second)},
                     "all": paired_comparison(self.rms(first), self.rms(second)),
                     "before_gate": paired_comparison(self.rms(first, key="ungated_rms_deg"),
                                                      self.rms(second, key="ungated_rms_deg")),
                     "classes": {}}
            for kind in classes:
                labels = [label for label, _, k in self.settings.scenarios if k == kind]
                entry["classes"][kind] = paired_comparison(self.rms(first, labels), self.rms(second, labels))
            out.append(entry)
        return out

    def summary_lines(self) -> list[str]:
        """Per pipeline its medians, then per pair who wins how often and whether it is beyond noise."""
        lines = [f"{len(self.settings.scenarios)} scenarios ({self.settings.source}) x {len(self.names)} pipelines, "
                 f"{self.wall_s:.0f} s"]
        for name in self.names:
            mine = [r for r in self.rows if r["pipeline"] == name]
            ok = [r for r in mine if r["status"] == "ok"]
            line = f"  {name}: {len(ok)}/{len(mine)} ran"
            if ok:
                recoveries = [r["recovery_reference"] for r in ok if (r.get("visible_db") or 0.0) >= VISIBLE_DB
                              and r.get("recovery_reference") is not None and np.isfinite(r["recovery_reference"])]
                line += (f"; median per-view RMS {np.median([r['estimated_rms_deg'] for r in ok]):.4f} deg (nominal "
                         f"{np.median([r['nominal_rms_deg'] for r in ok]):.4f}); "
                         + (f"median recovery {np.median(recoveries):+.3f} over the {len(recoveries)} with visible "
                            "jitter" if recoveries else "no scenario with visible jitter")
                         + f"; {sum(bool(r.get('worse_than_nominal')) for r in ok)} worse than nominal; median "
                         f"{np.median([r['seconds'] for r in ok]):.0f} s a scenario")
            lines.append(line)
        for pair in self.pairs():
            lines.append(_pair_line(pair["first"], pair["second"], pair["all"], pair["failed"], "all scenarios"))
            lines.append("    " + _pair_line(pair["first"], pair["second"], pair["before_gate"], None,
                                             "the refiners' own angles, before the gate"))
            for kind, stats in pair["classes"].items():
                lines.append("    " + _pair_line(pair["first"], pair["second"], stats, None, kind))
        return lines


def _pair_line(first: str, second: str, stats: dict, failed: dict | None, where: str) -> str:
    if stats["scenarios"] == 0:
        verdict = "cannot tell (no scenario where both ran)"
    elif stats["better"] is None:
        verdict = ("the same on every scenario" if stats["first_wins"] + stats["second_wins"] == 0
                   else f"not beyond noise (Wilcoxon p {stats['wilcoxon_p']:.2g}, sign test p {stats['sign_p']:.2g})")
    else:
        winner = first if stats["better"] == "first" else second
        verdict = (f"{winner} better beyond noise (Wilcoxon p {stats['wilcoxon_p']:.2g}, sign test p "
                   f"{stats['sign_p']:.2g}; median RMS ratio {math.exp(abs(stats['median_log_ratio'])):.2f}x)")
    failures = "" if not failed or not any(failed.values()) else \
        "; failed: " + ", ".join(f"{name} {count}" for name, count in failed.items() if count)
    return (f"{first} vs {second}, {where}: {first} closer on {stats['first_wins']}, {second} on "
            f"{stats['second_wins']}, tied on {stats['ties']} of {stats['scenarios']}: {verdict}{failures}")


def run_compare(settings: CompareSettings, *, executor=None, blocked: Sequence[str] = (),
                progress: Callable[[int], Any] | None = None) -> CompareReport:
    """Every pipeline on every scenario, one task per scenario on ``executor`` (default: here, one after another)."""
    from ctpipe.execution import ThreadExecutor

    report = CompareReport(settings)
    pipelines = [(p.name, p.config.to_dict()) for p in settings.pipelines]
    start = time.perf_counter()
    own = executor is None
    executor = executor or ThreadExecutor(1)
    try:
        handles = [executor.submit(run_compare_scenario, experiment, pipelines, tuple(blocked), name=f"scenario-{label}")
                   for label, experiment, _ in settings.scenarios]
        results = executor.gather(handles, progress=progress)
    finally:
        if own:
            executor.close()
    report.wall_s = time.perf_counter() - start
    for (label, _, kind), rows in zip(settings.scenarios, results):
        report.rows.extend({"scenario": label, "class": kind, **row} for row in rows)
    return report


def write_compare_outputs(report: CompareReport, out: str | Path) -> list[Path]:
    """``compare.csv``, ``compare.json``, ``compare.png``, ``summary.txt`` and ``scenarios/*.yaml`` in ``out``."""
    import yaml

    from ctpipe.evaluate.sweep import _cell
    from ctpipe.io.outputs import atomic_write, to_jsonable, write_csv, write_json

    out = Path(out)
    lines = report.summary_lines()
    picture = _plot(report, lines)
    written = [
        write_csv(out / "compare.csv", list(COLUMNS), [[_cell(row.get(c)) for c in COLUMNS] for row in report.rows]),
        write_json(out / "compare.json", to_jsonable({"settings": report.settings.to_dict(), "pairs": report.pairs(),
                                                      "summary": lines, "rows": report.rows,
                                                      "wall_s": report.wall_s})),
        atomic_write(out / "compare.png", lambda h: h.write(picture)),
        atomic_write(out / "summary.txt", lambda h: h.write(("\n".join(lines) + "\n").encode("utf-8"))),
    ]
    scenarios = out / "scenarios"
    scenarios.mkdir(parents=True, exist_ok=True)
    for label, experiment, _ in report.settings.scenarios:
        path = scenarios / f"{label}.yaml"
        path.write_text(f"# scenario {label} of {report.settings.source}; re-run one pipeline on it with: ctpipe "
                        f"validate {path.name} (add pipeline: PIPELINE.yaml)\n"
                        + yaml.safe_dump(to_jsonable(experiment), sort_keys=False), encoding="utf-8")
        written.append(path)
    return written


def _plot(report: CompareReport, lines: list[str]) -> bytes:
    """Per scenario and pipeline the RMS and the recovery; each pipeline against the first; PNG bytes."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    names = report.names
    labels = [label for label, _, _ in report.settings.scenarios]
    kinds = {label: kind for label, _, kind in report.settings.scenarios}
    by = {(r["scenario"], r["pipeline"]): r for r in report.rows}
    x = np.arange(len(labels))
    width = 0.8 / max(len(names), 1)
    colours = plt.get_cmap("tab10")
    fig, (rms_ax, rec_ax, pair_ax) = plt.subplots(1, 3, figsize=(16.0, 5.2))
    nominal = [next((by[(label, n)]["nominal_rms_deg"] for n in names
                     if by.get((label, n), {}).get("nominal_rms_deg") is not None), math.nan) for label in labels]
    rms_ax.scatter(x, nominal, marker="_", s=400, color="0.3", label="nominal angles", zorder=3)
    for k, name in enumerate(names):
        offset = (k - (len(names) - 1) / 2) * width
        rms = report.rms(name)
        rms_ax.bar(x + offset, np.nan_to_num(rms, nan=0.0), width, color=colours(k % 10), label=name)
        own = report.rms(name, key="ungated_rms_deg")
        rms_ax.scatter(x + offset, own, facecolors="none", edgecolors="black", s=18, zorder=4,
                       label="the refiner's own, before the gate" if k == 0 else None)
        failed = ~np.isfinite(rms)
        if failed.any():
            rms_ax.scatter(x[failed] + offset, np.full(failed.sum(), np.nanmin(nominal) if np.isfinite(nominal).any()
                                                       else 1e-3), marker="x", color=colours(k % 10), zorder=4)
        recovery = [by.get((label, name), {}).get("recovery_reference") for label in labels]
        recovery = np.array([math.nan if v is None else v for v in recovery], dtype=float)
        rec_ax.bar(x + offset, np.clip(np.nan_to_num(recovery, nan=0.0), -1.0, 1.5), width, color=colours(k % 10),
                   label=name)
        for position in (x + offset)[~np.isfinite(recovery)]:
            rec_ax.text(position, 0.02, "n/a", rotation=90, fontsize=6, ha="center", va="bottom", color="0.4")
    ticks = [f"{label}\n{kinds[label]}" for label in labels]
    finite = np.array([v for v in nominal if np.isfinite(v)] + [v for n in names for v in report.rms(n) if np.isfinite(v)])
    if finite.size and finite.min() > 0:
        rms_ax.set_yscale("log")
    rms_ax.set(xticks=x, ylabel="per-view RMS error against the truth (deg)")
    rms_ax.set_title("RMS per scenario (bars: returned; dash: nominal; x: failed)", fontsize=9)
    rms_ax.set_xticklabels(ticks, fontsize=7, rotation=45, ha="right")
    rms_ax.legend(fontsize=6, loc="best")
    rec_ax.axhline(0.0, color="0.4", lw=1)
    rec_ax.axhline(1.0, color="0.6", lw=1, ls="--")
    rec_ax.set(xticks=x, ylabel="recovery vs the jitter-free scan (1: what the true angles gain)")
    rec_ax.set_title("recovery per scenario (clipped to [-1, 1.5]; n/a: not visible or failed)", fontsize=9)
    rec_ax.set_xticklabels(ticks, fontsize=7, rotation=45, ha="right")
    first = report.rms(names[0])
    first_own = report.rms(names[0], key="ungated_rms_deg")
    for k, name in enumerate(names[1:], start=1):
        other = report.rms(name)
        pair_ax.scatter(first, other, color=colours(k % 10), label=f"{name} (below the diagonal: closer than "
                                                                   f"{names[0]})")
        pair_ax.scatter(first_own, report.rms(name, key="ungated_rms_deg"), facecolors="none",
                        edgecolors=colours(k % 10), label=f"{name}, before the gate")
        for label, a, b in zip(labels, first, other):
            if np.isfinite(a) and np.isfinite(b):
                pair_ax.annotate(label, (a, b), fontsize=6, xytext=(3, 3), textcoords="offset points")
    pair = np.concatenate([first, first_own, *(report.rms(n, key=key) for n in names[1:]
                                               for key in ("estimated_rms_deg", "ungated_rms_deg"))])
    pair = pair[np.isfinite(pair) & (pair > 0)]
    if pair.size:
        low, high = pair.min() / 1.5, pair.max() * 1.5
        pair_ax.plot([low, high], [low, high], color="0.6", lw=1)
        pair_ax.set(xscale="log", yscale="log", xlim=(low, high), ylim=(low, high))
    pair_ax.set(xlabel=f"{names[0]}: per-view RMS (deg)", ylabel="other pipeline: per-view RMS (deg)")
    pair_ax.set_title(f"each pipeline against {names[0]}, scenario by scenario", fontsize=9)
    pair_ax.legend(fontsize=7, loc="upper left")
    for axis in (rms_ax.yaxis, pair_ax.xaxis, pair_ax.yaxis):
        axis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        axis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    pairs = [line for line in lines if " vs " in line and not line.startswith("    ")]
    fig.suptitle("\n".join(pairs[:4]), fontsize=8)
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100)
    plt.close(fig)
    return buffer.getvalue()
