"""Refusing, before allocating, what cannot fit in memory.

A request for a 100,000-view scan or a 1024^3 volume would otherwise run for minutes and end
in numpy's ``MemoryError`` traceback. Every place that allocates in proportion to a size the
user chose estimates the bytes first and calls :func:`check_fits`; :func:`memory_guard` turns
a ``MemoryError`` that slips past the estimate into the same one-line error.
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path

from ctpipe.errors import ResourceError

__all__ = ["available_cores", "available_bytes", "format_bytes", "check_fits", "memory_guard", "release_free_memory",
           "FLOAT32"]


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity, not the machine's total)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        return os.cpu_count() or 1


#: Bytes of one float32 value, the dtype of every stack ctpipe computes.
FLOAT32 = 4

# Without any way to ask the system (neither /proc/meminfo nor sysconf), assume a modest
# workstation: refusing a 20 GB request there is better than a minutes-long MemoryError.
_FALLBACK_BYTES = 8 * 1024**3


def available_bytes() -> int:
    """Memory a new allocation can use now, in bytes.

    Linux: ``MemAvailable`` of ``/proc/meminfo`` (free memory plus reclaimable caches); other
    POSIX systems: free physical pages from ``os.sysconf``; otherwise a fallback of 8 GiB.
    """
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        pages = os.sysconf("SC_AVPHYS_PAGES")
        page = os.sysconf("SC_PAGE_SIZE")
        if pages > 0 and page > 0:
            return int(pages) * int(page)
    except (ValueError, OSError, AttributeError):
        pass
    return _FALLBACK_BYTES


def format_bytes(n_bytes: float) -> str:
    """``209.7 GB``: decimal units, one decimal, as a user compares with a machine's RAM."""
    value = float(n_bytes)
    for unit in ("B", "kB", "MB", "GB", "TB", "PB"):
        if value < 1000.0 or unit == "PB":
            return f"{value:.0f} B" if unit == "B" else f"{value:.1f} {unit}"
        value /= 1000.0
    raise AssertionError("unreachable")


def check_fits(what: str, n_bytes: int | float, *, of: str | None = "float32", hint: str | None = None) -> None:
    """Raise :class:`ResourceError` when ``n_bytes`` exceed the memory available now.

    Parameters
    ----------
    what : str
        The request in words, e.g. ``"simulating 100000 views of 512 x 512"``.
    n_bytes : int or float
        What it needs at its peak (a float, so sizes beyond int64 stay exact enough).
    of : str or None
        The dtype named in the message ("needs 209.7 GB of float32").
    hint : str or None
        What to change, appended to the message.

    Raises
    ------
    ResourceError
        ``"<what> needs 209.7 GB of float32; 22.8 GB is available[; hint]"``.
    """
    available = available_bytes()
    if n_bytes > available:
        raise ResourceError(_message(what, n_bytes, available, of, hint))


@contextmanager
def memory_guard(what: str, n_bytes: int | float | None = None, *, of: str | None = "float32",
                 hint: str | None = None):
    """Run a block, turning a ``MemoryError`` into the one-line :class:`ResourceError`.

    The last resort behind :func:`check_fits`: an estimate can miss a temporary, and other
    processes can take memory between the check and the allocation.
    """
    try:
        yield
    except MemoryError:
        available = available_bytes()
        if n_bytes is None:
            raise ResourceError(f"{what} ran out of memory; {format_bytes(available)} is available"
                                + (f"; {hint}" if hint else "")) from None
        raise ResourceError(_message(what, n_bytes, available, of, hint)) from None


def _message(what: str, n_bytes: float, available: int, of: str | None, hint: str | None) -> str:
    return (f"{what} needs {format_bytes(n_bytes)}" + (f" of {of}" if of else "")
            + f"; {format_bytes(available)} is available" + (f"; {hint}" if hint else ""))


def release_free_memory() -> bool:
    """Hand memory the process has freed back to the system (glibc's ``malloc_trim(0)``); True if any was.

    Many threads allocating views of a few hundred kB each (detection, matching) leave the memory
    they freed in glibc's per-thread heaps, below the size that would be handed back on its own,
    and the process stays that much larger for the rest of the run: 200 MB after the pair stages
    of 1,000 views of 512^2, measured. The large arrays the refiner allocates next are mapped
    afresh and do not reuse it. Dask's workers trim for the same reason (its documentation's
    "Memory not released back to the OS"). Elsewhere than glibc: nothing, False.
    """
    import ctypes

    try:
        trim = ctypes.CDLL(None).malloc_trim   # the symbols the process has loaded, libc's among them
    except (OSError, AttributeError, TypeError):   # not glibc (macOS, musl: no such symbol; Windows: no CDLL(None))
        return False
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return bool(trim(0))
