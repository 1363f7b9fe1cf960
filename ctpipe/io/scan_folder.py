"""Scan folders: projections with their geometry and angles, simulated or from a real scanner.

A scan folder is a folder with a ``scan.yaml`` and one TIFF per frame::

    scan.yaml
    projections/proj_00000.tif ...    # one 2-D image (rows, cols) per view, float32 or uint16
    flats/flat_00000.tif ...          # optional: beam, no object
    darks/dark_00000.tif ...          # optional: no beam

``scan.yaml``::

    format: ctpipe-scan/1
    geometry:                         # the fields of ctpipe.geometry.Geometry, units in the names
      source_to_object_mm: 190.0
      source_to_detector_mm: 390.0
      detector_cols: 512
      detector_rows: 512
      pixel_pitch_u_mm: 0.8
      pixel_pitch_v_mm: 0.8
      u0_px: 255.5                    # optional (null: the detector centre)
      v0_px: 255.5
    angles:
      nominal_deg: [0.0, 1.0, ...]    # one per view, the commanded turntable angles
      true_deg: [0.013, 0.987, ...]   # optional: the truth, when known (simulations)
    projections:
      values: line_integrals          # or intensities: raw counts, corrected with flats and darks
      files: projections/proj_{index:05d}.tif   # a pattern with {index} (0, 1, ...) or a list of names
      count: 360                      # with a pattern: how many files
    flats: {files: flats/flat_{index:05d}.tif, count: 8}   # optional; required for intensities
    darks: {files: [dark_a.tif, dark_b.tif]}                # optional
    provenance: {...}                 # free-form: phantom, scan spec, seed, generator, dates
    written_by: ctpipe 0.1.0          # optional, set by write_scan
    written_utc: "2025-01-01T00:00:00+00:00"

File names are relative to the folder. :func:`read_scan` returns the projections as float32
line integrals, applying :func:`ctpipe.io.flatfield.log_transform` when they are intensities.
A real scanner's export only needs a ``scan.yaml`` written next to its TIFFs. What a simulation
acquires is a scan spec, :mod:`ctpipe.sim.scan_spec`.
"""

from __future__ import annotations

import datetime
import os
import shutil
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ctpipe.config import check_keys, load_yaml, parse_geometry
from ctpipe.errors import ConfigError, InputError
from ctpipe.geometry import Geometry, check_geometry
from ctpipe.hookspecs import hookimpl
from ctpipe.io.flatfield import log_transform
from ctpipe.io.outputs import COMMIT_LOCK, temporary_prefix, pending, temporary_sibling, to_jsonable
from ctpipe.io.scans import ScanFiles, ViewFiles, ViewStack
from ctpipe.stages import ParamSpec, check_value

__all__ = ["Scan", "read_scan", "open_scan_folder", "write_scan", "check_scan_folder_free", "SCAN_FORMAT",
           "VALUE_KINDS"]

#: The ``format`` value of a scan.yaml this version reads and writes.
SCAN_FORMAT = "ctpipe-scan/1"
#: What the projection files hold.
VALUE_KINDS = ("line_integrals", "intensities")

_PATTERNS = {"projections": "projections/proj_{index:05d}.tif", "flats": "flats/flat_{index:05d}.tif",
             "darks": "darks/dark_{index:05d}.tif"}


@dataclass(frozen=True, eq=False)
class Scan:
    """A scan folder, read.

    Attributes
    ----------
    projections : ndarray of shape (V, rows, cols), float32
        Line integrals (``-log`` of the corrected intensities when the files hold intensities).
    geometry : Geometry
    nominal_angles_deg : ndarray of shape (V,), float64
    true_angles_deg : ndarray of shape (V,), float64, or None
    values : str
        What the files hold: ``line_integrals`` or ``intensities``.
    raw : ndarray of shape (V, rows, cols)
        The projection files as stored (float32, uint16, ...).
    flats, darks : ndarray of shape (F, rows, cols) or None
        As stored.
    provenance : dict
    folder : Path
    """

    projections: np.ndarray
    geometry: Geometry
    nominal_angles_deg: np.ndarray
    true_angles_deg: np.ndarray | None
    values: str
    raw: np.ndarray
    flats: np.ndarray | None
    darks: np.ndarray | None
    provenance: dict
    folder: Path


def _angles(value: Any, path: str) -> np.ndarray:
    spec = ParamSpec("", tuple[float, ...], None, "")
    try:
        return np.asarray(check_value(spec, value, path), dtype=np.float64)
    except ConfigError:
        raise ConfigError(f"{path}: must be a non-empty list of finite numbers (degrees), got "
                          f"{value if not isinstance(value, list) else f'a list of {len(value)} items'!r}") from None


def _file_names(value: Any, path: str, folder: Path, allowed: tuple[str, ...] = ("files", "count")) -> list[str]:
    check_keys(value, path, allowed=allowed, required=("files",))
    files = value["files"]
    if isinstance(files, str):
        if "{index" not in files:
            raise ConfigError(f"{path}.files: a single name must be a pattern with {{index}}, e.g. "
                              f"proj_{{index:05d}}.tif, got {files!r}")
        if "count" not in value:
            raise ConfigError(f"{path}.count: missing; a file pattern needs the number of files")
        count = check_value(ParamSpec("count", int, None, "", ge=1), value["count"], f"{path}.count")
        # Names are made one at a time and each file looked up, so a count beyond the files
        # present stops at the first missing one: 10^12 names are never built.
        names = []
        for i in range(count):
            try:
                name = files.format(index=i)
            except (KeyError, IndexError, ValueError) as exc:
                raise ConfigError(f"{path}.files: not a usable pattern ({exc}), got {files!r}") from None
            if not (folder / name).is_file():
                from ctpipe.io.scans import still_being_written_hint

                raise InputError(f"{folder / name}: no such file; {path}.count says {count} files, of which "
                                 f"only the first {i} exist, and count must match the files present"
                                 f"{still_being_written_hint([folder / n for n in names])}")
            names.append(name)
        return names
    if not isinstance(files, list) or not files or not all(isinstance(f, str) for f in files):
        raise ConfigError(f"{path}.files: must be a pattern with {{index}} or a non-empty list of file names, "
                          f"got {files!r}")
    if "count" in value and value["count"] != len(files):
        raise ConfigError(f"{path}.count: says {value['count']!r} but files lists {len(files)}")
    return list(files)


def _read_frames(folder: Path, names: list[str], shape: tuple[int, int], what: str) -> np.ndarray:
    from ctpipe.io.arrays import read_array
    from ctpipe._shared.resources import check_fits

    frames = None
    for i, name in enumerate(names):
        file = folder / name
        if not file.is_file():
            raise InputError(f"{file}: no such file ({what} {i} of {len(names)})")
        image = read_array(file, kind=".tif")
        if image.shape != shape:
            raise InputError(f"{file}: must be a {shape[0]} x {shape[1]} image (rows x cols, from the geometry), "
                             f"got shape {image.shape}")
        if not (np.issubdtype(image.dtype, np.integer) or np.issubdtype(image.dtype, np.floating)):
            raise InputError(f"{file}: must hold real numbers, got {image.dtype}")
        if frames is None:
            check_fits(f"reading {len(names)} {what} frames of {shape[0]} x {shape[1]}",
                       len(names) * shape[0] * shape[1] * image.dtype.itemsize, of=str(image.dtype))
            frames = np.empty((len(names), *shape), image.dtype)
        elif image.dtype != frames.dtype:
            raise InputError(f"{file}: is {image.dtype} but the first {what} file is {frames.dtype}")
        frames[i] = image
    return frames


def _parse(folder: Path) -> dict[str, Any]:
    """Everything ``scan.yaml`` says, checked, with the file names resolved (nothing read yet)."""
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder")
    source = folder / "scan.yaml"
    if not source.is_file():
        raise InputError(f"{folder}: not a scan folder (no scan.yaml)")
    mapping = load_yaml(source)
    path = str(source)
    check_keys(mapping, path, allowed=("format", "geometry", "angles", "projections", "flats", "darks", "provenance",
                                       "written_by", "written_utc"),
               required=("format", "geometry", "angles", "projections"))
    if mapping["format"] != SCAN_FORMAT:
        raise ConfigError(f"{path}.format: must be {SCAN_FORMAT!r}, got {mapping['format']!r}")
    geometry = parse_geometry(mapping["geometry"], f"{path}.geometry")
    angles = check_keys(mapping["angles"], f"{path}.angles", allowed=("nominal_deg", "true_deg"),
                        required=("nominal_deg",))
    nominal = _angles(angles["nominal_deg"], f"{path}.angles.nominal_deg")
    truth = None
    if angles.get("true_deg") is not None:
        truth = _angles(angles["true_deg"], f"{path}.angles.true_deg")
        if len(truth) != len(nominal):
            raise ConfigError(f"{path}.angles.true_deg: has {len(truth)} angles but nominal_deg has {len(nominal)}")
    projections = mapping["projections"]
    names = _file_names(projections, f"{path}.projections", folder, allowed=("values", "files", "count"))
    values = projections.get("values", "line_integrals")
    if values not in VALUE_KINDS:
        raise ConfigError(f"{path}.projections.values: must be one of {', '.join(VALUE_KINDS)}, got {values!r}")
    if len(names) != len(nominal):
        raise InputError(f"{path}: {len(names)} projection files but {len(nominal)} nominal angles; "
                         f"there must be one angle for every projection")
    frames = {}
    for kind in ("flats", "darks"):
        if mapping.get(kind) is not None:
            frames[kind] = _read_frames(folder, _file_names(mapping[kind], f"{path}.{kind}", folder), geometry.shape,
                                        kind[:-1])
    if values == "intensities" and frames.get("flats") is None:
        raise ConfigError(f"{path}.flats: missing; intensities need flat fields to be turned into line integrals")
    provenance = mapping.get("provenance") or {}
    if not isinstance(provenance, Mapping):
        raise ConfigError(f"{path}.provenance: must be a mapping, got {provenance!r}")
    return {"geometry": geometry, "nominal": nominal, "truth": truth, "values": values, "names": names,
            "flats": frames.get("flats"), "darks": frames.get("darks"), "provenance": dict(provenance)}


def read_scan(folder: str | Path) -> Scan:
    """Read a scan folder (see the module docstring).

    Raises
    ------
    ConfigError
        ``scan.yaml`` is malformed (the message names the YAML path).
    InputError
        Missing or unreadable files, shapes that disagree with the geometry, a count mismatch.
    """
    folder = Path(folder)
    parsed = _parse(folder)
    geometry, values, flats, darks = parsed["geometry"], parsed["values"], parsed["flats"], parsed["darks"]
    raw = _read_frames(folder, parsed["names"], geometry.shape, "projection")
    if values == "intensities":
        from ctpipe._shared.resources import FLOAT32, check_fits

        check_fits(f"the -log of {raw.shape[0]} views of {raw.shape[1]} x {raw.shape[2]}", raw[:1].size * len(raw) * FLOAT32)
        try:
            line_integrals = log_transform(raw, flats, darks)
        except InputError as exc:
            raise InputError(f"{folder}: {exc}") from None
    else:
        line_integrals = raw.astype(np.float32, copy=False)
    return Scan(line_integrals, geometry, parsed["nominal"], parsed["truth"], values, raw, flats, darks,
                parsed["provenance"], folder)


def open_scan_folder(folder: str | Path) -> ScanFiles:
    """Open a scan folder lazily: geometry, angles and calibration frames read, views on demand."""
    folder = Path(folder)
    parsed = _parse(folder)
    geometry, names = parsed["geometry"], parsed["names"]
    read = ViewFiles(tuple(folder / name for name in names))
    try:
        stack = ViewStack(read, len(names), geometry.shape, values=parsed["values"], flats=parsed["flats"],
                          darks=parsed["darks"], name=str(folder))
    except InputError as exc:
        raise InputError(f"{folder}: {exc}") from None
    return ScanFiles("ctpipe", folder, geometry, parsed["nominal"], stack, true_angles_deg=parsed["truth"],
                     metadata={"provenance": parsed["provenance"]})


def _check_stack(array, name: str, geometry: Geometry, count: int | None = None) -> np.ndarray:
    array = np.asarray(array)
    if array.ndim != 3 or array.shape[1:] != geometry.shape:
        raise InputError(f"{name}: must have shape (frames, {geometry.detector_rows}, {geometry.detector_cols}) "
                         f"to match the geometry, got {array.shape}")
    if count is not None and len(array) != count:
        raise InputError(f"{name}: there must be one angle for every projection; got {len(array)} projections "
                         f"and {count} nominal angles")
    if array.dtype == np.uint16 or array.dtype == np.float32:
        return array
    if np.issubdtype(array.dtype, np.floating):
        return array.astype(np.float32)
    raise InputError(f"{name}: must be float32 (or another float, stored as float32) or uint16, got {array.dtype}")


def write_scan(folder: str | Path, projections, geometry: Geometry, nominal_angles_deg, true_angles_deg=None, *,
               flats=None, darks=None, values: str = "line_integrals", provenance: Mapping | None = None,
               overwrite: bool = False) -> Path:
    """Write a scan folder atomically (see the module docstring).

    Everything goes into a temporary sibling folder that is renamed into place at the end, so
    a failure leaves neither a half-written ``folder`` nor the temporary one.

    Parameters
    ----------
    folder : path
        The scan folder; it must not exist or be empty, unless ``overwrite``.
    projections : ndarray of shape (V, rows, cols), float32 or uint16
        Other float dtypes are stored as float32.
    geometry : Geometry
    nominal_angles_deg, true_angles_deg : array of shape (V,), degrees
        ``true_angles_deg`` may be None (unknown).
    flats, darks : ndarray of shape (F, rows, cols), or None
    values : {"line_integrals", "intensities"}
        What ``projections`` holds; intensities need ``flats``.
    provenance : mapping or None
        Free-form, YAML-safe after numpy values become plain numbers.
    overwrite : bool
        Replace an existing non-empty ``folder``.

    Returns
    -------
    Path of the folder.
    """
    import tifffile

    from ctpipe._version import __version__

    folder = Path(folder)
    if values not in VALUE_KINDS:
        raise InputError(f"values: must be one of {', '.join(VALUE_KINDS)}, got {values!r}")
    check_geometry(geometry)
    nominal = np.asarray(nominal_angles_deg, dtype=np.float64)
    if nominal.ndim != 1 or not np.all(np.isfinite(nominal)):
        raise InputError(f"nominal_angles_deg: must be a 1-D array of finite angles, got shape {nominal.shape}")
    truth = None
    if true_angles_deg is not None:
        truth = np.asarray(true_angles_deg, dtype=np.float64)
        if truth.shape != nominal.shape or not np.all(np.isfinite(truth)):
            raise InputError(f"true_angles_deg: must be finite and have the shape of nominal_angles_deg "
                             f"{nominal.shape}, got {truth.shape}")
    projections = _check_stack(projections, "projections", geometry, len(nominal))
    stacks = {"projections": projections}
    for name, frames in (("flats", flats), ("darks", darks)):
        if frames is not None:
            stacks[name] = _check_stack(frames, name, geometry)
    if values == "intensities" and flats is None:
        raise InputError("flats: intensities need flat fields (values='intensities' without flats)")
    check_scan_folder_free(folder, overwrite=overwrite)

    document: dict[str, Any] = {"format": SCAN_FORMAT, "geometry": to_jsonable(geometry.to_dict()),
                                "angles": {"nominal_deg": nominal.tolist(),
                                           "true_deg": None if truth is None else truth.tolist()}}
    for name, stack in stacks.items():
        entry = {"files": _PATTERNS[name], "count": len(stack)}
        document[name] = {"values": values, **entry} if name == "projections" else entry
    document["provenance"] = to_jsonable(dict(provenance or {}))
    document["written_by"] = f"ctpipe {__version__}"
    document["written_utc"] = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")

    with temporary_sibling(folder) as tmp:
        # mkdtemp makes the folder private (0700); the scan folder should read like any other.
        mask = os.umask(0o022)
        os.umask(mask)
        os.chmod(tmp, 0o777 & ~mask)
        for name, stack in stacks.items():
            for i, image in enumerate(stack):
                file = tmp / _PATTERNS[name].format(index=i)
                file.parent.mkdir(exist_ok=True)
                tifffile.imwrite(file, image)
        text = yaml.safe_dump(document, sort_keys=False, default_flow_style=None, width=100)
        (tmp / "scan.yaml").write_text(text, encoding="utf-8")
        with COMMIT_LOCK:
            old = _swap_into_place(tmp, folder, overwrite)
        if old is not None:   # the scan replaced; a stop while it is removed finishes the removal (discard_pending)
            with pending(old):
                shutil.rmtree(old, ignore_errors=True)
    return folder


def check_scan_folder_free(folder: str | Path, *, overwrite: bool = False) -> None:
    """Raise :class:`InputError` unless a scan can be written to ``folder``.

    It must not exist, or be an empty folder, or ``overwrite`` must be set; callers that spend
    time producing the scan call this first, so a refusal costs nothing. ``overwrite`` only
    ever replaces a scan folder (one with a ``scan.yaml`` of this format), and never the
    current directory or one of its ancestors, which ``--out .`` would otherwise delete.
    """
    from ctpipe.io.outputs import check_output_dir

    folder = check_output_dir(folder, "--out")
    if not folder.is_dir() or not any(folder.iterdir()):
        return
    if not overwrite:
        raise InputError(f"{folder}: exists and is not empty; choose another folder or overwrite")
    resolved, here = folder.resolve(), Path.cwd().resolve()
    if resolved == here or resolved in here.parents:
        raise InputError(f"{folder}: is the current directory or one of its parents; overwrite only "
                         f"replaces a scan folder, so give a folder of its own")
    if not _is_scan_folder(folder):
        raise InputError(f"{folder}: is not a ctpipe scan folder (no scan.yaml with format {SCAN_FORMAT}); "
                         f"overwrite only replaces a scan folder, so choose another folder")


def _is_scan_folder(folder: Path) -> bool:
    try:
        with open(folder / "scan.yaml", "rb") as handle:
            head = handle.read(4096).decode("utf-8", errors="replace")
    except OSError:
        return False
    return any(line.split("#")[0].strip().strip("'\"").endswith(SCAN_FORMAT) and line.startswith("format:")
               for line in head.splitlines())


def _swap_into_place(tmp: Path, folder: Path, overwrite: bool) -> Path | None:
    """Rename ``tmp`` to ``folder``; the scan it replaced, moved aside, for the caller to remove (None if none)."""
    if folder.is_dir() and not any(folder.iterdir()):
        folder.rmdir()
    if not folder.exists():
        os.rename(tmp, folder)
        return None
    if not overwrite:
        raise InputError(f"{folder}: appeared while the scan was written; not overwriting it")
    old = Path(tempfile.mkdtemp(prefix=temporary_prefix(folder), suffix=".old", dir=folder.parent))
    old.rmdir()
    os.rename(folder, old)
    try:
        os.rename(tmp, folder)
    except BaseException:
        os.rename(old, folder)
        raise
    return old


def _detect(path: Path) -> bool:
    return path.is_dir() and (path / "scan.yaml").is_file()


@hookimpl
def ctpipe_register_formats(registry) -> None:
    registry.add_format("ctpipe", _detect, open_scan_folder, "a folder with scan.yaml (ctpipe's scan folder)")
