"""Bruker SkyScan scans: a ``<prefix>.log`` beside the projections ``<prefix>NNNNNNNN.tif``.

Files
-----
A SkyScan acquisition folder holds, for each scan (or each sub-scan ``~00``, ``~01``, ... of an
oversize "connected" scan)::

    <prefix>.log                     # INI-like text: [System], [User], [Acquisition], [Reconstruction]
    <prefix>00000000.tif ...         # one 16-bit TIFF per view, index from 0, "Filename Index Length" digits
    <prefix>.info                    # SkyScan 2214 only: the angle each view reached ("achieved angle")
    <prefix>_TS.csv, <prefix>.oog,   # optional: NRecon's thermal-shift table, thumbnails, ... (not read)
    <prefix>_spr.bmp, ...

The log is written by the scanner software (Windows text, read as Latin-1); NRecon appends a
``[Reconstruction]`` section once the scan has been reconstructed. Keys are matched ignoring
case and repeated blanks (scanners write both ``Number of Files`` and ``Number Of Files``). A
folder may hold several logs (``name.log``, ``name~00.log``, ``name~01.log`` for a connected
scan): open the one ``.log`` you mean, since each sub-scan is a scan of its own. SkyScan saves
no flat or dark frames beside the projections; only the 2214 logs per-view angles (``.info``).

Keys read and what ctpipe makes of them
---------------------------------------
``[Acquisition]``:

============================  =====================================================================
``Filename Prefix``           projection names ``<prefix>NNNNNNNN.tif`` (default: the log's name)
``Filename Index Length``     digits of NNNNNNNN (absent in older logs: 8, else 4, from the files)
``Number of Files``           views; files ``0 .. N-1`` must all exist and file ``N`` must not
``Number of Rows/Columns``    ``detector_rows`` / ``detector_cols`` (checked against every TIFF)
``Object to Source (mm)``     ``source_to_object_mm``
``Camera to Source (mm)``     ``source_to_detector_mm``
``Image Pixel Size (um)``     the pixel size at the rotation axis: ``pixel_pitch_u_mm =
                              pixel_pitch_v_mm = Image Pixel Size / 1000 * SDD / SOD``
``Optical Axis (line)``       ``v0_px``: the row of the central ray, counted from row 0 = the
                              first row of the TIFF as stored (a pixel centre)
``Rotation Step (deg)``       the step between views (positive; the direction is the next key)
``Rotation Direction``        ``CC`` (every SkyScan log we found) or ``CW``; absent: ``CC`` + note
``Scanning Start Angle``      angle of view 0, default 0 (every log we found has 0)
``Flat Field Correction``     ``ON``: the TIFFs are flat-corrected by the scanner (see below)
``Reference Intensity``       the grey level of the open beam in flat-corrected TIFFs
``Depth (bits)``              only when ``Reference Intensity`` is absent: white level ``2**Depth``
``Image Format``              must be ``TIFF`` when present
============================  =====================================================================

``[Reconstruction]``: ``Postalignment`` (or ``Sub-scan post alignment [k]`` of sub-scan
``~k``), NRecon's shift of the rotation axis in projection pixels: ``u0_px = (cols - 1) / 2 -
Postalignment``. Read for notes and metadata only: ``[System] Camera Pixel Size (um)`` and
``[Acquisition] Camera binning`` (checked against the pixel size above), ``Random Movement``,
``TS modified according to``, ``Image crop origin Y``, ``Number of connected scans``.

Conventions, and how they become ctpipe's
-----------------------------------------
*Pixel size.* NRecon's cone geometry is ``Image Pixel Size`` at ``Object to Source``: the cone
angles it logs (``Cone-beam Angle Horiz.(deg)`` and ``Vert.``) are ``2 atan(cols / 2 * Image
Pixel Size / SOD)`` (rows for ``Vert.``) to six digits in the SkyScan 1173, 1272, 1275 and 1278
logs we checked (a 1172 log rounds ``Image Pixel Size`` to 0.01 um: 0.06 % there), while the
camera pixel times the binning over ``Camera to Source`` is 1 to 8 % off. ctpipe only needs the
ratio ``pitch / SDD`` (= ``Image Pixel Size / SOD``), so it keeps the scanner's SDD and takes
the pitch that makes that ratio NRecon's; a camera pixel x binning more than 0.5 % away is said
in a note. ``Camera X/Y Ratio`` is ignored, as NRecon's vertical cone angle shows NRecon does
(square pixels).

*Principal point.* ``Optical Axis (line)`` is the line "in which the x-ray hits the detector
perpendicularly", counted from the top of the image as stored: the VXL/LEMS reader
(``imgr_skyscan_log.cxx``) puts the principal point at ``((cols - 1) / 2, Optical Axis)`` in
image coordinates (row 0 at the top). TIGRE (``CERN/TIGRE``,
``Python/tigre/utilities/io/BrukerDataLoader.py``) shifts the detector by ``Optical Axis - rows
/ 2`` pixels, i.e. measures from the edge ``rows / 2`` rather than the centre ``(rows - 1) /
2``: half a pixel from VXL. ctpipe follows VXL: ``v0_px = Optical Axis (line)``. Horizontally
SkyScan assumes the central ray on the middle column (a ``Partial Width`` crop is centred:
``Image crop origin X + cols / 2`` is the camera's middle column in every log we found);
NRecon's ``Postalignment`` moves the rotation axis to column ``(cols - 1) / 2 -
Postalignment``, where the ASTRA-based MATLAB ``SkyScanParser`` puts it (it shifts the detector
by ``+Postalignment`` pixels with ``astra_geom_postalignment``, ``astra-toolbox/astra-toolbox``,
``matlab/tools/astra_geom_postalignment.m``). ctpipe has no separate centre of rotation, so the
axis column becomes ``u0_px``: the usual approximation, which takes an axis offset ``d`` for a
sideways shift of source and detector together and neglects the yaw of ``d / SOD`` radians it
implies (1e-4 rad for 10 pixels of 10 um at 100 mm). Without a ``Postalignment`` (a scan not
reconstructed yet) ``u0_px`` is the middle column and a note says so.

*Angles.* SkyScan logs only the step: view ``i`` is at ``Scanning Start Angle + i * Rotation
Step``, for every file up to ``Number of Files - 1`` (some logs count the view at the end of
the range too: NRecon's ``Reconstruction Angular Range`` is ``(N - 1) * step`` there; ctpipe
keeps it, as one more view). ``Rotation Direction=CC`` is read as the source and detector
turning counter-clockwise around the object seen from above, i.e. the object turning clockwise
in ctpipe's frame (points between the axis and the source move towards smaller columns):
``nominal_angles_deg = -(start + i * step)``; ``CW`` gives ``+(start + i * step)``. This is how
TIGRE reads SkyScan scans: its ``BrukerDataLoader`` gives the angles ``+i * step`` with the TIFFs
as stored, and a positive TIGRE angle turns the source counter-clockwise about the axis
(``Common/CUDA/Siddon_projection.cu``, ``eulerZYZ`` applied to the source; CIL's TIGRE plugin,
``TomographicImaging/CIL`` ``Wrappers/Python/cil/plugins/tigre/Geometry.py``, negates CIL's
object angles to get TIGRE's); SkyScan also writes ``Gantry direction=CC`` beside ``Rotation
Direction=CC``, even on desktop scanners, whose object turns. It is the format's main open
question: ``tleissner/cil-import-bruker`` (``bruker2cil/geometry_utils.py``) hands the same
``+i * step`` to CIL, whose positive angle turns the object counter-clockwise, the other sense.
A reconstruction is sharp either way (the wrong sense gives the mirror image), so neither
reader shows which is right. On a real scan the wrong sense shows in ``ctpipe estimate``: the
angles do not follow the nominal ones (the pair angles are unwrapped against them) and the
residuals are degrees, not hundredths. ``open_bruker(path, rotation_direction="CW")`` overrides
the log.

*Recorded angles.* The SkyScan 2214 writes ``<prefix>.info``, whose lines holding ``achieved
angle`` end with the angle the turntable reached, one per view after the first, up to a line
``Drift compensation scan`` (reference views taken after the scan). This much is known from
``tleissner/cil-import-bruker`` (``bruker2cil/import_utils.py``, ``get_angles_from_infofile``),
which reads them in place of ``i * step`` with view 0 at 0: the scanner's own sense, so ctpipe
applies the same sign as to the nominal angles. The reader takes the last number after
``achieved angle`` on each such line, view 0 at ``Scanning Start Angle`` (N - 1 lines; N lines
are taken as they are), and gives them as ``recorded_angles_deg``, with ``angle_log`` the
``.info``; any other count, or angles straying more than 10 deg from the nominal ones, leave
``recorded_angles_deg`` None with a note. No other SkyScan logs per-view angles: None.

*Intensities.* With ``Flat Field Correction=ON`` the scanner divides every projection by its
reference (flat) images before saving and scales the result to ``Reference Intensity`` (57000
or 58000 in the logs we found, below 65535 so that noise above the open beam is not clipped):
the reader passes that as the ViewStack's ``white_level``. Which level the scanner scales to
is not documented publicly; TIGRE divides by ``2**Depth`` instead. The choice only adds the
constant ``log(white level / true level)`` to every line integral, which ctpipe's detectors do
not see (each view is mapped from its own min..max to 8 bits). ``Flat Field Correction=OFF``
leaves raw counts with no flat frames in the folder: they are divided by the white level all
the same and a note says so.

Unclear, and said in notes when it applies
------------------------------------------
``Random Movement=ON``: the scanner moves the sample vertically between views to smear ring
artefacts; the saved projections are believed to be shifted back, which ctpipe assumes (a
residual vertical shift between views biases the estimate). ``TS modified according to
<prefix>_TS.csv``: a thermal-shift table NRecon applies when reconstructing, not to the
TIFFs; ctpipe does not apply it. ``Image Rotation``: see below. A non-zero ``Image crop
origin Y``: ``Optical Axis (line)`` is taken as a row of the stored image, which is what
NRecon sees.

*Image Rotation.* ``[Acquisition] Image Rotation`` is a small angle the scanner writes for
every scan: 0.1700 (SkyScan 1173), 0.05700 (1272, ``xray-imaging/meta-cli``), -0.35000 (another
1272 log, quoted in a public file found by content whose repository was not resolved) and
0.9900 (a 1176 log quoted in ``ufo-kit/tofu`` issue 89 and ``leehoy/BPF`` issue 1), unchanged
by NRecon (the 1272's ``_Rec/..._rec.log`` repeats the acquisition keys; its own rotations are
``CS Static Rotation (deg)``, of the reconstructed slice, and ``Used extra rotation per
scan(deg)``, between sub-scans). Inferred, not documented: it is in degrees (0.99 radians would
be a 57 deg camera) and it is the in-plane rotation (roll) of the camera about the central ray
against the turntable axis, the one angle of a detector that a calibration can measure from the
projections. No public SkyScan reader found uses it (TIGRE's ``BrukerDataLoader.py``,
``tleissner/cil-import-bruker``'s ``bruker2cil/geometry_utils.py`` and ``import_utils.py``), no
document says whether the scanner rotated the saved TIFFs by it or leaves that to NRecon, nor
which way is positive. ctpipe's :class:`~ctpipe.geometry.Geometry` has no roll, so it is not
applied; when it is not 0 a note gives it and how far the rotation axis leans over the image
height, ``rows * tan(Image Rotation)`` pixels (6.6 px over the 2240 rows of the 1173 log, 0.9
px over the 896 rows of the 1272 one), so that a user can judge whether it matters for the
scan.

*Post alignment.* Only NRecon writes it, into the ``[Reconstruction]`` section it appends to
the acquisition log (``Postalignment=0.50`` in the 1173 log) or, for a connected scan, as
``Sub-scan post alignment [k]`` beside ``Postalignment Applied=1`` (1272: 0.000000 for
``~00``, 1.500000 for ``~01``); the ``_rec.log`` in the ``<name>_Rec`` folder repeats the same
keys, so the reader does not open it.

Anchors
-------
``CERN/TIGRE``: ``Python/tigre/utilities/io/BrukerDataLoader.py`` and
``MATLAB/Utilities/IO/Bruker/readBrukerGeometry.m`` (keys, binning, ``Optical Axis`` offset,
white level ``2**Depth``, angles ``i * step``); the VXL/LEMS ``imgr_skyscan_log.cxx`` (principal
point); the MATLAB ``SkyScanParser`` class with ASTRA's ``astra_geom_postalignment``
(post-alignment sign); ``tleissner/cil-import-bruker`` (a CIL reader of the 2214: the other
angle sense, and the ``.info`` achieved angles);
SkyScan logs published in ``xray-imaging/meta-cli`` (``docs/source/demo/skyscan_1272``,
``docs/source/demo/bruker/skyscan_1173``), ``habi/BrukerSkyScanLogfileRuminator``
(``logfiles/``, a 1172 log and its ``_TS.csv``) and on discourse.slicer.org (1275, 1278).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ctpipe.errors import ConfigError, InputError
from ctpipe.geometry import Geometry
from ctpipe.hookspecs import hookimpl
from ctpipe.io.scans import ScanFiles, ViewFiles, ViewStack, check_angles

__all__ = ["open_bruker", "read_skyscan_log"]

#: Camera pixel x binning and the pixel size NRecon uses may differ by this much without a note.
_PIXEL_TOLERANCE = 0.005
#: Achieved angles further than this from the nominal ones are not taken for the turntable's (degrees).
_MAX_STRAY_DEG = 10.0
#: Larger logs are not SkyScan logs (real ones are a few kB).
_MAX_LOG_BYTES = 4 * 1024 * 1024
_SNIFF_BYTES = 8192
_NUMBER = re.compile(r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?")
_INTEGER = re.compile(r"[-+]?\d+")


def _norm(text: str) -> str:
    return " ".join(text.split()).lower()


@dataclass(frozen=True)
class SkyScanLog:
    """A SkyScan ``.log`` file, parsed: ``sections[section][key] = value``, names normalised.

    Section and key names are lower case with single blanks (``"number of files"``); values
    are the text after the first ``=``, stripped.
    """

    path: Path
    sections: dict = field(default_factory=dict)

    def get(self, section: str, key: str) -> str | None:
        """The value of ``[section] key``, or None when absent."""
        return self.sections.get(_norm(section), {}).get(_norm(key))

    def has(self, section: str, key: str) -> bool:
        return self.get(section, key) is not None

    def _where(self, section: str, key: str) -> str:
        return f"{self.path}: [{section}] {key}"

    def number(self, section: str, key: str, what: str, *, default: float | None = None,
               positive: bool = False) -> float:
        """A number; required unless ``default`` is given. ``positive``: it must be > 0."""
        value = self.get(section, key)
        if value is None or value == "":
            if default is not None:
                return float(default)
            raise ConfigError(f"{self._where(section, key)}: missing; it gives {what}")
        if not _NUMBER.fullmatch(value):
            raise ConfigError(f"{self._where(section, key)}: must be a number ({what}), got {value!r}")
        number = float(value)
        if not math.isfinite(number) or (positive and number <= 0):
            raise ConfigError(f"{self._where(section, key)}: must be a finite number{' > 0' if positive else ''} "
                              f"({what}), got {value!r}")
        return number

    def integer(self, section: str, key: str, what: str, *, low: int = 1, high: int = 10**9,
                default: int | None = None) -> int:
        value = self.get(section, key)
        if (value is None or value == "") and default is not None:
            return default
        if value is None or value == "":
            raise ConfigError(f"{self._where(section, key)}: missing; it gives {what}")
        if not _INTEGER.fullmatch(value) or not low <= int(value) <= high:
            raise ConfigError(f"{self._where(section, key)}: must be a whole number from {low} to {high} ({what}), "
                              f"got {value!r}")
        return int(value)

    def choice(self, section: str, key: str, allowed: tuple[str, ...]) -> str | None:
        """One of ``allowed`` (compared ignoring case), or None when absent."""
        value = self.get(section, key)
        if value is None:
            return None
        for option in allowed:
            if value.upper() == option:
                return option
        raise ConfigError(f"{self._where(section, key)}: must be {' or '.join(allowed)}, got {value!r}")


def read_skyscan_log(path: str | Path) -> SkyScanLog:
    """Parse a SkyScan ``.log``: ``[Section]`` headers, ``key=value`` lines, ``;``/``#`` comments.

    Raises
    ------
    ConfigError
        Naming the file (and line): not INI-like text, a ``key=value`` before any section, a
        key given twice in one section with different values, or no ``[Acquisition]`` section.
        A section that comes again (NRecon appending a second ``[Reconstruction]``) updates
        the first.
    InputError
        The file cannot be read.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > _MAX_LOG_BYTES:
            raise ConfigError(f"{path}: is {size} bytes, too large for a SkyScan log (a few kB); not a scan log")
        text = path.read_bytes().decode("latin-1")
    except OSError as exc:
        raise InputError(f"{path}: cannot be read: {exc.strerror or exc}") from None
    text = text.removeprefix("\u00ef\u00bb\u00bf")  # a UTF-8 byte-order mark, seen through Latin-1
    sections: dict[str, dict[str, str]] = {}
    current: dict[str, str] | None = None
    block: dict[str, str] = {}
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith((";", "#")):
            continue
        if line.startswith("[") and line.endswith("]"):
            current, block = sections.setdefault(_norm(line[1:-1]), {}), {}
            continue
        key, equals, value = line.partition("=")
        if not equals or not key.strip():
            raise ConfigError(f"{path}: line {number}: {line[:60]!r} is neither '[Section]' nor 'key=value'; "
                              "a SkyScan log is INI-like text")
        if current is None:
            raise ConfigError(f"{path}: line {number}: {key.strip()!r} comes before the first [Section] header")
        name, value = _norm(key), value.strip()
        if block.get(name, value) != value:
            raise ConfigError(f"{path}: line {number}: {key.strip()!r} is given twice in one section, as "
                              f"{block[name]!r} and {value!r}")
        current[name] = block[name] = value
    if "acquisition" not in sections:
        raise ConfigError(f"{path}: has no [Acquisition] section; not a SkyScan scan log")
    return SkyScanLog(path, sections)


def _looks_like_skyscan_log(path: Path) -> bool:
    """The cheap test of :func:`detect`: a ``[System]`` header first, ``[Acquisition]`` soon after."""
    try:
        with path.open("rb") as handle:
            head = handle.read(_SNIFF_BYTES).decode("latin-1").removeprefix("\u00ef\u00bb\u00bf")
    except OSError:
        return False
    lines = [line.strip() for line in head.splitlines() if line.strip() and not line.strip().startswith((";", "#"))]
    return bool(lines) and lines[0].lower() == "[system]" and "[acquisition]" in head.lower()


def _logs_in(folder: Path) -> list[Path]:
    try:
        return sorted(p for p in folder.iterdir() if p.suffix.lower() == ".log" and p.is_file()
                      and _looks_like_skyscan_log(p))
    except OSError:
        return []


def detect(path: Path) -> bool:
    """True for a SkyScan ``.log`` file, or a folder holding one (file names and first bytes only)."""
    path = Path(path)
    if path.is_file():
        return path.suffix.lower() == ".log" and _looks_like_skyscan_log(path)
    return path.is_dir() and bool(_logs_in(path))


def _find_log(path: Path) -> Path:
    if path.is_file():
        return path
    logs = _logs_in(path)
    if not logs:
        raise InputError(f"{path}: no SkyScan .log (a text file starting with [System]) in this folder")
    if len(logs) > 1:
        names = ", ".join(p.name for p in logs)
        raise InputError(f"{path}: holds {len(logs)} SkyScan logs ({names}); each is a scan (or sub-scan) of its "
                         f"own, so open one of them, e.g. {logs[-1]}")
    return logs[0]


def _sub_scan(prefix: str) -> int | None:
    match = re.search(r"~(\d+)$", prefix)
    return int(match.group(1)) if match else None


def _projection_names(log: SkyScanLog, folder: Path, prefix: str, count: int) -> list[str]:
    digits = log.integer("Acquisition", "Filename Index Length", "the digits of the projection numbers", high=12,
                         default=0)
    if not digits:
        # Older logs (SkyScan 1172, 1173) do not say; newer scanners write 8 digits, older ones 4.
        digits = next((d for d in (8, 4) if (folder / f"{prefix}{0:0{d}d}.tif").is_file()), 8)
    names = [f"{prefix}{i:0{digits}d}.tif" for i in range(count)]
    for i, name in enumerate(names):
        if not (folder / name).is_file():
            raise InputError(f"{folder / name}: no such file; {log.path.name} says Number of Files={count} but only "
                             f"{i} projections {prefix}{'N' * digits}.tif from 0 exist, and the count must match")
    extra = folder / f"{prefix}{count:0{digits}d}.tif"
    if extra.is_file():
        raise InputError(f"{extra}: exists, but {log.path} says Number of Files={count} (files 0 to {count - 1}); "
                         "the count must match the files")
    return names


def _geometry(log: SkyScanLog, prefix: str, notes: list[str]) -> Geometry:
    acq = "Acquisition"
    rows = log.integer(acq, "Number of Rows", "the detector rows (image height)", high=65536)
    cols = log.integer(acq, "Number of Columns", "the detector columns (image width)", high=65536)
    sod = log.number(acq, "Object to Source (mm)", "the source-to-axis distance", positive=True)
    sdd = log.number(acq, "Camera to Source (mm)", "the source-to-detector distance", positive=True)
    if sdd <= sod:
        raise ConfigError(f"{log.path}: [Acquisition] Camera to Source (mm)={sdd:g} must exceed Object to Source "
                          f"(mm)={sod:g}: the axis lies between source and detector")
    pixel_um = log.number(acq, "Image Pixel Size (um)", "the pixel size at the rotation axis", positive=True)
    pitch_mm = pixel_um / 1000.0 * sdd / sod
    camera_um = log.get("System", "Camera Pixel Size (um)")
    binning = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", log.get(acq, "Camera binning") or "1x1")
    if camera_um and _NUMBER.fullmatch(camera_um) and binning and float(camera_um) > 0:
        camera_mm = float(camera_um) / 1000.0 * int(binning.group(1))
        if abs(camera_mm / pitch_mm - 1.0) > _PIXEL_TOLERANCE:
            notes.append(f"Camera Pixel Size x binning is {camera_mm * 1000:.4g} um but Image Pixel Size x "
                         f"(Camera to Source / Object to Source) is {pitch_mm * 1000:.4g} um "
                         f"({100 * abs(camera_mm / pitch_mm - 1):.1f} % apart); ctpipe uses the latter, NRecon's")
    v0 = log.number(acq, "Optical Axis (line)", "the row where the central ray meets the detector")
    # Never applied, so a value that is not a number is said rather than refused.
    rotation_text = log.get(acq, "Image Rotation") or "0"
    rotation = float(rotation_text) if _NUMBER.fullmatch(rotation_text) else 0.0
    if not _NUMBER.fullmatch(rotation_text) or not math.isfinite(rotation):
        notes.append(f"Image Rotation={rotation_text!r} is not a number (degrees expected); not read")
    elif rotation != 0:
        lean_px = rows * math.tan(math.radians(abs(rotation)))
        notes.append(f"Image Rotation={rotation:g} deg (read as the camera's roll against the turntable axis) is not "
                     f"applied: ctpipe's detector has no roll; over the {rows} rows the axis would lean "
                     f"{lean_px:.1f} px, and whether the saved TIFFs are already rotated by it is undocumented")
    if log.number(acq, "Image crop origin Y", "the first camera row of the image", default=0.0) != 0:
        notes.append("Image crop origin Y is not 0: Optical Axis (line) is taken as a row of the stored image")
    rec = "Reconstruction"
    sub = _sub_scan(prefix)
    shift_key = "Postalignment"
    if not log.has(rec, shift_key) and sub is not None and log.has(rec, f"Sub-scan post alignment [{sub}]"):
        shift_key = f"Sub-scan post alignment [{sub}]"
    if log.has(rec, shift_key):
        shift = log.number(rec, shift_key, "NRecon's rotation-axis shift, pixels")
    else:
        shift = 0.0
        notes.append("no [Reconstruction] Postalignment in the log (not reconstructed yet?): the rotation axis is "
                     "taken on the middle column")
    return Geometry(source_to_object_mm=sod, source_to_detector_mm=sdd, detector_cols=cols, detector_rows=rows,
                    pixel_pitch_u_mm=pitch_mm, pixel_pitch_v_mm=pitch_mm, u0_px=(cols - 1) / 2.0 - shift, v0_px=v0)


def _angles(log: SkyScanLog, count: int, notes: list[str], override: str | None) -> np.ndarray:
    acq = "Acquisition"
    step = log.number(acq, "Rotation Step (deg)", "the turntable step between views, degrees", positive=True)
    start = log.number(acq, "Scanning Start Angle", "the angle of view 0, degrees", default=0.0)
    direction = log.choice(acq, "Rotation Direction", ("CC", "CW"))
    if override is not None:
        if direction is not None and direction != override:
            notes.append(f"Rotation Direction={override} as asked, although the log says {direction}")
        direction = override
    elif direction is None:
        direction = "CC"
        notes.append("no Rotation Direction in the log: CC assumed, as every SkyScan log we know says")
    sign = -1.0 if direction == "CC" else 1.0
    nominal = check_angles(sign * (start + step * np.arange(count, dtype=np.float64)) + 0.0, count,
                           f"{log.path}: [Acquisition] Rotation Step (deg)")
    return nominal, sign, start


def _recorded_angles(info: Path, count: int, start: float, sign: float, nominal: np.ndarray,
                     notes: list[str]) -> np.ndarray | None:
    """The achieved angles of a SkyScan 2214 ``<prefix>.info``, in ctpipe's convention, or None (with a note)."""
    try:
        text = info.read_bytes().decode("latin-1")
    except OSError as exc:
        raise InputError(f"{info}: cannot be read: {exc.strerror or exc}") from None
    achieved = []
    for number, line in enumerate(text.splitlines(), start=1):
        lowered = line.lower()
        if "drift compensation scan" in lowered:
            break
        if "achieved angle" in lowered:
            values = _NUMBER.findall(line.lower().partition("achieved angle")[2])
            if not values:
                raise ConfigError(f"{info}: line {number}: an 'achieved angle' line must end with the angle, got "
                                  f"{line.strip()[:60]!r}")
            achieved.append(float(values[-1]))
    if len(achieved) == count - 1:
        achieved = [start, *achieved]  # view 0 is not logged: it is taken at the start angle
    if len(achieved) != count:
        notes.append(f"{info.name}: {len(achieved)} 'achieved angle' lines for {count} views (expected "
                     f"{count - 1}); the recorded angles are not used")
        return None
    recorded = sign * np.asarray(achieved, dtype=np.float64) + 0.0
    stray = float(np.max(np.abs(recorded - nominal)))
    if not np.isfinite(stray) or stray > _MAX_STRAY_DEG:
        notes.append(f"{info.name}: the achieved angles stray up to {stray:.3g} deg from the nominal ones, more "
                     f"than {_MAX_STRAY_DEG:g}; they are not taken as the turntable's angles")
        return None
    return recorded


def _white_level(log: SkyScanLog, notes: list[str]) -> float:
    acq = "Acquisition"
    corrected = log.choice(acq, "Flat Field Correction", ("ON", "OFF"))
    depth = log.integer(acq, "Depth (bits)", "the bits per pixel of the projections", high=32, default=16)
    if corrected == "OFF":
        notes.append(f"Flat Field Correction=OFF: the TIFFs hold raw counts and SkyScan saves no flat frames; they "
                     f"are divided by 2**{depth} instead, so the detector's fixed pattern stays in the images")
        return float(2**depth)
    if corrected is None:
        notes.append("no Flat Field Correction in the log: ON assumed (the TIFFs flat-corrected by the scanner)")
    if log.has(acq, "Reference Intensity"):
        return log.number(acq, "Reference Intensity", "the open-beam grey level of the flat-corrected TIFFs",
                          positive=True)
    notes.append(f"no Reference Intensity in the log: white level 2**{depth} assumed, as TIGRE does (this only "
                 "offsets every line integral by a constant)")
    return float(2**depth)


def open_bruker(path: str | Path, *, rotation_direction: str | None = None) -> ScanFiles:
    """Open a SkyScan scan lazily: the log, the geometry and angles; views read on demand.

    Parameters
    ----------
    path : str or Path
        The folder holding one SkyScan ``.log`` and its TIFFs, or the ``.log`` itself (needed
        when the folder holds several, e.g. the sub-scans of a connected scan).
    rotation_direction : {"CC", "CW"} or None
        Overrides the log's ``Rotation Direction`` (see the module docstring for what each
        means); None reads it from the log.

    Raises
    ------
    ConfigError
        The log is malformed, or a key is missing or has an unusable value (the message names
        the file, the section and the key).
    InputError
        Projection files missing or more than ``Number of Files``, or of the wrong size (when
        read), or several logs in the folder.
    """

    if rotation_direction not in (None, "CC", "CW"):
        raise InputError(f"rotation_direction: must be 'CC', 'CW' or None, got {rotation_direction!r}")
    path = Path(path)
    log_path = _find_log(path)
    log = read_skyscan_log(log_path)
    folder = log_path.parent
    notes: list[str] = []
    image_format = log.get("Acquisition", "Image Format")
    if image_format is not None and image_format.upper() not in ("TIFF", "TIF"):
        raise InputError(f"{log_path}: [Acquisition] Image Format={image_format}; ctpipe reads SkyScan scans saved "
                         "as TIFF")
    prefix = log.get("Acquisition", "Filename Prefix") or log_path.stem
    if re.search(r"[\\/]", prefix) or prefix in (".", ".."):
        raise ConfigError(f"{log_path}: [Acquisition] Filename Prefix={prefix!r}: must be a file name prefix, "
                          "without folders")
    count = log.integer("Acquisition", "Number of Files", "the number of projections", high=10**7)
    geometry = _geometry(log, prefix, notes)
    nominal, sign, start = _angles(log, count, notes, rotation_direction)
    white = _white_level(log, notes)
    names = _projection_names(log, folder, prefix, count)
    info = folder / f"{prefix}.info"
    recorded = _recorded_angles(info, count, start, sign, nominal, notes) if info.is_file() else None
    if (log.get("Acquisition", "Random Movement") or "").upper().startswith("ON"):
        notes.append("Random Movement=ON: the projections are assumed shifted back by the scanner; a residual "
                     "vertical shift between views would bias the angles")
    if log.has("Acquisition", "TS modified according to") or (folder / f"{prefix}_TS.csv").is_file():
        notes.append("a thermal-shift table (_TS.csv) goes with this scan; NRecon applies it, ctpipe does not")
    connected = log.get("Acquisition", "Number of connected scans")
    if connected and _INTEGER.fullmatch(connected) and int(connected) > 1:
        notes.append(f"sub-scan {prefix} of a connected scan of {connected}; each sub-scan is estimated on its own")
    rows, cols = geometry.shape
    read = ViewFiles(tuple(folder / name for name in names), (rows, cols),
                     missing="{file}: no such file (projection {index} of {count}, named by {log})",
                     wrong_shape="{file}: is an image of shape {got} but {log} says Number of Rows={rows}, "
                                 "Number of Columns={cols}", context={"log": log_path.name})
    read(0)  # one view, so that a log that disagrees with its images fails here, not mid-estimate
    try:
        stack = ViewStack(read, count, (rows, cols), values="intensities", white_level=white, name=str(folder))
    except InputError as exc:
        raise InputError(f"{log_path}: {exc}") from None
    used = {f"[{section}] {key}": value for section, keys in log.sections.items() for key, value in keys.items()
            if section in ("acquisition", "reconstruction") or key == "camera pixel size (um)"}
    return ScanFiles("bruker", path, geometry, nominal, stack, recorded_angles_deg=recorded,
                     angle_log=info if recorded is not None else None, notes=tuple(notes),
                     metadata={"log": str(log_path), "prefix": prefix, "white_level": white, "keys": used})


@hookimpl
def ctpipe_register_formats(registry) -> None:
    registry.add_format("bruker", detect, open_bruker,
                        "a Bruker SkyScan folder: a <prefix>.log starting with [System] beside <prefix>NNNNNNNN.tif "
                        "(or that .log)")
