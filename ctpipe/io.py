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

__all__ = ["atomic_write", "write_json", "write_csv", "read_projections", "to_jsonable"]


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
