"""Hostile and borderline inputs: every command and the Python API, one table row per case.

The promise under test (docs/errors.md): bad input gives one line ``ctpipe: error: ...`` on
stderr and exit status 2 -- no traceback, no hang, no runaway allocation, nothing written.

Each CLI case runs ``ctpipe.cli.main`` in a forked child with an address-space limit and a
timeout, so a hang or a huge allocation fails the case instead of stalling CI. Forking the
already-imported test process costs milliseconds where ``python -m ctpipe.cli`` costs about
two seconds a case; ``test_entry_point_*`` and the SIGTERM test run the real entry point.
"""

from __future__ import annotations

import os
import resource
import signal
import subprocess
import sys
import time
import traceback
from importlib import import_module
from pathlib import Path

import numpy as np
import pytest
import yaml

from ctpipe.errors import ConfigError, CtpipeError, EstimationError, InputError

TIMEOUT_S = 60
MEMORY_BYTES = 4 << 30

GEOMETRY = {"source_to_object_mm": 100.0, "source_to_detector_mm": 200.0, "detector_cols": 48,
            "detector_rows": 48, "pixel_pitch_u_mm": 1.0, "pixel_pitch_v_mm": 1.0}
SMALL = {**GEOMETRY, "detector_cols": 24, "detector_rows": 24, "pixel_pitch_u_mm": 4.0, "pixel_pitch_v_mm": 4.0}
SPEC = {"geometry": SMALL, "angles": {"n_views": 4, "range_deg": 360.0}, "seed": 0}
PIPELINE = {"detector": {"name": "sift"}, "matcher": {"name": "brute-force"}}
EXPERIMENT = {"phantom": "bead-cylinder", "scan": SPEC, "pipeline": PIPELINE,
              "reconstruction": {"grid_size": 16, "detector_binning": 1}, "seed": 0}
BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{c}: &{c} [{', '.join(['*' + p] * 9)}]\n" for p, c in zip("abcdefgh", "bcdefghi"))


def _dump(value) -> str:
    return yaml.safe_dump(value, sort_keys=False)


def _with(base: dict, path: str, value) -> dict:
    """A deep copy of ``base`` with the dotted ``path`` set to ``value`` (``...`` deletes it)."""
    import copy

    out = copy.deepcopy(base)
    node = out
    *parents, last = path.split(".")
    for key in parents:
        node = node[key]
    if value is ...:
        del node[last]
    else:
        node[last] = value
    return out


def _npy_header_only(shape, dtype="<f8") -> bytes:
    """A .npy header that claims ``shape`` followed by 16 bytes of data (a lying file)."""
    import io

    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": dtype, "fortran_order": False, "shape": shape})
    return buffer.getvalue() + b"\0" * 16


def _textured(shape, seed=0) -> np.ndarray:
    from ctpipe.testing import textured_image

    return textured_image(shape, seed=seed)


def _scan_folder(d: Path, name: str, *, flats_scale: float = 1.0, darks_scale: float = 0.01) -> None:
    """A 3-view intensity scan folder whose flats/darks are scaled (darks > flats is hostile)."""
    from ctpipe.geometry import Geometry
    from ctpipe.io.scan_folder import write_scan

    geometry = Geometry(**GEOMETRY)
    rng = np.random.default_rng(0)
    projections = (rng.uniform(0.3, 0.9, (3, 48, 48)) * 1000).astype(np.float32)
    frames = np.full((2, 48, 48), 1000.0, np.float32)
    write_scan(d / name, projections, geometry, [0.0, 1.0, 2.0], flats=frames * flats_scale,
               darks=frames * darks_scale, values="intensities")


def _common_files(d: Path) -> None:
    """What every CLI case may refer to, all small."""
    (d / "geometry.yaml").write_text(_dump({"geometry": GEOMETRY}))
    np.save(d / "proj.npy", np.stack([_textured((48, 48), seed=s) for s in range(3)]).astype(np.float32))
    np.save(d / "image.npy", _textured((64, 64)))
    (d / "spec.yaml").write_text(_dump(SPEC))
    (d / "afile").write_text("a regular file\n")
    (d / "emptydir").mkdir()


# Extra files for a case: name -> str (text), bytes, ndarray (np.save) or callable(folder).
def _f(**files):
    return files


G = GEOMETRY
CLI_CASES = [
    # id, argv ({d} is the case's folder), expected text in the message, extra files
    # -- usage
    ("no-command", [], "required", {}),
    ("unknown-command", ["frobnicate"], "invalid choice", {}),
    ("plugins-unknown-flag", ["plugins", "--bogus"], "--bogus", {}),
    ("experiment-no-subcommand", ["experiment"], "required", {}),
    # -- estimate: the projections argument
    ("est-missing-file", ["estimate", "{d}/nope.npy", "--geometry", "{d}/geometry.yaml"], "nope.npy", {}),
    ("est-empty-folder", ["estimate", "{d}/emptydir"], "emptydir", {}),
    ("est-empty-npy", ["estimate", "{d}/e.npy", "--geometry", "{d}/geometry.yaml"], "e.npy", _f(**{"e.npy": b""})),
    ("est-text-as-npy", ["estimate", "{d}/t.npy", "--geometry", "{d}/geometry.yaml"], "t.npy",
     _f(**{"t.npy": "hello\n"})),
    ("est-2d-npy", ["estimate", "{d}/image.npy", "--geometry", "{d}/geometry.yaml"], "3-D", {}),
    ("est-nan-pixels", ["estimate", "{d}/n.npy", "--geometry", "{d}/geometry.yaml"], "NaN",
     _f(**{"n.npy": np.full((3, 48, 48), np.nan, np.float32)})),
    ("est-inf-pixels", ["estimate", "{d}/n.npy", "--geometry", "{d}/geometry.yaml"], "inf",
     _f(**{"n.npy": np.full((3, 48, 48), np.inf, np.float32)})),
    ("est-unsupported-suffix", ["estimate", "{d}/afile", "--geometry", "{d}/geometry.yaml"], "afile", {}),
    ("est-pickled-npy", ["estimate", "{d}/o.npy", "--geometry", "{d}/geometry.yaml"], "o.npy",
     _f(**{"o.npy": lambda d: np.save(d / "o.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)})),
    ("est-complex-npy", ["estimate", "{d}/c.npy", "--geometry", "{d}/geometry.yaml"], "c.npy",
     _f(**{"c.npy": np.ones((3, 48, 48), np.complex64)})),
    ("est-huge-npy-header", ["estimate", "{d}/h.npy", "--geometry", "{d}/geometry.yaml"], "h.npy",
     _f(**{"h.npy": _npy_header_only((100000, 4096, 4096))})),
    ("est-zero-views", ["estimate", "{d}/z.npy", "--geometry", "{d}/geometry.yaml"], "at least 2 views",
     _f(**{"z.npy": np.zeros((0, 48, 48), np.float32)})),
    ("est-one-view", ["estimate", "{d}/one.npy", "--geometry", "{d}/geometry.yaml"], "view",
     _f(**{"one.npy": _textured((48, 48))[None].astype(np.float32)})),
    ("est-no-keypoints", ["estimate", "{d}/flat.npy", "--geometry", "{d}/geometry.yaml"], "",
     _f(**{"flat.npy": np.zeros((3, 48, 48), np.float32)})),
    ("est-shape-vs-geometry", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "48",
     _f(**{"g.yaml": _dump({"geometry": {**G, "detector_cols": 64}})})),
    ("est-needs-geometry", ["estimate", "{d}/proj.npy"], "--geometry", {}),
    ("est-scan-plus-geometry", ["estimate", "{d}/scan", "--geometry", "{d}/geometry.yaml"], "drop --geometry",
     _f(scan=lambda d: _scan_folder(d, "scan"))),
    ("est-darks-brighter-than-flats", ["estimate", "{d}/dark"], "dark",
     _f(dark=lambda d: _scan_folder(d, "dark", flats_scale=0.5, darks_scale=2.0))),
    ("est-scan-yaml-malformed", ["estimate", "{d}/s"], "scan.yaml",
     _f(s=lambda d: (d / "s").mkdir() or (d / "s" / "scan.yaml").write_text("format: [\n"))),
    ("est-scan-missing-tiffs", ["estimate", "{d}/s"], "proj_",
     _f(s=lambda d: _scan_folder(d, "s") or [p.unlink() for p in (d / "s" / "projections").iterdir()])),
    ("est-bad-tiff-in-scan", ["estimate", "{d}/s"], "proj_00001",
     _f(s=lambda d: _scan_folder(d, "s") or (d / "s" / "projections" / "proj_00001.tif").write_bytes(b"II*\0junk"))),
    # -- estimate: --geometry
    ("geo-missing", ["estimate", "{d}/proj.npy", "--geometry", "{d}/nope.yaml"], "nope.yaml", {}),
    ("geo-is-folder", ["estimate", "{d}/proj.npy", "--geometry", "{d}/emptydir"], "emptydir", {}),
    ("geo-empty-file", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "geometry", _f(**{"g.yaml": ""})),
    ("geo-malformed", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "g.yaml",
     _f(**{"g.yaml": "geometry: {source_to_object_mm: [\n"})),
    ("geo-not-utf8", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "UTF-8",
     _f(**{"g.yaml": b"geometry:\n  source_to_object_mm: \xff\xfe100\n"})),
    ("geo-alias-bomb", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "alias", _f(**{"g.yaml": BOMB})),
    ("geo-python-tag", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "g.yaml",
     _f(**{"g.yaml": "geometry: !!python/object/apply:os.system ['true']\n"})),
    ("geo-duplicate-key", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "source_to_object_mm",
     _f(**{"g.yaml": _dump({"geometry": G}).replace("  source_to_detector_mm", "  source_to_object_mm: 1.0\n"
                                                                            "  source_to_detector_mm")})),
    ("geo-top-level-list", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "geometry",
     _f(**{"g.yaml": "- 1\n- 2\n"})),
    ("geo-unknown-key", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "magnification",
     _f(**{"g.yaml": _dump({"geometry": {**G, "magnification": 2.0}})})),
    ("geo-missing-key", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "pixel_pitch_v_mm",
     _f(**{"g.yaml": _dump({"geometry": _with(G, "pixel_pitch_v_mm", ...)})})),
    ("geo-sdd-equals-sod", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "source_to_detector_mm",
     _f(**{"g.yaml": _dump({"geometry": {**G, "source_to_detector_mm": 100.0}})})),
    ("geo-sdd-below-sod", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "source_to_detector_mm",
     _f(**{"g.yaml": _dump({"geometry": {**G, "source_to_detector_mm": 50.0}})})),
    ("geo-negative-pitch", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "pixel_pitch_u_mm",
     _f(**{"g.yaml": _dump({"geometry": {**G, "pixel_pitch_u_mm": -1.0}})})),
    ("geo-zero-sod", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "source_to_object_mm",
     _f(**{"g.yaml": _dump({"geometry": {**G, "source_to_object_mm": 0.0}})})),
    ("geo-nan", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "source_to_object_mm",
     _f(**{"g.yaml": _dump({"geometry": G}).replace("source_to_object_mm: 100.0", "source_to_object_mm: .nan")})),
    ("geo-inf", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "source_to_detector_mm",
     _f(**{"g.yaml": _dump({"geometry": G}).replace("source_to_detector_mm: 200.0", "source_to_detector_mm: .inf")})),
    ("geo-huge-cols", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "detector_cols",
     _f(**{"g.yaml": _dump({"geometry": {**G, "detector_cols": 10**12}})})),
    ("geo-fractional-cols", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "detector_cols",
     _f(**{"g.yaml": _dump({"geometry": {**G, "detector_cols": 48.5}})})),
    ("geo-string-number", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "source_to_object_mm",
     _f(**{"g.yaml": _dump({"geometry": {**G, "source_to_object_mm": "far"}})})),
    ("geo-bool-number", ["estimate", "{d}/proj.npy", "--geometry", "{d}/g.yaml"], "detector_rows",
     _f(**{"g.yaml": _dump({"geometry": {**G, "detector_rows": True}})})),
    # -- estimate: --pipeline
    ("pipe-unknown-detector", ["estimate", "{d}/proj.npy", "--geometry", "{d}/geometry.yaml", "--pipeline",
                               "{d}/p.yaml"], "nope", _f(**{"p.yaml": _dump({"detector": {"name": "nope"}})})),
    ("pipe-unknown-key", ["estimate", "{d}/proj.npy", "--geometry", "{d}/geometry.yaml", "--pipeline", "{d}/p.yaml"],
     "colour", _f(**{"p.yaml": _dump({**PIPELINE, "colour": "red"})})),
    ("pipe-unknown-param", ["estimate", "{d}/proj.npy", "--geometry", "{d}/geometry.yaml", "--pipeline",
                            "{d}/p.yaml"], "sharpness",
     _f(**{"p.yaml": _dump({"detector": {"name": "sift", "sharpness": 3}})})),
    ("pipe-wrong-type", ["estimate", "{d}/proj.npy", "--geometry", "{d}/geometry.yaml", "--pipeline", "{d}/p.yaml"],
     "ratio", _f(**{"p.yaml": _dump({"matcher": {"name": "brute-force", "ratio": "high"}})})),
    ("pipe-ratio-out-of-range", ["estimate", "{d}/proj.npy", "--geometry", "{d}/geometry.yaml", "--pipeline",
                                 "{d}/p.yaml"], "ratio",
     _f(**{"p.yaml": _dump({"matcher": {"name": "brute-force", "ratio": 7.0}})})),
    ("pipe-negative-threshold", ["estimate", "{d}/proj.npy", "--geometry", "{d}/geometry.yaml", "--pipeline",
                                 "{d}/p.yaml"], "sampson_threshold",
     _f(**{"p.yaml": _dump({"estimator": {"name": "ransac-1pt", "sampson_threshold": -1.0}})})),
    ("pipe-nan-threshold", ["estimate", "{d}/proj.npy", "--geometry", "{d}/geometry.yaml", "--pipeline",
                            "{d}/p.yaml"], "sampson_threshold",
     _f(**{"p.yaml": "estimator: {name: ransac-1pt, sampson_threshold: .nan}\n"})),
    ("pipe-huge-features", ["estimate", "{d}/proj.npy", "--geometry", "{d}/geometry.yaml", "--pipeline",
                            "{d}/p.yaml"], "n_features",
     _f(**{"p.yaml": _dump({"detector": {"name": "sift", "n_features": 10**15}})})),
    ("pipe-zero-baseline", ["estimate", "{d}/proj.npy", "--geometry", "{d}/geometry.yaml", "--pipeline",
                            "{d}/p.yaml"], "baselines", _f(**{"p.yaml": _dump({"pairs": {"baselines": [0]}})})),
    ("pipe-list-top-level", ["estimate", "{d}/proj.npy", "--geometry", "{d}/geometry.yaml", "--pipeline",
                             "{d}/p.yaml"], "pipeline", _f(**{"p.yaml": "- sift\n"})),
    ("pipe-alias-bomb", ["estimate", "{d}/proj.npy", "--geometry", "{d}/geometry.yaml", "--pipeline", "{d}/p.yaml"],
     "alias", _f(**{"p.yaml": BOMB})),
    # -- outputs (checked before the work)
    ("est-out-is-file", ["estimate", "{d}/proj.npy", "--geometry", "{d}/geometry.yaml", "--out", "{d}/afile"],
     "afile", {}),
    ("est-out-under-file", ["estimate", "{d}/proj.npy", "--geometry", "{d}/geometry.yaml", "--out",
                            "{d}/afile/res"], "afile", {}),
    ("est-out-empty", ["estimate", "{d}/proj.npy", "--geometry", "{d}/geometry.yaml", "--out", ""], "--out", {}),
    ("est-out-unwritable", ["estimate", "{d}/proj.npy", "--geometry", "{d}/geometry.yaml", "--out", "{ro}/res"],
     "write", {}),
    # -- detect
    ("det-missing-image", ["detect", "{d}/nope.npy", "--detector", "sift", "--out", "{d}/kp.npz"], "nope.npy", {}),
    ("det-image-is-folder", ["detect", "{d}/emptydir", "--detector", "sift", "--out", "{d}/kp.npz"], "emptydir", {}),
    ("det-empty-npy-file", ["detect", "{d}/e.npy", "--detector", "sift", "--out", "{d}/kp.npz"], "e.npy",
     _f(**{"e.npy": b""})),
    ("det-text-as-png", ["detect", "{d}/t.png", "--detector", "sift", "--out", "{d}/kp.npz"], "t.png",
     _f(**{"t.png": "not a picture\n"})),
    ("det-truncated-png", ["detect", "{d}/t.png", "--detector", "sift", "--out", "{d}/kp.npz"], "t.png",
     _f(**{"t.png": b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR\0\0\0@"})),
    ("det-junk-tiff", ["detect", "{d}/t.tif", "--detector", "sift", "--out", "{d}/kp.npz"], "t.tif",
     _f(**{"t.tif": b"II*\0" + bytes(range(256)) * 4})),
    ("det-huge-npy-header", ["detect", "{d}/h.npy", "--detector", "sift", "--out", "{d}/kp.npz"], "h.npy",
     _f(**{"h.npy": _npy_header_only((300000, 300000))})),
    ("det-3d-image", ["detect", "{d}/proj.npy", "--detector", "sift", "--out", "{d}/kp.npz"], "2-dimensional", {}),
    ("det-nan-pixels", ["detect", "{d}/n.npy", "--detector", "sift", "--out", "{d}/kp.npz"], "NaN",
     _f(**{"n.npy": np.where(np.eye(64, dtype=bool), np.nan, 1.0)})),
    ("det-empty-image", ["detect", "{d}/e.npy", "--detector", "sift", "--out", "{d}/kp.npz"], "e.npy",
     _f(**{"e.npy": np.zeros((0, 8), np.float32)})),
    ("det-string-dtype", ["detect", "{d}/s.npy", "--detector", "sift", "--out", "{d}/kp.npz"], "s.npy",
     _f(**{"s.npy": np.full((16, 16), "x")})),
    ("det-tiny-image-orb", ["detect", "{d}/t.npy", "--detector", "orb", "--out", "{d}/kp.npz"], "orb",
     _f(**{"t.npy": np.zeros((1, 1), np.uint8)})),
    ("det-unknown-detector", ["detect", "{d}/image.npy", "--detector", "nope", "--out", "{d}/kp.npz"], "nope", {}),
    ("det-set-unknown-key", ["detect", "{d}/image.npy", "--detector", "sift", "--set", "sharpness=2", "--out",
                             "{d}/kp.npz"], "sharpness", {}),
    ("det-set-wrong-type", ["detect", "{d}/image.npy", "--detector", "sift", "--set", "n_features=many", "--out",
                            "{d}/kp.npz"], "n_features", {}),
    ("det-set-negative", ["detect", "{d}/image.npy", "--detector", "sift", "--set", "n_features=-5", "--out",
                          "{d}/kp.npz"], "n_features", {}),
    ("det-set-nan", ["detect", "{d}/image.npy", "--detector", "sift", "--set", "contrast_threshold=.nan", "--out",
                     "{d}/kp.npz"], "contrast_threshold", {}),
    ("det-set-inf", ["detect", "{d}/image.npy", "--detector", "sift", "--set", "sigma=.inf", "--out",
                     "{d}/kp.npz"], "sigma", {}),
    ("det-set-huge", ["detect", "{d}/image.npy", "--detector", "orb", "--set", "n_features=1e30", "--out",
                      "{d}/kp.npz"], "n_features", {}),
    ("det-set-name", ["detect", "{d}/image.npy", "--detector", "sift", "--set", "name=orb", "--out", "{d}/kp.npz"],
     "--detector", {}),
    ("det-set-twice", ["detect", "{d}/image.npy", "--detector", "sift", "--set", "n_features=5", "--set",
                       "n_features=6", "--out", "{d}/kp.npz"], "twice", {}),
    ("det-set-no-equals", ["detect", "{d}/image.npy", "--detector", "sift", "--set", "n_features", "--out",
                           "{d}/kp.npz"], "key=value", {}),
    ("det-set-bad-yaml", ["detect", "{d}/image.npy", "--detector", "sift", "--set", "n_features=[1,", "--out",
                          "{d}/kp.npz"], "n_features", {}),
    ("det-out-wrong-suffix", ["detect", "{d}/image.npy", "--detector", "sift", "--out", "{d}/kp.png"], ".npz", {}),
    ("det-out-is-folder", ["detect", "{d}/image.npy", "--detector", "sift", "--out", "{d}/dir.npz"], "dir.npz",
     _f(**{"dir.npz": lambda d: (d / "dir.npz").mkdir()})),
    ("det-out-under-file", ["detect", "{d}/image.npy", "--detector", "sift", "--out", "{d}/afile/kp.npz"], "afile",
     {}),
    ("det-out-empty", ["detect", "{d}/image.npy", "--detector", "sift", "--out", ""], "--out", {}),
    ("det-out-unwritable", ["detect", "{d}/image.npy", "--detector", "sift", "--out", "{ro}/kp.npz"], "write", {}),
    ("det-overlay-wrong-suffix", ["detect", "{d}/image.npy", "--detector", "sift", "--out", "{d}/kp.npz",
                                  "--overlay", "{d}/kp.jpg"], ".png", {}),
    ("det-overlay-under-file", ["detect", "{d}/image.npy", "--detector", "sift", "--out", "{d}/kp.npz",
                                "--overlay", "{d}/afile/kp.png"], "afile", {}),
    ("det-overlay-empty", ["detect", "{d}/image.npy", "--detector", "sift", "--out", "{d}/kp.npz",
                           "--overlay", ""], "--overlay", {}),
    # -- simulate
    ("sim-unknown-phantom", ["simulate", "no-such-phantom", "--scan", "{d}/spec.yaml", "--out", "{d}/o"],
     "no-such-phantom", {}),
    ("sim-phantom-malformed", ["simulate", "{d}/ph.yaml", "--scan", "{d}/spec.yaml", "--out", "{d}/o"], "ph.yaml",
     _f(**{"ph.yaml": "objects: [\n"})),
    ("sim-phantom-unknown-object", ["simulate", "{d}/ph.yaml", "--scan", "{d}/spec.yaml", "--out", "{d}/o"],
     "torus", _f(**{"ph.yaml": _dump({"name": "x", "objects": [{"torus": {"radius_mm": 3}}]})})),
    ("sim-phantom-negative-radius", ["simulate", "{d}/ph.yaml", "--scan", "{d}/spec.yaml", "--out", "{d}/o"],
     "radius_mm", _f(**{"ph.yaml": _dump({"name": "x", "objects": [
         {"sphere": {"centre_mm": [0, 0, 0], "radius_mm": -3, "density_per_mm": 0.1}}]})})),
    ("sim-spec-missing", ["simulate", "bead-cylinder", "--scan", "{d}/nope.yaml", "--out", "{d}/o"], "nope.yaml", {}),
    ("sim-spec-is-folder", ["simulate", "bead-cylinder", "--scan", "{d}/emptydir", "--out", "{d}/o"], "emptydir", {}),
    ("sim-spec-empty", ["simulate", "bead-cylinder", "--scan", "{d}/s.yaml", "--out", "{d}/o"], "s.yaml",
     _f(**{"s.yaml": ""})),
    ("sim-spec-unknown-key", ["simulate", "bead-cylinder", "--scan", "{d}/s.yaml", "--out", "{d}/o"], "exposure",
     _f(**{"s.yaml": _dump({**SPEC, "exposure": 3})})),
    ("sim-zero-views", ["simulate", "bead-cylinder", "--scan", "{d}/s.yaml", "--out", "{d}/o"], "n_views",
     _f(**{"s.yaml": _dump(_with(SPEC, "angles.n_views", 0))})),
    ("sim-huge-views", ["simulate", "bead-cylinder", "--scan", "{d}/s.yaml", "--out", "{d}/o"], "n_views",
     _f(**{"s.yaml": _dump(_with(SPEC, "angles.n_views", 10**9))})),
    ("sim-huge-detector", ["simulate", "bead-cylinder", "--scan", "{d}/s.yaml", "--out", "{d}/o"], "GB",
     _f(**{"s.yaml": _dump(_with(_with(SPEC, "geometry.detector_cols", 60000), "geometry.detector_rows", 60000))})),
    ("sim-sdd-below-sod", ["simulate", "bead-cylinder", "--scan", "{d}/s.yaml", "--out", "{d}/o"],
     "source_to_detector_mm", _f(**{"s.yaml": _dump(_with(SPEC, "geometry.source_to_detector_mm", 10.0))})),
    ("sim-unknown-jitter", ["simulate", "bead-cylinder", "--scan", "{d}/s.yaml", "--out", "{d}/o"], "wobble",
     _f(**{"s.yaml": _dump({**SPEC, "jitter": [{"wobble": {"sigma_deg": 1}}]})})),
    ("sim-negative-photons", ["simulate", "bead-cylinder", "--scan", "{d}/s.yaml", "--out", "{d}/o"],
     "photons_per_pixel", _f(**{"s.yaml": _dump({**SPEC, "noise": {"photons_per_pixel": -5}})})),
    ("sim-unknown-projector", ["simulate", "bead-cylinder", "--scan", "{d}/s.yaml", "--out", "{d}/o"], "raytrace",
     _f(**{"s.yaml": _dump({**SPEC, "projector": {"kind": "raytrace"}})})),
    ("sim-zero-supersample", ["simulate", "bead-cylinder", "--scan", "{d}/s.yaml", "--out", "{d}/o"], "supersample",
     _f(**{"s.yaml": _dump({**SPEC, "projector": {"kind": "analytic", "supersample": 0}})})),
    ("sim-seed-string", ["simulate", "bead-cylinder", "--scan", "{d}/s.yaml", "--out", "{d}/o"], "seed",
     _f(**{"s.yaml": _dump({**SPEC, "seed": "lucky"})})),
    ("sim-cli-seed-negative", ["simulate", "bead-cylinder", "--scan", "{d}/spec.yaml", "--out", "{d}/o", "--seed",
                               "-1"], "--seed", {}),
    ("sim-out-is-file", ["simulate", "bead-cylinder", "--scan", "{d}/spec.yaml", "--out", "{d}/afile"], "afile", {}),
    ("sim-out-under-file", ["simulate", "bead-cylinder", "--scan", "{d}/spec.yaml", "--out", "{d}/afile/o"],
     "afile", {}),
    ("sim-out-empty", ["simulate", "bead-cylinder", "--scan", "{d}/spec.yaml", "--out", ""], "--out", {}),
    ("sim-out-unwritable", ["simulate", "bead-cylinder", "--scan", "{d}/spec.yaml", "--out", "{ro}/o"], "write", {}),
    ("sim-out-not-empty", ["simulate", "bead-cylinder", "--scan", "{d}/spec.yaml", "--out", "{d}/full"],
     "not empty", _f(full=lambda d: (d / "full").mkdir() or (d / "full" / "keep.txt").write_text("mine"))),
    ("sim-overwrite-cwd", ["simulate", "bead-cylinder", "--scan", "{d}/spec.yaml", "--out", ".", "--overwrite"],
     "current directory", {}),
    ("sim-overwrite-ancestor", ["simulate", "bead-cylinder", "--scan", "{d}/spec.yaml", "--out", "{d}",
                                "--overwrite"], "current directory", {}),
    ("sim-overwrite-non-scan", ["simulate", "bead-cylinder", "--scan", "{d}/spec.yaml", "--out", "{d}/full",
                                "--overwrite"], "scan folder",
     _f(full=lambda d: (d / "full").mkdir() or (d / "full" / "keep.txt").write_text("mine"))),
    # -- validate (each fails while parsing, before anything is simulated)
    ("val-missing", ["validate", "{d}/nope.yaml", "--out", "{d}/res"], "nope.yaml", {}),
    ("val-is-folder", ["validate", "{d}/emptydir", "--out", "{d}/res"], "emptydir", {}),
    ("val-empty-file", ["validate", "{d}/e.yaml", "--out", "{d}/res"], "e.yaml", _f(**{"e.yaml": ""})),
    ("val-malformed", ["validate", "{d}/e.yaml", "--out", "{d}/res"], "e.yaml", _f(**{"e.yaml": "scan: {\n"})),
    ("val-alias-bomb", ["validate", "{d}/e.yaml", "--out", "{d}/res"], "alias", _f(**{"e.yaml": BOMB})),
    ("val-not-utf8", ["validate", "{d}/e.yaml", "--out", "{d}/res"], "UTF-8",
     _f(**{"e.yaml": b"phantom: \xe9t\xe9\n"})),
    ("val-unknown-key", ["validate", "{d}/e.yaml", "--out", "{d}/res"], "colour",
     _f(**{"e.yaml": _dump({**EXPERIMENT, "colour": 1})})),
    ("val-unknown-phantom", ["validate", "{d}/e.yaml", "--out", "{d}/res"], "no-such-phantom",
     _f(**{"e.yaml": _dump({**EXPERIMENT, "phantom": "no-such-phantom"})})),
    ("val-unknown-detector", ["validate", "{d}/e.yaml", "--out", "{d}/res"], "nope",
     _f(**{"e.yaml": _dump(_with(EXPERIMENT, "pipeline.detector.name", "nope"))})),
    ("val-zero-grid", ["validate", "{d}/e.yaml", "--out", "{d}/res"], "grid_size",
     _f(**{"e.yaml": _dump(_with(EXPERIMENT, "reconstruction.grid_size", 0))})),
    ("val-huge-grid", ["validate", "{d}/e.yaml", "--out", "{d}/res"], "grid_size",
     _f(**{"e.yaml": _dump(_with(EXPERIMENT, "reconstruction.grid_size", 10**6))})),
    ("val-negative-views", ["validate", "{d}/e.yaml", "--out", "{d}/res"], "n_views",
     _f(**{"e.yaml": _dump(_with(EXPERIMENT, "scan.angles.n_views", -4))})),
    ("val-degenerate-geometry", ["validate", "{d}/e.yaml", "--out", "{d}/res"], "source_to_detector_mm",
     _f(**{"e.yaml": _dump(_with(EXPERIMENT, "scan.geometry.source_to_detector_mm", 100.0))})),
    ("val-out-is-file", ["validate", "{d}/e.yaml", "--out", "{d}/afile"], "afile",
     _f(**{"e.yaml": _dump(EXPERIMENT)})),
    ("val-out-under-file", ["validate", "{d}/e.yaml", "--out", "{d}/afile/res"], "afile",
     _f(**{"e.yaml": _dump(EXPERIMENT)})),
    ("val-out-empty", ["validate", "{d}/e.yaml", "--out", ""], "--out", _f(**{"e.yaml": _dump(EXPERIMENT)})),
    ("val-seed-negative", ["validate", "{d}/e.yaml", "--seed", "-3"], "--seed", {}),
    # -- experiment synthetic (each fails while parsing)
    ("syn-config-missing", ["experiment", "synthetic", "--config", "{d}/nope.yaml"], "nope.yaml", {}),
    ("syn-config-malformed", ["experiment", "synthetic", "--config", "{d}/c.yaml"], "c.yaml",
     _f(**{"c.yaml": "reps: [\n"})),
    ("syn-config-unknown-key", ["experiment", "synthetic", "--config", "{d}/c.yaml"], "colour",
     _f(**{"c.yaml": lambda d: (d / "c.yaml").write_text(
         (Path(__file__).parents[1] / "ctpipe" / "evaluate" / "synthetic.yaml").read_text() + "colour: red\n")})),
    ("syn-config-zero-reps", ["experiment", "synthetic", "--config", "{d}/c.yaml"], "reps",
     _f(**{"c.yaml": lambda d: (d / "c.yaml").write_text(
         (Path(__file__).parents[1] / "ctpipe" / "evaluate" / "synthetic.yaml").read_text().replace("reps: 300",
                                                                                              "reps: 0"))})),
    ("syn-config-negative-sigma", ["experiment", "synthetic", "--config", "{d}/c.yaml"], "sigma",
     _f(**{"c.yaml": lambda d: (d / "c.yaml").write_text(
         (Path(__file__).parents[1] / "ctpipe" / "evaluate" / "synthetic.yaml").read_text().replace(
             "sigma: 1.0e-4", "sigma: -1.0e-4"))})),
    ("syn-reps-zero", ["experiment", "synthetic", "--reps", "0"], "--reps", {}),
    ("syn-jobs-zero", ["experiment", "synthetic", "--jobs", "0"], "--jobs", {}),
    ("syn-reps-float", ["experiment", "synthetic", "--reps", "2.5"], "--reps", {}),
    ("syn-out-is-file", ["experiment", "synthetic", "--reps", "1", "--out", "{d}/afile"], "afile", {}),
    ("syn-out-empty", ["experiment", "synthetic", "--reps", "1", "--out", ""], "--out", {}),
    # -- experiment compare (each fails before the first scenario is simulated)
    ("cmp-no-pipelines", ["experiment", "compare", "--out", "{d}/res"], "at least two", {}),
    ("cmp-one-pipeline", ["experiment", "compare", "{d}/p.yaml", "--out", "{d}/res"], "only",
     _f(**{"p.yaml": _dump(PIPELINE)})),
    ("cmp-unknown-pipeline-file", ["experiment", "compare", "{d}/p.yaml", "{d}/nope.yaml", "--out", "{d}/res"],
     "nope.yaml", _f(**{"p.yaml": _dump(PIPELINE)})),
    ("cmp-bad-pipeline", ["experiment", "compare", "{d}/p.yaml", "{d}/q.yaml", "--out", "{d}/res"], "nope",
     _f(**{"p.yaml": _dump(PIPELINE), "q.yaml": _dump({**PIPELINE, "detector": {"name": "nope"}})})),
    ("cmp-unknown-builtin", ["experiment", "compare", "--builtin", "estimators", "--out", "{d}/res"],
     "invalid choice", {}),
    ("cmp-scenario-cannot-be-simulated", ["experiment", "compare", "{d}/p.yaml", "{d}/q.yaml", "--scenario",
                                          "{d}/e.yaml", "--out", "{d}/res"], "grid_size",
     _f(**{"p.yaml": _dump(PIPELINE), "q.yaml": _dump(PIPELINE),
           "e.yaml": _dump(_with(EXPERIMENT, "reconstruction.grid_size", 10**6))})),
    ("cmp-scenario-missing", ["experiment", "compare", "{d}/p.yaml", "{d}/q.yaml", "--scenario", "{d}/nope.yaml",
                              "--out", "{d}/res"], "nope.yaml",
     _f(**{"p.yaml": _dump(PIPELINE), "q.yaml": _dump(PIPELINE)})),
    ("cmp-n-with-scenario", ["experiment", "compare", "{d}/p.yaml", "{d}/q.yaml", "--scenario", "{d}/e.yaml",
                             "--n", "3", "--out", "{d}/res"], "--n",
     _f(**{"p.yaml": _dump(PIPELINE), "q.yaml": _dump(PIPELINE), "e.yaml": _dump(EXPERIMENT)})),
    ("cmp-n-zero", ["experiment", "compare", "{d}/p.yaml", "{d}/q.yaml", "--n", "0"], "--n", {}),
    ("cmp-out-is-file", ["experiment", "compare", "{d}/p.yaml", "{d}/q.yaml", "--out", "{d}/afile"], "afile",
     _f(**{"p.yaml": _dump(PIPELINE), "q.yaml": _dump(PIPELINE)})),
]


@pytest.fixture
def readonly_dir(tmp_path_factory):
    """A folder ctpipe cannot write in: chmod 555, or a sysfs path when running as root."""
    if os.geteuid() == 0:
        yield Path("/sys/ctpipe-readonly")
        return
    path = tmp_path_factory.mktemp("ro")
    path.chmod(0o555)
    yield path
    path.chmod(0o755)


def _snapshot(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): (p.stat().st_size if p.is_file() else -1) for p in folder.rglob("*")}


def run_isolated(argv: list[str], cwd: Path, timeout: float = TIMEOUT_S) -> tuple[int, str, str]:
    """``ctpipe.cli.main(argv)`` in a forked child under a memory limit; (exit code, stdout, stderr).

    An exception that escapes ``main`` prints its traceback (so the case fails on 'Traceback');
    a child still running after ``timeout`` seconds is killed and the case fails.
    """
    out_path, err_path = cwd / ".case-stdout", cwd / ".case-stderr"
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        code = 1
        try:
            resource.setrlimit(resource.RLIMIT_AS, (MEMORY_BYTES, MEMORY_BYTES))
            os.chdir(cwd)
            out_fd, err_fd = (os.open(p, os.O_WRONLY | os.O_CREAT | os.O_TRUNC) for p in (out_path, err_path))
            os.dup2(out_fd, 1)
            os.dup2(err_fd, 2)
            sys.stdout, sys.stderr = open(1, "w", closefd=False), open(2, "w", closefd=False)
            from ctpipe.cli import main

            try:
                code = main(argv)
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else 1
            except BaseException:
                traceback.print_exc()
                code = 1
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code)
    deadline = time.monotonic() + timeout
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            pytest.fail(f"ctpipe {' '.join(argv)} still running after {timeout} s")
        time.sleep(0.01)
    stdout, stderr = out_path.read_text(errors="replace"), err_path.read_text(errors="replace")
    out_path.unlink()
    err_path.unlink()
    code = os.waitstatus_to_exitcode(status)
    return code, stdout, stderr


@pytest.mark.parametrize("argv, expected, files", [c[1:] for c in CLI_CASES], ids=[c[0] for c in CLI_CASES])
def test_cli_bad_input_exits_2_with_one_line_and_writes_nothing(tmp_path, readonly_dir, argv, expected, files):
    d = tmp_path / "case"
    d.mkdir()
    _common_files(d)
    for name, content in files.items():
        if callable(content):
            content(d)
        elif isinstance(content, np.ndarray):
            np.save(d / name, content)
        elif isinstance(content, bytes):
            (d / name).write_bytes(content)
        else:
            (d / name).write_text(content)
    before = _snapshot(d)
    argv = [a.format(d=d, ro=readonly_dir) for a in argv]
    code, stdout, stderr = run_isolated(argv, cwd=d)
    assert "Traceback" not in stderr, stderr
    assert code == 2, f"exit {code}; stderr: {stderr!r}"
    lines = stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("ctpipe: error: "), stderr
    assert expected in lines[0], f"{expected!r} not in {lines[0]!r}"
    assert _snapshot(d) == before, "files were written or changed"
    if readonly_dir.exists() and os.geteuid() != 0:
        assert list(readonly_dir.iterdir()) == []


# --- the Python API: the specific exception type -----------------------------------------------

def _geometry(**changes):
    from ctpipe.geometry import Geometry

    return Geometry(**{**GEOMETRY, **changes})


def _pipeline_run(projections, geometry=None, **kwargs):
    from ctpipe.pipeline import Pipeline

    return Pipeline.from_config(None).run(projections, geometry or _geometry(), **kwargs)


def _stack(views=3, shape=(48, 48)):
    return np.stack([_textured(shape, seed=s) for s in range(views)]).astype(np.float32)


def _fdk(projections=None, angles=(0.0, 120.0, 240.0), grid=None, **kwargs):
    from ctpipe.recon.feldkamp import fdk
    from ctpipe.recon.volume import VolumeGrid

    grid = grid if grid is not None else VolumeGrid(n_x=8, n_y=8, n_z=8, voxel_size_mm=1.0)
    return fdk(_stack() if projections is None else projections, _geometry(), list(angles), grid, **kwargs)


def _simulate(**spec_changes):
    from ctpipe.sim.phantoms import load_phantom
    from ctpipe.sim.scan_spec import parse_scan_spec
    from ctpipe.sim.simulator import simulate

    spec = SPEC
    for path, value in spec_changes.items():
        spec = _with(spec, path.replace("__", "."), value)
    return simulate(load_phantom("bead-cylinder"), parse_scan_spec(spec), rng=np.random.default_rng(0))


def _load_text(d: Path, content) -> object:
    from ctpipe.config import load_yaml

    path = d / "x.yaml"
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    return load_yaml(path)


def _write_scan(d: Path, folder: str, **kwargs):
    from ctpipe.io.scan_folder import write_scan

    args = {"projections": _stack(), "geometry": _geometry(), "nominal_angles_deg": [0.0, 1.0, 2.0], **kwargs}
    return write_scan(d / folder, **args)


def _write_files_into_a_folder(d: Path):
    from ctpipe.io.outputs import write_files

    (d / "taken").mkdir()
    return write_files({d / "ok.txt": lambda h: h.write(b"1"), d / "taken": lambda h: h.write(b"2")})


def _staged_folder_failing(d: Path):
    from ctpipe.io.outputs import staged_folder

    with staged_folder(d / "res") as tmp:
        (tmp / "a.json").write_text("{}")
        raise EstimationError("the run failed after the first file")


def _pipeline_from(config):
    from ctpipe.pipeline import Pipeline

    return Pipeline.from_config(config)


API_CASES = [
    # id, call(d), exception type (a YAML file that cannot be read is a ConfigError, like its content)
    ("geometry-sdd-equals-sod", lambda d: _geometry(source_to_detector_mm=100.0), InputError),
    ("geometry-negative-pitch", lambda d: _geometry(pixel_pitch_u_mm=-0.1), InputError),
    ("geometry-nan-sod", lambda d: _geometry(source_to_object_mm=float("nan")), InputError),
    ("geometry-inf-sdd", lambda d: _geometry(source_to_detector_mm=float("inf")), InputError),
    ("geometry-zero-rows", lambda d: _geometry(detector_rows=0), InputError),
    ("geometry-fractional-cols", lambda d: _geometry(detector_cols=48.5), InputError),
    ("geometry-string", lambda d: _geometry(source_to_object_mm="100"), InputError),
    ("geometry-huge-cols", lambda d: _geometry(detector_cols=10**12), InputError),
    ("geometry-array-field", lambda d: _geometry(pixel_pitch_u_mm=np.array([1.0, 2.0])), InputError),
    ("from-config-unknown-stage", lambda d: _pipeline_from({"detector": {"name": "nope"}}), ConfigError),
    ("from-config-unknown-key", lambda d: _pipeline_from({"bogus": 1}), ConfigError),
    ("from-config-not-a-mapping", lambda d: _pipeline_from(42), ConfigError),
    ("from-config-missing-file", lambda d: _pipeline_from(d / "nope.yaml"), ConfigError),
    ("from-config-negative-param", lambda d: _pipeline_from({"matcher": {"name": "brute-force", "ratio": -1}}),
     ConfigError),
    ("run-2d-projections", lambda d: _pipeline_run(_stack()[0]), InputError),
    ("run-nan-projections", lambda d: _pipeline_run(np.full((3, 48, 48), np.nan, np.float32)), InputError),
    ("run-shape-vs-geometry", lambda d: _pipeline_run(_stack(shape=(40, 48))), InputError),
    ("run-one-view", lambda d: _pipeline_run(_stack(views=1)), InputError),
    ("run-zero-views", lambda d: _pipeline_run(np.zeros((0, 48, 48), np.float32)), InputError),
    ("run-not-an-array", lambda d: _pipeline_run("projections"), InputError),
    ("run-geometry-is-a-list", lambda d: _pipeline_run(_stack(), [100.0, 200.0]), InputError),
    ("run-geometry-mapping-bad-key", lambda d: _pipeline_run(_stack(), {**GEOMETRY, "zoom": 2}), ConfigError),
    ("run-nominal-wrong-length", lambda d: _pipeline_run(_stack(), nominal_angles_deg=[0.0, 1.0]), InputError),
    ("run-nominal-nan", lambda d: _pipeline_run(_stack(), nominal_angles_deg=[0.0, np.nan, 2.0]), InputError),
    ("run-no-keypoints", lambda d: _pipeline_run(np.zeros((3, 48, 48), np.float32)), EstimationError),
    ("fdk-angles-wrong-length", lambda d: _fdk(angles=(0.0, 1.0)), InputError),
    ("fdk-nan-angle", lambda d: _fdk(angles=(0.0, np.nan, 240.0)), InputError),
    ("fdk-unknown-filter", lambda d: _fdk(filter="sharp"), InputError),
    ("fdk-huge-grid", lambda d: _fdk(grid=import_module("ctpipe.recon.volume").VolumeGrid(
        n_x=100000, n_y=100000, n_z=100000, voxel_size_mm=1.0)), InputError),
    ("simulate-huge-detector", lambda d: _simulate(geometry__detector_cols=60000, geometry__detector_rows=60000),
     InputError),
    ("simulate-huge-views", lambda d: _simulate(angles__n_views=10**8), CtpipeError),
    ("read-scan-missing", lambda d: import_module("ctpipe.io.scan_folder").read_scan(d / "nope"), InputError),
    ("read-scan-file", lambda d: import_module("ctpipe.io.scan_folder").read_scan(d / "afile"), InputError),
    ("read-scan-empty-folder", lambda d: import_module("ctpipe.io.scan_folder").read_scan(d / "emptydir"), InputError),
    ("load-yaml-alias-bomb", lambda d: _load_text(d, BOMB), ConfigError),
    ("load-yaml-not-utf8", lambda d: _load_text(d, b"a: \xff\n"), ConfigError),
    ("load-yaml-duplicate-key", lambda d: _load_text(d, "a: 1\na: 2\n"), ConfigError),
    ("load-yaml-python-tag", lambda d: _load_text(d, "a: !!python/name:os.system\n"), ConfigError),
    ("load-yaml-malformed", lambda d: _load_text(d, "a: [\n"), ConfigError),
    ("load-yaml-missing", lambda d: import_module("ctpipe.config").load_yaml(d / "nope.yaml"), ConfigError),
    ("load-yaml-folder", lambda d: import_module("ctpipe.config").load_yaml(d / "emptydir"), ConfigError),
    ("write-scan-into-file", lambda d: _write_scan(d, "afile"), InputError),
    ("write-scan-nan-angles", lambda d: _write_scan(d, "s", nominal_angles_deg=[0.0, np.nan, 2.0]), InputError),
    ("write-scan-int64-stack", lambda d: _write_scan(d, "s", projections=np.ones((3, 48, 48), np.int64)),
     InputError),
    ("check-output-dir-empty", lambda d: import_module("ctpipe.io.outputs").check_output_dir(""), InputError),
    ("check-output-dir-file", lambda d: import_module("ctpipe.io.outputs").check_output_dir(d / "afile"), InputError),
    ("check-output-file-under-file", lambda d: import_module("ctpipe.io.outputs").check_output_file(d / "afile" / "x.npz"),
     InputError),
    ("write-files-onto-a-folder", _write_files_into_a_folder, InputError),
    ("staged-folder-body-fails", _staged_folder_failing, EstimationError),
]


@pytest.mark.parametrize("call, error", [c[1:] for c in API_CASES], ids=[c[0] for c in API_CASES])
def test_api_bad_input_raises_the_specific_error(tmp_path, call, error):
    _common_files(tmp_path)
    before = _snapshot(tmp_path)
    with pytest.raises(error) as info:
        call(tmp_path)
    assert "\n" not in str(info.value).strip()
    after = {k: v for k, v in _snapshot(tmp_path).items() if k not in ("taken", "x.yaml")}
    assert after == before, "files were written or changed"


# Borderline inputs that are fine and must stay fine.
ACCEPTED_CASES = [
    ("yaml-1e-3-is-a-number", lambda d: _load_text(d, "x: 1e-3\n"), {"x": 0.001}),
    ("yaml-exponent-with-sign", lambda d: _load_text(d, "x: -2E+2\n"), {"x": -200.0}),
    ("geometry-numpy-scalars", lambda d: _geometry(source_to_object_mm=np.float32(100.0),
                                                   detector_cols=np.int64(48)).detector_cols, 48),
    ("check-output-dir-missing-parents", lambda d: import_module("ctpipe.io.outputs").check_output_dir(d / "a" / "b").name,
     "b"),
]


@pytest.mark.parametrize("call, expected", [c[1:] for c in ACCEPTED_CASES], ids=[c[0] for c in ACCEPTED_CASES])
def test_api_borderline_input_is_accepted(tmp_path, call, expected):
    (tmp_path / "afile").write_text("x")
    assert call(tmp_path) == expected
    assert not (tmp_path / "a").exists()


# --- the mechanisms, end to end ----------------------------------------------------------------

def test_entry_point_reports_a_bad_output_before_work_in_one_line(tmp_path):
    (tmp_path / "afile").write_text("x")
    proc = subprocess.run([sys.executable, "-m", "ctpipe.cli", "simulate", "bead-cylinder", "--scan",
                           str(tmp_path / "nope.yaml"), "--out", str(tmp_path / "afile" / "o")],
                          capture_output=True, text=True, timeout=TIMEOUT_S)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.startswith("ctpipe: error: --out ") and proc.stderr.count("\n") == 1


def test_sigterm_while_a_scan_is_written_leaves_no_temporary_folder(tmp_path):
    (tmp_path / "spec.yaml").write_text(_dump(_with(SPEC, "angles.n_views", 40)))
    # Slow the TIFF writer down so SIGTERM lands while the temporary folder is being filled.
    script = ("import sys, time, tifffile\n"
              "real = tifffile.imwrite\n"
              "def slow(*a, **k):\n"
              "    real(*a, **k); time.sleep(0.05)\n"
              "tifffile.imwrite = slow\n"
              "from ctpipe.cli import main\n"
              "sys.exit(main(sys.argv[1:]))\n")
    proc = subprocess.Popen([sys.executable, "-c", script, "simulate", "bead-cylinder", "--scan",
                             str(tmp_path / "spec.yaml"), "--out", str(tmp_path / "scan")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + TIMEOUT_S
    while not any(p.name.endswith(".tmp") and any(p.rglob("*.tif")) for p in tmp_path.iterdir()):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "the scan was never being written"
        time.sleep(0.01)
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=TIMEOUT_S)
    assert proc.returncode == 128 + signal.SIGTERM and stderr.strip().endswith("ctpipe: terminated")
    assert "Traceback" not in stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spec.yaml"]


def test_estimate_writes_both_files_or_neither(tmp_path, monkeypatch, capsys):
    """A failure renaming the second file takes the first one back out; a full disk is one line, status 1."""
    from ctpipe.io import outputs as ctio
    from ctpipe.cli import main

    _common_files(tmp_path)
    out = tmp_path / "res"
    out.mkdir()
    (out / "angles.csv").write_text("an older result\n")
    real_replace = os.replace

    def failing_replace(src, dst):
        if str(dst).endswith("result.json"):
            raise OSError(28, "No space left on device")
        return real_replace(src, dst)

    monkeypatch.setattr(ctio.os, "replace", failing_replace)
    assert main(["estimate", str(tmp_path / "proj.npy"), "--geometry", str(tmp_path / "geometry.yaml"),
                 "--out", str(out)]) == 1
    assert capsys.readouterr().err.startswith(f"ctpipe: error: {out}: no space left on the device")
    assert sorted(p.name for p in out.iterdir()) == ["angles.csv"]
    assert (out / "angles.csv").read_text() == "an older result\n"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_overwrite_replaces_a_scan_folder(tmp_path, monkeypatch):
    """--overwrite still does its job on what it is for: a ctpipe scan folder."""
    from ctpipe.io.scan_folder import check_scan_folder_free

    _scan_folder(tmp_path, "scan")
    monkeypatch.chdir(tmp_path / "scan")
    with pytest.raises(InputError, match="current directory"):
        check_scan_folder_free(".", overwrite=True)
    monkeypatch.chdir(tmp_path)
    check_scan_folder_free("scan", overwrite=True)
    _scan_folder(tmp_path, "again")
    from ctpipe.io.scan_folder import write_scan

    write_scan(tmp_path / "scan", _stack(), _geometry(), [0.0, 1.0, 2.0], overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again", "scan"]
