"""Tables and plots of experiment results (matplotlib, written atomically)."""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ctpipe.evaluate.experiments import SyntheticReport
from ctpipe.io.outputs import atomic_write, write_csv, write_json
from ctpipe.pipeline import ScanResult

__all__ = ["synthetic_table", "write_synthetic_outputs", "slices_png", "angle_errors_png", "estimate_angles_png",
           "keypoints_png"]

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


def _pyplot():
    """matplotlib.pyplot on the Agg backend: figures are rendered to PNG bytes, never shown."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _figure_png(fig) -> bytes:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    _pyplot().close(fig)
    return buffer.getvalue()


def _plot(report: SyntheticReport, study: str) -> bytes:
    plt = _pyplot()
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
    return _figure_png(fig)


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


# --- ctpipe validate -------------------------------------------------------------------------


def slices_png(volumes: dict[str, np.ndarray], reference: np.ndarray, *, axial_index: int, vertical_index: int,
               title: str = "") -> bytes:
    """Reconstructed slices side by side with their differences to ``reference``.

    Parameters
    ----------
    volumes : dict of label -> ndarray of shape (n_y, n_z, n_x)
        E.g. ``{"nominal angles": ..., "estimated angles": ..., "true angles": ...}``.
    reference : ndarray of shape (n_y, n_z, n_x)
        Shown in the first column; differences are ``volume - reference``.
    axial_index, vertical_index : int
        The axial slice ``[axial_index]`` (perpendicular to the rotation axis) and the vertical
        slice ``[:, vertical_index, :]`` (through the axis) that are shown.
    """
    plt = _pyplot()

    columns = {"phantom": reference, **volumes}
    low, high = np.percentile(reference, [0.5, 99.5])
    spread = max(float(np.percentile(np.abs(np.stack(list(volumes.values())) - reference), 99.5)), 1e-12)
    fig, axes = plt.subplots(4, len(columns), figsize=(3.1 * len(columns), 12.0), dpi=100, squeeze=False)
    cuts = (("axial", lambda v: v[axial_index]), ("vertical", lambda v: v[:, vertical_index, :]))
    for c, (label, volume) in enumerate(columns.items()):
        for r, (cut, take) in enumerate(cuts):
            ax = axes[2 * r, c]
            ax.imshow(take(volume), cmap="gray", vmin=low, vmax=high, interpolation="nearest")
            ax.set_title(f"{label}\n{cut} slice", fontsize=9)
            ax = axes[2 * r + 1, c]
            if label == "phantom":
                ax.axis("off")
                ax.text(0.5, 0.5, f"differences to the phantom\n(colour range +-{spread:.3g} /mm)", ha="center",
                        va="center", fontsize=9, transform=ax.transAxes)
                continue
            ax.imshow(take(volume) - take(reference), cmap="RdBu_r", vmin=-spread, vmax=spread, interpolation="nearest")
            ax.set_title(f"{label} - phantom", fontsize=9)
        for ax in axes[:, c]:
            ax.set_xticks([])
            ax.set_yticks([])
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _figure_png(fig)


def angle_errors_png(view_errors_deg: dict[str, np.ndarray], title: str = "", *,
                     ylabel: str = "angle error (deg), common offset removed",
                     scale_to: Sequence[str] | None = None) -> bytes:
    """Per-view angle error (degrees) of each angle set against the truth, one line each (NaN: a gap).

    ``scale_to`` names the curves the vertical axis is fitted to (default: all). A curve that
    goes past them (pairs chained tens of degrees off, beside nominal and estimated angles a few
    tenths of a degree off) is clipped there and said to be, and a second panel below shows
    every curve at its full scale, so neither flattens the others to a line.
    """
    plt = _pyplot()

    curves = {label: np.asarray(errors, dtype=float) for label, errors in view_errors_deg.items()}

    def extent(values: np.ndarray) -> float:
        finite = np.abs(values[np.isfinite(values)])
        return float(finite.max()) if finite.size else 0.0

    scaled = [label for label in (curves if scale_to is None else scale_to) if label in curves]
    limit = 1.15 * max([extent(curves[label]) for label in scaled] + [1e-6])
    beyond = [label for label, values in curves.items() if extent(values) > limit]
    panels = 2 if beyond else 1
    fig, axes = plt.subplots(panels, 1, figsize=(9, 4.2 if panels == 1 else 6.4), dpi=110, squeeze=False,
                             gridspec_kw={"height_ratios": [3, 1.4][:panels]})
    for row, ax in enumerate(axes[:, 0]):
        for label, errors in curves.items():
            finite = errors[np.isfinite(errors)]
            rms = np.sqrt(np.mean(finite**2)) if finite.size else np.nan
            mae = np.mean(np.abs(finite)) if finite.size else np.nan
            note = f" (RMS {rms:.3g}, MAE {mae:.3g} deg)"
            if row == 0 and label in beyond:
                note += f"; off this scale, max {extent(errors):.3g} deg: see below"
            ax.plot(np.arange(len(errors)), errors, lw=1, label=(label + note) if row == 0 else label)
        ax.axhline(0.0, color="k", lw=0.5)
        ax.grid(True, alpha=0.3)
        if row == 0:
            if beyond:
                ax.set_ylim(-limit, limit)
            ax.set_ylabel(ylabel)
            ax.legend(fontsize=8)
            if title:
                ax.set_title(title, fontsize=9)
        else:
            ax.set_ylabel("full scale (deg)", fontsize=8)
    axes[-1, 0].set_xlabel("view")
    fig.tight_layout()
    return _figure_png(fig)


def estimate_angles_png(result: ScanResult) -> bytes | None:
    """The angles.png of ``ctpipe estimate``: the estimate minus each reference angle set it has, per view.

    One line each for the nominal angles, the scanner's logged angles and the true angles
    (:func:`ctpipe.evaluate.scoring.score_against_truth`), as far as ``result`` knows them, each
    after its median offset; None when it knows none.
    """
    columns = result.angle_columns()
    curves = {name.replace("_", " "): columns[name] for name in ("estimated_minus_nominal_deg",
                                                                  "estimated_minus_recorded_deg") if name in columns}
    if "error_deg" in columns:
        curves["estimated minus true"] = columns["error_deg"]
    if "refiner_deg" in columns and "nominal_deg" in columns:
        curves["refiner's angles (not returned) minus nominal"] = columns["refiner_deg"] - columns["nominal_deg"]
    if not curves:
        return None
    scan = result.scan
    title = f"{scan.format} scan {scan.path.name}" if scan is not None else ""
    gate = result.gate
    verdict = None
    if gate is not None and not gate.decided and gate.chosen == "nominal":
        verdict = "nominal angles returned: the projections could not be asked"
    elif gate is not None and gate.decided:
        verdict = ("nominal angles returned: the projections do not show the correction better" if gate.chosen == "nominal"
                   else f"{gate.chosen} returned: conjugate rays agree {gate.improvement:.0%} better than nominal")
    if verdict is not None:
        title = f"{title}\ngate: {verdict}" if title else f"gate: {verdict}"
    named = {k[:-4] if k.endswith(" deg") else k: v for k, v in curves.items()}
    # The returned angles set the scale; a refiner's answer the gate held back may be far off.
    return angle_errors_png(named, title, ylabel="difference (deg), median offset removed",
                            scale_to=[k for k in named if not k.startswith("refiner's")] or None)


# --- ctpipe detect ---------------------------------------------------------------------------


def keypoints_png(image: np.ndarray, features, title: str = "", *, scale: int | None = None,
                  min_side_px: int = 768) -> bytes:
    """The image in grey with every keypoint drawn as a circle and an orientation tick.

    Parameters
    ----------
    image : ndarray of shape (rows, cols)
        Shown as the OpenCV detectors see it: mapped linearly from its [min, max] to 8 bits
        (:func:`ctpipe.images.to_uint8`).
    features : ctpipe.data.Features
        Each keypoint is a circle of diameter ``size`` pixels centred on ``xy`` (x=col, y=row,
        pixel centres at integers) with a radius drawn at ``angle_deg``, measured from +x
        towards +y in image coordinates (y down), OpenCV's convention; no tick where the
        angle is NaN.
    title : str
        Written in the top-left corner (inside the picture, so it does not change the size).
    scale : int, optional
        Output pixels per image pixel. Default: the smallest integer that makes the longer
        side at least ``min_side_px``, so the circles of small keypoints stay visible.
    min_side_px : int
        See ``scale``.

    Returns
    -------
    bytes
        A PNG of exactly ``(rows * scale, cols * scale)`` pixels.
    """
    plt = _pyplot()
    from matplotlib.collections import EllipseCollection, LineCollection

    from ctpipe.images import to_uint8

    grey = to_uint8(image)
    rows, cols = grey.shape
    if scale is None:
        scale = max(1, -(-min_side_px // max(rows, cols)))
    # One figure inch per 100 output pixels, and axes filling the figure, so one image pixel
    # is exactly ``scale`` PNG pixels and keypoint coordinates map onto the picture unchanged.
    dpi = 100
    fig = plt.figure(figsize=(cols * scale / dpi, rows * scale / dpi), dpi=dpi)
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.imshow(grey, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
    ax.set_xlim(-0.5, cols - 0.5)
    ax.set_ylim(rows - 0.5, -0.5)
    ax.axis("off")
    if len(features):
        xy = np.asarray(features.xy, dtype=np.float64)
        size = np.asarray(features.size, dtype=np.float64)
        colour = (1.0, 0.85, 0.0, 0.9)
        # units="xy": diameters in data units (image pixels), whatever the output scale.
        ax.add_collection(EllipseCollection(size, size, np.zeros(len(size)), units="xy", offsets=xy,
                                            offset_transform=ax.transData, facecolors="none",
                                            edgecolors=[colour], linewidths=1.0))
        angle = np.deg2rad(np.asarray(features.angle_deg, dtype=np.float64))
        oriented = np.isfinite(angle)
        # The y axis points down (imshow's origin "upper"), so +sin goes down the picture,
        # as OpenCV's angles do; no flip needed.
        tip = xy[oriented] + 0.5 * size[oriented, None] * np.stack([np.cos(angle[oriented]),
                                                                   np.sin(angle[oriented])], axis=1)
        ax.add_collection(LineCollection(np.stack([xy[oriented], tip], axis=1), colors=[colour], linewidths=1.0))
    if title:
        ax.text(0.01, 0.99, title, transform=ax.transAxes, ha="left", va="top", fontsize=9, color="white",
                bbox={"facecolor": "black", "alpha": 0.6, "edgecolor": "none", "pad": 2})
    return _figure_png(fig)
