"""Nikon / X-Tek scans written as a Nikon scanner and CT Pro leave them, for tests and benchmarks.

:func:`write_nikon` writes a ``<name>.xtekct``, the flat-corrected 16-bit projections and an
angle log (``_ctdata.txt`` or ``<name>.ang``) that :func:`ctpipe.io.nikon.open_nikon` reads;
the layout, keys and sign conventions are those of :mod:`ctpipe.io.nikon`'s docstring. The
corrected ``.ang`` a user gets back is written by the reader's module
(:func:`ctpipe.io.nikon.write_nikon_angles`), which this writer uses for ``angle_log="ang"``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ctpipe.errors import InputError
from ctpipe.geometry import Geometry, check_geometry
from ctpipe.io.nikon import _CTDATA, _CTDATA_HEADERS, _SECTION, _float, write_nikon_angles
from ctpipe.io.scans import check_angles

__all__ = ["write_nikon", "OFFSET_KEYS", "ANGLE_LOGS"]

#: How :func:`write_nikon` stores the principal point's column: in ``ObjectOffsetX`` (files of
#: Inspect-X 6 and later), ``CentreOfRotationTop/Bottom`` (older files) or ``DetectorOffsetX``.
OFFSET_KEYS = ("object_offset", "centre_of_rotation", "detector_offset")
#: Which angle log :func:`write_nikon` writes: the scanner's ``_ctdata.txt``, CT Pro's ``.ang``, or none.
ANGLE_LOGS = ("ctdata", "ang", None)


def _ctdata_text(relative: np.ndarray, projections: int) -> str:
    lines = [_CTDATA_HEADERS[0], f"{projections}\t1\t0.00", _CTDATA_HEADERS[1]]
    lines += [f"{i + 1}\t{_float(a)}\t0.0000" for i, a in enumerate(relative)]
    return "\r\n".join(lines) + "\r\n"


def _xtekct_text(name: str, geometry: Geometry, n_views: int, initial: float, step: float, white_level: float,
                 offset_keys: str) -> str:
    cols, rows = geometry.detector_cols, geometry.detector_rows
    shift_mm = (geometry.u0_px - (cols - 1) / 2.0) * geometry.pixel_pitch_u_mm
    offset_v = (geometry.v0_px - (rows - 1) / 2.0) * geometry.pixel_pitch_v_mm
    sod, sdd = geometry.source_to_object_mm, geometry.source_to_detector_mm
    cor = offset_u = object_offset = 0.0
    if offset_keys == "centre_of_rotation":
        cor = shift_mm
    elif offset_keys == "detector_offset":
        offset_u = -shift_mm
    else:
        object_offset = shift_mm * sod / sdd
    voxel = geometry.pixel_pitch_u_mm * sod / sdd
    keys = {
        "Name": name, "OperatorID": "", "InputSeparator": "_", "InputFolderName": "", "OutputSeparator": "_",
        "OutputFolderName": name, "VoxelsX": cols, "VoxelSizeX": _float(voxel), "OffsetX": "0.0", "VoxelsY": cols,
        "VoxelSizeY": _float(voxel), "OffsetY": "0.0", "VoxelsZ": rows, "VoxelSizeZ": _float(voxel),
        "OffsetZ": "0.0", "SrcToObject": _float(sod), "SrcToDetector": _float(sdd),
        "MaskRadius": _float(cols * voxel / 2.0), "DetectorPixelsX": cols,
        "DetectorPixelSizeX": _float(geometry.pixel_pitch_u_mm), "DetectorOffsetX": _float(offset_u),
        "DetectorPixelsY": rows, "DetectorPixelSizeY": _float(geometry.pixel_pitch_v_mm),
        "DetectorOffsetY": _float(offset_v), "RegionStartX": 0, "RegionPixelsX": cols, "RegionStartY": 0,
        "RegionPixelsY": rows, "Units": "mm", "Projections": n_views, "InitialAngle": _float(initial),
        "AngularStep": _float(step), "WhiteLevel": _float(white_level), "Scattering": "0.0",
        "InputName": name, "InputDigits": 4, "OutputName": name, "OutputDigits": 4,
    }
    if offset_keys == "centre_of_rotation":
        keys.update({"CentreOfRotationTop": _float(cor), "CentreOfRotationBottom": _float(cor)})
    else:
        keys.update({"ObjectOffsetX": _float(object_offset), "ObjectOffsetY": "0.0", "ObjectTilt": "0.0",
                     "ObjectRoll": "0.0"})
    lines = [f"[{_SECTION}]"] + [f"{key}={value}" for key, value in keys.items()]
    lines += ["[CTPro]", "Product=[ctpipe.testing.write_nikon]", "Shuttling=False", "AngleFile_Use=False",
              "AngleFile_IgnoreErrors=True"]
    return "\r\n".join(lines) + "\r\n"


def _flat_correct(intensities: np.ndarray, flats, darks, white_level: float) -> np.ndarray:
    """The scanner's correction: ``(I - mean dark) / (mean flat - mean dark) * WhiteLevel``, rounded, as uint16."""
    shape = intensities.shape[1:]
    if flats is None:
        raise InputError("flats: required; the scanner divides by the flat fields before it saves a projection")
    flat = np.asarray(flats, dtype=np.float64)
    flat = flat.mean(axis=0) if flat.ndim == 3 else flat
    dark = np.zeros(shape) if darks is None else np.asarray(darks, dtype=np.float64)
    dark = dark.mean(axis=0) if dark.ndim == 3 else dark
    for label, frame in (("flats", flat), ("darks", dark)):
        if frame.shape != shape:
            raise InputError(f"{label}: each frame must have the projections' shape {shape}, got {frame.shape}")
    beam = flat - dark
    alive = beam > 0
    beam = np.where(alive, beam, 1.0)
    out = np.empty(intensities.shape, np.uint16)
    for v, view in enumerate(intensities):
        corrected = (view.astype(np.float64) - dark) / beam * white_level
        # A dead pixel (flat not above dark) reads as unattenuated, which ctpipe turns into 0.
        corrected = np.where(alive, corrected, white_level)
        out[v] = np.clip(np.rint(corrected), 0, np.iinfo(np.uint16).max)
    return out


def write_nikon(folder: str | Path, *, geometry: Geometry, nominal_angles_deg, recorded_angles_deg=None,
                intensities, flats, darks=None, name: str = "scan", white_level: float = 60000.0,
                offset_keys: str = "object_offset", angle_log: str | None = "ctdata") -> Path:
    """Write a scan the way a Nikon scanner and CT Pro leave it (see the module docstring).

    The raw counts are flat-corrected as the scanner does before saving,
    ``(I - mean dark) / (mean flat - mean dark) * white_level`` rounded to uint16 (pixels whose
    flat is not above their dark read ``white_level``), and written as ``<name>_0001.tif`` ...;
    the geometry and the uniform nominal angles go into ``<name>.xtekct``, the recorded angles
    into the angle log, counted from ``InitialAngle`` (``_ctdata.txt`` with the sense of
    ``AngularStep``, ``<name>.ang`` against it, as the scanners write them). Nominal angles that
    end one full turn after they start are written as a real scanner saves a full turn:
    ``Projections = V - 1`` and ``V`` images, the last closing the turn, and ``V`` log rows.

    Parameters
    ----------
    folder : path
        Must not exist or be empty.
    geometry : Geometry
    nominal_angles_deg : array of shape (V,)
        Uniformly spaced (the ``.xtekct`` holds only ``InitialAngle`` and ``AngularStep``).
    recorded_angles_deg : array of shape (V,) or None
        What the turntable logged, ctpipe's convention; None writes no angle log.
    intensities : ndarray of shape (V, rows, cols)
        Raw detector counts.
    flats, darks : ndarray of shape (F, rows, cols) or (rows, cols); darks may be None
    name : str
        The scan's ``Name``, which names every file.
    white_level : float
        ``WhiteLevel``: the counts an unattenuated pixel is scaled to.
    offset_keys : {"object_offset", "centre_of_rotation", "detector_offset"}
        Where the principal point's column goes (:data:`OFFSET_KEYS`); its row always goes
        into ``DetectorOffsetY``.
    angle_log : {"ctdata", "ang", None}
        ``_ctdata.txt`` as the scanner writes it, CT Pro's ``<name>.ang``, or none.

    Returns
    -------
    Path of the folder.
    """
    import tifffile

    from ctpipe.io.outputs import staged_folder

    folder = Path(folder)
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise InputError(f"{folder}: exists and is not an empty folder; write the Nikon scan to a new folder")
    check_geometry(geometry)
    if offset_keys not in OFFSET_KEYS:
        raise InputError(f"offset_keys: must be one of {', '.join(OFFSET_KEYS)}, got {offset_keys!r}")
    if angle_log not in ANGLE_LOGS:
        raise InputError(f"angle_log: must be one of ctdata, ang, None, got {angle_log!r}")
    if not name or any(c in name for c in '/\\:*?"<>|'):
        raise InputError(f"name: must be a non-empty file name without path separators, got {name!r}")
    if not (math.isfinite(white_level) and 0 < white_level <= np.iinfo(np.uint16).max):
        raise InputError(f"white_level: must be > 0 and <= 65535 (16-bit counts), got {white_level!r}")
    counts = np.asarray(intensities)
    if counts.ndim != 3 or counts.shape[1:] != geometry.shape:
        raise InputError(f"intensities: must have shape (views, {geometry.detector_rows}, {geometry.detector_cols}) "
                         f"to match the geometry, got {counts.shape}")
    n_views = len(counts)
    nominal = check_angles(nominal_angles_deg, n_views, "nominal_angles_deg")
    initial = float(nominal[0])
    step = float((nominal[-1] - nominal[0]) / (n_views - 1)) if n_views > 1 else 0.0
    uniform = initial + step * np.arange(n_views, dtype=np.float64)
    if not np.allclose(uniform, nominal, rtol=0.0, atol=1e-9):
        raise InputError("nominal_angles_deg: must be uniformly spaced; a .xtekct holds only InitialAngle and "
                         "AngularStep")
    # A full turn with an image at 360 deg: the scanner's Projections + 1 images.
    projections = n_views - 1 if n_views > 2 and math.isclose(abs(step) * (n_views - 1), 360.0, abs_tol=1e-9) \
        else n_views
    recorded = None
    if recorded_angles_deg is not None and angle_log is not None:
        recorded = check_angles(recorded_angles_deg, n_views, "recorded_angles_deg")
    corrected = _flat_correct(counts, flats, darks, float(white_level))

    with staged_folder(folder, "Nikon scan folder") as tmp:
        text = _xtekct_text(name, geometry, projections, initial, step, float(white_level), offset_keys)
        (tmp / f"{name}.xtekct").write_bytes(text.encode("ascii"))
        for i, view in enumerate(corrected):
            tifffile.imwrite(tmp / f"{name}_{i + 1:04d}.tif", view)
        if recorded is not None and angle_log == "ctdata":
            (tmp / _CTDATA).write_bytes(_ctdata_text(recorded - initial, projections).encode("ascii"))
        elif recorded is not None:
            write_nikon_angles(tmp / f"{name}.ang", recorded, initial_angle_deg=initial)
    return folder
