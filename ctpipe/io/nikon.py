"""Nikon / X-Tek scans (Inspect-X, CT Pro): an ``.xtekct`` settings file beside 16-bit TIFF projections.

Files
-----
A scan folder as CT Pro leaves it::

    <Name>.xtekct              # INI text, section [XTekCT] (plus [Xrays], [CTPro], ...)
    <Name>_0001.tif ...        # one 16-bit TIFF per projection, numbered from 1
    _ctdata.txt                # the scanner's per-projection angle log (tab-separated)
    <Name>.ang                 # optional: a per-projection angle file CT Pro can read

Projections are ``<InputName><InputSeparator><number>.tif`` in the folder ``InputFolderName``
(relative to the ``.xtekct``; empty means the same folder), the number counting from 1 with
``InputDigits`` digits (``%04d`` when the key is missing, as CIL's predecessor of 2019 and
CCPi's ``XtekReader`` assume). They are flat-corrected by the scanner before they are
saved and scaled so that an unattenuated pixel reads ``WhiteLevel``: there are no flat or dark
frames, and the views become line integrals ``-log(I / WhiteLevel)`` through
:class:`~ctpipe.io.scans.ViewStack` with ``white_level=WhiteLevel``.

Keys read from ``[XTekCT]``
---------------------------
=========================  =========================================================  ======
key                        meaning, and what ctpipe makes of it                       unit
=========================  =========================================================  ======
SrcToObject                source to rotation axis -> ``source_to_object_mm``         mm
SrcToDetector              source to detector -> ``source_to_detector_mm``            mm
DetectorPixelsX, ...Y      columns, rows -> ``detector_cols``, ``detector_rows``      px
DetectorPixelSizeX, ...Y   pixel pitch -> ``pixel_pitch_u_mm``, ``pixel_pitch_v_mm``  mm
DetectorOffsetX, ...Y      detector shift (optional, 0) -> ``u0_px``, ``v0_px``       mm
ObjectOffsetX              rotation-axis shift at the object (newer files) -> u0_px   mm
CentreOfRotationTop, ...   axis shift at the detector, top and bottom rows (older     mm
Bottom                     files; used when ObjectOffsetX is absent) -> ``u0_px``
ObjectRoll, ObjectTilt     axis roll and tilt (optional): not modelled, a note        deg
ObjectOffsetY              axis shift along the beam (optional): not modelled, a note mm
Projections                number of projections; the folder holds as many images, or
                           one more that closes the turn (see below)
InitialAngle, AngularStep  nominal angle of projection i: InitialAngle + i * Step     deg
WhiteLevel                 counts of an unattenuated pixel -> ``white_level``
Name, InputName,           file names of the projections (InputName defaults to
InputSeparator,            Name, InputSeparator to ``_``, InputDigits to 4,
InputDigits,               InputFolderName to the folder of the .xtekct)
InputFolderName
Scattering                 a scatter percentage CT Pro subtracts: not applied, a note  %
=========================  =========================================================  ======

The closing image
-----------------
A Nikon scan of a full turn saves ``Projections + 1`` images and logs ``Projections + 1``
angles: every real folder in ``shared/real-metadata`` does (XT H: ``ivan-cube``, ``pillars``,
``ivan-balls 3`` with 257, 129, 257 ``.ang`` rows for Projections 256, 128, 256, and
``ivan-balls-7`` with 513 ``_ctdata.txt`` rows for 512; CT Pro 5.4's Lego scan with 1571 for
1570), and the images are named on to ``<Name>_<Projections + 1>.tif``. The last image is taken
at ``InitialAngle + Projections * AngularStep``: one turn after view 0 (360.000 deg in the XT H
sets, 360.02 in ``ivan-balls-7``, 361.03 in the Lego scan, whose step is 0.2299575). TIGRE's
``NikonDataLoader`` reads every ``.tif`` in the folder and every log row, so it reconstructs with
the closing image too. ctpipe reads it as the last view (``ScanFiles.closing_view``) at that
nominal angle, and the pair graph pairs it with view 0 (:func:`ctpipe.solve.turn_pairs`), so
the turn is measured from the images. A folder with only ``Projections`` images reads as
``Projections`` views (a log row for the missing image is left out, and said); anything else
is refused.

Angle logs
----------
``_ctdata.txt`` (real ones: xray-imaging/meta-cli ``docs/source/demo/nikon/``,
igrega348/nerf_data ``balls7``)::

    Projections<TAB>Frames<TAB>Exposure(ms)
    1570<TAB>1<TAB>708.00
    Projection<TAB>Angle(deg)<TAB>Time(s)
    1<TAB>000.0342<TAB>002.8319
    ...
    1571<TAB>361.0664<TAB>1114.7200

``<Name>.ang`` (real ones: igrega348/nerf_data ``cube``, ``pillars``, ``balls``): a header
line ``Proj<TAB>Angle(deg)``, then ``<projection>:<TAB><angle>`` per image, numbered from 1::

    Proj<TAB>Angle(deg)
    1:<TAB>000.000
    2:<TAB>-001.406
    ...
    257:<TAB>-359.999

Both are read where both exist (``<Name>.ang`` is the one used, and the notes say how far
``_ctdata.txt`` agrees with it). Both count from the start of the scan: the real
``_ctdata.txt`` files start at 0.0342 and 0.5613 deg while their ``.xtekct`` say
``InitialAngle`` = 40.20631 and 5.211245, so the recorded angles are ``InitialAngle`` plus or
minus the logged values (CIL's predecessor of 2019 added ``InitialAngle`` to both logs too).

Sense of the logs. The real ``.ang`` files run *against* ``AngularStep`` (0, -1.406, ...,
-359.999 for a step of +1.40625), the real ``_ctdata.txt`` files *with* it (0.5613, 1.2693, ...,
360.5835 for +0.7031701). The public readers agree once their own frames are accounted for:
TIGRE (``Python/tigre/utilities/io/NikonDataLoader.py``, after CERN/TIGRE#418 fixed "a
difference in expected rotation direction") negates the nominal angles and ``_ctdata.txt`` but
takes the ``.ang`` as it is; OMEGA (villekf/OMEGA ``loadNikonData.py``) negates the ``.ang``;
CCPi's ``XtekReader`` reverses its order, the same correction for uniform steps. So the reader
measures each log's sense from its values against ``AngularStep`` (a log that does not move
takes the real files' sense: ``.ang`` against, ``_ctdata.txt`` with) and reads
``recorded = InitialAngle + sense * value``; the sense is in ``metadata["angle_log_sense"]`` and
the notes. Taking the ``.ang`` as it stands, as ctpipe did before, put "logged minus nominal"
at -717 deg on the XT H sets. :func:`write_nikon_angles` writes ``.ang`` files the scanners'
way (against ``AngularStep``), with as many rows as the scanner's own log.

Sign of the angles
------------------
The ``.xtekct`` angles are not negated: an angle that grows by +a is a turn of +a in
ctpipe's convention, for the images as they are stored. The anchor is CIL's
``NikonDataReader`` (TomographicImaging/CIL, ``Wrappers/Python/cil/io/NikonDataReader.py``):
it sets ``angles = -(InitialAngle + i * AngularStep) + 180`` *and* declares the panel origin
``top-right``, i.e. stored column 0 lies at CIL's +x. In CIL's frame (source at -y, detector at
+y, axis +z, ``cil/plugins/astra/utilities/convert_geometry_to_astra_vec_3D.py`` turning the
source by ``-angle``) a CIL angle +t moves a point between axis and source towards +x, i.e.
towards *smaller* stored columns; in ctpipe a turn of +t moves it towards *larger* columns.
So ctpipe's angle is ``-(CIL angle)`` plus a constant, which is ``+(InitialAngle + i * Step)``:
CIL's two reversals (of the angle and of the column axis) cancel for a reader that keeps the
stored image as it is. The conclusion holds whichever way round the real turntable turns, as
long as CIL's angle and panel origin are right relative to each other. CIL has ignored both
logs since 2020 ("appear to hold angular data but it's not correct", TomographicImaging/CIL#703).

Offsets and the principal point
-------------------------------
After CIL (the version of 2022 that still read ``DetectorOffsetX/Y``; the current one ignores
them and scanners write 0): the detector centre lies at -DetectorOffsetX along CIL's x and
+DetectorOffsetY along z, and the rotation axis at -ObjectOffsetX, or at
``-(CentreOfRotationTop + CentreOfRotationBottom) / 2 * SrcToObject / SrcToDetector`` in
files without ``ObjectOffsetX``. With stored columns running towards -x and rows downwards::

    v0_px = (rows - 1) / 2 + DetectorOffsetY / DetectorPixelSizeY                     (exact)
    u0_px = (cols - 1) / 2 + (shift - DetectorOffsetX) / DetectorPixelSizeX
    shift = ObjectOffsetX * SrcToDetector / SrcToObject   (or the mean CentreOfRotation)

``v0_px`` is where the ray perpendicular to the detector hits it. ctpipe has no separate
centre of rotation, so ``u0_px`` is the column the rotation axis projects to, and the source is
taken to lie on the perpendicular through the axis: exact when the axis offset is zero, else
the usual approximation that neglects a detector yaw of ``atan(ObjectOffsetX / SrcToObject)``
(0.05 deg in the real file above). A note gives the offset whenever it is not zero.

A tilted axis (``CentreOfRotationTop != CentreOfRotationBottom``, or ``ObjectRoll`` /
``ObjectTilt`` not zero) cannot be represented: the reader takes the mean of top and bottom
(CIL's ``ObjectOffsetX`` for such files) and adds a note with how far the axis leans, in pixels,
between the top and bottom rows. Refusing would turn away every older scan whose two values
differ at all, however little; the estimate degrades with the lean, and the note says how much.

What is unclear
---------------
* Whether ``.ang`` values include ``InitialAngle`` (taken: they do not, like ``_ctdata.txt``;
  every real ``.ang`` here has ``InitialAngle=0``), and whether a real ``.ang`` numbers its lines
  ``1:`` or ``0001:`` (both are read).
* Whether an ``.ang`` of a scan with a negative ``AngularStep`` runs against it too (taken: the
  sense is measured from each file's values, so either reads right).
* ``DetectorOffsetX``'s sign and use: the current CIL ignores it, the one of 2022 used it as
  above, TIGRE passes it to ``offDetector`` unsigned and says it is untested.
* ``Scattering``: CT Pro subtracts ``WhiteLevel * Scattering / 100`` in some way before the
  log (CCPi's early Python ``Xtek`` reader did so); ctpipe does not, and says so in a note.
* Which way the real turntable turns (the chirality of a reconstruction): it does not matter
  here, see above, but nothing public states it.

Public readers used as anchors: CIL ``NikonDataReader`` (current and of 2022), its test
``Wrappers/Python/test/test_io.py`` and its predecessor of 2019; CCPi ``XtekReader``; TIGRE
``NikonDataLoader`` and CERN/TIGRE#418; OMEGA ``loadNikonData``; real files in
xray-imaging/meta-cli ``docs/source/demo/nikon/`` (CT Pro 5.4) and igrega348/nerf_data
``experimental/`` (XT H), read value by value in ``tests/io/test_real_nikon.py``.
"""

from __future__ import annotations

import configparser
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ctpipe.errors import ConfigError, InputError
from ctpipe.geometry import Geometry
from ctpipe.hookspecs import hookimpl
from ctpipe.io.scans import ScanFiles, ViewFiles, ViewStack, check_angles

__all__ = ["open_nikon", "write_nikon_angles", "read_xtekct"]

_SECTION = "XTekCT"
_CTDATA = "_ctdata.txt"
_ANG_HEADER = "Proj\tAngle(deg)"
_CTDATA_HEADERS = ("Projections\tFrames\tExposure(ms)", "Projection\tAngle(deg)\tTime(s)")
#: The sense of a log whose values do not move: the ``.ang`` files of Nikon XT H scans run
#: against ``AngularStep`` (0, -1.406, ..., -359.999 for a step of +1.40625), ``_ctdata.txt``
#: with it (0.5613, 1.2693, ..., 360.5835 for +0.7031701); see the module docstring.
_ANG_SENSE, _CTDATA_SENSE = -1, 1


# --------------------------------------------------------------------------- reading


def detect(path: Path) -> bool:
    """A ``.xtekct`` file, or a folder holding one (names only, nothing is read)."""
    path = Path(path)
    try:
        if path.is_file():
            return path.suffix.lower() == ".xtekct"
        return path.is_dir() and any(p.suffix.lower() == ".xtekct" and p.is_file() for p in path.iterdir())
    except OSError:
        return False


def _xtekct_file(path: Path) -> tuple[Path, tuple[str, ...]]:
    """The ``.xtekct`` to read, and notes on any others beside it.

    CT Pro saves one ``.xtekct`` per reconstruction of a scan (``<Name>.xtekct``,
    ``<Name>_01.xtekct``, ... as in the real Lego scan of xray-imaging/meta-cli): they differ
    only in their ``Output*`` keys, so any of them describes the acquisition; ``<Name>.xtekct``
    is read. Files that disagree on anything else are different scans, and the user must choose.
    """
    if path.is_file():
        if path.suffix.lower() != ".xtekct":
            raise InputError(f"{path}: not a Nikon .xtekct file")
        return path, ()
    found = sorted(p for p in path.iterdir() if p.suffix.lower() == ".xtekct" and p.is_file())
    if not found:
        raise InputError(f"{path}: no .xtekct file in this folder, so not a Nikon scan")
    if len(found) == 1:
        return found[0], ()
    try:
        acquisitions = [{k: v for k, v in read_xtekct(p).items() if not k.startswith("Output")} for p in found]
    except (ConfigError, InputError):
        acquisitions = [{}, None]
    if any(a != acquisitions[0] for a in acquisitions[1:]):
        raise InputError(f"{path}: holds {len(found)} .xtekct files ({', '.join(p.name for p in found)}) of "
                         "different scans; open the one you mean")
    named = [p for p in found if p.stem == acquisitions[0].get("Name")]
    chosen = named[0] if named else found[0]
    others = ", ".join(p.name for p in found if p != chosen)
    return chosen, (f"{others} beside {chosen.name}: the same acquisition (only their Output* keys differ, "
                    f"another reconstruction); {chosen.name} is read",)


def read_xtekct(file: str | Path) -> dict[str, str]:
    """The ``[XTekCT]`` section of ``file`` as a dict of strings (keys as written).

    Raises
    ------
    InputError
        The file cannot be read.
    ConfigError
        It is not an INI file or has no ``[XTekCT]`` section.
    """
    file = Path(file)
    try:
        text = file.read_text(encoding="utf-8-sig", errors="replace")
    except OSError as exc:
        raise InputError(f"{file}: cannot be read: {exc.strerror or exc}") from None
    parser = configparser.ConfigParser(delimiters=("=",), interpolation=None, strict=False,
                                       comment_prefixes=(";", "#"), inline_comment_prefixes=None)
    parser.optionxform = str  # keys keep their case: SrcToObject, not srctoobject
    try:
        parser.read_string(text, source=str(file))
    except configparser.Error as exc:
        first = " ".join(str(exc).split())[:160]
        raise ConfigError(f"{file}: not a readable .xtekct (INI) file ({type(exc).__name__}: {first})") from None
    section = next((s for s in parser.sections() if s.lower() == _SECTION.lower()), None)
    if section is None:
        raise ConfigError(f"{file}: no [{_SECTION}] section, so not a Nikon .xtekct file")
    return {key: value.strip() for key, value in parser[section].items()}


#: Marks a key that has no default: its absence is an error.
_REQUIRED = object()


class _Keys:
    """Typed, checked access to the [XTekCT] keys; errors name the file and the key."""

    def __init__(self, file: Path, values: Mapping[str, str]) -> None:
        self.file, self.values, self.used = file, values, {}

    def _raw(self, key: str, default: Any) -> str | None:
        value = self.values.get(key)
        if value is None or value == "":
            if default is _REQUIRED:
                raise ConfigError(f"{self.file}: [{_SECTION}] {key}: missing")
            return None
        self.used[key] = value
        return value

    def number(self, key: str, default: Any = None, *, positive: bool = False, unit: str = "") -> float:
        value = self._raw(key, default)
        if value is None:
            return default
        try:
            number = float(value)
        except ValueError:
            number = math.nan
        if not math.isfinite(number) or (positive and number <= 0):
            what = "a finite number > 0" if positive else "a finite number"
            raise ConfigError(f"{self.file}: [{_SECTION}] {key}: must be {what}{f' ({unit})' if unit else ''}, "
                              f"got {value!r}")
        return number

    def integer(self, key: str, default: Any = None) -> int:
        value = self._raw(key, default)
        if value is None:
            return default
        try:
            number = int(value)
        except ValueError:
            number = 0
        if number < 1:
            raise ConfigError(f"{self.file}: [{_SECTION}] {key}: must be an integer >= 1, got {value!r}")
        return number

    def text(self, key: str, default: Any = None) -> str | None:
        value = self._raw(key, default)
        return default if value is None else value



def _parse(file: Path) -> dict[str, Any]:
    """Everything the .xtekct says, checked and in ctpipe's terms (no projection is read)."""
    keys = _Keys(file, read_xtekct(file))
    sod = keys.number("SrcToObject", _REQUIRED, positive=True, unit="mm")
    sdd = keys.number("SrcToDetector", _REQUIRED, positive=True, unit="mm")
    cols = keys.integer("DetectorPixelsX", _REQUIRED)
    rows = keys.integer("DetectorPixelsY", _REQUIRED)
    pitch_u = keys.number("DetectorPixelSizeX", _REQUIRED, positive=True, unit="mm")
    pitch_v = keys.number("DetectorPixelSizeY", _REQUIRED, positive=True, unit="mm")
    n_views = keys.integer("Projections", _REQUIRED)
    initial = keys.number("InitialAngle", _REQUIRED, unit="deg")
    step = keys.number("AngularStep", _REQUIRED, unit="deg")
    white = keys.number("WhiteLevel", _REQUIRED, positive=True)
    offset_u = keys.number("DetectorOffsetX", 0.0, unit="mm")
    offset_v = keys.number("DetectorOffsetY", 0.0, unit="mm")
    object_offset = keys.number("ObjectOffsetX", None, unit="mm")
    cor_top = keys.number("CentreOfRotationTop", 0.0, unit="mm")
    cor_bottom = keys.number("CentreOfRotationBottom", 0.0, unit="mm")
    roll = keys.number("ObjectRoll", 0.0, unit="deg")
    tilt = keys.number("ObjectTilt", 0.0, unit="deg")
    object_offset_y = keys.number("ObjectOffsetY", 0.0, unit="mm")
    scattering = keys.number("Scattering", 0.0, unit="%")
    name = keys.text("Name", _REQUIRED)
    input_name = keys.text("InputName", name)
    # A missing InputSeparator is CT Pro's "_"; one written empty means none.
    separator = keys.values.get("InputSeparator", "_")
    keys.used["InputSeparator"] = separator
    digits = keys.integer("InputDigits", 4)
    input_folder = keys.text("InputFolderName", "")

    notes = []
    centre_u, centre_v = (cols - 1) / 2.0, (rows - 1) / 2.0
    if object_offset is not None:
        shift_mm = object_offset * sdd / sod
        source = f"ObjectOffsetX={object_offset:g} mm"
    else:
        shift_mm = (cor_top + cor_bottom) / 2.0
        source = f"CentreOfRotationTop/Bottom={cor_top:g}/{cor_bottom:g} mm"
        if cor_top != cor_bottom:
            lean_px = (cor_top - cor_bottom) / pitch_u
            notes.append(f"CentreOfRotationTop={cor_top:g} mm and CentreOfRotationBottom={cor_bottom:g} mm differ: the "
                         f"rotation axis leans by {lean_px:+.2f} px between the top and bottom rows; ctpipe models a "
                         "vertical axis and uses their mean")
    u0 = centre_u + (shift_mm - offset_u) / pitch_u
    v0 = centre_v + offset_v / pitch_v
    if shift_mm != 0.0:
        yaw = math.degrees(math.atan(shift_mm / sdd))  # = atan(axis offset at the object / SrcToObject)
        notes.append(f"{source} puts the rotation axis at column {u0:.2f}, used as the principal point u0_px; the "
                     f"source is taken to lie on the perpendicular through the axis (a detector yaw of {yaw:.3g} deg "
                     "is neglected)")
    if roll != 0.0 or tilt != 0.0:
        notes.append(f"ObjectRoll={roll:g} deg and ObjectTilt={tilt:g} deg (a tilted rotation axis) are not modelled; "
                     "ctpipe assumes a vertical axis")
    if object_offset_y != 0.0:
        notes.append(f"ObjectOffsetY={object_offset_y:g} mm is not modelled")
    if scattering != 0.0:
        notes.append(f"Scattering={scattering:g} % is not subtracted; the views are -log(I / WhiteLevel)")
    try:
        geometry = Geometry(sod, sdd, cols, rows, pitch_u, pitch_v, u0, v0)
    except InputError as exc:
        raise ConfigError(f"{file}: {exc} (from SrcToObject, SrcToDetector, DetectorPixels*, DetectorPixelSize*)") from None
    return {"geometry": geometry, "n_views": n_views, "initial": initial, "step": step, "white": white,
            "name": name, "input_name": input_name, "separator": separator, "digits": digits,
            "input_folder": input_folder, "notes": notes, "used": dict(keys.used)}


def _projection_names(parsed: Mapping[str, Any]) -> list[str]:
    """``Projections + 2`` file names: the views, the closing image, and one that must not exist."""
    pattern = f"{parsed['input_name']}{parsed['separator']}{{:0{parsed['digits']}d}}.tif"
    return [pattern.format(i + 1) for i in range(parsed["n_views"] + 2)]


def _data_folder(file: Path, parsed: Mapping[str, Any]) -> Path:
    folder = file.parent
    sub = parsed["input_folder"]
    if sub:
        candidate = folder / sub.replace("\\", "/")
        if not candidate.is_dir():
            raise InputError(f"{file}: [{_SECTION}] InputFolderName={sub!r}: no such folder beside the .xtekct")
        folder = candidate
    return folder


def _check_projection_files(file: Path, folder: Path, names: list[str], shape: tuple[int, int]) -> int:
    """How many images the scan has: ``Projections``, or ``Projections + 1`` with the closing image.

    Every one of the first ``Projections`` files must exist, nothing may follow the closing
    image, and the first must have the detector's size.
    """
    import tifffile

    n_views = len(names) - 2
    for i, name in enumerate(names[:n_views]):
        if not (folder / name).is_file():
            from ctpipe.io.scans import still_being_written_hint

            raise InputError(f"{folder / name}: no such file; {file.name} says Projections={n_views} but projection "
                             f"{i + 1} is missing{still_being_written_hint([folder / n for n in names[:n_views]])}")
    if (folder / names[-1]).is_file():
        raise InputError(f"{folder / names[-1]}: exists, but {file.name} says Projections={n_views}; there must be "
                         f"{n_views} projection files, or {n_views + 1} with the image that closes the turn")
    first = folder / names[0]
    try:
        with tifffile.TiffFile(first) as tif:
            page_shape = tuple(tif.pages[0].shape)
    except Exception as exc:  # noqa: BLE001 (tifffile raises many types for a damaged file)
        raise InputError(f"{first}: not a readable TIFF file ({type(exc).__name__})") from None
    if page_shape != shape:
        raise InputError(f"{first}: must be a {shape[0]} x {shape[1]} image (DetectorPixelsY x DetectorPixelsX in "
                         f"{file.name}), got shape {page_shape}")
    return n_views + 1 if (folder / names[n_views]).is_file() else n_views


def _read_ang(path: Path, n_views: int) -> np.ndarray:
    """Values of ``<Name>.ang``: a header line, then ``<projection>:<TAB><angle>`` numbered from 1."""
    lines = _text_lines(path)
    if not lines or not lines[0].lower().startswith("proj"):
        raise InputError(f"{path}: must start with the header line 'Proj<TAB>Angle(deg)'")
    rows = []
    for number, line in enumerate(lines[1:], start=2):
        fields = line.replace(":", " ").split()
        rows.append(_log_row(path, number, fields, line, "'<projection>:<TAB><angle>'"))
    return _ordered(path, rows, n_views)


def _read_ctdata(path: Path, n_views: int) -> np.ndarray:
    """Values of ``_ctdata.txt``: three header lines, then ``<projection> <angle> <time>`` numbered from 1."""
    lines = _text_lines(path)
    if len(lines) < 3:
        raise InputError(f"{path}: must start with three header lines (Projections Frames Exposure, their values, "
                         "Projection Angle Time)")
    try:
        logged = int(lines[1].split()[0])
    except (IndexError, ValueError):
        raise InputError(f"{path}: line 2 must give the number of projections first, got {lines[1]!r}") from None
    if logged != n_views:
        raise InputError(f"{path}: says {logged} projections but the .xtekct says Projections={n_views}")
    rows = [_log_row(path, number, line.split(), line, "'<projection> <angle> <time>'")
            for number, line in enumerate(lines[3:], start=4)]
    return _ordered(path, rows, n_views)


def _text_lines(path: Path) -> list[str]:
    try:
        text = path.read_text(encoding="utf-8-sig", errors="replace")
    except OSError as exc:
        raise InputError(f"{path}: cannot be read: {exc.strerror or exc}") from None
    return [line.strip() for line in text.splitlines() if line.strip()]


def _log_row(path: Path, number: int, fields: list[str], line: str, layout: str) -> tuple[int, float]:
    try:
        index, angle = int(fields[0]), float(fields[1])
    except (IndexError, ValueError):
        raise InputError(f"{path}: line {number}: expected {layout}, got {line[:60]!r}") from None
    if not math.isfinite(angle):
        raise InputError(f"{path}: line {number}: the angle must be a finite number (degrees), got {fields[1]!r}")
    return index, angle


def _ordered(path: Path, rows: list[tuple[int, float]], n_views: int) -> np.ndarray:
    """The logged values by projection number: ``Projections`` rows, or one more for the closing image."""
    if len(rows) not in (n_views, n_views + 1):
        raise InputError(f"{path}: lists {len(rows)} angles but the .xtekct says Projections={n_views}; there must be "
                         f"one angle for every projection ({n_views}), or {n_views + 1} with the one that closes "
                         "the turn")
    angles = np.full(len(rows), np.nan)
    for index, angle in rows:
        if not 1 <= index <= len(rows):
            raise InputError(f"{path}: projection number {index} is outside 1..{len(rows)}")
        if not np.isnan(angles[index - 1]):
            raise InputError(f"{path}: projection {index} is listed twice")
        angles[index - 1] = angle
    return angles


def _log_sense(values: np.ndarray, step: float, default: int) -> int:
    """+1 when a log's values count like ``AngularStep``, -1 when they count against it.

    Measured from the log itself (the sign of its mean step against ``AngularStep``'s); a log
    that does not move, or a zero step, gets ``default``.
    """
    moved = float(values[-1] - values[0]) if values.size > 1 else 0.0
    if step == 0.0 or moved == 0.0:
        return default
    return 1 if (moved > 0) == (step > 0) else -1


def _sense_words(sense: int) -> str:
    return "counts like AngularStep" if sense > 0 else "counts against AngularStep"


def _recorded_angles(file: Path, parsed: Mapping[str, Any], n_images: int) -> tuple:
    """The recorded angles of every image, the log read, its sense, row count and notes.

    Both logs are read where both exist; ``<Name>.ang`` is the one returned and the two must agree.
    """
    initial, step, n_views = parsed["initial"], parsed["step"], parsed["n_views"]
    ang, ctdata = file.parent / f"{parsed['name']}.ang", file.parent / _CTDATA
    logs = []  # (path, recorded angles, sense, rows)
    for path, read, default in ((ang, _read_ang, _ANG_SENSE), (ctdata, _read_ctdata, _CTDATA_SENSE)):
        if path.is_file():
            values = read(path, n_views)
            sense = _log_sense(values, step, default)
            logs.append((path, initial + sense * values, sense, len(values)))
    if not logs:
        return None, None, None, None, [f"no angle log ({ang.name} or {_CTDATA}) beside {file.name}: the recorded "
                                         "angles are unknown"]
    path, recorded, sense, rows = logs[0]
    notes = [f"recorded angles: {path.name} {_sense_words(sense)} ({_span(recorded - initial, sense)}), read as "
             f"InitialAngle {'+' if sense > 0 else '-'} its values"]
    if len(logs) == 2:
        other, other_recorded = logs[1][0], logs[1][1]
        common = min(len(recorded), len(other_recorded))
        gap = float(np.max(np.abs(recorded[:common] - other_recorded[:common])))
        notes.append(f"{other.name} is read too and agrees with {path.name} within {gap:.4g} deg"
                     + (" (they disagree: check which log belongs to this scan)" if gap > abs(step) / 2 else ""))
    if rows < n_images:
        # The log stops at Projections while the closing image exists: it was taken one turn after view 0.
        recorded = np.append(recorded, recorded[0] + n_views * step)
        notes.append(f"{path.name} has no row for the closing image {n_images}: its recorded angle is taken one "
                     f"turn after view 0's ({n_views} x AngularStep)")
    elif rows > n_images:
        recorded = recorded[:n_images]
        notes.append(f"{path.name} has a row {rows} for an image that closes the turn, which is not in the folder; "
                     "that row is not used")
    return recorded, path, sense, rows, notes


def _span(relative: np.ndarray, sense: int) -> str:
    """``0, -1.406, ..., -359.999``: how a log's values run, in its own sense."""
    values = sense * relative
    values = values + 0.0  # no "-0"
    shown = [f"{v:.4g}" for v in values[:2]] + ["..."] + [f"{values[-1]:.6g}"] if values.size > 3 else \
        [f"{v:.4g}" for v in values]
    return ", ".join(shown)


def open_nikon(path: str | Path) -> ScanFiles:
    """Open a Nikon scan (a folder with one ``.xtekct``, or the ``.xtekct`` itself) lazily.

    Reads the ``.xtekct``, the angle logs and the first projection's TIFF header; the views are
    read on demand. The closing image (``Projections + 1``) is read as the last view, at
    ``InitialAngle + Projections * AngularStep``. See the module docstring for the keys, signs,
    closing image and offsets.

    Raises
    ------
    ConfigError
        The ``.xtekct`` is malformed, lacks a key or has a value out of range.
    InputError
        Missing or extra projection files, a wrong image size, or an angle log that disagrees
        with ``Projections``.
    """

    path = Path(path)
    file, file_notes = _xtekct_file(path)
    parsed = _parse(file)
    geometry, n_views, step = parsed["geometry"], parsed["n_views"], parsed["step"]
    folder = _data_folder(file, parsed)
    names = _projection_names(parsed)
    n_images = _check_projection_files(file, folder, names, geometry.shape)
    nominal = parsed["initial"] + step * np.arange(n_images, dtype=np.float64)
    closing = n_images == n_views + 1

    notes = [*file_notes, *parsed["notes"]]
    if closing:
        notes.append(f"{names[n_views]} is the image that closes the scan: Projections={n_views} and {n_images} images, "
                     f"the last read as a view at InitialAngle + {n_views} x AngularStep, {n_views * step:.6g} deg "
                     "after the first")
    recorded, angle_log, sense, rows, log_notes = _recorded_angles(file, parsed, n_images)
    notes += log_notes
    if recorded is not None:
        recorded = check_angles(recorded, n_images, str(angle_log))
    shape = geometry.shape
    read = ViewFiles(tuple(folder / name for name in names[:n_images]), shape, missing="{file}: no such file",
                     wrong_shape="{file}: must be a {rows} x {cols} image (DetectorPixelsY x DetectorPixelsX in "
                                 "{xtekct}), got shape {got}", context={"xtekct": file.name})
    stack = ViewStack(read, n_images, shape, values="intensities", white_level=parsed["white"], name=str(folder))
    metadata = {"xtekct": str(file), "projection_folder": str(folder),
                "projection_files": f"{parsed['input_name']}{parsed['separator']}%0{parsed['digits']}d.tif",
                "images": n_images, **parsed["used"]}
    if angle_log is not None:
        metadata.update(angle_log_sense=sense, angle_log_rows=rows)
    return ScanFiles("nikon", path, geometry, nominal, stack, recorded_angles_deg=recorded, angle_log=angle_log,
                     notes=tuple(notes), metadata=metadata, closing_view=closing)


# --------------------------------------------------------------------------- writing angle logs


def _float(value: float) -> str:
    """Shortest text that reads back as exactly ``value`` (no exponent: CT Pro parses plain decimals)."""
    return np.format_float_positional(float(value), unique=True, trim="0")


def write_nikon_angles(path: str | Path, angles_deg, *, initial_angle_deg: float | None = None,
                       sense: int = _ANG_SENSE) -> Path:
    """Write a CT Pro angle file (``.ang``) from angles in ctpipe's convention.

    The file has the header ``Proj<TAB>Angle(deg)`` and one line ``<n>:<TAB><angle>`` per
    projection, numbered from 1, the angle counted from the scan's ``InitialAngle`` and, as in
    the ``.ang`` files Nikon XT H scanners write, against the sense of its ``AngularStep``
    (``sense=-1``: 0, -1.406, ... for a step of +1.40625; the module docstring has the
    evidence). To have CT Pro reconstruct with it, name it ``<Name>.ang`` beside the ``.xtekct``
    and set ``AngleFile_Use=True`` in its ``[CTPro]`` section.

    Parameters
    ----------
    path : path
        The file to write, ending in ``.ang``; it must not exist.
    angles_deg : array of shape (V,)
        One angle per projection (the closing image included, if the scan has one), degrees,
        ctpipe's convention, in the frame of the scan's nominal angles
        (``InitialAngle + i * AngularStep``, as :func:`open_nikon` reads them).
    initial_angle_deg : float or None
        The scan's ``InitialAngle``; None reads it from the one ``.xtekct`` in the folder of ``path``.
    sense : {-1, 1}
        -1 writes ``InitialAngle - angle`` (the scanners' ``.ang``), 1 ``angle - InitialAngle``.

    Returns
    -------
    Path of the file written.
    """
    from ctpipe.io.outputs import atomic_write, check_output_file

    path = check_output_file(path, "angle file", suffix=".ang")
    if path.exists():
        raise InputError(f"{path}: exists; write the angles to a new file rather than over the scanner's")
    if sense not in (-1, 1):
        raise InputError(f"sense: must be -1 (against AngularStep, as the scanners write) or 1, got {sense!r}")
    angles = np.asarray(angles_deg, dtype=np.float64)
    if angles.ndim != 1 or angles.size == 0:
        raise InputError(f"angles_deg: must be a 1-D array with one angle per projection, got shape {angles.shape}")
    angles = check_angles(angles, angles.size, "angles_deg")
    if initial_angle_deg is None:
        found = sorted(p for p in path.parent.glob("*") if p.suffix.lower() == ".xtekct" and p.is_file())
        if len(found) != 1:
            raise InputError(f"{path}: initial_angle_deg not given and {len(found)} .xtekct files beside it; give the "
                             "scan's InitialAngle")
        initial_angle_deg = _Keys(found[0], read_xtekct(found[0])).number("InitialAngle", _REQUIRED, unit="deg")
    if not math.isfinite(initial_angle_deg):
        raise InputError(f"initial_angle_deg: must be a finite number (degrees), got {initial_angle_deg!r}")
    values = sense * (angles - initial_angle_deg) + 0.0
    lines = [_ANG_HEADER] + [f"{i + 1}:\t{_float(a)}" for i, a in enumerate(values)]
    text = "\r\n".join(lines) + "\r\n"
    return atomic_write(path, lambda handle: handle.write(text.encode("ascii")))


def _corrected_angle_log(scan: ScanFiles, angles_deg) -> tuple[str, bytes]:
    """``<Name>.ang`` for CT Pro with ``angles_deg`` (ctpipe's convention, the nominal angles' frame).

    It has as many rows as the scanner's own log (a row for the closing image too, taken one
    turn after view 0 when that image is not in the folder) and counts in the sense of the
    scanner's ``.ang`` (:data:`_ANG_SENSE` when the scanner wrote only ``_ctdata.txt``).
    """
    import tempfile

    angles = np.asarray(angles_deg, dtype=np.float64)
    metadata = scan.metadata
    rows = int(metadata.get("angle_log_rows", len(angles)))
    if rows == len(angles) + 1:
        angles = np.append(angles, angles[0] + int(metadata["Projections"]) * float(metadata["AngularStep"]))
    elif rows == len(angles) - 1:
        angles = angles[:rows]
    log = scan.angle_log
    sense = int(metadata["angle_log_sense"]) if log is not None and log.suffix.lower() == ".ang" else _ANG_SENSE
    name = f"{metadata['Name']}.ang"
    with tempfile.TemporaryDirectory() as tmp:
        path = write_nikon_angles(Path(tmp) / name, angles, initial_angle_deg=float(metadata["InitialAngle"]),
                                  sense=sense)
        return name, path.read_bytes()


@hookimpl
def ctpipe_register_formats(registry) -> None:
    registry.add_format("nikon", detect, open_nikon, "a folder with one <Name>.xtekct beside <Name>_0001.tif ... "
                        "(Nikon / X-Tek, CT Pro)", corrected_angle_log=_corrected_angle_log)
