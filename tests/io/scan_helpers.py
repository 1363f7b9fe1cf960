"""One small simulated acquisition every format test writes in its own format, and the reference it must match.

The ``raw_scan`` fixture (``conftest.py``) is :func:`simulate_raw_scan` once per session.

The detector is not square (96 rows x 128 cols) and its principal point is off centre, so that a
swapped axis, a flipped sign or an offset measured from the wrong edge shows; the angles carry
jitter, so that a reader who drops the scanner's per-view log or flips its sign is caught.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from ctpipe.cli import main
from ctpipe.geometry import Geometry
from ctpipe.io.scan_folder import write_scan

#: A fast pipeline for comparing angles between formats (identical inputs give identical angles).
FAST_PIPELINE = {
    "detector": {"name": "sift"},
    "matcher": {"name": "brute-force", "ratio": 0.8, "mutual": True},
    "estimator": {"name": "ransac-1pt", "hypotheses": "all", "scoring": "msac", "sampson_threshold": 3.0e-3},
    "refiner": {"name": "least-squares"},
    "pairs": {"baselines": [1, 2]},
    # The formats are compared through the refiner's own angles. On these small scans (tens of
    # views, 64-128 px) conjugate rays have too few pairs to show a correction better, and the
    # gate would return the nominal angles, which say nothing about a reader.
    "gate": "off",
}


@dataclass(frozen=True)
class RawScan:
    """A simulated acquisition as a scanner records it.

    ``intensities``, ``flats`` and ``darks`` are uint16 counts (Poisson counts, exact in uint16);
    ``nominal_deg`` are the commanded angles and ``true_deg`` the turntable's real ones (what an
    encoder log records), both in ctpipe's convention (a turn of +a is +a).
    """

    geometry: Geometry
    nominal_deg: np.ndarray
    true_deg: np.ndarray
    intensities: np.ndarray
    flats: np.ndarray
    darks: np.ndarray


def simulate_raw_scan(phantom: str = "bead-cylinder", **spec_changes) -> RawScan:
    """The acquisition of :func:`raw_scan`, with top-level scan-spec keys replaced by ``spec_changes``."""
    from ctpipe.sim import load_phantom, parse_scan_spec, simulate

    spec = {
        "geometry": {"source_to_object_mm": 130.0, "source_to_detector_mm": 300.0, "detector_cols": 128,
                     "detector_rows": 96, "pixel_pitch_u_mm": 1.6, "pixel_pitch_v_mm": 1.6,
                     "u0_px": 66.25, "v0_px": 45.5},
        "angles": {"n_views": 120, "range_deg": 360.0, "start_deg": 0.0},
        "jitter": [{"gaussian": {"sigma_deg": 0.4}}],
        "noise": {"photons_per_pixel": 20000, "flat_frames": 4, "dark_frames": 2, "dark_counts": 100},
        "projector": {"kind": "analytic", "supersample": 1, "blur_px": 0.5},
        "seed": 5,
    }
    spec = parse_scan_spec({**spec, **spec_changes})
    scan = simulate(load_phantom(phantom), spec, rng=np.random.default_rng(5))
    as_counts = lambda a: np.round(a).astype(np.uint16)  # noqa: E731 (Poisson counts are integers already)
    return RawScan(spec.geometry, scan.nominal_angles_deg, scan.true_angles_deg, as_counts(scan.intensities),
                   as_counts(scan.flats), as_counts(scan.darks))


def write_reference(folder: Path, raw: RawScan, intensities: np.ndarray, *, flats=None, darks=None,
                    white_level: float | None = None, geometry: Geometry | None = None) -> Path:
    """The ctpipe scan folder holding ``intensities`` with the simulation's own geometry and angles.

    A format that stores flat-corrected counts scaled to a white level (no flat frames) passes
    ``white_level``: the reference then has one flat frame of that level, which is what the
    format's reader must apply too.
    """
    if white_level is not None:
        flats = np.full((1, *raw.geometry.shape), white_level, np.float32)
    return write_scan(folder, intensities, geometry or raw.geometry, raw.nominal_deg, raw.true_deg, flats=flats,
                      darks=darks, values="intensities")


def estimate_angles(path: Path, tmp_path: Path, capsys) -> np.ndarray:
    """``ctpipe estimate PATH --json`` with :data:`FAST_PIPELINE`, in-process: the per-view angles."""
    pipeline = tmp_path / "fast.yaml"
    pipeline.write_text(yaml.safe_dump(FAST_PIPELINE))
    capsys.readouterr()
    code = main(["estimate", str(path), "--pipeline", str(pipeline), "--json"])
    out = capsys.readouterr().out
    assert code == 0
    return np.array(json.loads(out)["angles_deg"], dtype=np.float64)
