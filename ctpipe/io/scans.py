"""Scans on disk in any format ctpipe reads: detect the format, open the scan, read views on demand.

:func:`open_scan` looks at a path (a folder, or a single file for formats that keep the whole
scan in one), asks every registered scan format whether it is theirs, and returns a
:class:`ScanFiles`: the geometry in ctpipe's names and conventions, the nominal angles, the
angles the scanner logged if it did, and the projections as a :class:`ViewStack`, which reads,
flat/dark-corrects and returns one view at a time. Nothing the size of the whole scan is read
until a caller asks for it, view by view.

Formats are plugins, like stages: every format module (:mod:`ctpipe.io.nikon`, ...) registers
a ``detect(path) -> bool`` and an ``open(path) -> ScanFiles`` through the
``ctpipe_register_formats`` hook, and a third-party package adds its own through the ``ctpipe``
entry-point group (:mod:`ctpipe.hookspecs`). The readers' docstrings and
``docs/real-scans.md`` say which keys they read, how their units and signs become ctpipe's,
and what is left unclear.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ctpipe.errors import InputError
from ctpipe.geometry import Geometry
from ctpipe.images import check_image
from ctpipe.io.flatfield import log_transform, mean_frame

__all__ = ["ViewStack", "ViewFiles", "StackReference", "ScanFiles", "open_scan", "check_angles", "find_bad_views"]


class ViewStack:
    """A projection stack read one view at a time, as float32 line integrals.

    Indexing with an integer reads that view's file(s), checks it, and for intensities applies
    the flat/dark correction of :func:`ctpipe.io.flatfield.log_transform` with the mean flat and
    dark computed once; the arithmetic is the one of correcting the whole stack at once, so a
    view read here is bitwise the view of the corrected stack. ``shape``, ``dtype``, ``ndim`` and
    ``len`` behave like those of the (V, rows, cols) float32 array it stands for, so the pipeline
    takes either. Reads are safe from several threads.

    Parameters
    ----------
    read : callable
        ``read(index) -> ndarray`` of shape (rows, cols): the view as stored (uint16, float32, ...).
    n_views : int
    shape : (rows, cols)
    values : {"intensities", "line_integrals"}
        What ``read`` returns.
    flats, darks : ndarray of shape (F, rows, cols) or (rows, cols), or None
        For intensities: flat fields (required unless ``white_level``) and dark fields.
    white_level : float or None
        For intensities without flat frames: the counts of an unattenuated pixel (the scanner's
        own flat correction scaled its output to this level).
    name : str
        How errors name the stack (usually the folder).
    """

    def __init__(self, read: Callable[[int], np.ndarray], n_views: int, shape: tuple[int, int], *,
                 values: str = "line_integrals", flats=None, darks=None, white_level: float | None = None,
                 name: str = "projections") -> None:
        if values not in ("intensities", "line_integrals"):
            raise InputError(f"{name}: values must be 'intensities' or 'line_integrals', got {values!r}")
        if n_views < 1:
            raise InputError(f"{name}: no projections")
        self._read = read
        self._n_views = int(n_views)
        self._shape = (int(shape[0]), int(shape[1]))
        self.values = values
        self.name = name
        self._flat = self._dark = None
        if values == "intensities":
            if flats is None:
                if white_level is None or not np.isfinite(white_level) or white_level <= 0:
                    raise InputError(f"{name}: intensities need flat fields or a positive white level, got neither")
                flats = np.full(self._shape, float(white_level))
            self._flat = mean_frame(flats, self._shape, f"{name}: flats")
            self._dark = None if darks is None else mean_frame(darks, self._shape, f"{name}: darks")
            # Refuse swapped or mislabelled calibration frames now, not at the first view.
            log_transform(np.zeros((1, *self._shape), np.float32), self._flat, self._dark)
        self._lock = threading.Lock()
        self._source: tuple[str, str] | None = None
        self._views: tuple[int, ...] | None = None

    def opened_from(self, format_name: str, path: str | Path) -> "ViewStack":
        """This stack, marked as the projections of the ``format_name`` scan at ``path``.

        A shallow copy (the views are read through the same function): what :func:`open_scan`
        returns, so that :meth:`reference` can name the scan for another process.
        """
        stack = copy.copy(self)
        stack._source = (str(format_name), str(Path(path).resolve()))
        return stack

    def reference(self) -> "StackReference | None":
        """What reopens this stack in another process: its format and path; None if not opened from disk."""
        if self._source is None:
            return None
        views = None if self._views is None else tuple(self._views)
        return StackReference(*self._source, self.shape, views=views)

    def subset(self, views: Sequence[int]) -> "ViewStack":
        """The stack of ``views`` only (indices into this one, in the order given).

        What a scan with unreadable views is estimated from (:meth:`ScanFiles.without_views`);
        :attr:`view_numbers` says which of the scan's views each one is.
        """
        views = [self._index(int(v)) for v in views]
        if not views:
            raise InputError(f"{self.name}: no views left")
        stack = copy.copy(self)
        stack._read = _Picked(self._read, tuple(views))
        stack._n_views = len(views)
        stack._views = tuple(self.view_numbers[v] for v in views)
        return stack

    @property
    def view_numbers(self) -> tuple[int, ...]:
        """Which of the scan's views each view of this stack is (0, 1, ... unless it is a :meth:`subset`)."""
        return tuple(range(self._n_views)) if self._views is None else self._views

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        del state["_lock"]
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()

    @property
    def shape(self) -> tuple[int, int, int]:
        return (self._n_views, *self._shape)

    ndim = 3
    dtype = np.dtype(np.float32)

    def __len__(self) -> int:
        return self._n_views

    def raw(self, index: int) -> np.ndarray:
        """View ``index`` as stored, checked against the stack's shape."""
        index = self._index(index)
        try:
            view = np.asarray(self._read(index))
        except InputError as exc:
            raise InputError(f"{self._which(index)}: {exc}{_SKIP_HINT}") from None
        except OSError as exc:   # a read error of the disk or the network, a file taken away
            where = exc.filename if exc.filename is not None else self.name
            raise InputError(f"{self._which(index)}: {where}: cannot be read ({exc.strerror or exc}){_SKIP_HINT}") \
                from None
        if view.shape != self._shape:
            raise InputError(f"{self.name}: {self._which(index)} has shape {view.shape}, the others {self._shape}")
        if view.dtype == bool or not (np.issubdtype(view.dtype, np.integer) or np.issubdtype(view.dtype, np.floating)):
            raise InputError(f"{self.name}: {self._which(index)} must hold real numbers, got {view.dtype}")
        return view

    def __getitem__(self, index) -> np.ndarray:
        if isinstance(index, (slice, Sequence, np.ndarray)):
            indices = range(self._n_views)[index] if isinstance(index, slice) else np.asarray(index)
            return np.stack([self[int(i)] for i in indices]) if len(indices) else np.empty((0, *self._shape),
                                                                                            np.float32)
        index = self._index(index)
        raw = self.raw(index)
        if self.values == "intensities":
            view = log_transform(raw[None], self._flat, self._dark)[0]
        else:
            view = raw.astype(np.float32, copy=False)
        check_image(view, name=f"{self.name}: {self._which(index)}")
        return view

    def __iter__(self):
        return (self[i] for i in range(self._n_views))

    def __array__(self, dtype=None, copy=None):
        out = np.empty(self.shape, np.float32)
        for i in range(self._n_views):
            out[i] = self[i]
        return out if dtype is None else out.astype(dtype)

    def _which(self, index: int) -> str:
        """How errors name view ``index``: by its number in the scan."""
        return f"view {index} of {self._n_views}" if self._views is None else f"view {self._views[index]}"

    def _index(self, index) -> int:
        if isinstance(index, (bool, np.bool_)) or not isinstance(index, (int, np.integer)):
            raise InputError(f"{self.name}: a view index must be an integer, got {index!r}")
        if not -self._n_views <= index < self._n_views:
            raise InputError(f"{self.name}: view {index} out of range: the scan has {self._n_views} views")
        return int(index) % self._n_views


_SKIP_HINT = " (ctpipe estimate --skip-bad-views leaves out the views that cannot be read)"


@dataclass(frozen=True)
class _Picked:
    """``read`` of a :meth:`ViewStack.subset`: view ``k`` is view ``picks[k]`` of the stack it was taken from.

    A module-level class, so that the stack pickles.
    """

    read: Callable[[int], np.ndarray]
    picks: tuple[int, ...]

    def __call__(self, index: int) -> np.ndarray:
        return self.read(self.picks[index])


def find_bad_views(stack: ViewStack, *, workers: int | None = None) -> dict[int, str]:
    """The views of ``stack`` that cannot be read, each with the reason: {index: one line}.

    Every view is read (and flat-corrected and checked) once, on ``workers`` threads: a pass
    over the scan before the estimate, which :meth:`ScanFiles.without_views` then leaves the
    bad ones out of.
    """
    from concurrent.futures import ThreadPoolExecutor

    from ctpipe._shared.resources import available_cores

    def reason(index: int) -> str | None:
        try:
            stack[index]
        except InputError as exc:
            return str(exc).removesuffix(_SKIP_HINT)
        return None

    with ThreadPoolExecutor(max_workers=workers or available_cores(), thread_name_prefix="ctpipe-check") as pool:
        reasons = list(pool.map(reason, range(len(stack))))
    return {index: why for index, why in enumerate(reasons) if why is not None}


@dataclass(frozen=True)
class ViewFiles:
    """``read(index)`` of a :class:`ViewStack` whose views are one image file each.

    Every format that stores a file per view reads it the same way: the file must exist, and
    have the scan's shape when ``shape`` is given. Only the wording of the two errors is the
    format's own, so that they name its keys. A module-level class rather than a closure, so
    that the stack pickles.

    Attributes
    ----------
    files : tuple of Path
        One per view, in view order.
    shape : (rows, cols) or None
        None: leave the shape to :meth:`ViewStack.raw`'s check.
    missing : str
        Message for a missing file, formatted with ``file``, ``index``, ``number`` (index + 1),
        ``count`` and the entries of ``context``.
    wrong_shape : str
        Message for an image of another shape, formatted with ``file``, ``rows``, ``cols``,
        ``got`` (the image's shape) and the entries of ``context``.
    context : dict
        More fields for the messages (the settings file's name, ...): passed as values, so a
        brace in a file name is printed, not parsed.
    """

    files: tuple[Path, ...]
    shape: tuple[int, int] | None = None
    missing: str = "{file}: no such file (projection {index} of {count})"
    wrong_shape: str = "{file}: is an image of shape {got} but the scan's views are {rows} x {cols}"
    context: Mapping[str, Any] = field(default_factory=dict)
    stamps: tuple[tuple[int, int] | None, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Each file's size and modification time when the scan was opened: a scan that a scanner
        # is still writing shows as files not there yet, or files that change while they are read.
        stamps = tuple(_stamp(file) for file in self.files)
        object.__setattr__(self, "stamps", stamps)
        absent = [k for k, stamp in enumerate(stamps) if stamp is None]
        age = _newest_age(stamps)
        if absent and age is not None and age < FRESH_S:
            raise InputError(f"{self.files[absent[0]].parent}: is still being written: {len(absent)} of "
                             f"{len(self.files)} view files are not there yet (the first: {self.files[absent[0]].name}) "
                             f"and the newest was written {age:.0f} s ago; run again when the scanner has finished")

    def __call__(self, index: int) -> np.ndarray:
        from ctpipe.io.arrays import read_array

        file = self.files[index]
        before = _stamp(file)
        if before is None:
            raise InputError(self.missing.format(**self.context, file=file, index=index, number=index + 1,
                                                 count=len(self.files)))
        self._check_unchanged(file, self.stamps[index], before)
        try:
            image = read_array(file, kind=".tif")
        except InputError as exc:
            age = time.time() - before[1] / 1e9
            if age < FRESH_S:   # cut short by a copy or a scanner still at it
                raise InputError(f"{exc}; it was written {age:.0f} s ago: the scan may still be being written; run "
                                 f"again when the scanner has finished") from None
            raise
        self._check_unchanged(file, before, _stamp(file))
        if self.shape is not None and image.shape != self.shape:
            raise InputError(self.wrong_shape.format(**self.context, file=file, rows=self.shape[0],
                                                     cols=self.shape[1], got=image.shape))
        return image

    @staticmethod
    def _check_unchanged(file: Path, then: tuple[int, int] | None, now: tuple[int, int] | None) -> None:
        if now == then:
            return
        how = ("appeared" if then is None else "disappeared" if now is None
               else f"grew from {then[0]} to {now[0]} bytes" if now[0] > then[0]
               else f"was rewritten ({then[0]} bytes then, {now[0]} now)")
        raise InputError(f"{file}: {how} since the scan was opened: the scan is being written or replaced while it "
                         f"is read; run again when the scanner has finished")


#: Files younger than this (seconds) may still be being written by the scanner.
FRESH_S = 30.0


def _stamp(file: Path) -> tuple[int, int] | None:
    """(size, modification time in ns) of ``file``, or None if it is not there."""
    try:
        stat = file.stat()
    except OSError:
        return None
    return stat.st_size, stat.st_mtime_ns


def still_being_written_hint(files: Sequence[Path]) -> str:
    """``"; the newest ... was written N s ago: ..."`` when one of ``files`` is fresh, else ``""``.

    For a reader's "missing file" message: a scan whose files are not all there and one of them
    was written moments ago is most likely still being written by the scanner.
    """
    age = _newest_age([_stamp(file) for file in files])
    if age is None or age >= FRESH_S:
        return ""
    return (f"; its newest image was written {age:.0f} s ago: the scan is most likely still being written; run "
            f"again when the scanner has finished")


def _newest_age(stamps) -> float | None:
    """Seconds since the newest of ``stamps`` was modified, or None if none is there."""
    times = [stamp[1] for stamp in stamps if stamp is not None]
    return None if not times else time.time() - max(times) / 1e9


@dataclass(frozen=True)
class StackReference:
    """A scan's projections by name: format, absolute path and (views, rows, cols).

    What a cluster's task carries instead of the images. :meth:`open` reopens the scan with the
    same reader, once per process, so the views it reads are the ones the client would read.
    The path must mean the same files where it is opened: a filesystem shared by the workers.
    """

    format: str
    path: str
    shape: tuple[int, int, int]
    views: tuple[int, ...] | None = None

    def open(self) -> ViewStack:
        """The stack, reopened (and kept for the next task of this process)."""
        try:
            changed = Path(self.path).stat().st_mtime_ns
        except OSError as exc:
            raise InputError(f"{self.path}: cannot be read here ({exc.strerror}); the workers read each scan from its "
                             f"files, which must be on a filesystem they share with the client, at the same path") \
                from None
        stack = _reopened(self.format, self.path, changed)
        if self.views is not None:
            stack = stack.subset(self.views)
        if stack.shape != self.shape:
            raise InputError(f"{self.path}: changed on disk since it was opened: {stack.shape} (views, rows, cols) "
                             f"now, {self.shape} then")
        return stack


@functools.lru_cache(maxsize=4)
def _reopened(format_name: str, path: str, changed_ns: int) -> ViewStack:
    from ctpipe.plugins import get_formats

    formats = get_formats()
    if format_name not in formats:
        raise InputError(f"{path}: format {format_name!r} is not registered in this process (known: "
                         f"{', '.join(formats.names())}); install the plugin that provides it where the workers run")
    return formats[format_name].open(Path(path)).projections


def check_angles(angles, n_views: int, what: str) -> np.ndarray:
    """``angles`` as a (n_views,) float64 array of finite degrees, or an InputError naming ``what``."""
    angles = np.asarray(angles, dtype=np.float64)
    if angles.shape != (n_views,):
        raise InputError(f"{what}: {angles.size} angles for {n_views} projections; there must be one per view")
    if not np.all(np.isfinite(angles)):
        raise InputError(f"{what}: angles must be finite numbers (degrees)")
    return angles


@dataclass(frozen=True, eq=False)
class ScanFiles:
    """A scan on disk, opened: geometry and angles read, projections read on demand.

    Attributes
    ----------
    format : str
        The name of the registered format that read it.
    path : Path
        What was opened (a folder, or the file of a one-file format).
    geometry : Geometry
        In ctpipe's names and conventions (see each format's docstring).
    nominal_angles_deg : ndarray of shape (V,), float64
        The commanded angles in ctpipe's sign convention (a turntable turn of +a is +a).
    projections : ViewStack
        Line integrals, one float32 view per index.
    recorded_angles_deg : ndarray of shape (V,) or None
        The angles the scanner logged per view (its encoder), in ctpipe's convention.
    true_angles_deg : ndarray of shape (V,) or None
        Known only for simulations.
    angle_log : Path or None
        The scanner's own per-view angle file, beside which corrected angles are written.
    notes : tuple of str
        What the reader assumed or could not read, said once in the summary.
    metadata : dict
        The raw keys the reader used, for the report.
    closing_view : bool
        The last view is the image a scanner saves to close the scan (Nikon and Waygate save
        ``Projections + 1`` images of a full turn), nominally one turn after view 0 (361.03 deg
        in a real CT Pro scan whose step does not divide 360). It is read as a view like the
        others; the pair graph pairs it with the view one turn before it
        (:func:`ctpipe.solve.turn_pairs`), so the whole turn is measured from the images.
    skipped_views : dict of int -> str
        Views left out because they could not be read (:meth:`without_views`), by their number
        in the scan, with the reason; the arrays above then hold the other views only.
    whole : ScanFiles or None
        With skipped views: the scan as opened, every view in it.
    """

    format: str
    path: Path
    geometry: Geometry
    nominal_angles_deg: np.ndarray
    projections: ViewStack
    recorded_angles_deg: np.ndarray | None = None
    true_angles_deg: np.ndarray | None = None
    angle_log: Path | None = None
    notes: tuple[str, ...] = ()
    metadata: Mapping[str, Any] = field(default_factory=dict)
    closing_view: bool = False
    skipped_views: Mapping[int, str] = field(default_factory=dict)
    whole: "ScanFiles | None" = None

    @property
    def n_views(self) -> int:
        return len(self.projections)

    @property
    def view_numbers(self) -> tuple[int, ...]:
        """Which of the scan's views each view here is: 0, 1, ... unless views were skipped."""
        return self.projections.view_numbers

    def without_views(self, bad: Mapping[int, str]) -> "ScanFiles":
        """The scan without the views ``bad`` ({index: why}, e.g. from :func:`find_bad_views`).

        The projections, nominal, logged and true angles keep the other views; a closing view
        stays one if it is kept. A note names how many were left out and why the first was.

        Raises
        ------
        InputError
            Fewer than two views would be left.
        """
        if not bad:
            return self
        keep = [k for k in range(self.n_views) if k not in bad]
        first = min(bad)
        if len(keep) < 2:
            raise InputError(f"{self.path}: {len(bad)} of {self.n_views} views cannot be read, e.g. {bad[first]}; "
                             f"too few are left to estimate from")
        numbers = [self.view_numbers[k] for k in sorted(bad)]
        listed = ", ".join(map(str, numbers[:12])) + (", ..." if len(numbers) > 12 else "")

        def pick(values):
            return None if values is None else np.asarray(values)[keep]

        note = (f"{len(bad)} of {self.n_views} views could not be read and are left out (--skip-bad-views): "
                f"view{'s' if len(bad) > 1 else ''} {listed}; the first: {bad[first]}")
        return dataclasses.replace(
            self, projections=self.projections.subset(keep), nominal_angles_deg=pick(self.nominal_angles_deg),
            recorded_angles_deg=pick(self.recorded_angles_deg), true_angles_deg=pick(self.true_angles_deg),
            closing_view=self.closing_view and keep[-1] == self.n_views - 1, notes=(*self.notes, note),
            skipped_views={**self.skipped_views, **{self.view_numbers[k]: why for k, why in bad.items()}},
            whole=self.whole or self)

    def describe(self) -> list[str]:
        """What was read, as the lines a person checks before the long work starts.

        Format and detector, geometry, views (a closing one said as such), the nominal angles,
        the scanner's angle log and which way it runs against the nominal angles, and the
        reader's notes.
        """
        g, nominal = self.geometry, np.asarray(self.nominal_angles_deg, dtype=np.float64)
        views = f"{self.n_views} views"
        if self.closing_view:
            views += (f" ({self.n_views - 1} and the closing view, {nominal[-1] - nominal[0]:g} deg after view 0, "
                      "paired with it)")
        lines = [f"{self.format} scan {self.path}: {views} of {g.detector_rows} x {g.detector_cols} px, "
                 f"pixels {g.pixel_pitch_u_mm:g} x {g.pixel_pitch_v_mm:g} mm",
                 f"geometry: source to axis {g.source_to_object_mm:g} mm, source to detector "
                 f"{g.source_to_detector_mm:g} mm (magnification {g.source_to_detector_mm / g.source_to_object_mm:.4g}), "
                 f"principal point u0 {g.u0_px:.2f} px, v0 {g.v0_px:.2f} px"]
        if nominal.size > 1:
            lines.append(f"nominal angles: {nominal[0]:g} .. {nominal[-1]:g} deg in steps of "
                         f"{float(np.median(np.diff(nominal))):+g} deg")
        recorded = self.recorded_angles_deg
        if recorded is not None and recorded.size > 1:
            log = self.angle_log.name if self.angle_log is not None else "the scanner's log"
            along = np.sign(recorded[-1] - recorded[0]) == np.sign(nominal[-1] - nominal[0])
            difference = recorded - nominal
            lines.append(f"logged angles ({log}): {recorded[0]:g} .. {recorded[-1]:g} deg, "
                         f"{'turning with' if along else 'turning AGAINST'} the nominal ones; logged minus nominal: "
                         f"median {float(np.median(difference)):+.4f} deg, spread {float(np.ptp(difference)):.4f} deg")
        lines += [f"  note: {note}" for note in self.notes]
        return lines


def open_scan(path: str | Path, *, blocked: Sequence[str] = ()) -> ScanFiles:
    """Open the scan at ``path`` in whichever registered format it is.

    The built-in formats are tried first (ctpipe's own folder, then Nikon, Zeiss, Bruker,
    Waygate, NSI, a TIFF stack with a YAML), then those of third-party plugins.

    Parameters
    ----------
    path : str or Path
        A scan folder, or a file for formats that keep a scan in one.
    blocked : sequence of str
        Plugins not to load (``--block-plugin``): a built-in format module such as
        ``ctpipe.io.nikon`` or a third-party entry-point name.

    Raises
    ------
    InputError
        ``path`` does not exist, or no format recognises it (the message lists the formats), or
        the format's files are inconsistent.
    ConfigError
        A format's settings file is malformed.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file or folder")
    from ctpipe.plugins import get_formats

    formats = list(get_formats(blocked=blocked))
    for fmt in formats:
        if fmt.detect(path):
            scan = fmt.open(path)
            return dataclasses.replace(scan, projections=scan.projections.opened_from(fmt.name, path))
    known = "; ".join(f"{f.name}: {f.description}" for f in formats)
    raise InputError(f"{path}: not a scan in any format ctpipe reads ({known})")
