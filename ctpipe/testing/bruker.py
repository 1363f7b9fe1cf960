"""Bruker SkyScan scans written as a SkyScan saves them, for tests and benchmarks.

:func:`write_bruker` writes a ``<prefix>.log``, the flat-corrected 16-bit projections
``<prefix>NNNNNNNN.tif`` (:func:`flat_correct`) and, for recorded angles, a SkyScan 2214
``<prefix>.info`` that :func:`ctpipe.io.bruker.open_bruker` reads; the keys and sign
conventions are those of :mod:`ctpipe.io.bruker`'s docstring.
"""

from __future__ import annotations

import datetime
import math
import re
from pathlib import Path

import numpy as np

from ctpipe.errors import InputError
from ctpipe.geometry import Geometry, check_geometry

__all__ = ["write_bruker", "flat_correct", "DEFAULT_REFERENCE_INTENSITY"]

#: The open-beam grey level the writer scales flat-corrected projections to (SkyScan 1272 logs 57000).
DEFAULT_REFERENCE_INTENSITY = 57000.0


def flat_correct(intensities, flats, darks=None, *, white_level: float = DEFAULT_REFERENCE_INTENSITY) -> np.ndarray:
    """What a SkyScan saves with ``Flat Field Correction=ON``: ``(I - D) / (F - D) * white_level`` in uint16.

    ``F`` and ``D`` are the mean flat and dark frames. Pixels whose flat is not above their dark
    are set to the white level (no information, as :func:`ctpipe.io.flatfield.log_transform`
    treats them); values are rounded to the nearest integer and clipped to 0..65535.

    Parameters
    ----------
    intensities : ndarray of shape (V, rows, cols)
        Raw counts.
    flats : ndarray of shape (F, rows, cols) or (rows, cols)
    darks : ndarray of shape (D, rows, cols) or (rows, cols), or None
    white_level : float

    Returns
    -------
    ndarray of shape (V, rows, cols), uint16
    """
    counts = np.asarray(intensities)
    if counts.ndim != 3:
        raise InputError(f"intensities: must have shape (views, rows, cols), got {counts.shape}")
    shape = counts.shape[1:]

    def mean(frames, name):
        frames = np.asarray(frames, dtype=np.float64)
        frames = frames.mean(axis=0) if frames.ndim == 3 else frames
        if frames.shape != shape:
            raise InputError(f"{name}: each frame must have the projections' shape {shape}, got {frames.shape}")
        return frames

    flat = mean(flats, "flats")
    dark = np.zeros(shape) if darks is None else mean(darks, "darks")
    beam = flat - dark
    alive = beam > 0
    out = np.empty(counts.shape, np.uint16)
    for v in range(len(counts)):
        corrected = np.where(alive, (counts[v] - dark) / np.where(alive, beam, 1.0) * white_level, white_level)
        out[v] = np.clip(np.rint(corrected), 0, 65535)
    return out


def _fixed(value: float, decimals: int) -> str:
    """``value`` with ``decimals`` decimals as SkyScan writes it, or every digit if that would change it."""
    text = f"{value:.{decimals}f}"
    return text if float(text) == value else repr(float(value))


def write_bruker(folder: str | Path, *, geometry: Geometry, nominal_angles_deg, intensities, flats, darks=None,
                 recorded_angles_deg=None, prefix: str = "scan_",
                 reference_intensity: float = DEFAULT_REFERENCE_INTENSITY) -> Path:
    """Write a scan the way a SkyScan saves it: ``<prefix>.log`` and flat-corrected 16-bit TIFFs.

    The projections are flat-corrected as the scanner does with ``Flat Field Correction=ON``
    (:func:`flat_correct`, scaled to ``Reference Intensity``); no flat or dark frames are saved.
    The geometry goes into the keys the reader reads (see the module docstring): ``Image Pixel
    Size (um) = pitch * 1000 * SOD / SDD``, ``Optical Axis (line) = v0_px``, ``[Reconstruction]
    Postalignment = (cols - 1) / 2 - u0_px`` (written only when not 0), ``Camera Pixel Size (um)
    = pitch * 1000`` with ``Camera binning=1x1``. The nominal angles must be evenly spaced:
    ``Rotation Step (deg)`` is the size of their step, ``Rotation Direction`` is ``CC`` for
    decreasing (ctpipe) angles and ``CW`` for increasing ones, ``Scanning Start Angle`` that of
    view 0 in the scanner's sense.

    Parameters
    ----------
    folder : path
        Must not exist, or be empty.
    geometry : Geometry
        With square pixels (SkyScan logs one pixel size).
    nominal_angles_deg : array of shape (V,)
        ctpipe's convention.
    intensities : ndarray of shape (V, rows, cols)
        Raw counts.
    flats, darks : ndarray of shape (F, rows, cols), or (rows, cols); ``darks`` may be None
    recorded_angles_deg : array of shape (V,) or None
        The turntable's angles (ctpipe's convention), written as a SkyScan 2214 ``<prefix>.info``:
        one line ``Projection NNNNNNNN: achieved angle A.`` per view after the first, ``A`` in
        the scanner's sense. View 0 is not logged (the reader takes it at the start angle), so
        ``recorded_angles_deg[0]`` is not stored. The line layout is ours: only that the angle
        ends a line holding ``achieved angle`` is known of the real file (see the module
        docstring). None writes no ``.info``, as the other SkyScans.
    prefix : str
        The ``Filename Prefix``; the log is ``<prefix>.log``, the views ``<prefix>00000000.tif``.
    reference_intensity : float
        The open-beam grey level of the saved TIFFs.

    Returns
    -------
    Path of the folder.
    """
    import tifffile

    from ctpipe._version import __version__
    from ctpipe.io.outputs import staged_folder

    folder = Path(folder)
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise InputError(f"{folder}: exists and is not an empty folder; write_bruker writes into a new or empty one")
    check_geometry(geometry)
    if geometry.pixel_pitch_u_mm != geometry.pixel_pitch_v_mm:
        raise InputError(f"geometry: SkyScan logs one pixel size, so pixel_pitch_u_mm and pixel_pitch_v_mm must be "
                         f"equal, got {geometry.pixel_pitch_u_mm} and {geometry.pixel_pitch_v_mm}")
    if not re.fullmatch(r"[^\\/:*?\"<>|]+", prefix) or prefix in (".", ".."):
        raise InputError(f"prefix: must be a file name prefix such as 'scan_', got {prefix!r}")
    nominal = np.asarray(nominal_angles_deg, dtype=np.float64)
    if nominal.ndim != 1 or nominal.size < 2 or not np.all(np.isfinite(nominal)):
        raise InputError(f"nominal_angles_deg: must be at least 2 finite angles, got shape {nominal.shape}")
    step = float(nominal[1] - nominal[0])
    expected = nominal[0] + step * np.arange(nominal.size)
    if step == 0 or not np.allclose(nominal, expected, rtol=0, atol=1e-9 * max(1.0, abs(step) * nominal.size)):
        raise InputError("nominal_angles_deg: must be evenly spaced, since a SkyScan log gives one Rotation Step")
    counts = np.asarray(intensities)
    if counts.shape != (nominal.size, *geometry.shape):
        raise InputError(f"intensities: must have shape ({nominal.size}, {geometry.detector_rows}, "
                         f"{geometry.detector_cols}) (one view per nominal angle, the geometry's size), "
                         f"got {counts.shape}")
    recorded = None
    if recorded_angles_deg is not None:
        recorded = np.asarray(recorded_angles_deg, dtype=np.float64)
        if recorded.shape != nominal.shape or not np.all(np.isfinite(recorded)):
            raise InputError(f"recorded_angles_deg: must be None or {nominal.size} finite angles, one per view, got "
                             f"shape {recorded.shape}")
    if not (math.isfinite(reference_intensity) and 0 < reference_intensity <= 65535):
        raise InputError(f"reference_intensity: must be in (0, 65535], got {reference_intensity!r}")
    saved = flat_correct(counts, flats, darks, white_level=reference_intensity)

    direction, sign = ("CW", 1.0) if step > 0 else ("CC", -1.0)
    start = sign * float(nominal[0])
    pixel_um = geometry.pixel_pitch_u_mm * 1000.0 * geometry.source_to_object_mm / geometry.source_to_detector_mm
    shift = (geometry.detector_cols - 1) / 2.0 - geometry.u0_px
    axis = geometry.v0_px
    span = abs(step) * nominal.size
    now = datetime.datetime.now(datetime.timezone.utc)
    lines = [
        "[System]",
        "Scanner=SkyScan (simulated)",
        f"Software Version=ctpipe {__version__}",
        f"Camera Pixel Size (um)={_fixed(geometry.pixel_pitch_u_mm * 1000.0, 2)}",
        "Camera X/Y Ratio=1.0000",
        "[Acquisition]",
        f"Filename Prefix={prefix}",
        "Filename Index Length=8",
        f"Number Of Files={nominal.size:5d}",
        f"Number Of Rows={geometry.detector_rows:5d}",
        f"Number Of Columns={geometry.detector_cols:5d}",
        "Partial Width=OFF",
        "Image crop origin X=0",
        "Image crop origin Y=0",
        "Camera binning=1x1",
        "Image Rotation=0.00000",
        f"Optical Axis (line)={int(axis):5d}" if axis == int(axis) else f"Optical Axis (line)={axis!r}",
        f"Camera to Source (mm)={_fixed(geometry.source_to_detector_mm, 5)}",
        f"Object to Source (mm)={_fixed(geometry.source_to_object_mm, 5)}",
        f"Image Pixel Size (um)={_fixed(pixel_um, 6)}",
        f"Scaled Image Pixel Size (um)={_fixed(pixel_um, 6)}",
        "Image Format=TIFF",
        "Depth (bits)=16",
        f"Reference Intensity={_fixed(reference_intensity, 0)}",
        f"Rotation Step (deg)={_fixed(abs(step), 3)}",
        f"Use 360 Rotation={'YES' if span >= 360.0 - 1e-9 else 'NO'}",
        "Frame Averaging=OFF (1)",
        "Random Movement=OFF (0)",
        "Flat Field Correction=ON",
        "Geometrical Correction=OFF",
        f"Gantry direction={direction}",
        f"Rotation Direction={direction}",
        f"Scanning Start Angle={_fixed(start, 3)}",
        "Type of Detector Motion=STEP AND SHOOT",
        "Scanning Trajectory=ROUND",
        "Number of connected scans=1",
        f"Study Date and Time={now:%d %b %Y  %Hh:%Mm:%Ss}",
    ]
    if shift != 0:
        lines += ["[Reconstruction]", f"Postalignment={_fixed(shift, 2)}"]
    with staged_folder(folder, "folder") as tmp:
        (tmp / f"{prefix}.log").write_bytes(("\r\n".join(lines) + "\r\n").encode("latin-1"))
        if recorded is not None:
            info = [f"Turntable positions reached, degrees (written by ctpipe {__version__})"]
            info += [f"Projection {i:08d}: achieved angle {_fixed(sign * recorded[i], 4)}."
                     for i in range(1, nominal.size)]
            (tmp / f"{prefix}.info").write_bytes(("\r\n".join(info) + "\r\n").encode("latin-1"))
        for i, image in enumerate(saved):
            tifffile.imwrite(tmp / f"{prefix}{i:08d}.tif", image)
    return folder
