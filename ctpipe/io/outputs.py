"""Writing outputs without ever leaving a half-written file: atomic files and folders, JSON, CSV."""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import json
import os
import re
import shutil
import tempfile
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np

from ctpipe.errors import InputError, OutputError

__all__ = ["atomic_write", "write_json", "write_csv", "write_files", "staged_folder", "json_bytes", "csv_bytes",
           "check_output_dir", "check_output_file", "write_keypoints", "keypoints_writer", "to_jsonable", "leftovers"]

#: Held while renames put results in place (and while a replaced scan folder is swapped), so that
#: a program ended by a signal never stops half-way through: :func:`discard_pending` takes it.
COMMIT_LOCK = threading.RLock()
_PENDING: set[Path] = set()
#: Folders made for outputs not yet committed (an ``--out`` that did not exist): removed again, when
#: empty, if the writing fails or the run is stopped.
_MADE: list[Path] = []


def temporary_prefix(target: Path) -> str:
    """The start of a temporary's name beside ``target``: ``.NAME.ctpipe-PID-`` (see :func:`leftovers`)."""
    return f".{target.name}.ctpipe-{os.getpid()}-"


#: A temporary of this program: ``.NAME.ctpipe-PID-RANDOM.tmp`` (``.old``: what a commit moved aside;
#: ``-discarded``: being removed); the process id tells one a killed run left from another run's work.
_TEMPORARY = re.compile(r"^\.(?P<name>.+)\.ctpipe-(?P<pid>\d+)-[^/]+$")
#: The names of earlier versions, without the process id: ``.NAME.RANDOM8.tmp`` or ``.old``.
_TEMPORARY_BEFORE = re.compile(r"^\.(?P<name>.+)\.[a-z0-9_]{8}\.(tmp|old)$")


@contextlib.contextmanager
def pending(path: Path) -> Iterator[Path]:
    """Mark the temporary file or folder ``path`` as being written for the block (see :func:`discard_pending`)."""
    _PENDING.add(path)
    try:
        yield path
    finally:
        _PENDING.discard(path)


def discard_pending(timeout_s: float = 1.0) -> None:
    """Remove every temporary file and folder that writers on other threads are still filling.

    For a program that ends at once on Ctrl-C or SIGTERM while worker threads still run: what
    they have not committed is removed (the targets keep their previous contents), after any
    commit in progress has finished (up to ``timeout_s``; the commits are renames), and so are
    the output folders made for them, now empty.
    """
    locked = COMMIT_LOCK.acquire(timeout=timeout_s)
    try:
        for path in list(_PENDING):
            _remove(path)
        for folder in reversed(list(_MADE)):
            with contextlib.suppress(OSError):
                folder.rmdir()
    finally:
        if locked:
            COMMIT_LOCK.release()


def _remove(path: Path) -> None:
    """Remove a temporary file, or a folder another thread may still be writing files into.

    The folder is renamed first: a writer then finds no folder by its old name and can add
    nothing more (``shutil.rmtree`` on the folder itself raced a writer that kept adding files,
    and left it behind with the last few in it).
    """
    if not path.is_dir() or path.is_symlink():
        path.unlink(missing_ok=True)
        return
    gone = path.with_name(f"{path.name}-discarded")
    try:
        os.rename(path, gone)
    except OSError:
        gone = path
    for _ in range(5):   # a file whose creation was under way at the rename can still appear once
        shutil.rmtree(gone, ignore_errors=True)
        if not gone.exists():
            return


def _make_folders(folder: Path) -> list[Path]:
    """Make ``folder`` and its missing parents; those made, outermost first (registered in ``_MADE``)."""
    missing = []
    for parent in (folder.absolute(), *folder.absolute().parents):
        if parent.exists() or parent.is_symlink():
            break
        missing.append(parent)
    made = []
    for parent in reversed(missing):
        try:
            parent.mkdir()
        except FileExistsError:
            continue    # made by another writer meanwhile: not ours to remove
        made.append(parent)
        _MADE.append(parent)
    return made


@contextlib.contextmanager
def _folders_for(folders: Iterable[Path]) -> Iterator[None]:
    """Make the folders outputs go into for the block; those it made are removed again, if empty, when it fails."""
    made: list[Path] = []
    try:
        for folder in folders:
            made += _make_folders(Path(folder))
        yield
    except BaseException:
        for folder in reversed(made):
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise
    finally:
        for folder in made:
            with contextlib.suppress(ValueError):
                _MADE.remove(folder)


def leftovers(path: str | Path) -> list[Path]:
    """Temporaries that runs killed before they could clean up left beside ``path`` (or, for a folder, in it).

    A SIGKILL, a crash of the machine or a power cut ends a run without its clean-up; what it was
    staging stays, hidden by its leading dot (``.NAME.ctpipe-PID-RANDOM.tmp``). Nothing reads it.
    One whose process is still running is another run's work in progress and is not listed.
    """
    path = Path(path)
    places = [(path.parent, path.name)] + ([(path, None)] if path.is_dir() else [])
    found = []
    for folder, name in places:
        try:
            entries = list(folder.iterdir())
        except OSError:
            continue
        for entry in entries:
            match = _TEMPORARY.match(entry.name)
            if match and (name is None or match["name"] == name) and not _running(int(match["pid"])):
                found.append(entry)
                continue
            before = _TEMPORARY_BEFORE.match(entry.name)
            if not match and before and (name is None or before["name"] == name):
                found.append(entry)
    return sorted(found)


def _running(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True     # someone else's process
    return True


#: The errors of a write that found no room: the device (ENOSPC) or the user's quota (EDQUOT) is full.
_NO_ROOM = {errno.ENOSPC, errno.EDQUOT}
#: Less room than this where a write failed without an errno is a full disk too.
_FULL_BYTES = 1 << 20


@contextlib.contextmanager
def disk_full_is_one_line(target: Path) -> Iterator[None]:
    """Turn "no space left" while ``target`` is written into :class:`OutputError` naming it.

    The writers here stage everything in temporaries and rename them into place only once all
    are written, so a full disk leaves every earlier result as it was; the message says so, with
    the room left where ``target`` goes.
    """
    try:
        yield
    except OSError as exc:
        try:
            free = shutil.disk_usage(_existing_ancestor(Path(target) / "x")).free
        except OSError:
            free = None
        # numpy's tofile (np.save) reports a short write without an errno: "N requested and M written".
        short_write = exc.errno is None and free is not None and free < _FULL_BYTES
        if exc.errno not in _NO_ROOM and not short_write:
            raise
        free = "free space unknown" if free is None else f"{free / 1e6:.1f} MB free there"
        full = "the disk quota is exceeded" if exc.errno == errno.EDQUOT else "no space left on the device"
        raise OutputError(f"{target}: {full} while writing it ({free}); nothing was replaced: make room "
                          f"and run again") from None


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _existing_ancestor(path: Path) -> Path:
    """The nearest of ``path``'s ancestors that exists (``path`` itself is not considered)."""
    parent = path.absolute().parent
    while not parent.exists() and not parent.is_symlink():
        parent = parent.parent
    return parent


def _check_target(path, what: str, kind: str) -> Path:
    if path is None or not str(path).strip():
        raise InputError(f"{what}: empty path; give a {kind} name")
    path = Path(path)
    ancestor = _existing_ancestor(path)
    if not ancestor.is_dir():
        raise InputError(f"{what} {path}: {ancestor} is a file, not a folder; choose a {kind} elsewhere")
    _probe_writable(ancestor, f"{what} {path}: cannot write in {ancestor}")
    return path


def _probe_writable(folder: Path, message: str) -> None:
    """Create and remove a file in ``folder``, or raise ``InputError(message (reason))``.

    os.access says yes to root and to read-only mounts alike; creating a file is the honest test.
    """
    try:
        fd, probe = tempfile.mkstemp(prefix=".ctpipe-probe.", dir=folder)
    except OSError as exc:
        raise InputError(f"{message} ({exc.strerror or exc})") from None
    os.close(fd)
    os.unlink(probe)


def check_output_dir(path, what: str = "--out") -> Path:
    """Raise :class:`InputError` unless result files can be written into the folder ``path``.

    Called before any work, so a typo in an output path costs nothing. ``path`` may be
    missing (it is created with its parents when the results are written) or an existing
    folder; it must not be empty, be a file, lie under a file, or lie somewhere not writable.
    """
    if path is not None and str(path).strip() and Path(path).exists() and not Path(path).is_dir():
        raise InputError(f"{what} {path}: exists and is not a folder")
    path = _check_target(path, what, "folder")
    if path.is_dir():
        _probe_writable(path, f"{what} {path}: cannot write in it")
    return path


def check_output_file(path, what: str = "--out", suffix: str | None = None) -> Path:
    """Raise :class:`InputError` unless the file ``path`` can be written (see :func:`check_output_dir`).

    ``suffix`` (e.g. ``".npz"``), when given, is the one extension allowed, case-insensitive.
    """
    if path is not None and str(path).strip():
        path = Path(path)
        if suffix is not None and path.suffix.lower() != suffix:
            raise InputError(f"{what} {path}: must be a {suffix} file name")
        if path.is_dir():
            raise InputError(f"{what} {path}: is a folder; give a file name")
    return _check_target(path, what, "file")


def _commit(moves: Sequence[tuple[Path, Path]]) -> None:
    """Rename every ``(staged, target)`` pair; on any failure put every target back as it was."""
    for _, target in moves:
        if target.is_dir():
            raise InputError(f"{target}: is a folder; cannot replace it with a file")
    with COMMIT_LOCK:
        _commit_locked(moves)


def _commit_locked(moves: Sequence[tuple[Path, Path]]) -> None:
    done: list[tuple[Path, Path | None]] = []
    try:
        for staged, target in moves:
            saved = None
            if target.exists():
                fd, name = tempfile.mkstemp(prefix=temporary_prefix(target), suffix=".old", dir=target.parent)
                os.close(fd)
                saved = Path(name)
                os.replace(target, saved)
            done.append((target, saved))
            os.replace(staged, target)
    except BaseException:
        for target, saved in reversed(done):
            if saved is not None:
                os.replace(saved, target)
            else:
                target.unlink(missing_ok=True)
        raise
    for _, saved in done:
        if saved is not None:
            saved.unlink(missing_ok=True)


def _stage(path: Path, write: Callable[[io.BufferedWriter], None]) -> Path:
    """Write a temporary sibling of ``path`` with the permissions a plain ``open`` would give."""
    with disk_full_is_one_line(path):
        with COMMIT_LOCK:   # made and registered at once: a signal between the two would leave it
            fd, tmp = tempfile.mkstemp(prefix=temporary_prefix(path), suffix=".tmp", dir=path.parent)
            _PENDING.add(Path(tmp))  # until write_files renames or removes it
        try:
            os.fchmod(fd, 0o666 & ~_umask())
            with os.fdopen(fd, "wb") as handle:
                write(handle)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            _PENDING.discard(Path(tmp))
            raise
    return Path(tmp)


def atomic_write(path: str | Path, write: Callable[[io.BufferedWriter], None]) -> Path:
    """Write a file through a temporary sibling and rename it into place."""
    return write_files({path: write})[0]


def write_files(files: Mapping[str | Path, Callable[[io.BufferedWriter], None]]) -> list[Path]:
    """Write several files all-or-nothing: every one, or none of them and nothing else.

    Each is written to a temporary sibling first; only when all are written are they renamed
    into place, and a failure in a rename puts back the files already replaced.

    Parameters
    ----------
    files : mapping of path -> callable(handle)
        Each callable writes one file's bytes to the binary handle it is given.

    Returns
    -------
    The paths, in the mapping's order.
    """
    staged: list[tuple[Path, Path]] = []
    paths = [Path(path) for path in files]
    # The folders made for the files go again if they fail (and so after their temporaries).
    with disk_full_is_one_line(paths[0] if len(paths) == 1 else paths[0].parent) if paths else \
            contextlib.nullcontext(), _folders_for(dict.fromkeys(path.parent for path in paths)):
        try:
            for path, write in zip(paths, files.values()):
                staged.append((_stage(path, write), path))
            if staged:   # replacing a file first moves the old one aside, under a new name: that can find no room
                _commit(staged)
        finally:
            for tmp, _ in staged:
                tmp.unlink(missing_ok=True)
                _PENDING.discard(tmp)
    return [path for _, path in staged]


@contextlib.contextmanager
def staged_folder(folder: str | Path, what: str = "--out") -> Iterator[Path]:
    """Yield a temporary sibling of ``folder`` to write results in; move them into ``folder`` at the end.

    For writers that take a folder (``write_validate_outputs``): if the ``with`` body raises,
    nothing reaches ``folder``; otherwise every file is moved in all-or-nothing (see
    :func:`write_files`). The temporary folder is removed either way, also on Ctrl-C or SIGTERM
    (which ``ctpipe.cli`` turns into :class:`KeyboardInterrupt`).
    """
    folder = check_output_dir(folder, what)
    with temporary_sibling(folder) as tmp:
        yield tmp
        files = sorted(p for p in tmp.rglob("*") if p.is_file())
        created = not folder.exists()
        with COMMIT_LOCK:
            try:
                for file in files:
                    (folder / file.relative_to(tmp)).parent.mkdir(parents=True, exist_ok=True)
                _commit([(file, folder / file.relative_to(tmp)) for file in files])
            except BaseException:
                if created:
                    shutil.rmtree(folder, ignore_errors=True)
                raise


@contextlib.contextmanager
def temporary_sibling(folder: Path) -> Iterator[Path]:
    """A new folder beside ``folder`` to fill before it (or what is in it) is moved into place.

    Registered as pending (:func:`discard_pending`) while the block runs, and removed at its end
    whatever happened (once moved into place, there is nothing left to remove); a full disk on
    the way is one line naming ``folder`` (:func:`disk_full_is_one_line`).
    """
    with _folders_for([folder.parent]):
        with disk_full_is_one_line(folder), COMMIT_LOCK:  # made and registered at once (see _stage)
            tmp = Path(tempfile.mkdtemp(prefix=temporary_prefix(folder), suffix=".tmp", dir=folder.parent))
            _PENDING.add(tmp)
        try:
            with disk_full_is_one_line(folder):
                yield tmp
        finally:
            _remove(tmp)
            _PENDING.discard(tmp)


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


def json_bytes(data) -> bytes:
    """``data`` as indented UTF-8 JSON (numpy values plain, NaN as null), ending in a newline."""
    return (json.dumps(to_jsonable(data), indent=2) + "\n").encode()


def csv_bytes(header: Sequence[str], rows: Iterable[Sequence]) -> bytes:
    """A CSV table as UTF-8 bytes; non-finite floats are empty cells."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    for row in rows:
        writer.writerow(["" if isinstance(v, float) and not np.isfinite(v) else v for v in row])
    return buffer.getvalue().encode()


def write_json(path: str | Path, data) -> Path:
    text = json_bytes(data)
    return atomic_write(path, lambda h: h.write(text))


def write_csv(path: str | Path, header: Sequence[str], rows: Iterable[Sequence]) -> Path:
    text = csv_bytes(header, rows)
    return atomic_write(path, lambda h: h.write(text))


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
    ``class_id`` (N,) int32, ``descriptors`` (N, D) float32 for float norms (also SIFT's, which
    :class:`~ctpipe.data.Features` holds as uint8) or uint8 for binary ones, ``norm`` (the distance
    the descriptors are compared with, e.g. ``"L2"``), ``detector`` and ``params``, and where the
    detector reports them ``clipped_side`` (N, 2) float32 (:attr:`~ctpipe.data.Features.clipped_side`),
    ``centre_edge_px`` (N,) float32 (:attr:`~ctpipe.data.Features.centre_edge_px`) and ``centre_se_px`` (N,) float32
    (:attr:`~ctpipe.data.Features.centre_se_px`).
    Strings are stored as 0-d unicode arrays, so ``np.load`` needs no pickle.
    """
    return atomic_write(path, keypoints_writer(features, detector=detector, params=params))


def keypoints_writer(features, *, detector: str, params: dict) -> Callable[[io.BufferedWriter], None]:
    """What :func:`write_keypoints` writes, as a callable for :func:`write_files`."""
    angle = np.asarray(features.angle_deg, dtype=np.float32)
    arrays = {
        "pt": np.asarray(features.xy, dtype=np.float32).reshape(-1, 2),
        "size": np.asarray(features.size, dtype=np.float32),
        "angle": np.where(np.isnan(angle), np.float32(-1.0), angle).astype(np.float32),
        "response": np.asarray(features.response, dtype=np.float32),
        "octave": np.asarray(features.octave, dtype=np.int32),
        "class_id": np.asarray(features.class_id, dtype=np.int32),
        # Float norms are written as float32 whatever the Features hold (OpenCV's reference files' type).
        "descriptors": np.asarray(features.descriptors,
                                  dtype=np.uint8 if features.norm.startswith("HAMMING") else np.float32),
        "norm": np.array(features.norm),
        "detector": np.array(detector),
        "params": np.array(json.dumps(to_jsonable(params), sort_keys=True)),
    }
    if features.clipped_side is not None:
        arrays["clipped_side"] = np.asarray(features.clipped_side, dtype=np.float32).reshape(-1, 2)
    for name in ("centre_edge_px", "centre_se_px"):
        if getattr(features, name) is not None:
            arrays[name] = np.asarray(getattr(features, name), dtype=np.float32).reshape(-1)
    return lambda handle: np.savez(handle, **arrays)
