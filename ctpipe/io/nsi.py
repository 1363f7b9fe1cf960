"""North Star Imaging scans (efX-DR acquisition, efX-CT reconstruction): a ``.nsipro`` project beside its radiographs.

Files
-----
A project folder as efX-CT leaves it, ``<name>`` being the part's name (the real one below:
``Plastic Part 6-5-2024``)::

    <name>.nsipro                  the reconstruction project: tagged text (see below)
    Radiographs-<name>/            the projections, <Object Radiograph> <file>:
        <name>-radio<NNNN>.tif     one TIFF per view, numbered from <Numbering start>
    Corrections/gain0.tif          the detector's gain (bright) image at the scan's tube current
    Corrections/offset.tif         its offset (dark) image
    Corrections/*.defect           defective pixels; not read
    Geometry/geom*.tif             the radiographs of the geometry calibration; not read
    Reconstruction/<name>.nsihdr   the reconstructed volume; not read

The ``.nsipro`` is not XML: every line is ``<tag>value`` (CRLF, no closing tag), and a line
``<tag>`` alone opens a section that ``</tag>`` closes, or is an empty value (``<fixturing>``
in the real file): a ``<tag>`` that no ``</tag>`` closes is read as an empty value. Names
contain blanks (``<source to table distance>``), the same section name recurs at different
depths (``<Detector>`` of the scan and of each calibration image), so keys are looked up by
their path from the root, written here ``<A><B><key>``.

Keys read, and what they become
-------------------------------
=============================================  ======================  ==================================
key (path under <NSI Reconstruction Project>)  ctpipe                  unit and conversion
=============================================  ======================  ==================================
<Geometry><Result><source>, <center>,          source_to_object_mm     mm vectors of efX-CT's calibrated
<reference>, <normal>, <horizontal>, <axis>    source_to_detector_mm   geometry (see below):
                                               u0_px, v0_px            SOD = (center - source) . normal,
                                                                       SDD = (reference - source) . normal
<Object Radiograph><pitch>                     pixel_pitch_u/v_mm      mm, "u v" of the corrected image
<CT Project Configuration><Technique           detector_cols, _rows    pixels of the stored TIFF (width =
Configuration><Detector><width pixels>,                                columns, height = rows), swapped by
<height pixels>                                                        a 90 or 270 deg <Correction>
<Object Radiograph><number>                    number of views         must match the radiographs
<Object Radiograph><angleStep>                 nominal angles          deg: view i at +/- i * angleStep
<Geometry><Processed><clockwise>               sign of the angles      False: +i * angleStep, True: -i ...
<Object Radiograph><file>                      projection files        folder and name with one ``*``,
<Object Radiograph><sort numerically>                                  the view order, numbered from
<CT Project Configuration><Numbering start>                            <Numbering start> (default 0)
<Correction><flipV>, <flipH>, <rotate>         image orientation       applied to every image as read:
                                                                       flips, then <rotate> deg clockwise
<CT Project Configuration><Flat Field Status>  flats, darks            -log((I - offset) / (gain - offset))
<Gain> (the one with <id> 0) <filename>,                               (the files located under the
<Offset><filename>                                                     project folder, see below)
=============================================  ======================  ==================================

Also read, to check or to say what is left out: <Project Folder> (to locate the calibration
images, whose names are absolute Windows paths), <CT Project Configuration> <Rotation range>,
<Number of projections>, <Continuous>, <Technique Configuration><Setup> <source to table
distance> and <source to detector distance> (the nominal distances, kept in the metadata and
compared with the calibrated ones), <Detector><pixel width microns>, <pixel height microns>,
<Computation><radio binning>.

Conventions, and what is unclear
--------------------------------
* **Image coordinates** are ctpipe's: x = column, y = row of the image *after* the
  <Correction> (flips, then ``rotate`` deg clockwise, as displayed with row 0 on top). This
  is how cabouman/mbirjax's NSI reader (``mbirjax/preprocess/nsi.py``, ``load_scans_and_params``)
  orients the radiographs before it uses <reference> and <horizontal>: ``np.flip`` for flipV
  then flipH, then ``np.rot90(..., axes=(2, 1))`` (a clockwise quarter turn) ``rotate // 90``
  times, with <width pixels> and <height pixels> swapped for 90 and 270. That the vectors
  refer to the corrected image is mbirjax's reading, not a documented fact (the real file has
  ``rotate`` 270; its square detector cannot show a swap of width and height). The reader
  refuses vectors whose <axis> does not run along the image columns (``v`` below), which
  ctpipe's upright axis could not represent.
* **Geometry.** The calibrated <Geometry><Result> vectors are used (efX-CT's geometry
  calibration, "10 points used, over 60 views" in the real file), as mbirjax does, not the
  nominal <Setup> distances (382.136 and 774.891 mm there, against 381.851 and 775.533 mm
  calibrated). With ``n`` = <normal>, ``h`` = <horizontal> (unit vectors), ``v = n x h`` (the
  direction of increasing rows, mbirjax's ``r_v``) and <reference> the centre of the corrected
  image's pixel (row 0, col 0) (mbirjax: "vector from origin to first row and column of the
  detector")::

      source_to_object_mm   = (center - source) . n
      source_to_detector_mm = (reference - source) . n
      v0_px = (source - reference) . v / pitch_v                      (exact)
      u0_px = (source - reference) . h / pitch_u + d * SDD / SOD / pitch_u,
      d     = (center - source) . h   (the axis off the central ray, mm at the object)

  ``u0_px`` is the column the rotation axis projects to (ctpipe has no separate centre of
  rotation); with ``d`` not 0 this neglects a detector yaw of ``atan(d / SOD)``, and a note
  says so. In the real file d = 0, u0_px = 711.883 and v0_px = 709.036 (the image centre is
  709.5). mbirjax overwrites the x and y of <reference> with the "Image center" of the
  geometry report (``Geometry Report.rtf``), which it finds more accurate; that report is not
  part of the public file, so ctpipe uses <reference> as it is.
* **Axis lean.** <axis> is not exactly along the columns (real file: -0.000192 per unit,
  0.011 deg, 0.27 px from the top to the bottom row). ctpipe's axis is upright: the lean is
  not modelled and a note gives it; an axis tilted towards the source gets a note too.
* **Angle sign.** No NSI document says which way the table turns relative to the image. The
  anchor is mbirjax: it sets view ``i`` at ``i * angleStep`` deg, negated when
  <Processed><clockwise> is False (``angle_step = -angle_step``, "counter-clockwise
  rotation"), and its cone-beam projector (``mbirjax/cone_beam.py``: ``recon_ijk_to_xyz``
  turns a voxel by ``x = cos(a) x~ - sin(a) y~``, ``y = sin(a) x~ + cos(a) y~``;
  ``geometry_xyz_to_uv_mag`` puts the source at +y with ``u = mag * x``; ``detector_uv_to_mn``
  makes the channel grow with ``u``) moves a point between axis and source towards *smaller*
  columns when its angle grows. In ctpipe a turn of +a moves such a point towards larger
  columns, so ctpipe's angle is minus mbirjax's: ``+i * angleStep`` when clockwise is False
  (the real file: 0, 0.3, ..., 359.7 deg) and ``-i * angleStep`` when True. This holds as long
  as mbirjax's angles and image orientation agree with each other (its reconstructions of real
  NSI scans would be blurred otherwise); it is inferred from its code, not documented by NSI.
* **No start angle, no per-view log.** The ``.nsipro`` gives only <angleStep>: view 0 is at 0
  and ``recorded_angles_deg`` is None. An Equinor script reading NSI ``.nsprg`` projects with
  TIGRE reads a ``positions.txt`` beside the radiographs (and negates it "because Tigre and CT
  disagree"); no such file is public, so it is not read.
* **View order.** The radiographs are the files matching <file> (its ``*`` standing for digits)
  sorted by name, or by number when <sort numerically> is True, and must be numbered
  <Numbering start>, +1, ... without gaps; mbirjax takes the views in name order too
  (``sorted(glob(... '*[0-9].tif'))``). One file more than <number> on a full turn
  (<number> * <angleStep> = 360) is taken as a closing view at the first angle + 360 deg in the
  sense of the steps (``closing_view=True``); the real file does not tell whether efX-DR saves
  one (<Acquire zero position> True may mean it does), so this is accepted rather than
  expected.
* **Flat and dark.** efX-DR records a multi-point gain calibration (<Gain> <id> 0, 1, 2 at 300,
  150 and 30 uA in the real file) and an offset image. Whether the saved radiographs are raw or
  already gain/offset corrected is undocumented. ctpipe does what mbirjax does: line integrals
  ``-log((I - offset) / (gain0 - offset))`` with ``Corrections/gain0.tif`` as the flat and
  ``Corrections/offset.tif`` as the dark, each oriented like the views. mbirjax then subtracts
  a background offset estimated from the edge pixels, which would also absorb a constant
  error of this assumption; ctpipe does not, and says in a note that the assumption is
  mbirjax's. The files are found under the ``.nsipro``'s folder: the <filename> relative to
  <Project Folder> when it lies under it, else ``<its folder's name>/<its name>``.
* **Binning.** <Detector><binning> (2, "2x2 accum") is the panel's own: <width pixels>,
  <pixel width microns> and <Object Radiograph><pitch> (0.3 mm) are already binned, as the
  file's own ``<effective pixel pitch text>0.1479 [mm]`` = 0.3 mm x 382.136 / 774.891 shows.
  <Computation><radio binning> is the reconstruction's; when it is not 1 a note says the
  radiographs are read unbinned.
* **Not modelled, said in the notes:** a continuous (not step) scan, <Rotation range> or
  <Number of projections> disagreeing with <number> x <angleStep>, defective pixels, and a
  nominal <Setup> that differs from the calibration by more than 1 %.

Anchors
-------
* xray-imaging/meta-cli, ``docs/source/demo/nsi/Plastic Part 6-5-2024.nsipro``: a real efX-CT
  2.4.1.3 project of an X5000 with a PerkinElmer XRD 4343 (1200 views, 0.3 deg steps, 1420^2,
  <rotate> 270, <clockwise> False); the key names, sections and values above.
* cabouman/mbirjax, ``mbirjax/preprocess/nsi.py`` (and its predecessor in cabouman/mbircone,
  ``mbircone/preprocess.py``): the keys a working NSI reconstruction reads, the orientation,
  the vectors' meaning, the angle sign and the flat/dark files; ``mbirjax/cone_beam.py`` and
  ``mbirjax/preprocess/utilities.py`` (``read_scan_dir``) for the projector and file order.
* An Equinor TIGRE script found by content in the code index (repository not resolved):
  reads <source to detector distance>, <source to table distance>, <pixel width microns> and
  <width pixels> of an NSI project, ``gain0.tif`` and ``offset.tif`` as flat and dark.
* TomographicImaging/CIL#2125 ("Add North Star Imaging (NSI) Reader", open): CIL has none;
  nor do dxchange, tomopy or TIGRE, so none of them settles the sign.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path, PureWindowsPath

import numpy as np

from ctpipe.errors import ConfigError, InputError
from ctpipe.geometry import Geometry
from ctpipe.hookspecs import hookimpl
from ctpipe.io.scans import ScanFiles, ViewFiles, ViewStack

__all__ = ["open_nsi", "read_nsipro"]

#: Largest ``.nsipro`` read (the real one is 21 kB).
_NSIPRO_MAX_BYTES = 16 << 20
_ROOT = "NSI Reconstruction Project"
_REQUIRED = object()
#: The setup distances may differ from the calibrated ones by this much before a note says so.
_SETUP_TOLERANCE = 0.01
#: An axis leaning by fewer pixels than this over the image height gets no note.
_LEAN_NOTE_PX = 0.05

_CONFIG = ("CT Project Configuration",)
_TECHNIQUE = _CONFIG + ("Technique Configuration",)
_DETECTOR = _TECHNIQUE + ("Detector",)
_RESULT = ("Geometry", "Result")


def detect(path: Path) -> bool:
    """A ``.nsipro`` file, or a folder holding one (names only, nothing is read)."""
    path = Path(path)
    try:
        if path.is_file():
            return path.suffix.lower() == ".nsipro"
        if path.is_dir():
            with os.scandir(path) as entries:
                return any(e.name.lower().endswith(".nsipro") and e.is_file() for e in entries)
    except OSError:
        return False
    return False


# --- the project file ---------------------------------------------------------------------------


@dataclass
class _Node:
    name: str
    value: str
    line: int
    children: list["_Node"] = field(default_factory=list)


def _key(path: Sequence[str]) -> str:
    return "".join(f"<{name}>" for name in path)


def _parse(file: Path) -> _Node:
    """The tag tree of a ``.nsipro`` (see the module docstring), or a ConfigError naming the line."""
    try:
        size = file.stat().st_size
        if size > _NSIPRO_MAX_BYTES:
            raise ConfigError(f"{file}: {size} bytes is too large for an NSI project file "
                              f"(at most {_NSIPRO_MAX_BYTES}; real ones are a few tens of kB)")
        raw = file.read_bytes()
    except OSError as exc:
        raise InputError(f"{file}: cannot be read ({exc.strerror})") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("cp1252", errors="replace")  # efX-CT runs on Windows: ANSI text
    root: _Node | None = None
    stack: list[_Node] = []
    last: _Node | None = None
    for lineno, line in enumerate(text.splitlines(), 1):
        stripped = line.strip()
        if not stripped:
            continue
        if root is not None and not stack:
            raise ConfigError(f"{file}: line {lineno}: {stripped[:60]!r} after </{_ROOT}>")
        if stripped.startswith("</"):
            name = stripped[2:-1] if stripped.endswith(">") else ""
            depth = next((d for d in range(len(stack) - 1, -1, -1) if stack[d].name == name), None)
            if not name or depth is None:
                raise ConfigError(f"{file}: line {lineno}: {stripped[:60]!r} closes no open section")
            while len(stack) > depth + 1:
                _demote(stack.pop(), stack[-1])
            stack.pop()
            last = None
            continue
        if not stripped.startswith("<") or ">" not in stripped:
            if last is None:
                raise ConfigError(f"{file}: line {lineno}: {stripped[:60]!r} is neither <tag>value nor </tag>")
            last.value += "\n" + stripped  # a value that runs over several lines (a comment)
            continue
        close = stripped.index(">")
        name, value = stripped[1:close].strip(), stripped[close + 1:].strip()
        if not name:
            raise ConfigError(f"{file}: line {lineno}: empty tag name in {stripped[:60]!r}")
        inline_end = f"</{name}>"
        closed_inline = value.endswith(inline_end)
        if closed_inline:
            value = value[:-len(inline_end)].strip()
        node = _Node(name, value, lineno)
        if root is None:
            if name != _ROOT:
                raise ConfigError(f"{file}: line {lineno}: starts with <{name}>, not <{_ROOT}>: not an NSI project")
            root = node
            stack.append(node)
            continue
        stack[-1].children.append(node)
        last = node
        if not value and not closed_inline:
            stack.append(node)  # a section, unless no </name> ever closes it
    if root is None:
        raise ConfigError(f"{file}: empty; an NSI project starts with <{_ROOT}>")
    if stack:
        raise ConfigError(f"{file}: ends before </{_ROOT}> (line {stack[-1].line} <{stack[-1].name}> is still open): "
                          f"the file is cut short")
    return root


def _demote(node: _Node, parent: _Node) -> None:
    # A <tag> that nothing closed was an empty value: what followed it belongs to its parent.
    at = next(i for i, child in enumerate(parent.children) if child is node)
    parent.children[at + 1:at + 1] = node.children
    node.children = []


def read_nsipro(file: str | Path) -> dict[str, str]:
    """Every value of an NSI ``.nsipro`` project, by its path (``"<Object Radiograph><number>"``).

    A key that recurs (the ``<Detector>`` of each calibration image, say) keeps its first
    value, the one :func:`open_nsi` reads.

    Raises
    ------
    ConfigError
        The file is not an NSI project (see the module docstring for the syntax).
    """
    values: dict[str, str] = {}

    def walk(node: _Node, path: tuple[str, ...]) -> None:
        for child in node.children:
            key = _key(path + (child.name,))
            if child.children:
                walk(child, path + (child.name,))
            else:
                values.setdefault(key, child.value)

    walk(_parse(Path(file)), ())
    return values


class _Project:
    """Typed access to the keys of a parsed ``.nsipro``; every error names the file and the key."""

    def __init__(self, file: Path) -> None:
        self.file = file
        self.root = _parse(file)
        self.used: dict[str, str] = {}

    def node(self, path: Sequence[str], start: _Node | None = None) -> _Node | None:
        node = self.root if start is None else start
        for name in path:
            node = next((child for child in node.children if child.name == name), None)
            if node is None:
                return None
        return node

    def nodes(self, path: Sequence[str]) -> list[_Node]:
        parent = self.node(path[:-1])
        return [] if parent is None else [child for child in parent.children if child.name == path[-1]]

    def text(self, path: Sequence[str], default=_REQUIRED, start: _Node | None = None,
             prefix: Sequence[str] = ()) -> str | None:
        node = self.node(path, start)
        key = _key(tuple(prefix) + tuple(path))
        if node is None or node.children:
            if default is _REQUIRED:
                what = "a section, not a value" if node is not None else "missing"
                raise ConfigError(f"{self.file}: {key}: {what}")
            return default
        self.used[key] = node.value
        return node.value

    def number(self, path: Sequence[str], default=_REQUIRED, *, positive: bool = False) -> float:
        raw = self.text(path, default)
        if raw is default and default is not _REQUIRED:
            return default
        try:
            value = float(raw)
        except ValueError:
            value = math.nan
        if not math.isfinite(value) or (positive and value <= 0):
            raise ConfigError(f"{self.file}: {_key(path)}: must be a number{' > 0' if positive else ''}, got {raw!r}")
        return value

    def integer(self, path: Sequence[str], default=_REQUIRED, *, minimum: int | None = None) -> int:
        raw = self.text(path, default)
        if raw is default and default is not _REQUIRED:
            return default
        try:
            value = int(raw.strip())
        except ValueError:
            value = None
        if value is None or (minimum is not None and value < minimum):
            bound = "" if minimum is None else f" >= {minimum}"
            raise ConfigError(f"{self.file}: {_key(path)}: must be an integer{bound}, got {raw!r}")
        return value

    def flag(self, path: Sequence[str], default=_REQUIRED) -> bool:
        raw = self.text(path, default)
        if raw is default and default is not _REQUIRED:
            return default
        if raw.strip().lower() not in ("true", "false"):
            raise ConfigError(f"{self.file}: {_key(path)}: must be True or False, got {raw!r}")
        return raw.strip().lower() == "true"

    def vector(self, path: Sequence[str], length: int) -> np.ndarray:
        raw = self.text(path)
        try:
            values = np.array([float(x) for x in raw.split()], dtype=np.float64)
        except ValueError:
            values = np.array([math.nan])
        if values.shape != (length,) or not np.all(np.isfinite(values)):
            raise ConfigError(f"{self.file}: {_key(path)}: must be {length} numbers separated by blanks, got {raw!r}")
        return values


# --- opening a scan -----------------------------------------------------------------------------


def _orient(image: np.ndarray, flip_h: bool, flip_v: bool, quarter_turns: int) -> np.ndarray:
    """``image`` as efX-CT's <Correction> turns it: flipV, flipH, then clockwise quarter turns."""
    if flip_v:
        image = image[::-1, :]
    if flip_h:
        image = image[:, ::-1]
    return np.ascontiguousarray(np.rot90(image, -quarter_turns))


@dataclass(frozen=True)
class _OrientedViews:
    """``read(index)`` of the stack: the stored radiograph, checked, then oriented (picklable)."""

    files: ViewFiles
    flip_h: bool
    flip_v: bool
    quarter_turns: int

    def __call__(self, index: int) -> np.ndarray:
        return _orient(self.files(index), self.flip_h, self.flip_v, self.quarter_turns)


def open_nsi(path: str | Path) -> ScanFiles:
    """Open an NSI efX-CT scan lazily: the project read, projections on demand.

    Parameters
    ----------
    path : str or Path
        The project folder (holding one ``.nsipro``) or the ``.nsipro`` file.

    Returns
    -------
    ScanFiles
        ``format="nsi"``; views oriented as efX-CT's <Correction> says and turned into line
        integrals with the gain and offset images; ``recorded_angles_deg`` is None (the
        project holds no per-view angles); ``closing_view`` when the folder holds one
        radiograph more than <number> on a full turn.

    Raises
    ------
    ConfigError
        The ``.nsipro`` is malformed, misses a key, or holds a value ctpipe refuses.
    InputError
        A radiograph or calibration image is missing, the files disagree with
        <Object Radiograph><number>, or the geometry is impossible.
    """
    path = Path(path)
    nsipro = _find_nsipro(path)
    folder = nsipro.parent
    project = _Project(nsipro)
    notes: list[str] = []

    n_views = project.integer(("Object Radiograph", "number"), minimum=1)
    step = project.number(("Object Radiograph", "angleStep"), positive=True)
    clockwise = project.flag(("Geometry", "Processed", "clockwise"))
    _check_turn(project, n_views, step, notes)

    rotate = project.integer(("Correction", "rotate"), 0)
    if rotate not in (0, 90, 180, 270):
        raise ConfigError(f"{nsipro}: <Correction><rotate>: must be 0, 90, 180 or 270 (degrees), got {rotate}")
    flip_h = project.flag(("Correction", "flipH"), False)
    flip_v = project.flag(("Correction", "flipV"), False)
    stored_cols = project.integer(_DETECTOR + ("width pixels",), minimum=1)
    stored_rows = project.integer(_DETECTOR + ("height pixels",), minimum=1)
    rows, cols = (stored_cols, stored_rows) if rotate in (90, 270) else (stored_rows, stored_cols)

    pitch = project.vector(("Object Radiograph", "pitch"), 2)
    if not np.all(pitch > 0):
        raise ConfigError(f"{nsipro}: <Object Radiograph><pitch>: must be two numbers > 0 (mm), got "
                          f"{project.used['<Object Radiograph><pitch>']!r}")
    pitch_u, pitch_v = float(pitch[0]), float(pitch[1])
    _check_pitch(project, pitch_u, pitch_v, rotate, notes)

    sod, sdd, u0, v0 = _calibrated_geometry(project, pitch_u, pitch_v, rows, notes)
    setup = {"source_to_object_mm": project.number(_TECHNIQUE + ("Setup", "source to table distance"), None),
             "source_to_detector_mm": project.number(_TECHNIQUE + ("Setup", "source to detector distance"), None)}
    for name, calibrated in (("source_to_object_mm", sod), ("source_to_detector_mm", sdd)):
        nominal_mm = setup[name]
        if nominal_mm is not None and abs(nominal_mm - calibrated) > _SETUP_TOLERANCE * calibrated:
            notes.append(f"<Setup> gives {name} = {nominal_mm:g} mm, the calibrated <Geometry><Result> "
                         f"{calibrated:.3f} mm; the calibration is used")
    try:
        geometry = Geometry(source_to_object_mm=sod, source_to_detector_mm=sdd, detector_cols=cols,
                            detector_rows=rows, pixel_pitch_u_mm=pitch_u, pixel_pitch_v_mm=pitch_v, u0_px=u0, v0_px=v0)
    except InputError as exc:
        raise InputError(f"{nsipro}: {exc}") from None

    files, closing = _projection_files(project, folder, n_views, step)
    sign = -1.0 if clockwise else 1.0
    nominal = sign * step * np.arange(len(files), dtype=np.float64)
    if closing:
        notes.append(f"{files[-1].name}: one radiograph more than <Object Radiograph><number>={n_views} on a full "
                     f"turn, read as the closing view at {nominal[-1]:g} deg")

    turns = rotate // 90
    flat_file, dark_file = _calibration_files(project, folder)
    flat, dark = (_orient(_read_calibration(f, (stored_rows, stored_cols), key, nsipro), flip_h, flip_v, turns)
                  for f, key in ((flat_file, _key(_CONFIG + ("Flat Field Status", "Gain", "filename"))),
                                 (dark_file, _key(_CONFIG + ("Flat Field Status", "Offset", "filename")))))
    read = ViewFiles(tuple(files), (stored_rows, stored_cols),
                     missing="{file}: no such file (projection {number} of {count} in {nsipro})",
                     wrong_shape="{file}: must be a {rows} x {cols} image (<height pixels> x <width pixels> in "
                                 "{nsipro}), got shape {got}", context={"nsipro": nsipro})
    try:
        stack = ViewStack(_OrientedViews(read, flip_h, flip_v, turns), len(files), (rows, cols),
                          values="intensities", flats=flat, darks=dark, name=str(files[0].parent))
    except InputError as exc:
        raise InputError(f"{nsipro}: {exc}") from None

    if rotate or flip_h or flip_v:
        notes.append(f"radiographs oriented as <Correction> says (flipV={flip_v}, flipH={flip_h}, then {rotate} deg "
                     f"clockwise) before use, as mbirjax's NSI reader does")
    notes.append(f"angles {'-' if clockwise else '+'}i * <angleStep> for <clockwise>={clockwise} (the sign of "
                 f"mbirjax's NSI reader, reversed to ctpipe's; NSI does not document it); no per-view angle log")
    notes.append(f"line integrals from {flat_file.name} (flat) and {dark_file.name} (dark), as mbirjax does; whether "
                 f"efX-DR saved the radiographs already corrected is undocumented")
    radio_binning = project.integer(("Computation", "radio binning"), 1)
    if radio_binning != 1:
        notes.append(f"<Computation><radio binning>={radio_binning} (efX-CT's reconstruction binning) is not applied: "
                     f"the radiographs are read at their stored size")
    metadata = {"nsipro": str(nsipro), "flat": str(flat_file), "dark": str(dark_file),
                "angle_step_deg": step, "clockwise": clockwise, "correction_rotate_deg": rotate,
                "correction_flip_h": flip_h, "correction_flip_v": flip_v, "setup": setup,
                "settings": dict(project.used)}
    return ScanFiles("nsi", path, geometry, nominal, stack, notes=tuple(notes), metadata=metadata,
                     closing_view=closing)


def _find_nsipro(path: Path) -> Path:
    if path.is_file():
        if path.suffix.lower() != ".nsipro":
            raise InputError(f"{path}: not an NSI .nsipro project file")
        return path
    try:
        found = sorted(Path(e.path) for e in os.scandir(path) if e.name.lower().endswith(".nsipro") and e.is_file())
    except OSError as exc:
        raise InputError(f"{path}: cannot be listed ({exc.strerror})") from None
    if not found:
        raise InputError(f"{path}: no .nsipro file in this folder, so not an NSI scan")
    if len(found) > 1:
        raise InputError(f"{path}: holds {len(found)} .nsipro files ({', '.join(p.name for p in found)}); "
                         f"open the one to read")
    return found[0]


def _check_turn(project: _Project, n_views: int, step: float, notes: list[str]) -> None:
    span = n_views * step
    rotation_range = project.number(_CONFIG + ("Rotation range",), None)
    if rotation_range is not None and not math.isclose(rotation_range, span, rel_tol=1e-6, abs_tol=1e-6):
        notes.append(f"<Rotation range>={rotation_range:g} but <number> x <angleStep> = {span:g} deg; "
                     f"the angles follow <angleStep>")
    projections = project.integer(_CONFIG + ("Number of projections",), None)
    if projections is not None and projections != n_views:
        notes.append(f"<Number of projections>={projections} but <Object Radiograph><number>={n_views}; "
                     f"the radiographs are counted by <number>")
    if project.flag(_CONFIG + ("Continuous",), False):
        notes.append("<Continuous>True: views taken while the table turns, read at i * <angleStep>")


def _check_pitch(project: _Project, pitch_u: float, pitch_v: float, rotate: int, notes: list[str]) -> None:
    width = project.number(_DETECTOR + ("pixel width microns",), None)
    height = project.number(_DETECTOR + ("pixel height microns",), None)
    if width is None or height is None:
        return
    # The detector's width is the stored image's; the pitch is the corrected image's.
    along_u, along_v = (height, width) if rotate in (90, 270) else (width, height)
    if not (math.isclose(along_u / 1000, pitch_u, rel_tol=1e-6) and math.isclose(along_v / 1000, pitch_v, rel_tol=1e-6)):
        notes.append(f"<Object Radiograph><pitch> {pitch_u:g} x {pitch_v:g} mm differs from the detector's "
                     f"<pixel width/height microns> {width:g} x {height:g}; the <pitch> is used")


def _unit(project: _Project, path: Sequence[str]) -> np.ndarray:
    vector = project.vector(path, 3)
    norm = float(np.linalg.norm(vector))
    if norm == 0.0:
        raise ConfigError(f"{project.file}: {_key(path)}: must be a non-zero direction, got {project.used[_key(path)]!r}")
    return vector / norm


def _calibrated_geometry(project: _Project, pitch_u: float, pitch_v: float, rows: int,
                         notes: list[str]) -> tuple[float, float, float, float]:
    """SOD, SDD, u0_px, v0_px from the <Geometry><Result> vectors (see the module docstring)."""
    source = project.vector(_RESULT + ("source",), 3)
    center = project.vector(_RESULT + ("center",), 3)
    reference = project.vector(_RESULT + ("reference",), 3)
    n = _unit(project, _RESULT + ("normal",))
    h = _unit(project, _RESULT + ("horizontal",))
    axis = _unit(project, _RESULT + ("axis",))
    if abs(float(n @ h)) > 1e-3:
        raise ConfigError(f"{project.file}: <Geometry><Result><horizontal>: must be perpendicular to <normal>, "
                          f"got an angle of {math.degrees(math.acos(abs(float(n @ h)))):.3f} deg between them")
    v = np.cross(n, h)
    along_v, along_h, along_n = float(axis @ v), float(axis @ h), float(axis @ n)
    if abs(along_v) < math.cos(math.radians(45.0)):
        raise ConfigError(f"{project.file}: <Geometry><Result><axis>: the rotation axis must run along the corrected "
                          f"image's columns, but it runs {math.degrees(math.acos(min(1.0, abs(along_v)))):.1f} deg "
                          f"from them (v = <normal> x <horizontal>)")
    sod = float((center - source) @ n)
    sdd = float((reference - source) @ n)
    if not sod > 0:
        raise ConfigError(f"{project.file}: <Geometry><Result>: <center> must lie beyond <source> along <normal>, "
                          f"got source to axis {sod:g} mm")
    offset_mm = float((center - source) @ h)
    u0 = float((source - reference) @ h) / pitch_u + offset_mm * sdd / sod / pitch_u
    v0 = float((source - reference) @ v) / pitch_v
    if offset_mm != 0.0:
        notes.append(f"the rotation axis passes {offset_mm:g} mm off the central ray (<center> - <source> along "
                     f"<horizontal>): u0_px is where it projects, the detector yaw of "
                     f"{math.degrees(math.atan2(offset_mm, sod)):.3f} deg this implies is not modelled")
    lean = math.atan2(abs(along_h), abs(along_v))
    lean_px = rows * pitch_v * math.tan(lean) / pitch_u
    if lean_px >= _LEAN_NOTE_PX:
        notes.append(f"<Geometry><Result><axis> leans {math.degrees(lean):.3f} deg from the image columns "
                     f"({lean_px:.2f} px from the top to the bottom row): not modelled")
    if abs(along_n) > 1e-4:
        notes.append(f"<Geometry><Result><axis> tilts {math.degrees(math.asin(min(1.0, abs(along_n)))):.3f} deg "
                     f"towards the source: not modelled")
    return sod, sdd, u0, v0


def _local(project: _Project, folder: Path, value: str, key: str) -> Path:
    """A path written in the project (Windows, absolute or relative) as a path under ``folder``."""
    written = PureWindowsPath(value.strip())
    if not written.is_absolute() and not written.drive and not written.root:
        return folder.joinpath(*written.parts)
    project_folder = project.text(("Project Folder",), None)
    if project_folder:
        try:
            return folder.joinpath(*written.relative_to(PureWindowsPath(project_folder.strip())).parts)
        except ValueError:
            pass
    if len(written.parts) < 2:
        raise ConfigError(f"{project.file}: {key}: {value!r} names no file")
    return folder / written.parent.name / written.name


def _projection_files(project: _Project, folder: Path, n_views: int, step: float) -> tuple[list[Path], bool]:
    """The radiographs in view order, and whether the last one closes the turn."""
    nsipro = project.file
    key = "<Object Radiograph><file>"
    pattern = project.text(("Object Radiograph", "file"))
    written = _local(project, folder, pattern, key)
    if written.name.count("*") != 1 or "*" in str(written.parent) or "?" in str(written):
        raise ConfigError(f"{nsipro}: {key}: must name the radiographs with one '*' in the file name "
                          f"(as Radiographs-<name>\\<name>-radio*.tif), got {pattern!r}")
    radio_dir = written.parent
    if not radio_dir.is_dir():
        raise InputError(f"{radio_dir}: no such folder ({key} in {nsipro.name})")
    prefix, suffix = written.name.split("*")
    found: list[tuple[int, str]] = []
    with os.scandir(radio_dir) as entries:
        for entry in entries:
            name = entry.name
            # efX-CT runs on Windows, whose file names ignore case.
            if len(name) > len(prefix) + len(suffix) and name.lower().startswith(prefix.lower()) \
                    and name.lower().endswith(suffix.lower()):
                digits = name[len(prefix):len(name) - len(suffix)]
                if digits.isdigit() and digits.isascii():
                    found.append((int(digits), name))
    if not found:
        raise InputError(f"{radio_dir}: no file matches {written.name} ({key} in {nsipro.name}), "
                         f"<Object Radiograph><number>={n_views}")
    numerically = project.flag(("Object Radiograph", "sort numerically"), False)
    found.sort(key=(lambda item: (item[0], item[1])) if numerically else (lambda item: item[1]))
    start = project.integer(_CONFIG + ("Numbering start",), 0, minimum=0)
    widths = {len(name) - len(prefix) - len(suffix) for _, name in found}
    width = widths.pop() if len(widths) == 1 else 0

    def named(number: int) -> Path:
        return radio_dir / f"{prefix}{number:0{width}d}{suffix}"

    present = {number for number, _ in found}
    for i, (number, name) in enumerate(found):
        if number != start + i:
            expected = start + i
            if expected not in present:
                raise InputError(f"{named(expected)}: no such file; <Object Radiograph><number>={n_views} in "
                                 f"{nsipro.name} asks for radiographs {start} .. {start + n_views - 1}")
            raise ConfigError(f"{nsipro}: <Object Radiograph><sort numerically>={numerically} puts {name} at "
                              f"view {i}: the radiographs' numbers must sort in that order (zero-padded names)")
    if len(found) < n_views:
        raise InputError(f"{named(start + len(found))}: no such file; <Object Radiograph><number>={n_views} in "
                         f"{nsipro.name} but only {len(found)} radiographs")
    full_turn = math.isclose(n_views * step, 360.0, rel_tol=0.0, abs_tol=1e-6)
    closing = len(found) == n_views + 1 and full_turn
    if len(found) > n_views and not closing:
        raise InputError(f"{radio_dir / found[n_views][1]}: exists, but <Object Radiograph><number>={n_views} in "
                         f"{nsipro.name} (one more is a closing view only on a full turn of 360 deg)")
    return [radio_dir / name for _, name in found], closing


def _calibration_files(project: _Project, folder: Path) -> tuple[Path, Path]:
    """The gain (<id> 0) and offset images the flat field status names."""
    nsipro = project.file
    status = _CONFIG + ("Flat Field Status",)
    gains = [node for node in project.nodes(status + ("Gain",))
             if project.text(("id",), None, start=node, prefix=status + ("Gain",)) == "0"]
    if not gains:
        raise ConfigError(f"{nsipro}: {_key(status)}<Gain> with <id>0: missing (the gain image that turns the "
                          f"radiographs into line integrals)")
    gain = project.text(("filename",), start=gains[0], prefix=status + ("Gain",))
    offset = project.text(status + ("Offset", "filename"))
    return (_local(project, folder, gain, _key(status + ("Gain", "filename"))),
            _local(project, folder, offset, _key(status + ("Offset", "filename"))))


def _read_calibration(file: Path, shape: tuple[int, int], key: str, nsipro: Path) -> np.ndarray:
    from ctpipe.io.arrays import read_array

    if not file.is_file():
        raise InputError(f"{file}: no such file ({key} in {nsipro.name}, looked up under the project's folder)")
    image = read_array(file, kind=".tif")
    if image.shape != shape:
        raise InputError(f"{file}: must be a {shape[0]} x {shape[1]} image (<height pixels> x <width pixels> in "
                         f"{nsipro.name}), got shape {image.shape}")
    return image.astype(np.float64)


@hookimpl
def ctpipe_register_formats(registry) -> None:
    registry.add_format("nsi", detect, open_nsi,
                        "a folder with <name>.nsipro beside Radiographs-<name>/ and Corrections/ (North Star Imaging efX-CT)")
