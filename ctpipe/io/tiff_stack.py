"""A plain TIFF stack with a small YAML beside it: the format of any scanner ctpipe has no reader for.

A folder with the projections as TIFF files (one per view, in name order, or one multi-page
TIFF) and one YAML file (any name ending ``.yaml`` or ``.yml`` other than ``scan.yaml``, which
is ctpipe's own scan folder) that says what they are::

    geometry:                          # the fields of ctpipe.geometry.Geometry
      source_to_object_mm: 190.0
      source_to_detector_mm: 390.0
      detector_cols: 512
      detector_rows: 512
      pixel_pitch_u_mm: 0.2
      pixel_pitch_v_mm: 0.2
    angles:                            # one of:
      nominal_deg: [0.0, 0.5, ...]     #   one per view, or
      range_deg: 360.0                 #   evenly spaced over range_deg from start_deg, the
      start_deg: 0.0                   #   last view one step short of a full range
      recorded_deg: [...]              # optional: the scanner's logged angle of every view
    projections: "proj_*.tif"          # optional glob (default: every .tif/.tiff but flats and darks)
    values: intensities                # or line_integrals (already -log)
    white_level: 60000                 # intensities without flats: counts of an open beam
    flats: "flat_*.tif"                # optional globs of flat and dark frames
    darks: "dark_*.tif"

Angles are in ctpipe's convention (a turntable turn of +a is +a, see ``docs/model.md``): a
scanner that counts the other way needs its angles negated when the YAML is written.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ctpipe.config import check_keys, load_yaml, parse_geometry
from ctpipe.errors import ConfigError, InputError
from ctpipe.hookspecs import hookimpl
from ctpipe.io.scans import ScanFiles, ViewStack, check_angles

__all__ = ["open_tiff_stack"]

_TIFF = (".tif", ".tiff")


def _yaml_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in (".yaml", ".yml") and p.name != "scan.yaml")


def detect(path: Path) -> bool:
    if not path.is_dir() or (path / "scan.yaml").exists():
        return False
    return len(_yaml_files(path)) == 1 and any(p.suffix.lower() in _TIFF for p in path.iterdir())


def _glob(folder: Path, pattern: Any, what: str, source: str) -> list[Path]:
    if not isinstance(pattern, str) or not pattern or "/" in pattern or "\\" in pattern:
        raise ConfigError(f"{source}.{what}: must be a file-name pattern in the folder (e.g. 'proj_*.tif'), "
                          f"got {pattern!r}")
    files = sorted(p for p in folder.glob(pattern) if p.is_file())
    if not files:
        raise InputError(f"{folder}: no file matches {what} pattern {pattern!r} (from {source})")
    return files


def _read(file: Path) -> np.ndarray:
    from ctpipe.io.arrays import read_array

    return read_array(file, kind=".tif")


def open_tiff_stack(folder: str | Path) -> ScanFiles:
    """Open a TIFF stack described by its YAML (see the module docstring)."""
    folder = Path(folder)
    yamls = _yaml_files(folder) if folder.is_dir() else []
    if len(yamls) != 1:
        raise InputError(f"{folder}: a TIFF stack needs exactly one YAML file beside the TIFFs, found {len(yamls)}")
    source = yamls[0]
    mapping = load_yaml(source)
    check_keys(mapping, str(source), allowed=("geometry", "angles", "projections", "values", "white_level", "flats",
                                              "darks"), required=("geometry", "angles", "values"))
    geometry = parse_geometry(mapping["geometry"], f"{source}.geometry")
    values = mapping["values"]
    if values not in ("intensities", "line_integrals"):
        raise ConfigError(f"{source}.values: must be 'intensities' or 'line_integrals', got {values!r}")
    calibration = {kind: _glob(folder, mapping[kind], kind, str(source)) for kind in ("flats", "darks")
                   if mapping.get(kind) is not None}
    taken = {p for files in calibration.values() for p in files}
    if mapping.get("projections") is not None:
        files = [p for p in _glob(folder, mapping["projections"], "projections", str(source)) if p not in taken]
    else:
        files = sorted(p for p in folder.iterdir() if p.suffix.lower() in _TIFF and p not in taken)
    if not files:
        raise InputError(f"{folder}: no projection TIFFs")

    if len(files) == 1:
        stack = _read(files[0])
        if stack.ndim != 3:
            raise InputError(f"{files[0]}: a single projection file must be a multi-page TIFF (views, rows, cols), "
                             f"got shape {stack.shape}")
        n_views, read = len(stack), (lambda index: stack[index])
    else:
        n_views, read = len(files), (lambda index: _read(files[index]))

    angles = check_keys(mapping["angles"], f"{source}.angles",
                        allowed=("nominal_deg", "range_deg", "start_deg", "recorded_deg"))
    if "nominal_deg" in angles:
        if "range_deg" in angles or "start_deg" in angles:
            raise ConfigError(f"{source}.angles: give nominal_deg or range_deg/start_deg, not both")
        nominal = check_angles(angles["nominal_deg"], n_views, f"{source}.angles.nominal_deg")
    elif "range_deg" in angles:
        start, span = angles.get("start_deg", 0.0), angles["range_deg"]
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in (start, span)):
            raise ConfigError(f"{source}.angles: range_deg and start_deg must be numbers (degrees), got "
                              f"{span!r} and {start!r}")
        nominal = start + span * np.arange(n_views) / n_views
    else:
        raise ConfigError(f"{source}.angles: needs nominal_deg (one per view) or range_deg")
    recorded = None
    if angles.get("recorded_deg") is not None:
        recorded = check_angles(angles["recorded_deg"], n_views, f"{source}.angles.recorded_deg")

    frames = {kind: np.stack([_read(p) for p in files_]) for kind, files_ in calibration.items()}
    white = mapping.get("white_level")
    if white is not None and (isinstance(white, bool) or not isinstance(white, (int, float)) or not white > 0):
        raise ConfigError(f"{source}.white_level: must be a number > 0, got {white!r}")
    if values == "intensities" and "flats" not in frames and white is None:
        raise ConfigError(f"{source}: intensities need flats (a glob of flat frames) or white_level")
    projections = ViewStack(read, n_views, geometry.shape, values=values, flats=frames.get("flats"),
                            darks=frames.get("darks"), white_level=None if white is None else float(white),
                            name=str(folder))
    return ScanFiles("tiff-yaml", folder, geometry, nominal.astype(np.float64), projections,
                     recorded_angles_deg=recorded, metadata={"yaml": source.name, "files": len(files)})


@hookimpl
def ctpipe_register_formats(registry) -> None:
    registry.add_format("tiff-yaml", detect, open_tiff_stack,
                        "a folder of TIFFs with one YAML beside them (geometry, angles, values)")
