"""Draw docs/architecture.png: how data flows through ctpipe, and the module that owns each arrow.

    python docs/architecture_figure.py [--out docs/architecture.png]

The boxes and arrows are the tables ``DATA`` and ``ARROWS`` below; ``tests/test_architecture.py``
imports them and checks that every module and name they cite exists, so the picture cannot
silently go stale after a move.
"""

from __future__ import annotations

import argparse
from pathlib import Path

#: Data boxes: key -> (title, what it is in code, (x, y) centre in figure units).
DATA = {
    "files": ("scan on disk", "Nikon, Zeiss, SkyScan, Waygate, NSI", (2.0, 20.4)),
    "phantom": ("phantom + scan spec", "phantoms/*.yaml, jitter, noise", (8.4, 20.4)),
    "projections": ("projections", "ndarray (V, rows, cols) + Geometry", (5.2, 17.9)),
    "features": ("features", "data.Features, one per view", (5.2, 15.4)),
    "matches": ("matches", "data.Matches, one per view pair", (5.2, 12.9)),
    "pairs": ("pair estimates", "data.PairEstimate -> ScanObservations", (5.2, 10.4)),
    "tracks": ("feature tracks", "solve.tracks.Tracks", (1.6, 7.9)),
    "solution": ("whole-scan solution", "data.ScanSolution", (5.2, 5.4)),
    "angles": ("result", "ScanResult: angles, geometry, report", (5.2, 2.9)),
    "volume": ("volume", "ndarray on a recon.volume.VolumeGrid", (5.2, 0.4)),
    "scores": ("scores", "angle RMS, PSNR, recovery", (5.2, -2.1)),
}

#: Arrows: (from, to, owning modules, how it runs). Modules are checked by the tests.
ARROWS = (
    ("files", "projections", ("ctpipe.io.scans", "ctpipe.plugins", "ctpipe.io.nikon", "ctpipe.io.flatfield"),
     "open_scan: format plugins, views read on demand"),
    ("phantom", "projections", ("ctpipe.sim.simulator", "ctpipe.sim.projectors"), "simulate with known jitter"),
    ("projections", "features", ("ctpipe.builtin.surf", "ctpipe.features.surf", "ctpipe.builtin.opencv_detectors"),
     "detector stage, per view"),
    ("features", "matches", ("ctpipe.builtin.matchers", "ctpipe.solve.graph"), "matcher stage, per pair of view_pairs"),
    ("matches", "pairs", ("ctpipe.builtin.estimators", "ctpipe.model"), "estimator stage: 1-point RANSAC"),
    ("pairs", "tracks", ("ctpipe.solve.tracks",), "chain matches over views"),
    ("tracks", "solution", ("ctpipe.solve.bundle",), "bundle adjustment"),
    ("pairs", "solution", ("ctpipe.solve.graph",), "robust view graph"),
    ("projections", "solution", ("ctpipe.solve.reprojection",), "projection matching"),
    ("solution", "angles", ("ctpipe.pipeline", "ctpipe.builtin.refiners"), "refiner stage; Pipeline.run's ScanResult"),
    ("angles", "volume", ("ctpipe.recon.feldkamp", "ctpipe.io.corrected"), "FDK, or your reconstructor"),
    ("volume", "scores", ("ctpipe.evaluate.scoring", "ctpipe.evaluate.validate"), "ctpipe validate"),
)

_BOX_W, _BOX_H = 4.3, 1.05


def draw(out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import FancyArrowPatch, FancyBboxPatch

    fig, ax = plt.subplots(figsize=(11.0, 16.0))
    ax.set_xlim(-0.8, 12.6)
    ax.set_ylim(-4.0, 22.0)
    ax.axis("off")

    for title, detail, (x, y) in DATA.values():
        box = FancyBboxPatch((x - _BOX_W / 2, y - _BOX_H / 2), _BOX_W, _BOX_H, boxstyle="round,pad=0.05",
                             facecolor="#eef3fb", edgecolor="#2f5597", linewidth=1.4)
        ax.add_patch(box)
        ax.text(x, y + 0.17, title, ha="center", va="center", fontsize=11.5, weight="bold")
        ax.text(x, y - 0.22, detail, ha="center", va="center", fontsize=8.2, color="#333333", family="monospace")

    def edge(key: str, side: str) -> tuple[float, float]:
        x, y = DATA[key][2]
        return {"top": (x, y + _BOX_H / 2 + 0.05), "bottom": (x, y - _BOX_H / 2 - 0.05),
                "left": (x - _BOX_W / 2 - 0.05, y), "right": (x + _BOX_W / 2 + 0.05, y)}[side]

    # Where each arrow leaves and enters, how it bends, and where its label sits.
    routes = {
        ("files", "projections"): ("bottom", "left", 0.25, (-0.6, 18.9), "left"),
        ("phantom", "projections"): ("bottom", "right", -0.25, (11.2, 18.9), "right"),
        ("pairs", "tracks"): ("left", "top", 0.3, (-0.6, 9.35), "left"),
        ("tracks", "solution"): ("bottom", "left", 0.3, (-0.6, 6.3), "left"),
        ("pairs", "solution"): ("bottom", "top", 0.0, (5.45, 7.9), "left"),
        ("projections", "solution"): ("right", "right", -0.55, (9.3, 11.6), "left"),
    }
    for source, target, modules, how in ARROWS:
        start_side, end_side, bend, label_at, align = routes.get((source, target), ("bottom", "top", 0.0, None, "left"))
        start, end = edge(source, start_side), edge(target, end_side)
        colour = "#c55a11" if (source, target) == ("projections", "solution") else "#2f5597"
        ax.add_patch(FancyArrowPatch(start, end, connectionstyle=f"arc3,rad={bend}", arrowstyle="-|>",
                                     mutation_scale=16, linewidth=1.5, color=colour))
        if label_at is None:
            label_at = (start[0] + 0.25, (start[1] + end[1]) / 2)
        text = how + "\n" + "\n".join(modules)
        ax.text(*label_at, text, ha=align, va="center", fontsize=8.2, color=colour, linespacing=1.25)

    ax.text(-0.7, 21.9, "ctpipe: how data flows, and the module that owns each arrow", fontsize=13, weight="bold",
            va="top")
    ax.text(-0.7, -3.95, "Stage arrows run through the plugin registry (ctpipe.plugins); refiners choose one of the "
            "three routes to the solution:\nleast-squares (view graph), bundle-adjustment (tracks), projection-matching "
            "(every pixel, started from one of the others).", fontsize=8.5, va="bottom", color="#333333")
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).with_name("architecture.png"))
    print(draw(parser.parse_args(argv).out))


if __name__ == "__main__":
    main()
