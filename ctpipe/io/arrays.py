"""Reading projections and images from ``.npy``, TIFF and PNG files, with one-line errors."""

from __future__ import annotations

import contextlib
import logging
import warnings
from pathlib import Path

import numpy as np

from ctpipe.errors import InputError

__all__ = ["read_projections", "read_image", "read_array"]

#: File signatures ("magic bytes") of the formats ctpipe reads, by suffix.
_FORMATS = {".npy": ("npy", (b"\x93NUMPY",)),
            ".tif": ("TIFF", (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")),
            ".tiff": ("TIFF", (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")),
            ".png": ("PNG", (b"\x89PNG\r\n\x1a\n",))}


def read_projections(path: str | Path) -> np.ndarray:
    """Read a projection stack of shape (views, rows, cols) from ``.npy`` or a multi-page TIFF."""
    array = _read_array(Path(path))
    if array.ndim != 3:
        raise InputError(f"{path}: projections must be a 3-D array (views, rows, cols), got shape {array.shape}")
    if array.dtype == bool or not (np.issubdtype(array.dtype, np.integer) or np.issubdtype(array.dtype, np.floating)):
        raise InputError(f"{path}: projections must have an integer or floating dtype, got {array.dtype}")
    return array


def read_image(path: str | Path) -> np.ndarray:
    """Read one 2-D image of shape (rows, cols) from ``.npy``, ``.tif``/``.tiff`` or ``.png``.

    Raises
    ------
    InputError
        Naming the file and what is wrong: missing, unreadable, not 2-D (a colour picture or a
        stack), empty, not numeric, or with NaN/inf pixels (see :func:`ctpipe.images.check_image`).
    """
    from ctpipe.images import check_image

    array = _read_array(Path(path))
    # A colour PNG/TIFF reads as (rows, cols, 3 or 4); say so rather than only "not 2-D",
    # since which grey conversion is right (luminance, one channel) is the user's call.
    if array.ndim == 3 and array.shape[-1] in (3, 4):
        raise InputError(f"{path}: image must be a 2-dimensional grey-level array (rows, cols), got a "
                         f"colour image of shape {array.shape}; convert it to grey first")
    return check_image(array, name=f"{path}: image")


def read_array(path: str | Path, *, kind: str | None = None) -> np.ndarray:
    """Read a whole ``.npy``, TIFF (every page) or PNG file as an ndarray; the one reader of input files.

    Parameters
    ----------
    path : str or Path
    kind : {".npy", ".tif", ".png"} or None
        The format; None takes it from the suffix. Scan folders pass ``".tif"``.

    Returns
    -------
    ndarray
        A TIFF with several pages is stacked to (pages, ...) after checking that every page
        has the first page's shape and dtype.

    Raises
    ------
    InputError
        One line naming the file and what is wrong with it: missing, empty, not the format its
        name says (text named ``.npy``, say), truncated or damaged, holding Python objects
        (``.npy`` is always loaded with ``allow_pickle=False``), or pages of different shapes.
    ctpipe._shared.resources.ResourceError
        The array would not fit in the memory available.
    """
    path = Path(path)
    suffix = (kind or path.suffix).lower()
    if suffix not in _FORMATS:
        raise InputError(f"{path}: unsupported file type {suffix!r}; allowed: .npy, .tif, .tiff, .png")
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    label, magics = _FORMATS[suffix]
    try:
        with path.open("rb") as handle:
            head = handle.read(16)
    except OSError as exc:
        raise InputError(f"{path}: cannot be opened: {exc.strerror or exc}") from None
    if not head:
        raise InputError(f"{path}: is empty (0 bytes), not a {label} file")
    if not head.startswith(magics):
        looks = "; it looks like text" if _is_text(head) else ""
        raise InputError(f"{path}: is not a {label} file (it does not start with the {label} signature{looks})")
    from ctpipe._shared.resources import memory_guard

    try:
        with _quiet_libraries(), memory_guard(f"reading {path}"):
            array = _READERS[label](path)
    except (InputError, MemoryError):
        raise
    # numpy, tifffile and imageio raise many exception types for a damaged file (ValueError,
    # EOFError, struct.error, TiffFileError, IndexError, ...); at this boundary all of them
    # mean the same thing to the user, and their text (one line of it) says which damage.
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"{path}: damaged or truncated {label} file ({_one_line(exc)})") from None
    if array.size == 0 and label != "npy":
        # An empty .npy is a valid (empty) array, reported as such by the caller; an image
        # format without pixels is damaged (tifffile returns shape (0,) for some such files).
        raise InputError(f"{path}: damaged {label} file: it holds no pixels (shape {array.shape})")
    return array


def _read_npy(path: Path) -> np.ndarray:
    from ctpipe._shared.resources import check_fits

    from numpy.lib import format as npy_format

    with path.open("rb") as handle:
        version = npy_format.read_magic(handle)
        read_header = npy_format.read_array_header_1_0 if version == (1, 0) else npy_format.read_array_header_2_0
        shape, _, dtype = read_header(handle)
        offset = handle.tell()
    if dtype.hasobject:
        raise InputError(f"{path}: holds Python objects ({dtype}), which ctpipe never unpickles; save a numeric "
                         "array (e.g. float32)")
    expected = int(np.prod(shape, dtype=object)) * dtype.itemsize
    present = path.stat().st_size - offset
    if present < expected:
        raise InputError(f"{path}: truncated npy file: its header says {dtype} of shape {shape} ({expected} bytes) "
                         f"but it holds {present} bytes of data")
    check_fits(f"reading {path} ({dtype} of shape {shape})", expected, of=None)
    return np.load(path, allow_pickle=False)


def _read_tiff(path: Path) -> np.ndarray:
    import tifffile

    from ctpipe._shared.resources import check_fits

    with tifffile.TiffFile(path) as tif:
        pages = list(tif.pages)
        if not pages:
            raise InputError(f"{path}: damaged TIFF file: it has no pages")
        first = pages[0]
        for i, page in enumerate(pages[1:], start=1):
            if page.shape != first.shape or page.dtype != first.dtype:
                raise InputError(f"{path}: page {i} of {len(pages)} is {page.dtype} of shape {page.shape} but page 0 is "
                                 f"{first.dtype} of shape {first.shape}; every page must have the same shape and dtype")
        if first.dtype is None or not first.shape:
            raise InputError(f"{path}: damaged TIFF file: page 0 has no readable image")
        n_bytes = len(pages) * int(np.prod(first.shape, dtype=object)) * np.dtype(first.dtype).itemsize
        check_fits(f"reading {path} ({len(pages)} pages of {first.dtype} {first.shape})", n_bytes, of=None)
        if len(pages) == 1:
            return first.asarray()
        stack = np.empty((len(pages), *first.shape), first.dtype)
        for i, page in enumerate(pages):
            stack[i] = page.asarray()
        return stack


def _read_png(path: Path) -> np.ndarray:
    import imageio.v3 as iio

    return np.asarray(iio.imread(path, extension=".png"))


_READERS = {"npy": _read_npy, "TIFF": _read_tiff, "PNG": _read_png}


@contextlib.contextmanager
def _quiet_libraries():
    """Silence tifffile's and imageio's logging and warnings: the error we raise says it all."""
    loggers = [logging.getLogger(name) for name in ("tifffile", "imageio", "PIL")]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.CRITICAL + 1)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        for logger, level in zip(loggers, levels):
            logger.setLevel(level)


def _is_text(head: bytes) -> bool:
    try:
        head.decode("utf-8")
    except UnicodeDecodeError:
        return False
    return all(c >= 32 or c in (9, 10, 13) for c in head)


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    text = text if len(text) <= 160 else text[:157] + "..."
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _read_array(path: Path) -> np.ndarray:
    return read_array(path)
