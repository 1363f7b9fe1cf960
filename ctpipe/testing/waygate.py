"""GE / Waygate phoenix scans written as datos|x acquisition leaves them, for tests and benchmarks.

:func:`write_waygate` writes a ``<name>.pca``, the offset- and gain-corrected 16-bit projections
(with the closing image of a full turn), the gain and offset images, a ``.pcp`` protocol with
the recorded angles and a ``.pcj``, which :func:`ctpipe.io.waygate.open_waygate` reads; the keys
and sign conventions are those of :mod:`ctpipe.io.waygate`'s docstring. The corrected ``.pcp``
a user gets back is written by the reader's module (:func:`ctpipe.io.waygate.write_waygate_angles`).
"""

from __future__ import annotations

import datetime
import math
from pathlib import Path

import numpy as np

from ctpipe.errors import InputError
from ctpipe.geometry import Geometry, check_geometry
from ctpipe.io.scans import check_angles
from ctpipe.io.waygate import _pcp_lines, _projection_name

__all__ = ["write_waygate"]

#: Tube settings and exposure the writer puts in the .pca and the calibration-image names.
_KV, _UA, _MS = 90, 100, 500
#: The free-ray window ([CT] Wnd_L, Wnd_T, Wnd_R, Wnd_B) whose mean is the .pcp MeanGV.
_WINDOW = (0, 0, 10, 10)


def write_waygate(folder: str | Path, *, geometry: Geometry, nominal_angles_deg, recorded_angles_deg, intensities,
                  flats, darks=None, free_ray: int | None = None, detector_shift_px: int = 0,
                  calib_value: float = 0.0, name: str | None = None) -> Path:
    """Write a scan as datos|x acquisition would: ``.pca``, corrected 16-bit TIFFs, ``.pcp``, ``.pcj``.

    The projections are stored as the scanner stores them: offset- and gain-corrected,
    ``rint((I - dark) / (flat - dark) * FreeRay)`` clipped to uint16, with the mean flat and mean
    dark as the gain and offset images (also written, as ``<name>_bright_...tif`` and
    ``<name>_Dark_...tif``). A full turn gets image NumberImages + 1, a copy of the first, at
    RotPos = first + 360. Numbers are written as datos|x writes them: 8 decimals in the
    ``.pca``, 3 for RotPos.

    Parameters
    ----------
    folder : path
        The scan folder; it must not exist or be empty.
    geometry : Geometry
        Becomes [Geometry] FDD, FOD, cx, cy, [Detector] PixelsizeX/Y and [Image] DimX, DimY.
    nominal_angles_deg : array of shape (V,)
        Must be ``i * RotationSector / V`` from 0 (what the ``.pca`` can say), with
        0 < RotationSector <= 360.
    recorded_angles_deg : array of shape (V,) or None
        The turntable's angles in ctpipe's convention, logged as the ``.pcp`` RotPos with the
        same sign (see the module docstring); None logs the nominal angles.
    intensities : ndarray of shape (V, rows, cols)
        Raw counts.
    flats, darks : ndarray of shape (F, rows, cols) or (rows, cols); darks may be None
    free_ray : int or None
        [Image] FreeRay, the level of an unattenuated pixel after correction; None takes the
        mean of ``flat - dark``.
    detector_shift_px : int
        [DetectorShift] Amplitude: > 0 records a detector shift whose images were shifted back and
        cropped (NrPixelsX = cols + 2 * amplitude, XDShift per image in the ``.pcp``).
    calib_value : float
        [Geometry] CalibValue (reported, not applied by the reader; see the module docstring).
    name : str or None
        The scan's name (file prefix); None takes the folder's name.

    Returns
    -------
    Path of the folder.
    """
    import tifffile

    from ctpipe.io.outputs import check_output_dir, staged_folder

    folder = Path(folder)
    check_geometry(geometry)
    counts = np.asarray(intensities)
    if counts.ndim != 3 or counts.shape[1:] != geometry.shape or not np.issubdtype(counts.dtype, np.number):
        raise InputError(f"intensities: must be a real array of shape (views, {geometry.detector_rows}, "
                         f"{geometry.detector_cols}) to match the geometry, got {counts.dtype} {counts.shape}")
    n_views = len(counts)
    nominal = check_angles(nominal_angles_deg, n_views, "nominal_angles_deg")
    sector = 360.0 if n_views == 1 else float(nominal[-1] - nominal[0]) * n_views / (n_views - 1)
    if not (0.0 < sector <= 360.0 + 1e-9 and np.allclose(nominal, np.arange(n_views) * (sector / n_views),
                                                          rtol=0.0, atol=1e-9)):
        raise InputError("nominal_angles_deg: a .pca can only say i * RotationSector / NumberImages from 0 with "
                         f"0 < RotationSector <= 360; got {nominal[:3].tolist()}...")
    sector = min(sector, 360.0)
    recorded = nominal if recorded_angles_deg is None else check_angles(recorded_angles_deg, n_views,
                                                                        "recorded_angles_deg")
    flat = _mean_frame(flats, geometry.shape, "flats")
    dark = np.zeros(geometry.shape) if darks is None else _mean_frame(darks, geometry.shape, "darks")
    gain = flat - dark
    alive = gain > 0
    if not alive.any():
        raise InputError("flats: must be brighter than darks somewhere; every pixel has flat <= dark")
    if free_ray is None:
        free_ray = int(round(float(gain[alive].mean())))
    if isinstance(free_ray, bool) or not isinstance(free_ray, (int, np.integer)) or not 0 < free_ray <= 65535:
        raise InputError(f"free_ray: must be an integer in 1 .. 65535 (a 16-bit level), got {free_ray!r}")
    if isinstance(detector_shift_px, bool) or not isinstance(detector_shift_px, (int, np.integer)) \
            or detector_shift_px < 0:
        raise InputError(f"detector_shift_px: must be an integer >= 0, got {detector_shift_px!r}")
    shift = int(detector_shift_px)
    if not math.isfinite(calib_value):
        raise InputError(f"calib_value: must be a finite number, got {calib_value!r}")
    name = folder.name if name is None else name
    if not name or any(c in name for c in '\\/:*?"<>|'):
        raise InputError(f"name: must be a file-name prefix without \\ / : * ? \" < > |, got {name!r}")
    check_output_dir(folder, "folder")
    if folder.is_dir() and any(folder.iterdir()):
        raise InputError(f"{folder}: exists and is not empty; a datos|x scan is written into a new or empty folder")

    full_turn = abs(sector - 360.0) <= 1e-9
    numbers = list(range(1, n_views + 1)) + ([n_views + 1] if full_turn else [])
    rot_pos = list(recorded) + ([recorded[0] + 360.0] if full_turn else [])
    xd_shift = [0 if shift == 0 else (7 * i) % (2 * shift + 1) - shift for i in range(len(numbers))]
    scale = np.where(alive, float(free_ray) / np.where(alive, gain, 1.0), 0.0)

    def corrected(view: np.ndarray) -> np.ndarray:
        values = np.where(alive, (view.astype(np.float64) - dark) * scale, float(free_ray))
        return np.clip(np.rint(values), 0, 65535).astype(np.uint16)

    bright_name = f"{name}_bright_{_KV}kV_{_UA}uA_{_MS}ms_1Det.tif"
    dark_name = f"{name}_Dark_{_MS}.tif"
    with staged_folder(folder, "folder") as tmp:
        mean_gv = []
        first = None
        for number in numbers:
            stored = corrected(counts[number - 1]) if number <= n_views else first
            first = stored if number == 1 else first
            tifffile.imwrite(tmp / _projection_name(name, number), stored)
            left, top, right, bottom = _WINDOW
            mean_gv.append(float(stored[top:bottom + 1, left:right + 1].mean()))
        tifffile.imwrite(tmp / bright_name, np.clip(np.rint(flat), 0, 65535).astype(np.uint16))
        tifffile.imwrite(tmp / dark_name, np.clip(np.rint(dark), 0, 65535).astype(np.uint16))
        frames = 1 if np.ndim(flats) == 2 else len(flats)
        pca = _pca_text(geometry, n_views, sector, len(numbers), free_ray, shift, calib_value, frames,
                        bright_name, dark_name)
        (tmp / f"{name}.pca").write_bytes(pca.encode("ascii"))
        (tmp / f"{name}.pcp").write_bytes(_pcp_text(numbers, rot_pos, mean_gv, xd_shift).encode("ascii"))
        (tmp / f"{name}.pcj").write_bytes(_pcj_text(numbers, rot_pos, xd_shift, geometry, n_views).encode("ascii"))
    return folder


def _mean_frame(frames, shape: tuple[int, int], what: str) -> np.ndarray:
    frames = np.asarray(frames, dtype=np.float64)
    if frames.ndim == 3 and len(frames):
        frames = frames.mean(axis=0)
    if frames.shape != shape or not np.all(np.isfinite(frames)):
        raise InputError(f"{what}: must be finite frames of shape (F, {shape[0]}, {shape[1]}) or {shape}, "
                         f"got shape {frames.shape}")
    return frames


def _ini(sections: dict[str, dict[str, object]]) -> str:
    # datos|x writes Windows text: CRLF line ends.
    lines = []
    for section, keys in sections.items():
        lines.append(f"[{section}]")
        lines.extend(f"{key}={value}" for key, value in keys.items())
        lines.append("")
    return "\r\n".join(lines)


def _pca_text(geometry: Geometry, n_views: int, sector: float, n_images: int, free_ray: int, shift: int,
              calib_value: float, frames: int, bright_name: str, dark_name: str) -> str:
    from ctpipe._version import __version__

    g = geometry
    f8 = "{:.8f}".format
    return _ini({
        "General": {"Version": "2.4.0", "Version-pca": 2,
                    "Comment": f"simulated scan written by ctpipe {__version__} (ctpipe.testing.write_waygate)",
                    "SystemName": "ctpipe simulation"},
        "Geometry": {"FDD": f8(g.source_to_detector_mm), "FOD": f8(g.source_to_object_mm),
                     "Magnification": f8(g.magnification),
                     "VoxelSizeX": f8(g.pixel_pitch_u_mm / g.magnification),
                     "VoxelSizeY": f8(g.pixel_pitch_v_mm / g.magnification),
                     "CalibValue": f"{calib_value:.3f}", "cx": f8(g.u0_px), "cy": f8(g.v0_px),
                     "DetectorRot": f8(0.0), "Tilt": f8(0.0)},
        "CT": {"Type": 0, "NumberImages": n_views, "StartImg": n_images, "RotationSector": f8(sector),
               "NoRotation": 0, "NrImgDone": n_images, "NrImgCmplScan": n_images, "SkipAcc": 1,
               "Wnd_L": _WINDOW[0], "Wnd_T": _WINDOW[1], "Wnd_R": _WINDOW[2], "Wnd_B": _WINDOW[3]},
        "Trajectory": {"Active": 0},
        "Image": {"Top": 0, "Left": 0, "Bottom": g.detector_rows - 1, "Right": g.detector_cols + 2 * shift - 1,
                  "DimX": g.detector_cols, "DimY": g.detector_rows, "Rotation": 0, "MirrorX": 0, "MirrorY": 0,
                  "BitPP": 16, "FreeRay": free_ray},
        "CalibImages": {"MGainPoints": 1, "Avg": frames, "Skip": 0, "GainImg": bright_name, "MGainImg": bright_name,
                        "OffsetImg": dark_name},
        "DetectorShift": {"Enable": int(shift > 0), "Mode": 0, "Amplitude": shift, "Interval": 1, "Step": 1},
        "Detector": {"Name": "ctpipe simulation", "PixelsizeX": f8(g.pixel_pitch_u_mm),
                     "PixelsizeY": f8(g.pixel_pitch_v_mm), "NrPixelsX": g.detector_cols + 2 * shift,
                     "NrPixelsY": g.detector_rows, "TimingVal": f"{_MS:.3f}", "Avg": 1, "Skip": 0, "Binning": 0,
                     "BitPP": 16},
        "Xray": {"Voltage": _KV, "Current": _UA},
    })


def _pcp_text(numbers, rot_pos, mean_gv, xd_shift) -> str:
    start = datetime.datetime(2026, 1, 1, 9, 0, 0)
    rows = [[str(n), f"{a:.3f}", str(_KV), str(_UA), f"{gv:.1f}", "0.0", "0.0", "1", "0.000", str(xd),
             (start + datetime.timedelta(seconds=2 * i)).strftime("%Y-%m-%d %H:%M:%S")]
            for i, (n, a, gv, xd) in enumerate(zip(numbers, rot_pos, mean_gv, xd_shift))]
    return _pcp_lines("datos|x 2 acquisition 2.4.0",
                      ["ImgNr", "RotPos", "U", "I", "MeanGV", "DevGV", "Dose", "Use", "CValue", "XDShift", "Time"],
                      rows)


def _pcj_text(numbers, rot_pos, xd_shift, geometry: Geometry, n_views: int) -> str:
    rows = [f"{n}\t0.0000000\t0.0000000\t{-geometry.source_to_object_mm:.7f}\t{a:.7f}\t"
            f"{xd * geometry.pixel_pitch_u_mm:.7f}\t0\t0\t{2000 * i}\t0\t"
            for i, (n, a, xd) in enumerate(zip(numbers, rot_pos, xd_shift))]
    head = ["[Info]", "TrajectoryType=0", f"NumImages={n_views}", "NumSensors=1", "", "[Data]",
            ";ImgNr\tXS\t\tYS\t\tZS\t\tRS\t\tXD\t\tWarmup\tVSenCnt\tTimeStamp\tChangeCnt"]
    return "\r\n".join(head + rows) + "\r\n"
