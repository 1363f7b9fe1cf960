"""Zeiss Xradia scans: the projections, flat and geometry of one ``.txrm`` file.

A Zeiss Xradia (Versa, Context, ...) scan is one OLE compound file (a little file system of
*storages* holding *streams*, [MS-CFB]). ``.txrm`` holds the projections; ``.txm`` holds a
reconstructed volume in the same container and is refused. :func:`open_zeiss` takes the
``.txrm`` file itself, or a folder holding exactly one. Streams are little-endian;
``u4``/``i4`` are 32-bit unsigned/signed integers, ``f4`` 32-bit floats.

Streams read
------------
================================== ===== ============================================================
stream                             type  use
================================== ===== ============================================================
ImageInfo/ImageWidth, ImageHeight  u4    ``detector_cols``, ``detector_rows`` (pixels)
ImageInfo/ImagesTaken              u4    number of views (``NoOfImages``, the planned count, if
                                         absent; fewer taken than planned is noted, more refused)
ImageInfo/DataType                 u4    pixel type of the images: 5 = uint16, 10 = float32
ImageData<k>/Image<i>              --    view ``i - 1`` (``i`` from 1; 100 images per storage,
                                         ``k = ceil(i / 100)``), row-major, ``ImageHeight`` rows
ImageInfo/Angles                   f4[]  the turntable angle logged per view, degrees
                                         (-> ``recorded_angles_deg``, sign unchanged, see below)
ImageInfo/StoRADistance            f4[]  source to rotation axis, mm; ``|first|`` ->
                                         ``source_to_object_mm``
ImageInfo/DtoRADistance            f4[]  rotation axis to detector, mm; ``SOD + |first|`` ->
                                         ``source_to_detector_mm``
ImageInfo/PixelSize                f4    pixel size *at the rotation axis*, um; times
                                         ``SDD / SOD``, in mm -> ``pixel_pitch_u_mm``, ``_v_mm``
AutoRecon/CenterShift              f4    rotation-axis offset of the scanner's reconstruction,
(or ReconSettings/CenterShift)           pixels: ``u0_px = (cols - 1) / 2 - CenterShift``; absent: 0
ReferenceData/Image                --    the flat field (beam, no object): one (rows, cols) image of
                                         ``ReferenceData/DataType`` (or ``.../ImageInfo/DataType``),
                                         usually float32 -> ``flats``
MultiReferenceData/Image<j>        --    their mean (noted) when there is no ``ReferenceData``
ImageInfo/AcquisitionMode          i4    0: projections; anything else is a reconstruction: refused
                                         (so is a ``.txm`` file without this stream)
ImageInfo/XrayGeometry             i4    1: cone beam; anything else (parallel beam) is refused
PositionInfo/AxisNames, AxisUnits  text  NUL-separated motor names and units: the unit of
                                         ``Sample Theta`` (deg or rad) and of ``Source Z`` (that of
                                         the distances: um, mm, cm, m); absent: deg and mm
Alignment/X-Shifts, Y-Shifts       f4[]  per-view image shifts, pixels: not applied (noted if not 0)
ImageInfo/ExpTimes,                f4    exposures of the views and of the reference; a mismatch
ReferenceData/ExpTime                    is noted (the flat is used unscaled, as CIL does)
================================== ===== ============================================================

``ImageInfo/XrayMagnification``, ``ImageInfo/CamPixelSize``, ``ImageInfo/ConeAngle`` and
``ImageInfo/FanAngle`` go to ``metadata`` unused (their exact definitions are not public).

Conventions
-----------
*Angles.* ``ImageInfo/Angles`` is used with its sign: CIL's ``ZEISSDataReader`` passes the
angles unchanged (``dxchange.read_txrm`` converts them to radians) to
``AcquisitionGeometry.set_angles``, with the source at ``-y``, the detector at ``+y`` and the
detector's first column towards ``-x``; CIL's ASTRA conversion
(``Wrappers/Python/cil/plugins/astra/utilities/convert_geometry_to_astra_vec_3D.py``) rotates source and
detector by ``-angle`` about ``+z``, i.e. the object by ``+angle``, which moves points between
the axis and the source towards larger columns: ctpipe's positive sense (``docs/model.md``).
CIL used to negate the angles and stopped because its test on a real file failed with the
negation (TomographicImaging/CIL issue #829). mbirjax
(``mbirjax/preprocess/zeiss.py``) negates them into its own convention, in which a positive
angle moves those points towards smaller channels (``ConeBeamModel.recon_ijk_to_xyz``: source
at ``+y``, channel along ``+x``): the same sense once more. A vertical flip of the images (the
stored images are upside down with respect to Zeiss's XRM Data Explorer, says txrm2tiff)
does not change the sign of a rotation about a vertical axis, so ctpipe reads them as stored.

*Nominal angles.* The file holds no commanded angles: the nominal angles are the evenly spaced
sequence from the first to the last logged angle (said in ``notes``).

*Geometry.* ``ImageInfo/PixelSize`` is the pixel size at the rotation axis (CIL: "really the
voxel size"); CIL makes the detector pixel ``PixelSize * (SOD + ODD) / SOD`` and ctpipe does the
same, so ``pixel_pitch / source_to_detector`` is ``PixelSize / SOD`` whatever the optical
magnification of the Versa's objective (mbirjax's equivalent detector gives the same ratio).
The file says nothing about a vertical offset (mbirjax: "there doesn't appear to be a Zeiss
parameter for detector row offset"): ``v0_px`` is the detector centre.

*Centre of rotation.* ``CenterShift`` is where Zeiss's reconstruction puts the rotation axis,
in pixels from the detector centre; mbirjax turns it into its channel offset with the opposite
sign ("MBIRJAX has the reverse convention"), i.e. the axis projects onto column
``(cols - 1) / 2 - CenterShift``. ctpipe's axis passes through the central ray, so that column
becomes ``u0_px``: the usual approximation, which takes the axis offset for a lateral shift of
the detector (the source is assumed to face the axis). CIL does not use it (its issue #1076).

*Flat correction.* The views are raw counts; ``ReferenceData/Image`` is the flat, and a
``.txrm`` holds no dark frame (CIL divides by the reference alone; mbirjax reads TXRM darks as
zeros), so ``log_transform`` gets flats and no darks.

*Alignment shifts.* ``Alignment/X-Shifts``/``Y-Shifts`` are per-view shifts in pixels that CIL
and txrm2tiff apply by rolling each view (``np.roll``, +x towards larger columns; dxchange
notes the y shifts count upwards); ctpipe reads the views unshifted and says so in ``notes``
when the shifts are not all zero, since they move the features it matches.

Unclear
-------
The unit of the distances is not stated in the file (mm in every reader; mbirjax takes the unit
of the ``Source Z`` motor, which this reader does too). Every reader drops their signs, and none
says which one the scanner stores negative (:func:`ctpipe.testing.write_zeiss`, which writes the
test scans, stores ``StoRADistance`` negative, the source being on the far side of the axis from
the detector). The sign of ``CenterShift`` comes from mbirjax alone, and it may be in the pixels
of a binned reconstruction. When the distances change during the scan, the first values are
used (as CIL does) and a note says so.

Anchors: CIL ``Wrappers/Python/cil/io/ZEISSDataReader.py`` (TomographicImaging/CIL), dxchange
``dxchange/reader.py`` (``read_txrm``, ``read_ole_metadata``), mbirjax
``mbirjax/preprocess/zeiss.py`` (cabouman/mbirjax), txrm2tiff ``src/txrm2tiff/xradia_properties``
and ``txrm/mixins`` (DiamondLightSource/txrm2tiff).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from ctpipe.errors import InputError
from ctpipe.geometry import Geometry
from ctpipe.hookspecs import hookimpl
from ctpipe.io._ole import StreamReader, find_entry
from ctpipe.io.scans import ScanFiles, ViewStack

__all__ = ["open_zeiss"]

#: File name suffixes of Zeiss Xradia files: projections, reconstructions.
SUFFIXES = (".txrm", ".txm")
#: ``ImageInfo/DataType`` codes of image pixels ctpipe reads (XRM_UNSIGNED_SHORT, XRM_FLOAT).
DATA_TYPES = {5: np.dtype("<u2"), 10: np.dtype("<f4")}
_PER_STORAGE = 100
_UNITS_MM = {"um": 1e-3, "µm": 1e-3, "μm": 1e-3, "micron": 1e-3, "microns": 1e-3, "mm": 1.0, "cm": 10.0, "m": 1000.0}
_UNITS_DEG = {"deg": 1.0, "degree": 1.0, "degrees": 1.0, "rad": 180.0 / np.pi, "radian": 180.0 / np.pi,
              "radians": 180.0 / np.pi}
_STREAM = 2  # olefile's STGTY_STREAM


def _image_stream(index: int) -> str:
    """The stream of view ``index`` (from 0): ``ImageData<k>/Image<index + 1>``."""
    return f"ImageData{index // _PER_STORAGE + 1}/Image{index + 1}"


def detect(path: Path) -> bool:
    """A ``.txrm``/``.txm`` file, or a folder (without ``scan.yaml``) holding one."""
    path = Path(path)
    if path.is_file():
        return path.suffix.lower() in SUFFIXES
    if path.is_dir() and not (path / "scan.yaml").exists():
        return any(p.suffix.lower() in SUFFIXES and p.is_file() for p in path.iterdir())
    return False


def _scan_file(path: Path) -> Path:
    if path.is_file():
        return path
    txrm = sorted(p for p in path.iterdir() if p.suffix.lower() == ".txrm" and p.is_file())
    if len(txrm) == 1:
        return txrm[0]
    if txrm:
        raise InputError(f"{path}: holds {len(txrm)} .txrm files ({', '.join(p.name for p in txrm[:4])}); "
                         f"give the one to open")
    txm = sorted(p.name for p in path.iterdir() if p.suffix.lower() == ".txm")
    raise InputError(f"{path}: holds only Zeiss .txm files ({', '.join(txm[:4])}), which are reconstructed "
                     f"volumes; ctpipe needs the .txrm file of the projections")


class _Streams:
    """The small streams of an open file, read and checked, with errors that name the file and stream."""

    def __init__(self, ole, file: Path) -> None:
        self.ole, self.file = ole, file

    def entry(self, key: str):
        entry = find_entry(self.ole, key)
        return entry if entry is not None and entry.entry_type == _STREAM else None

    def raw(self, key: str, required: bool = True) -> bytes | None:
        entry = self.entry(key)
        if entry is None:
            if required:
                raise InputError(f"{self.file}: no {key} stream; a Zeiss .txrm scan has one")
            return None
        try:
            data = self.ole.openstream(key).read()
        except Exception as exc:  # olefile's errors for broken sector chains vary
            raise InputError(f"{self.file}: cannot read {key} ({exc})") from None
        if len(data) != entry.size:
            raise InputError(f"{self.file}: the file ends inside {key} ({len(data)} of its {entry.size} bytes are "
                             f"there)")
        return data

    def scalar(self, key: str, kind: str, required: bool = True):
        data = self.raw(key, required)
        if data is None:
            return None
        size = struct.calcsize(kind)
        if len(data) < size:
            raise InputError(f"{self.file}: {key} must hold a {size}-byte {_KIND_NAMES[kind]}, got {len(data)} bytes")
        value = struct.unpack_from(kind, data)[0]
        if kind == "<f" and not np.isfinite(value):
            raise InputError(f"{self.file}: {key} must be a finite number, got {value}")
        return value

    def floats(self, key: str, count: int, required: bool = True) -> np.ndarray | None:
        """The first ``count`` float32 values of ``key`` as float64 (all of them if it holds more)."""
        data = self.raw(key, required)
        if data is None:
            return None
        values = np.frombuffer(data[:len(data) // 4 * 4], "<f4").astype(np.float64)
        if len(values) < count:
            raise InputError(f"{self.file}: {key} holds {len(values)} values for {count} images; "
                             f"there must be one per image")
        if not np.all(np.isfinite(values[:count])):
            raise InputError(f"{self.file}: {key} must hold finite numbers, got NaN or infinite values")
        return values

    def words(self, key: str) -> list[str] | None:
        data = self.raw(key, required=False)
        if data is None:
            return None
        return [_text(w) for w in data.split(b"\x00") if w.strip()]


_KIND_NAMES = {"<I": "unsigned integer", "<i": "integer", "<f": "float"}


def _text(word: bytes) -> str:
    try:
        return word.decode("utf-8").strip()
    except UnicodeDecodeError:  # Windows software writes "µm" in Latin-1
        return word.decode("latin-1").strip()


def _axis_unit(streams: _Streams, axis: str, table: dict, default: str) -> tuple[float, str | None]:
    """The factor to ctpipe's unit of motor ``axis`` from PositionInfo, and the unit read (None: not stated)."""
    names, units = streams.words("PositionInfo/AxisNames"), streams.words("PositionInfo/AxisUnits")
    if not names or not units:
        return table[default], None
    lowered = [n.lower() for n in names]
    if axis.lower() not in lowered:
        return table[default], None
    index = lowered.index(axis.lower())
    if index >= len(units):
        raise InputError(f"{streams.file}: PositionInfo/AxisUnits lists {len(units)} units for {len(names)} "
                         f"PositionInfo/AxisNames; there must be one per axis")
    unit = units[index]
    if unit.lower() not in table:
        raise InputError(f"{streams.file}: PositionInfo/AxisUnits gives {axis!r} the unit {unit!r}; "
                         f"ctpipe knows {', '.join(table)}")
    return table[unit.lower()], unit


def _reference(streams: _Streams, shape: tuple[int, int], notes: list[str]) -> tuple[np.ndarray, str]:
    """The flat field, ReferenceData/Image or the mean of MultiReferenceData/Image<j>, and where it came from."""
    file = streams.file

    def image(key: str, type_keys: tuple[str, ...]) -> np.ndarray:
        code = type_key = None
        for type_key in type_keys:
            code = streams.scalar(type_key, "<I", required=False)
            if code is not None:
                break
        if code is None:
            raise InputError(f"{file}: no {' or '.join(type_keys)} stream; the pixel type of {key} must be given")
        if code not in DATA_TYPES:
            raise InputError(f"{file}: {type_key} is {code}; ctpipe reads "
                             f"{', '.join(f'{k} ({v})' for k, v in DATA_TYPES.items())}")
        dtype = DATA_TYPES[code]
        data = streams.raw(key)
        if len(data) != shape[0] * shape[1] * dtype.itemsize:
            raise InputError(f"{file}: {key} holds {len(data)} bytes, but a {shape[0]} x {shape[1]} {dtype.name} "
                             f"image (ImageInfo/ImageHeight, ImageWidth) takes {shape[0] * shape[1] * dtype.itemsize}")
        values = np.frombuffer(data, dtype).reshape(shape).astype(np.float32)
        if not np.all(np.isfinite(values)):
            raise InputError(f"{file}: {key} must hold finite numbers, got NaN or infinite values")
        return values

    if streams.entry("ReferenceData/Image") is not None:
        return (image("ReferenceData/Image", ("ReferenceData/DataType", "ReferenceData/ImageInfo/DataType")),
                "ReferenceData/Image")
    frames = []
    while streams.entry(f"MultiReferenceData/Image{len(frames) + 1}") is not None:
        frames.append(image(f"MultiReferenceData/Image{len(frames) + 1}",
                            ("MultiReferenceData/DataType", "MultiReferenceData/ImageInfo/DataType")))
    if not frames:
        raise InputError(f"{file}: no ReferenceData/Image stream (the flat field); ctpipe needs the reference the "
                         f"scanner stored to turn the counts into line integrals")
    notes.append(f"flat field: the mean of the {len(frames)} MultiReferenceData images; the scanner's per-view "
                 f"interpolation between references is not applied")
    return np.mean(frames, axis=0, dtype=np.float64).astype(np.float32), "MultiReferenceData/Image*"


def open_zeiss(path: str | Path) -> ScanFiles:
    """Open a Zeiss ``.txrm`` scan lazily: headers, angles and the flat read, views on demand.

    Parameters
    ----------
    path : path
        The ``.txrm`` file, or a folder holding exactly one.

    Raises
    ------
    InputError
        Not a readable compound file, a ``.txm`` reconstruction or a parallel-beam scan, a
        missing or malformed stream (named), image streams that disagree with the image count
        or size.
    """
    import olefile

    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file or folder")
    file = _scan_file(path)
    try:
        if not olefile.isOleFile(str(file)):
            raise InputError(f"{file}: not an OLE compound file (a Zeiss .txrm is one); it does not start with "
                             f"the compound-file signature")
        ole = olefile.OleFileIO(str(file))
    except InputError:
        raise
    except Exception as exc:  # olefile raises assorted errors on a damaged file
        raise InputError(f"{file}: not a readable OLE compound file ({exc})") from None
    with ole:
        parsed = _parse(_Streams(ole, file))
        reader = StreamReader(ole, file)

    geometry, dtype, entries = parsed["geometry"], parsed["dtype"], parsed["entries"]

    def read(index: int) -> np.ndarray:
        name = _image_stream(index)
        try:
            data = reader.read(*entries[index], name)
        except OSError as exc:
            raise InputError(f"{file}: {exc}") from None  # the message names the stream
        return np.frombuffer(data, dtype).reshape(geometry.shape)

    try:
        stack = ViewStack(read, len(entries), geometry.shape, values="intensities", flats=parsed["flat"],
                          name=str(file))
    except InputError as exc:
        raise InputError(f"{exc} (the flat field is {parsed['flat_key']})") from None
    return ScanFiles("zeiss", file, geometry, parsed["nominal"], stack, recorded_angles_deg=parsed["recorded"],
                     notes=tuple(parsed["notes"]), metadata=parsed["metadata"])


def _parse(s: _Streams) -> dict:
    file, notes = s.file, []
    mode = s.scalar("ImageInfo/AcquisitionMode", "<i", required=False)
    if (mode is not None and mode != 0) or (mode is None and file.suffix.lower() == ".txm"):
        raise InputError(f"{file}: is a Zeiss reconstruction (a volume; ImageInfo/AcquisitionMode "
                         f"{'absent' if mode is None else mode}), not projections; give the .txrm file of the scan")
    beam = s.scalar("ImageInfo/XrayGeometry", "<i", required=False)
    if beam is not None and beam != 1:
        raise InputError(f"{file}: ImageInfo/XrayGeometry is {beam}, a parallel-beam scan; ctpipe's model is "
                         f"cone beam (XrayGeometry 1)")
    cols, rows = s.scalar("ImageInfo/ImageWidth", "<I"), s.scalar("ImageInfo/ImageHeight", "<I")
    taken = s.scalar("ImageInfo/ImagesTaken", "<I", required=False)
    planned = s.scalar("ImageInfo/NoOfImages", "<I", required=False)
    if taken is None and planned is None:
        raise InputError(f"{file}: no ImageInfo/ImagesTaken or ImageInfo/NoOfImages stream; the number of images "
                         f"must be given")
    n_views, count_key = (taken, "ImagesTaken") if taken is not None else (planned, "NoOfImages")
    if planned is not None and taken is not None and taken != planned:
        if taken > planned:
            raise InputError(f"{file}: ImageInfo/ImagesTaken says {taken} images but ImageInfo/NoOfImages {planned}; "
                             f"no more can be taken than planned")
        notes.append(f"{taken} of the {planned} planned images were taken (ImageInfo/ImagesTaken); reading those")
    if n_views < 1:
        raise InputError(f"{file}: ImageInfo/{count_key} is 0; the scan has no images")
    code = s.scalar("ImageInfo/DataType", "<I")
    if code not in DATA_TYPES:
        raise InputError(f"{file}: ImageInfo/DataType is {code}; ctpipe reads "
                         f"{', '.join(f'{k} ({v})' for k, v in DATA_TYPES.items())}")
    dtype = DATA_TYPES[code]
    # The image streams must be there before anything else is read per view.
    entries = []
    for index in range(n_views):
        name = _image_stream(index)
        entry = s.entry(name)
        if entry is None:
            raise InputError(f"{file}: no {name} stream; ImageInfo/{count_key} says {n_views} images")
        if entry.size != rows * cols * dtype.itemsize:
            raise InputError(f"{file}: {name} holds {entry.size} bytes, but a {rows} x {cols} {dtype.name} image "
                             f"(ImageInfo/ImageHeight, ImageWidth, DataType) takes {rows * cols * dtype.itemsize}")
        entries.append((int(entry.isectStart), int(entry.size)))

    degrees, angle_unit = _axis_unit(s, "Sample Theta", _UNITS_DEG, "deg")
    recorded = s.floats("ImageInfo/Angles", n_views)[:n_views] * degrees
    mm, distance_unit = _axis_unit(s, "Source Z", _UNITS_MM, "mm")
    if distance_unit is None:
        notes.append("ImageInfo/StoRADistance and DtoRADistance taken as mm (PositionInfo states no unit for "
                     "Source Z)")
    to_axis = s.floats("ImageInfo/StoRADistance", 1)
    to_detector = s.floats("ImageInfo/DtoRADistance", 1)
    pixel_um = s.scalar("ImageInfo/PixelSize", "<f")
    for key, values in (("ImageInfo/StoRADistance", to_axis), ("ImageInfo/DtoRADistance", to_detector)):
        spread = np.ptp(values[:n_views])
        if spread > 1e-4 * max(abs(values[0]), 1e-12):
            notes.append(f"{key} changes during the scan ({values[:n_views].min():g} to {values[:n_views].max():g}); "
                         f"using the first value, as CIL does")
    sod, odd = abs(to_axis[0]) * mm, abs(to_detector[0]) * mm
    if not pixel_um > 0:
        raise InputError(f"{file}: ImageInfo/PixelSize must be > 0 (um at the rotation axis), got {pixel_um}")
    if not sod > 0:
        raise InputError(f"{file}: ImageInfo/StoRADistance must not be 0 (source to rotation axis), got {to_axis[0]}")
    shift, shift_key = None, None
    for key in ("AutoRecon/CenterShift", "ReconSettings/CenterShift"):
        shift = s.scalar(key, "<f", required=False)
        if shift is not None:
            shift_key = key
            break
    if shift is None:
        notes.append("no AutoRecon/CenterShift or ReconSettings/CenterShift: the rotation axis is taken at the "
                     "detector's centre column")
    pitch = pixel_um / 1000.0 * (sod + odd) / sod
    try:
        geometry = Geometry(sod, sod + odd, cols, rows, pitch, pitch, u0_px=(cols - 1) / 2.0 - (shift or 0.0))
    except InputError as exc:
        raise InputError(f"{file}: ImageInfo/ImageWidth, ImageHeight, StoRADistance, DtoRADistance, PixelSize, "
                         f"{shift_key or 'CenterShift'} make no cone-beam geometry: {exc}") from None

    nominal = recorded.copy() if n_views == 1 else np.linspace(recorded[0], recorded[-1], n_views)
    notes.append("nominal angles: evenly spaced from the first to the last logged angle (ImageInfo/Angles); "
                 "a .txrm keeps no commanded angles")
    shifts = {}
    for axis in ("X", "Y"):
        values = s.floats(f"Alignment/{axis}-Shifts", 0, required=False)  # unused: a short list is no error
        if values is not None:
            shifts[axis] = values[:n_views]
    moved = {axis: float(np.max(np.abs(v))) for axis, v in shifts.items() if np.any(v != 0)}
    if moved:
        notes.append("Alignment/X-Shifts, Y-Shifts are not zero (largest " +
                     ", ".join(f"|{axis.lower()}| {value:.3g} px" for axis, value in moved.items()) +
                     "): per-view image shifts the scanner recorded, which CIL and txrm2tiff apply; "
                     "ctpipe reads the views unshifted")
    flat, flat_key = _reference(s, (rows, cols), notes)
    exposure = s.floats("ImageInfo/ExpTimes", 1, required=False)
    ref_exposure = None
    for key in ("ReferenceData/ExpTime", "ReferenceData/ImageInfo/ExpTimes", "ReferenceData/ImageInfo/ExpTime"):
        ref_exposure = s.floats(key, 1, required=False)
        if ref_exposure is not None:
            break
    if exposure is not None and ref_exposure is not None and abs(exposure[0] - ref_exposure[0]) > 1e-3 * exposure[0]:
        notes.append(f"the reference was exposed {ref_exposure[0]:g} s, the views {exposure[0]:g} s; the flat is used "
                     f"unscaled (as CIL does), which offsets every line integral by the same constant")
    metadata = {
        "file": str(file), "ImageInfo/ImageWidth": cols, "ImageInfo/ImageHeight": rows,
        f"ImageInfo/{count_key}": n_views, "ImageInfo/NoOfImages": planned, "ImageInfo/DataType": code,
        "ImageInfo/StoRADistance": float(to_axis[0]), "ImageInfo/DtoRADistance": float(to_detector[0]),
        "distance_unit": distance_unit or "mm (assumed)", "angle_unit": angle_unit or "deg (assumed)",
        "ImageInfo/PixelSize_um": pixel_um, "CenterShift_px": shift, "CenterShift_stream": shift_key,
        "Alignment/X-Shifts_max_px": moved.get("X", 0.0), "Alignment/Y-Shifts_max_px": moved.get("Y", 0.0),
    }
    for key in ("ImageInfo/XrayMagnification", "ImageInfo/CamPixelSize", "ImageInfo/ConeAngle",
                "ImageInfo/FanAngle"):
        data = s.raw(key, required=False)
        if data is not None and len(data) >= 4:
            metadata[key] = float(np.frombuffer(data[:4], "<f4")[0])
    return {"entries": entries, "dtype": dtype, "geometry": geometry, "recorded": recorded, "nominal": nominal,
            "flat": flat, "flat_key": flat_key, "notes": notes, "metadata": metadata}


@hookimpl
def ctpipe_register_formats(registry) -> None:
    registry.add_format("zeiss", detect, open_zeiss, "a Zeiss Xradia .txrm file (or a folder holding one)")
