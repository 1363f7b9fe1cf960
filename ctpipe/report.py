"""Tables and plots of experiment results (matplotlib, written atomically)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from ctpipe.experiments import SyntheticReport
from ctpipe.io import atomic_write, write_csv, write_json

__all__ = ["synthetic_table", "write_synthetic_outputs"]

_TITLES = {
    "angle": "rotation sweep, 30 inliers + 70 re-paired outliers, sigma 1e-4",
    "near": "rotation sweep, 30 inliers + 70 outliers 2-6 px from their partner, sigma 1e-4",
    "noise": "noise sweep, 100 inliers, no outliers, alpha uniform in (-90, 90) deg",
}


def _fmt(value: float) -> str:
    return "fail" if not np.isfinite(value) else f"{value:.4f}" if value >= 1e-3 else f"{value:.1e}"


def synthetic_table(report: SyntheticReport, study: str) -> str:
    """Markdown table: one row per swept value, one column per estimator (MAE, degrees)."""
    result = report.studies[study]
    labels = report.labels
    unit = "sigma" if study == "noise" else "alpha (deg)"
    lines = [f"MAE in degrees, {report.reps} repetitions per row; {_TITLES[study]}.", "",
             "| " + unit + " | " + " | ".join(labels) + " |", "|---" * (len(labels) + 1) + "|"]
    stats = {label: result.stats(label) for label in labels}
    for v, value in enumerate(result.values):
        cells = []
        for label in labels:
            s = stats[label]
            cell = _fmt(s["mae_deg"][v])
            cells.append(cell + (f" ({s['failures'][v]} failed)" if s["failures"][v] else ""))
        lines.append(f"| {value:g} | " + " | ".join(cells) + " |")
    lines.append("| **max MAE** | " + " | ".join(_fmt(np.nanmax(stats[l]["mae_deg"])) for l in labels) + " |")
    lines.append("| failures | " + " | ".join(str(int(stats[l]["failures"].sum())) for l in labels) + " |")
    lines.append("| ms per pair | " + " | ".join(f"{result.ms_per_pair(l):.2f}" for l in labels) + " |")
    return "\n".join(lines) + "\n"


def _plot(report: SyntheticReport, study: str) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    result = report.studies[study]
    fig, ax = plt.subplots(figsize=(8, 4.8), dpi=110)
    x = np.asarray(result.values, dtype=float)
    for label in report.labels:
        stats = result.stats(label)
        ax.plot(x, stats["mae_deg"], marker="o", ms=3, label=label)
    ax.set_yscale("log")
    if study == "noise":
        ax.set_xscale("log")
        ax.set_xlabel("noise sigma (normalised units)")
    else:
        ax.set_xlabel("rotation alpha (deg)")
    ax.set_ylabel("mean absolute error (deg)")
    ax.set_title(_TITLES[study], fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    plt.close(fig)
    return buffer.getvalue()


def write_synthetic_outputs(report: SyntheticReport, out: str | Path) -> list[Path]:
    """Write ``synthetic.csv``, ``summary.json``, ``tables.md`` and one PNG per study.

    Everything is computed before the first file is written, and each file is renamed into
    place, so an interrupted run leaves no partial file.
    """
    out = Path(out)
    rows = []
    for study, result in report.studies.items():
        for label in report.labels:
            s = result.stats(label)
            for v, value in enumerate(result.values):
                rows.append([study, label, value, s["mae_deg"][v], s["std_deg"][v], s["median_deg"][v],
                             s["max_deg"][v], int(s["failures"][v]), report.reps, round(result.ms_per_pair(label), 4)])
    tables = "\n".join(f"## {study}\n\n{synthetic_table(report, study)}" for study in report.studies)
    pictures = {study: _plot(report, study) for study in report.studies}
    written = [
        write_csv(out / "synthetic.csv", ["study", "estimator", "value", "mae_deg", "std_deg", "median_deg",
                                          "max_deg", "failures", "reps", "ms_per_pair"], rows),
        write_json(out / "summary.json", report.summary()),
        atomic_write(out / "tables.md", lambda h: h.write(tables.encode())),
    ]
    for study, png in pictures.items():
        written.append(atomic_write(out / f"{study}_sweep.png", lambda h, png=png: h.write(png)))
    return written
