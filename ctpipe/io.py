"""Reading inputs and writing outputs without ever leaving a half-written file."""

from __future__ import annotations

import csv
import io
import json
import os
import tempfile
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np

from ctpipe.errors import InputError

__all__ = ["atomic_write", "write_json", "write_csv", "read_projections", "read_image", "write_keypoints",
           "to_jsonable"]


def atomic_write(path: str | Path, write: Callable[[io.BufferedWriter], None]) -> Path:
    """Write a file through a temporary sibling and rename it into place."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            write(handle)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def to_jsonable(value):
    """Convert numpy scalars/arrays (NaN -> None) inside nested containers for JSON."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, (np.bool_,)):
        return bool(value)
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return None if not np.isfinite(value) else float(value)
    return value


def write_json(path: str | Path, data) -> Path:
    text = json.dumps(to_jsonable(data), indent=2) + "\n"
    return atomic_write(path, lambda h: h.write(text.encode()))


def write_csv(path: str | Path, header: Sequence[str], rows: Iterable[Sequence]) -> Path:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    for row in rows:
        writer.writerow(["" if isinstance(v, float) and not np.isfinite(v) else v for v in row])
    return atomic_write(path, lambda h: h.write(buffer.getvalue().encode()))


def read_projections(path: str | Path) -> np.ndarray:
    """Read a projection stack of shape (views, rows, cols) from ``.npy`` or a multi-page TIFF."""
    array = _read_array(Path(path))
    if array.ndim != 3:
        raise InputError(f"{path}: projections must be a 3-D array (views, rows, cols), got shape {array.shape}")
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


def write_keypoints(path: str | Path, features, *, detector: str, params: dict) -> Path:
    """Write keypoints and descriptors as ``.npz`` with the keys of OpenCV reference files.

    Parameters
    ----------
    path : str or Path
        The ``.npz`` file; written through a temporary sibling and renamed into place.
    features : ctpipe.data.Features
        What the detector returned, N keypoints.
    detector : str
        Registered name of the detector, stored as ``detector``.
    params : dict
        Its parameters, stored as the JSON string ``params``.

    Notes
    -----
    The keys are ``pt`` (N, 2) float32 (x=col, y=row), ``size`` (N,) float32, ``angle`` (N,)
    float32 in degrees with -1 where the detector assigns no orientation (OpenCV's marker;
    :class:`~ctpipe.data.Features` holds NaN there), ``response`` (N,) float32, ``octave`` and
    ``class_id`` (N,) int32, ``descriptors`` (N, D) float32 or uint8, ``norm`` (the distance the
    descriptors are compared with, e.g. ``"L2"``), ``detector`` and ``params``. Strings are
    stored as 0-d unicode arrays, so ``np.load`` needs no pickle.
    """
    angle = np.asarray(features.angle_deg, dtype=np.float32)
    arrays = {
        "pt": np.asarray(features.xy, dtype=np.float32).reshape(-1, 2),
        "size": np.asarray(features.size, dtype=np.float32),
        "angle": np.where(np.isnan(angle), np.float32(-1.0), angle).astype(np.float32),
        "response": np.asarray(features.response, dtype=np.float32),
        "octave": np.asarray(features.octave, dtype=np.int32),
        "class_id": np.asarray(features.class_id, dtype=np.int32),
        "descriptors": np.asarray(features.descriptors),
        "norm": np.array(features.norm),
        "detector": np.array(detector),
        "params": np.array(json.dumps(to_jsonable(params), sort_keys=True)),
    }
    return atomic_write(path, lambda handle: np.savez(handle, **arrays))


def _read_array(path: Path) -> np.ndarray:
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            return np.load(path, allow_pickle=False)
        if suffix in (".tif", ".tiff"):
            import tifffile

            return tifffile.imread(path)
        if suffix == ".png":
            from skimage.io import imread

            return imread(path)
    except (ValueError, OSError) as exc:
        raise InputError(f"{path}: cannot be read as {suffix[1:]}: {exc}") from None
    raise InputError(f"{path}: unsupported file type {suffix!r}; allowed: .npy, .tif, .tiff, .png")
