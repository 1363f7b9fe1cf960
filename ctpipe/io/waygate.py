"""GE / Waygate Technologies phoenix scans (datos|x acquisition): a ``.pca`` settings file beside one TIFF per view.

Files
-----
A scan folder as datos|x 2 acquisition leaves it, ``<name>`` being the scan's name (the stem of
its ``.pca``)::

    <name>.pca                    settings, INI text: [Geometry], [CT], [Image], [Detector], ...
    <name>00001.tif ...           the projections, numbered from 1 with (at least) 5 digits, one
                                  16-bit image of [Image] DimY rows x DimX columns each
    <name>.pcp                    acquisition protocol: a title line, then one tab-separated row
                                  per image: ImgNr RotPos U I MeanGV DevGV Dose Use CValue XDShift Time
    <name>.pcj                    per-image axis positions (XS YS ZS RS XD ...); not read
    <name>_bright_<kV>kV_<uA>uA_<ms>ms_1Det.tif, <name>_Dark_<ms>.tif
                                  the gain and offset images of [CalibImages]; not read (see below)
    <name>.pcr                    reconstruction settings, written later by datos|x rec; not read

A full turn ([CT] RotationSector = 360) has NumberImages + 1 images: the last one, at
RotPos = 360, repeats the first. When its file is there it is read as a view, the *closing
view* (``ScanFiles.closing_view``): nominal angle first + 360, recorded angle the ``.pcp`` row
ImgNr = NumberImages + 1, so that the pair graph can measure the whole turn from the images.
datos|x rec itself reconstructs from images 1 .. NumberImages only (``.pcr`` StartImage=1,
LastImage=NumberImages). Without that file, or when the ``.pcp`` has no row for it, the scan
has NumberImages views (the latter said in the notes). Corrected angles go back with as many
rows as the scanner's ``.pcp`` (see :func:`write_waygate_angles`).

Keys read, and what they become
-------------------------------
========================  ======================  =============================================
key (section, name)       ctpipe                  unit and conversion
========================  ======================  =============================================
[Geometry] FDD            source_to_detector_mm   mm (focus-detector distance)
[Geometry] FOD            source_to_object_mm     mm (focus-object distance = source to axis)
[Geometry] cx, cy         u0_px, v0_px            pixels of the stored image, 0-based from the
                                                  left column and the top row (see below)
[Detector] PixelsizeX/Y   pixel_pitch_u/v_mm      mm (checked against VoxelSizeX * FDD / FOD)
[Image] DimX, DimY        detector_cols, _rows    pixels of the stored images
[CT] NumberImages         number of views         images 1 .. NumberImages, + 1 closing view
[CT] RotationSector       nominal angles          deg: view i at i * RotationSector / NumberImages
[Image] FreeRay           white level             counts of an unattenuated pixel
<name>.pcp RotPos         recorded_angles_deg     deg, rows ImgNr = 1 .. NumberImages (+ 1), as
                                                  logged
========================  ======================  =============================================

Also read, to refuse what ctpipe cannot model or to say what it leaves out: [Detector] Binning,
[Geometry] VoxelSizeX, CalibValue, DetectorRot, Tilt, [Image] Rotation, MirrorX, MirrorY,
[Trajectory] Active, [CT] NoRotation, [CT] Type, [DetectorShift] Enable/Amplitude and the
``Use`` column of the ``.pcp``. Keys are matched case-insensitively, sections exactly.

Conventions, and what is unclear
--------------------------------
* **Flat correction.** The TIFFs are taken to be corrected by datos|x acquisition with its
  offset (dark) and (multi-point) gain (bright) images before saving, on a scale where an
  unattenuated pixel reads about [Image] FreeRay. This is inferred, not documented: datos|x
  rec's ``.pcr`` turns the projections into line integrals with ``FreeRay`` alone (or, with
  ``UseFreeRayFromPCP=1``, presumably with each image's MeanGV from the ``.pcp``) and never
  names the calibration images, which only the ``.pca`` [CalibImages] (the acquisition's own
  settings) lists; and the ``.pcp`` MeanGV of the free-ray window ([CT] Wnd_L/T/R/B) runs at
  the FreeRay level (3151 to 3250 in FEG230530_409, whose FreeRay is 3250). ctpipe therefore
  applies ``-log(I / FreeRay)`` (a :class:`~ctpipe.io.scans.ViewStack` with
  ``white_level=FreeRay``), with the one FreeRay for every view, and does not apply the
  calibration images again.
* **Principal point.** In every public ``.pca`` found, cx = (DimX - 1) / 2 and
  cy = (DimY - 1) / 2 exactly, also when DimX is NrPixelsX minus the detector-shift margin: cx
  and cy are pixels of the stored image with pixel centres at integers, as ctpipe's u0_px and
  v0_px. Whether they count from the left/top or the right/bottom edge cannot be told from
  centred values; ctpipe takes left/top (the image as stored), the usual image convention.
* **Rotation-axis offset.** [Geometry] CalibValue is datos|x's correction for the rotation
  axis not projecting onto cx. What the public files show: the ``.pcr`` of every run copies it
  as [Reconstruction Settings] CorrectionValue (28.524 -> 28.52400016784668, a float32 round
  trip), so datos|x rec applies it; its ``.pca`` section [CalibValue] (NumberImages=18,
  Averaging=2, Skip=3) suggests it is measured from 18 images before each scan. In the five
  FEG230530_409..413 runs (same FDD 807.135 mm, same sample-stage XS = 0 in the ``.pca`` [Axis]
  and every ``.pcj`` row, magnification 9.94 to 29.11) CalibValue runs 11.283 to 43.873 in
  step with the magnification: CalibValue * PixelsizeX / Magnification is 0.227 to 0.301 mm,
  and a least-squares line CalibValue = 1.70 * M - 5.39 fits all five to 0.82. A value proportional
  to the magnification is an offset at the object seen on the detector, which is what a
  rotation axis beside the central ray gives: the unit is then detector pixels (the same
  figure as voxels: VoxelSizeX = PixelsizeX / M), an axis 0.23 to 0.30 mm from the central ray.
  This is inferred, not documented. The sign is not shown by anything public: the axis would
  project at column cx + CalibValue or cx - CalibValue, and taking the wrong one would put
  u0 2 * CalibValue (57 px in FEG230530_409) from the truth, twice the error of ignoring it.
  No public reader applies it (the one public ``.pca`` reader found reads it as a number and
  never uses it). ctpipe therefore keeps u0_px = cx and says in the notes, whenever CalibValue
  is not 0, its value, the offset at the object it implies, and that it is not applied.
* **Detector shift.** With [DetectorShift] Enable=1 the detector moves sideways between images
  by XDShift pixels (``.pcp``; the ``.pcj`` logs the same move as XD = XDShift * PixelsizeX
  mm). The public files have DimX = NrPixelsX - 2 Amplitude and cx = (DimX - 1) / 2, so the
  stored images were shifted back and cropped by Amplitude columns on each side: they are
  aligned, their geometry is DimX x DimY with cx as above, and XDShift needs no correction.
* **Angle sign.** RotPos (``.pcp``, deg) counts up with ImgNr, RotPos = (ImgNr - 1) *
  RotationSector / NumberImages in the public files. No public reader (CIL, dxchange, tomopy,
  TIGRE, ODL, RTK have none for datos|x) and no vendor document says which way the turntable
  turns seen from above relative to the stored image, so ctpipe takes RotPos with its own sign
  (a turn of +a is +a; no negation) and says so in the notes: a real scan whose estimated
  angles run against the nominal ones would show that datos|x counts the other way. In the
  public logs RotPos equals the commanded position to its 3 decimals, so the ``.pcp`` may log
  commands rather than encoder readings.
* **Binning.** Whether PixelsizeX is the binned or the physical pixel is undocumented: with
  [Detector] Binning = 0 ctpipe uses PixelsizeX/Y; otherwise it uses VoxelSizeX * FDD / FOD
  (the effective pitch datos|x's own voxel size implies) and refuses the scan without VoxelSizeX.
* **Refused:** non-circular trajectories ([Trajectory] Active=1), [CT] NoRotation=1, rotated or
  mirrored images ([Image] Rotation, MirrorX, MirrorY not 0: whether cx and the angle log refer
  to the image before or after the flip is undocumented), RotationSector outside (0, 360].
* **Not modelled, said in the notes:** DetectorRot and Tilt (detector roll and tilt) when not 0,
  images the ``.pcp`` marks Use = 0, a missing ``.pcp``.

Anchors
-------
* xray-imaging/meta-cli, ``docs/source/demo/ge/FEG230530_409-run-files/FEG230530_409.pca``,
  ``.pcp``, ``.pcj``, ``.pcr`` (and the 410-413 scans beside them): real datos|x 2.4.0 files of a
  phoenix v|tome|x m. Key names and sections, the ``.pcp`` columns, ImgNr 1 .. NumberImages + 1
  with RotPos = (ImgNr - 1) * RotationSector / NumberImages, cx = (DimX - 1) / 2,
  DimX = NrPixelsX - 2 Amplitude, VoxelSizeX = PixelsizeX * FOD / FDD, the calibration image
  names, and the ``.pcr`` (FreeRay, UseFreeRayFromPCP, CorrectionValue = CalibValue,
  LastImage = NumberImages).
* johntrue15/Rosetta, ``scripts/pca_to_json.py``: reads the ``.pca`` as INI with configparser
  ([Geometry] FDD, FOD, VoxelSizeX, Magnification; [Detector] Binning, 0 meaning 1x1; [Image]
  DimX, DimY; [CalibImages]); no geometry or angle conventions.
* Two public scripts found by content in the code index (their repositories were not
  resolved): an ODL example quoting a whole datos|x 2 ``.pca`` that reads
  ``<name>{n:05d}.tif`` from n = 1, and a Waygate archive-replay script that reads
  ``<name>{n:05d}.tif``, n = 1 .. 1200 of 1201, takes its angles from the ``.pcp`` RotPos column
  in increasing order (saying its orientation was not verified) and computes
  ``-log(I / FreeRay)``.
* CIL (``NikonDataReader``, ``ZEISSDataReader``), dxchange and tomopy have no datos|x reader, so
  none settles the sign.
* A public ``.pca`` reader found by content in the code index (``read_pca_file``, "T H 2025",
  with a ``get_ct_parameters`` beside it; repository not resolved): it reads CalibValue, cx,
  cy, Tilt, DetectorRot as numbers but builds its geometry from FOD, FDD, PixelsizeX, DimX/Y
  and ``linspace(0, RotationSector, NumberImages, endpoint=False)`` only: CalibValue unused,
  the closing image not read.
"""

from __future__ import annotations

import ast
import configparser
import contextlib
import math
import os
from pathlib import Path

import numpy as np

from ctpipe.errors import ConfigError, InputError
from ctpipe.geometry import Geometry
from ctpipe.hookspecs import hookimpl
from ctpipe.io.scans import ScanFiles, ViewFiles, ViewStack, check_angles

__all__ = ["open_waygate", "write_waygate_angles"]

#: Largest ``.pca`` read (real ones are a few kB).
_PCA_MAX_BYTES = 4 << 20
#: Largest ``.pcp`` read (about 90 bytes per image).
_PCP_MAX_BYTES = 64 << 20
#: How far into the ``.pcp`` its column header may be.
_PCP_HEADER_LINES = 10
_REQUIRED = object()


def detect(path: Path) -> bool:
    """True if ``path`` is a ``.pca`` file, or a folder holding one, that starts like an INI file."""
    path = Path(path)
    try:
        if path.is_file():
            candidates = [path] if path.suffix.lower() == ".pca" else []
        elif path.is_dir():
            with os.scandir(path) as entries:
                candidates = [Path(e.path) for e in entries if e.name.lower().endswith(".pca") and e.is_file()]
        else:
            return False
        return any(_starts_like_ini(file) for file in candidates)
    except OSError:
        return False


def _starts_like_ini(file: Path) -> bool:
    with open(file, "rb") as handle:
        head = handle.read(512)
    return head.removeprefix(b"\xef\xbb\xbf").lstrip().startswith(b"[")


def open_waygate(path: str | Path) -> ScanFiles:
    """Open a datos|x scan lazily: settings and angle log read, projections on demand.

    Parameters
    ----------
    path : str or Path
        The scan folder (holding one ``.pca``) or its ``.pca`` file.

    Returns
    -------
    ScanFiles
        ``format="waygate"``; the projections are corrected counts with white level
        [Image] FreeRay; ``recorded_angles_deg`` is the ``.pcp`` RotPos column (None without a
        ``.pcp``), with ctpipe's sign (see the module docstring).

    Raises
    ------
    ConfigError
        The ``.pca`` or ``.pcp`` is malformed, misses a key, or holds a value ctpipe refuses.
    InputError
        A projection is missing, the files disagree with [CT] NumberImages, or the geometry is
        impossible.
    """
    path = Path(path)
    pca, folder = _find_pca(path)
    settings = _Settings(pca)
    name = pca.stem
    notes: list[str] = []

    if settings.integer("Trajectory", "Active", 0) != 0:
        raise ConfigError(f"{pca}: [Trajectory] Active=1: only circular scans are read; allowed: 0")
    if settings.integer("CT", "NoRotation", 0) != 0:
        raise ConfigError(f"{pca}: [CT] NoRotation=1: a scan without rotation has no angles to estimate; allowed: 0")
    for key in ("Rotation", "MirrorX", "MirrorY"):
        if settings.integer("Image", key, 0) != 0:
            raise ConfigError(f"{pca}: [Image] {key}={settings.text('Image', key)}: rotated or mirrored images are not "
                              f"read (whether cx/cy and the angle log refer to the image before or after it is "
                              f"undocumented); allowed: 0")
    n_views = settings.integer("CT", "NumberImages", minimum=1)
    sector = settings.number("CT", "RotationSector")
    if not 0.0 < sector <= 360.0:
        raise ConfigError(f"{pca}: [CT] RotationSector: must be in (0, 360] degrees, got {sector!r}")
    scan_type = settings.integer("CT", "Type", 0)
    if scan_type != 0:
        notes.append(f"[CT] Type={scan_type} (not the 0 of the public scans) read as a plain circular scan")
    cols = settings.integer("Image", "DimX", minimum=1)
    rows = settings.integer("Image", "DimY", minimum=1)
    sdd = settings.number("Geometry", "FDD", positive=True)
    sod = settings.number("Geometry", "FOD", positive=True)
    cx = settings.number("Geometry", "cx")
    cy = settings.number("Geometry", "cy")
    pitch_u, pitch_v = _pixel_pitch(settings, sdd, sod, notes)
    free_ray = settings.number("Image", "FreeRay", positive=True)
    calib = settings.number("Geometry", "CalibValue", 0.0)
    if calib != 0.0:
        at_object_mm = calib * pitch_u * sod / sdd
        notes.append(f"[Geometry] CalibValue={calib:g} (datos|x rec's rotation-axis correction) is not applied: "
                     f"read as detector pixels it puts the axis {at_object_mm:.3f} mm from the central ray at the "
                     f"object, at column cx {calib:+g} or cx {-calib:+g}, but its sign is undocumented, so u0_px is "
                     f"[Geometry] cx={cx:g}")
    for key in ("DetectorRot", "Tilt"):
        value = settings.number("Geometry", key, 0.0)
        if value != 0.0:
            notes.append(f"[Geometry] {key}={value:g} is not modelled (ctpipe's detector is upright and "
                         f"perpendicular to the central ray)")
    try:
        geometry = Geometry(source_to_object_mm=sod, source_to_detector_mm=sdd, detector_cols=cols,
                            detector_rows=rows, pixel_pitch_u_mm=pitch_u, pixel_pitch_v_mm=pitch_v, u0_px=cx, v0_px=cy)
    except InputError as exc:
        raise InputError(f"{pca}: {exc}") from None

    files = _projection_files(folder, name, n_views, pca)
    closing_file = folder / _projection_name(name, n_views + 1)
    full_turn = sector == 360.0
    closing = full_turn and closing_file.is_file()
    if closing_file.is_file() and not full_turn:
        notes.append(f"{closing_file.name} (image NumberImages + 1) is not read: [CT] RotationSector={sector:g} is "
                     f"not a full turn, so it does not repeat image 1")
    pcp = folder / f"{name}.pcp"
    recorded = None
    pcp_rows = 0
    closing_offset = None
    if pcp.is_file():
        recorded, use, extra = _read_pcp(pcp, n_views, pca)
        pcp_rows = n_views + (extra is not None)
        if extra is not None:
            closing_offset = extra[0] - recorded[0]
        if closing and extra is None:
            closing = False
            notes.append(f"{closing_file.name} closes the turn, but {pcp.name} has no row ImgNr {n_views + 1} for "
                         f"it: read as {n_views} views, without it")
        elif closing:
            recorded, use = np.append(recorded, extra[0]), np.append(use, extra[1])
        unused = np.flatnonzero(use != 1)
        if unused.size:
            notes.append(f"{pcp.name} marks {unused.size} image(s) Use != 1 (first: ImgNr {unused[0] + 1}); "
                         f"they are kept as views")
        notes.append(f"{pcp.name} RotPos is read with ctpipe's sign (no negation); datos|x does not document its "
                     f"rotation direction, so estimated angles running against the nominal ones would mean it "
                     f"counts the other way")
    else:
        notes.append(f"no {pcp.name}: no per-view angle log, only the nominal angles")
    if closing:
        files.append(closing_file)
    n_read = len(files)
    nominal = np.arange(n_read) * (sector / n_views)

    read = ViewFiles(tuple(files), (rows, cols),
                     missing="{file}: no such file (image {number} of the {count} read, [CT] NumberImages="
                             f"{n_views} in {{pca}})",
                     wrong_shape="{file}: must be a {rows} x {cols} image ([Image] DimY x DimX in {pca}), got "
                                 "shape {got}", context={"pca": pca})
    try:
        stack = ViewStack(read, n_read, (rows, cols), values="intensities", white_level=free_ray, name=str(folder))
    except InputError as exc:
        raise InputError(f"{pca}: {exc}") from None
    metadata = {"pca": str(pca), "name": name, "free_ray": free_ray, "calib_value": calib,
                "rotation_sector_deg": sector, "number_images": n_views, "pcp_rows": pcp_rows,
                "pcp_closing_offset_deg": closing_offset, "settings": settings.used}
    return ScanFiles("waygate", path, geometry, nominal, stack, recorded_angles_deg=recorded,
                     angle_log=pcp if recorded is not None else None, notes=tuple(notes), metadata=metadata,
                     closing_view=closing)


def _find_pca(path: Path) -> tuple[Path, Path]:
    """The scan's ``.pca`` and its folder, from either."""
    if path.is_file():
        if path.suffix.lower() != ".pca":
            raise InputError(f"{path}: not a datos|x settings file; give the scan folder or its .pca file")
        return path, path.parent
    if not path.is_dir():
        raise InputError(f"{path}: no such file or folder")
    found = sorted(p for p in path.iterdir() if p.suffix.lower() == ".pca" and p.is_file())
    if not found:
        raise InputError(f"{path}: no .pca file; a datos|x scan folder holds <name>.pca beside its TIFFs")
    if len(found) > 1:
        raise InputError(f"{path}: holds {len(found)} .pca files ({', '.join(p.name for p in found[:4])}); "
                         f"a datos|x scan folder holds one, so give the .pca of the scan")
    return found[0], path


def _read_text(path: Path, limit: int, what: str) -> str:
    try:
        size = path.stat().st_size
        if size > limit:
            raise InputError(f"{path}: {size} bytes is too large for a datos|x {what} (at most {limit})")
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        # datos|x runs on Windows and writes ANSI text (the µ of "µCT" in SystemName).
        return data.decode("latin-1")


class _Settings:
    """The ``.pca``, parsed, with typed look-ups whose errors name the file, section and key."""

    def __init__(self, pca: Path) -> None:
        self.pca = pca
        self.used: dict[str, str] = {}
        parser = configparser.ConfigParser(interpolation=None, strict=True, delimiters=("=",),
                                           comment_prefixes=(";", "#"), inline_comment_prefixes=None,
                                           empty_lines_in_values=False)
        try:
            parser.read_string(_read_text(pca, _PCA_MAX_BYTES, "settings file"), source=str(pca))
        except configparser.MissingSectionHeaderError as exc:
            raise ConfigError(f"{pca}: line {exc.lineno}: {exc.line.strip()!r} comes before any [Section]; "
                              f"not a datos|x settings file") from None
        except configparser.ParsingError as exc:
            lineno, line = exc.errors[0]
            with contextlib.suppress(ValueError, SyntaxError):
                line = ast.literal_eval(line)  # configparser keeps the repr of the line
            raise ConfigError(f"{pca}: line {lineno}: {str(line).strip()!r} is neither [Section] nor key=value; "
                              f"not a datos|x settings file") from None
        except configparser.DuplicateSectionError as exc:
            raise ConfigError(f"{pca}: line {exc.lineno}: section [{exc.section}] appears twice") from None
        except configparser.DuplicateOptionError as exc:
            raise ConfigError(f"{pca}: line {exc.lineno}: [{exc.section}] {exc.option} appears twice") from None
        except configparser.Error as exc:
            raise ConfigError(f"{pca}: not a datos|x settings file ({' '.join(str(exc).split())})") from None
        self._parser = parser

    def text(self, section: str, key: str, default=_REQUIRED) -> str | None:
        if self._parser.has_option(section, key):
            value = self._parser.get(section, key).strip()
            self.used[f"[{section}] {key}"] = value
            return value
        if default is _REQUIRED:
            where = f"section [{section}]" if self._parser.has_section(section) else f"no section [{section}]"
            raise ConfigError(f"{self.pca}: [{section}] {key}: missing ({where} has no {key}=); a datos|x scan "
                              f"needs it")
        return default

    def number(self, section: str, key: str, default=_REQUIRED, *, positive: bool = False) -> float:
        value = self.text(section, key, None if default is not _REQUIRED else _REQUIRED)
        if value is None:
            return default
        try:
            number = float(value)
        except ValueError:
            number = math.nan
        if not math.isfinite(number) or (positive and not number > 0):
            allowed = "a number > 0" if positive else "a finite number"
            raise ConfigError(f"{self.pca}: [{section}] {key}: must be {allowed}, got {value!r}")
        return number

    def integer(self, section: str, key: str, default=_REQUIRED, *, minimum: int | None = None) -> int:
        value = self.text(section, key, None if default is not _REQUIRED else _REQUIRED)
        if value is None:
            return default
        try:
            number = int(value)
        except ValueError:
            raise ConfigError(f"{self.pca}: [{section}] {key}: must be an integer, got {value!r}") from None
        if minimum is not None and number < minimum:
            raise ConfigError(f"{self.pca}: [{section}] {key}: must be an integer >= {minimum}, got {value!r}")
        return number


def _pixel_pitch(settings: _Settings, sdd: float, sod: float, notes: list[str]) -> tuple[float, float]:
    """(u, v) pixel pitch in mm of the stored images (see "Binning" in the module docstring)."""
    pca = settings.pca
    binning = settings.integer("Detector", "Binning", 0)
    voxel = settings.number("Geometry", "VoxelSizeX", None, positive=True)
    implied = None if voxel is None else voxel * sdd / sod
    if binning != 0:
        if implied is None:
            raise ConfigError(f"{pca}: [Detector] Binning={binning} without [Geometry] VoxelSizeX: whether "
                              f"[Detector] PixelsizeX is the binned pixel is undocumented; allowed: Binning=0, "
                              f"or a VoxelSizeX to take the pitch from")
        notes.append(f"[Detector] Binning={binning}: pixel pitch {implied:.6g} mm taken from [Geometry] VoxelSizeX "
                     f"* FDD / FOD, not from [Detector] PixelsizeX")
        return implied, implied
    pitch_u = settings.number("Detector", "PixelsizeX", positive=True)
    pitch_v = settings.number("Detector", "PixelsizeY", positive=True)
    if implied is not None and abs(implied / pitch_u - 1.0) > 1e-3:
        notes.append(f"[Geometry] VoxelSizeX * FDD / FOD = {implied:.6g} mm disagrees with [Detector] "
                     f"PixelsizeX = {pitch_u:.6g} mm; PixelsizeX is used")
    return pitch_u, pitch_v


def _projection_name(name: str, number: int) -> str:
    return f"{name}{number:05d}.tif"


def _projection_files(folder: Path, name: str, n_views: int, pca: Path) -> list[Path]:
    """The files of images 1 .. n_views, each checked to exist (one at a time: a huge count stops early)."""
    files = []
    for number in range(1, n_views + 1):
        file = folder / _projection_name(name, number)
        if not file.is_file():
            raise InputError(f"{file}: no such file; [CT] NumberImages={n_views} in {pca.name} but only {number - 1} "
                             f"projections {_projection_name(name, 1)}... exist, and the count must match the files")
        files.append(file)
    # Image NumberImages + 1 closes a full turn; one more means NumberImages undercounts the files.
    beyond = folder / _projection_name(name, n_views + 2)
    if beyond.is_file():
        raise InputError(f"{beyond}: exists, but [CT] NumberImages={n_views} in {pca.name} allows images 1 .. "
                         f"{n_views + 1}; NumberImages must match the projections")
    return files


def _read_pcp(pcp: Path, n_views: int, pca: Path) -> tuple[np.ndarray, np.ndarray, tuple[float, int] | None]:
    """RotPos (deg) and Use of images 1 .. n_views from the acquisition protocol, and (RotPos, Use) of image
    n_views + 1 (the closing image of a full turn) or None when it has no row."""
    lines = _read_text(pcp, _PCP_MAX_BYTES, "acquisition protocol").splitlines()
    header = next((i for i, line in enumerate(lines[:_PCP_HEADER_LINES])
                   if {"ImgNr", "RotPos"} <= {c.strip() for c in line.split("\t")}), None)
    if header is None:
        raise ConfigError(f"{pcp}: no tab-separated column header with ImgNr and RotPos in its first "
                          f"{_PCP_HEADER_LINES} lines; not a datos|x acquisition protocol")
    columns = [c.strip() for c in lines[header].split("\t")]
    i_nr, i_rot = columns.index("ImgNr"), columns.index("RotPos")
    i_use = columns.index("Use") if "Use" in columns else None
    needed = max(i for i in (i_nr, i_rot, i_use) if i is not None) + 1
    angles = np.full(n_views + 1, np.nan)
    use = np.ones(n_views + 1, np.int64)
    for lineno, line in enumerate(lines[header + 1:], start=header + 2):
        if not line.strip():
            continue
        fields = line.split("\t")
        if len(fields) < needed:
            raise ConfigError(f"{pcp}: line {lineno}: {len(fields)} tab-separated fields, but the header puts "
                              f"{columns[needed - 1]} in column {needed}")
        try:
            number, angle = int(fields[i_nr]), float(fields[i_rot])
            flag = 1 if i_use is None else int(fields[i_use])
        except ValueError:
            raise ConfigError(f"{pcp}: line {lineno}: ImgNr, RotPos{', Use' if i_use is not None else ''} must be "
                              f"numbers, got {line.strip()!r}") from None
        if not math.isfinite(angle):
            raise ConfigError(f"{pcp}: line {lineno}: RotPos must be a finite angle (deg), got {fields[i_rot]!r}")
        if 1 <= number <= n_views + 1:
            if not np.isnan(angles[number - 1]):
                raise ConfigError(f"{pcp}: line {lineno}: ImgNr {number} appears twice")
            angles[number - 1], use[number - 1] = angle, flag
    missing = np.flatnonzero(np.isnan(angles[:n_views]))
    if missing.size:
        raise InputError(f"{pcp}: no row for ImgNr {missing[0] + 1}; {missing.size} of the {n_views} images of "
                         f"[CT] NumberImages in {pca.name} are not logged, and the protocol must list every projection")
    extra = None if np.isnan(angles[n_views]) else (float(angles[n_views]), int(use[n_views]))
    return angles[:n_views], use[:n_views], extra


# --- writing angle logs -------------------------------------------------------------------------


def _pcp_lines(title: str, columns: list[str], rows: list[list[str]]) -> str:
    return "\r\n".join([title, "\t".join(columns), *("\t".join(row) for row in rows)]) + "\r\n"


def write_waygate_angles(path: str | Path, angles_deg) -> Path:
    """Write per-view angles (ctpipe's convention) as a datos|x acquisition protocol (``.pcp``).

    One row per view, ``ImgNr`` from 1 and ``RotPos`` in degrees with 3 decimals, the sign kept
    (the reader takes RotPos with ctpipe's sign; see the module docstring). A scan read with its
    closing view has NumberImages + 1 views, so the file has the NumberImages + 1 rows of the
    scanner's own ``.pcp``; the corrected log of a scan read without it still gets that row
    (``ctpipe estimate`` writes it through the format's ``corrected_angle_log``). Only these two
    columns are written: the tube and grey-value columns of a scanner's ``.pcp`` are not ctpipe's
    to invent, and :func:`open_waygate` needs only ImgNr and RotPos. The title line says that
    ctpipe wrote the file. Whether datos|x rec reads angles back from a ``.pcp`` is undocumented.

    Parameters
    ----------
    path : path
        A new ``.pcp`` file; an existing file is never overwritten.
    angles_deg : array of shape (V,)
        Finite degrees, view 0 first.

    Returns
    -------
    Path of the file.
    """
    from ctpipe._version import __version__
    from ctpipe.io.outputs import atomic_write, check_output_file

    path = Path(path)
    angles = np.asarray(angles_deg, dtype=np.float64)
    if angles.ndim != 1 or not angles.size:
        raise InputError(f"angles_deg: must be a non-empty 1-D array (one angle per view), got shape {angles.shape}")
    angles = check_angles(angles, angles.size, "angles_deg")
    check_output_file(path, "path", ".pcp")
    if path.exists() or path.is_symlink():
        raise InputError(f"{path}: exists; corrected angles go to a new file, an angle log is never overwritten")
    text = _pcp_lines(f"datos|x 2 acquisition protocol written by ctpipe {__version__}: corrected angles",
                      ["ImgNr", "RotPos"], [[str(i + 1), f"{a:.3f}"] for i, a in enumerate(angles)])
    return atomic_write(path, lambda handle: handle.write(text.encode("ascii")))


def _corrected_angle_log(scan: ScanFiles, angles_deg) -> tuple[str, bytes]:
    """``<name>.pcp`` with ``angles_deg`` (ctpipe's convention, the nominal angles' frame), one row per row of the
    scanner's ``.pcp``.

    A scan read without its closing view whose ``.pcp`` logs image NumberImages + 1 gets that row too, at view
    0's corrected angle plus the scanner's own RotPos step from image 1 to it (360 for a full turn): the closing
    image is view 0 one turn later, a turn the images of this scan did not measure.
    """
    import tempfile

    angles = np.asarray(angles_deg, dtype=np.float64)
    offset = scan.metadata.get("pcp_closing_offset_deg")
    if not scan.closing_view and offset is not None and angles.shape == (scan.metadata["number_images"],):
        angles = np.append(angles, angles[0] + offset)
    name = f"{scan.metadata['name']}.pcp"
    with tempfile.TemporaryDirectory() as tmp:
        return name, write_waygate_angles(Path(tmp) / name, angles).read_bytes()


@hookimpl
def ctpipe_register_formats(registry) -> None:
    registry.add_format("waygate", detect, open_waygate,
                        "a folder with <name>.pca beside <name>00001.tif ... (GE/Waygate phoenix datos|x)",
                        corrected_angle_log=_corrected_angle_log)
