"""Zeiss Xradia scans written as a scanner saves them (one ``.txrm`` file), for tests and benchmarks.

:func:`write_zeiss` writes the views, the reference (flat) and the streams
:func:`ctpipe.io.zeiss.open_zeiss` reads into one OLE compound file
(:func:`ctpipe.testing.ole.write_compound_file`); the streams, units and signs are those of
:mod:`ctpipe.io.zeiss`'s docstring.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from ctpipe.errors import InputError
from ctpipe.geometry import Geometry, check_geometry
from ctpipe.io.scans import check_angles
from ctpipe.io.zeiss import _image_stream
from ctpipe.testing.ole import write_compound_file

__all__ = ["write_zeiss"]


def write_zeiss(folder: str | Path, *, geometry: Geometry, nominal_angles_deg, recorded_angles_deg=None,
                intensities, flats, darks=None, name: str = "scan.txrm", x_shifts_px=None, y_shifts_px=None,
                exposure_s: float = 1.0) -> Path:
    """Write a scan as a Zeiss Xradia scanner does: one ``.txrm`` file in ``folder``.

    The file holds the views as stored counts, the mean flat as ``ReferenceData/Image``
    (float32) and the streams of the module docstring, in the scanner's units and signs: the
    logged angles unchanged (Zeiss counts as ctpipe does), ``StoRADistance`` negative,
    ``PixelSize`` at the rotation axis in um, ``AutoRecon/CenterShift = (cols - 1) / 2 - u0_px``.
    Also written for other readers: ``NoOfImages``, ``X/Y/ZPosition`` (zeros), ``ExpTimes``,
    ``CamPixelSize`` (the detector pitch, um) and ``XrayMagnification`` (taken as SDD / SOD).

    Parameters
    ----------
    folder : path
        Created if missing; must be empty.
    geometry : Geometry
        Square pixels, and ``v0_px`` at the detector centre: the format has no key for anything else.
    nominal_angles_deg : array of shape (V,)
        Checked only: a ``.txrm`` keeps the logged angles, not the commanded ones.
    recorded_angles_deg : array of shape (V,) or None
        The turntable's logged angles, ctpipe's convention (None: the nominal ones).
    intensities : ndarray of shape (V, rows, cols), uint16 or float32
    flats : ndarray of shape (F, rows, cols) or (rows, cols)
        Averaged into the reference.
    darks : None
        A ``.txrm`` keeps no dark frame; anything else is refused.
    name : str
        The file name, ending in ``.txrm``.
    x_shifts_px, y_shifts_px : array of shape (V,) or None
        ``Alignment/X-Shifts``, ``Y-Shifts`` (zeros if None).
    exposure_s : float
        ``ImageInfo/ExpTimes`` and ``ReferenceData/ExpTime``.

    Returns
    -------
    Path of the ``.txrm`` file.
    """
    from ctpipe.io.outputs import atomic_write

    folder = Path(folder)
    check_geometry(geometry)
    if geometry.pixel_pitch_u_mm != geometry.pixel_pitch_v_mm:
        raise InputError(f"geometry: a .txrm has one pixel size (ImageInfo/PixelSize), so pixel_pitch_u_mm and "
                         f"pixel_pitch_v_mm must be equal, got {geometry.pixel_pitch_u_mm} and "
                         f"{geometry.pixel_pitch_v_mm}")
    rows, cols = geometry.shape
    if abs(geometry.v0_px - (rows - 1) / 2.0) > 1e-9:
        raise InputError(f"geometry.v0_px: a .txrm has no key for a vertical offset, so it must be the detector centre "
                         f"{(rows - 1) / 2.0}, got {geometry.v0_px}")
    if not isinstance(name, str) or Path(name).name != name or not name.lower().endswith(".txrm"):
        raise InputError(f"name: must be a file name ending in .txrm, got {name!r}")
    intensities = np.asarray(intensities)
    if intensities.ndim != 3 or intensities.shape[1:] != geometry.shape or not len(intensities):
        raise InputError(f"intensities: must have shape (views, {rows}, {cols}) to match the geometry, "
                         f"got {intensities.shape}")
    codes = {np.dtype(np.uint16): 5, np.dtype(np.float32): 10}
    if intensities.dtype not in codes:
        raise InputError(f"intensities: a .txrm stores uint16 or float32 images (ImageInfo/DataType 5 or 10), "
                         f"got {intensities.dtype}")
    n_views = len(intensities)
    check_angles(nominal_angles_deg, n_views, "nominal_angles_deg")
    logged = check_angles(nominal_angles_deg if recorded_angles_deg is None else recorded_angles_deg, n_views,
                          "recorded_angles_deg")
    if darks is not None:
        raise InputError("darks: a .txrm keeps no dark frame (its views are divided by the reference alone); "
                         "pass darks=None")
    flat = np.asarray(flats, dtype=np.float64) if flats is not None else None
    if flat is None or flat.ndim not in (2, 3) or flat.shape[-2:] != geometry.shape or not flat.size:
        raise InputError(f"flats: must have shape (frames, {rows}, {cols}) or ({rows}, {cols}): the reference a "
                         f".txrm keeps, got {None if flat is None else flat.shape}")
    flat = (flat.mean(axis=0) if flat.ndim == 3 else flat).astype("<f4")
    shifts = {}
    for axis, values in (("X", x_shifts_px), ("Y", y_shifts_px)):
        values = np.zeros(n_views) if values is None else np.asarray(values, dtype=np.float64)
        if values.shape != (n_views,) or not np.all(np.isfinite(values)):
            raise InputError(f"{axis.lower()}_shifts_px: must be {n_views} finite numbers (pixels), one per view, "
                             f"got shape {values.shape}")
        shifts[axis] = values
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise InputError(f"{folder}: exists and is not an empty folder; a Zeiss scan is written into a new folder")

    sod, sdd = geometry.source_to_object_mm, geometry.source_to_detector_mm
    u4 = lambda value: struct.pack("<I", value)  # noqa: E731
    i4 = lambda value: struct.pack("<i", value)  # noqa: E731
    f4 = lambda values: np.asarray(values, "<f4").tobytes()  # noqa: E731
    per_view = lambda value: f4(np.full(n_views, value))  # noqa: E731
    streams = {
        "ImageInfo/ImageWidth": u4(cols), "ImageInfo/ImageHeight": u4(rows),
        "ImageInfo/NoOfImages": u4(n_views), "ImageInfo/ImagesTaken": u4(n_views),
        "ImageInfo/DataType": u4(codes[intensities.dtype]), "ImageInfo/AcquisitionMode": i4(0),
        "ImageInfo/XrayGeometry": i4(1), "ImageInfo/Angles": f4(logged),
        "ImageInfo/StoRADistance": per_view(-sod), "ImageInfo/DtoRADistance": per_view(sdd - sod),
        "ImageInfo/PixelSize": f4(geometry.pixel_pitch_u_mm * 1000.0 * sod / sdd),
        "ImageInfo/CamPixelSize": f4(geometry.pixel_pitch_u_mm * 1000.0), "ImageInfo/XrayMagnification": f4(sdd / sod),
        "ImageInfo/ExpTimes": per_view(exposure_s), "ImageInfo/XPosition": per_view(0.0),
        "ImageInfo/YPosition": per_view(0.0), "ImageInfo/ZPosition": per_view(0.0),
        "Alignment/X-Shifts": f4(shifts["X"]), "Alignment/Y-Shifts": f4(shifts["Y"]),
        "AutoRecon/CenterShift": f4((cols - 1) / 2.0 - geometry.u0_px),
        "PositionInfo/TotalAxis": i4(6),
        "PositionInfo/AxisNames": b"Sample X\x00Sample Y\x00Sample Z\x00Sample Theta\x00Source Z\x00Detector Z\x00",
        "PositionInfo/AxisUnits": b"um\x00um\x00um\x00deg\x00mm\x00mm\x00",
        "ReferenceData/Image": flat, "ReferenceData/DataType": u4(10), "ReferenceData/ExpTime": f4(exposure_s),
        "ReferenceData/ImageInfo/ImageWidth": u4(cols), "ReferenceData/ImageInfo/ImageHeight": u4(rows),
        "ReferenceData/ImageInfo/DataType": u4(10),
    }
    little = intensities.dtype.newbyteorder("<")
    for index in range(n_views):
        streams[_image_stream(index)] = np.ascontiguousarray(intensities[index], dtype=little)
    folder.mkdir(parents=True, exist_ok=True)
    return atomic_write(folder / name, lambda handle: write_compound_file(handle, streams))
