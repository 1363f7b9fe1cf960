"""Where ctpipe's heavy kernels run: the CPU, or a CUDA GPU when there is one (public as :mod:`ctpipe.gpu`).

The voxel projector and its fused pair (:class:`ctpipe.sim.projectors.VoxelProjector`), its
adjoint and the analytic simulator's projector (:func:`ctpipe.sim.projectors.project_analytic`)
have CUDA kernels in :mod:`ctpipe.sim._cuda`, FDK's backprojection
(:func:`ctpipe.recon.feldkamp.fdk`) in :mod:`ctpipe.recon._cuda`; projection matching and
``ctpipe validate`` reach the GPU through them. Everything else (filters, solvers, keypoints)
stays on the CPU. This module holds what they share: the choice of device and the GPU's memory.

The route is numba-cuda (``pip install 'ctpipe[gpu]'``), chosen over CuPy's RawKernels because
it keeps the kernels in the language of the CPU ones (the ray set-up and stepping helpers are the
same functions, compiled for both targets, so the two cannot drift apart) and because it has a
CPU simulator (``NUMBA_ENABLE_CUDASIM=1``) that runs the GPU kernels in CI, which has no GPU.
Its price: numba-cuda 0.30 needs numpy < 2.5 (it imports ``np.row_stack``), pinned in the extra.

Which device runs is asked for with ``--device`` on the command line, a pipeline's ``device:``
key, :func:`use` in Python, or the ``CTPIPE_DEVICE`` environment variable (else ``"auto"``):

- ``"auto"``: the GPU when numba-cuda is installed and sees a CUDA device, else the CPU, silently;
- ``"cuda"``: the GPU; where it cannot be used the CPU runs and the reason is printed once;
- ``"cpu"``: the CPU.

The simulator counts as a device only when asked for by name (``"cuda"``): ``"auto"`` never
picks it, as it runs kernels a thousand times slower than the CPU ones.

Examples
--------
>>> from ctpipe import gpu   # this module's public face
>>> with gpu.use("cpu"):
...     gpu.active()
'cpu'
"""

from __future__ import annotations

import contextlib
import functools
import os
import sys
from dataclasses import dataclass
from typing import Iterator

from ctpipe.errors import InputError

__all__ = ["DEVICES", "FALLBACKS", "DeviceMemoryError", "Selection", "active", "blocks_for", "chunk_views", "fall_back",
           "memory_budget", "prepare_cuda", "select", "set_default", "use"]

#: What a user may ask for: ``--device``, a pipeline's ``device:`` key, ``CTPIPE_DEVICE``.
DEVICES = ("auto", "cpu", "cuda")

#: The process-wide request (``--device``, a pipeline's ``device:``, :func:`use`), above the environment.
_DEFAULT: list[str | None] = [None]


@dataclass(frozen=True)
class Selection:
    """The device a request resolved to, and why (empty when it is the one asked for)."""

    requested: str
    device: str
    reason: str = ""


def check_device(value, path: str = "device") -> str:
    """``value`` as one of :data:`DEVICES`, or an :class:`InputError` naming what is allowed."""
    if not isinstance(value, str) or value.lower() not in DEVICES:
        raise InputError(f"{path}: must be one of {', '.join(DEVICES)}, got {value!r}")
    return value.lower()


@functools.lru_cache(maxsize=None)
def _cuda_status() -> tuple[bool, bool, str]:
    """(usable, simulated, reason it is not usable): numba-cuda importable and a device seen."""
    try:
        import numba
        from numba import cuda
    except Exception as exc:  # noqa: BLE001 - any import failure means: no GPU route here
        return False, False, f"numba-cuda cannot be imported ({type(exc).__name__}: {exc}); pip install 'ctpipe[gpu]'"
    simulated = bool(numba.config.ENABLE_CUDASIM)
    try:
        available = bool(cuda.is_available())
    except Exception as exc:  # noqa: BLE001 - a broken driver reads as no device
        return False, simulated, f"the CUDA driver failed ({type(exc).__name__}: {exc})"
    if not available:
        return False, simulated, "no CUDA device or driver was found"
    return True, simulated, ""


@functools.lru_cache(maxsize=None)
def select(requested: str = "auto") -> Selection:
    """Resolve ``requested`` (one of :data:`DEVICES`) to ``"cpu"`` or ``"cuda"``, with the reason for a fallback."""
    requested = check_device(requested)
    if requested == "cpu":
        return Selection(requested, "cpu")
    usable, simulated, reason = _cuda_status()
    if requested == "auto":
        return Selection(requested, "cuda" if usable and not simulated else "cpu")
    if usable:
        return Selection(requested, "cuda")
    selection = Selection(requested, "cpu", reason)
    print(f"ctpipe: a GPU was asked for but cannot be used: {reason}; running on the CPU", file=sys.stderr)
    return selection


def set_default(device: str | None) -> None:
    """Ask for ``device`` from now on, in every thread (``None``: ``CTPIPE_DEVICE``, else ``"auto"``).

    Process-wide, so that the worker threads of a command see what its ``--device`` asked for.
    """
    _DEFAULT[0] = None if device is None else check_device(device)


def requested() -> str:
    """What was asked for: :func:`set_default`'s or :func:`use`'s, else ``CTPIPE_DEVICE``, else ``"auto"``."""
    if _DEFAULT[0] is not None:
        return _DEFAULT[0]
    return check_device(os.environ.get("CTPIPE_DEVICE", "auto"), "CTPIPE_DEVICE")


def active() -> str:
    """The device the heavy kernels run on now: ``"cpu"`` or ``"cuda"``."""
    return select(requested()).device


#: Every fall-back of this process: (what, why). :mod:`ctpipe.gpu.check` reads it, so that a
#: kernel that failed on the GPU cannot pass for one that agreed with the CPU.
FALLBACKS: list[tuple[str, str]] = []


def fall_back(what: str, error: BaseException) -> None:
    """Note that ``what`` runs on the CPU after the GPU refused it, saying so once per kind of work.

    The GPU's refusals are its free memory (:class:`DeviceMemoryError`), a driver or launch
    error, or a kernel numba-cuda could not compile for this card; the CPU kernels give the
    answer in every case.
    """
    why = str(error) if isinstance(error, DeviceMemoryError) else f"{type(error).__name__}: {error}"
    if all(done != what for done, _ in FALLBACKS):
        print(f"ctpipe: {what} runs on the CPU: {why.splitlines()[0] if why else type(error).__name__}",
              file=sys.stderr)
    FALLBACKS.append((what, why))


@contextlib.contextmanager
def use(device: str) -> Iterator[Selection]:
    """Run the heavy kernels on ``device`` (one of :data:`DEVICES`) inside the ``with`` block.

    Yields the :class:`Selection` it resolved to. The request is process-wide while the block
    runs (worker threads see it too) and the previous one is restored after it.
    """
    device = check_device(device)
    previous = _DEFAULT[0]
    _DEFAULT[0] = device
    try:
        yield select(device)
    finally:
        _DEFAULT[0] = previous


# --------------------------------------------------------------------------- the GPU's memory

#: Share of the free device memory one call plans to use (the rest: the context, other work).
_MEMORY_SHARE = 0.6


class DeviceMemoryError(MemoryError):
    """The data a kernel needs resident at once does not fit in the GPU's free memory."""


@functools.lru_cache(maxsize=None)
def prepare_cuda() -> None:
    """What the GPU kernels' modules do once, on import: their disk cache out of the package, quiet small grids.

    numba-cuda keeps its own copy of numba's caching machinery (none under the simulator); a
    launch over a few blocks (one view of a few primitives, a handful of rows) is expected here,
    and numba-cuda's warning about it would only be noise.
    """
    import warnings

    from ctpipe._shared.jit import cache_outside_the_package

    try:
        from numba.cuda.core import caching
    except ImportError:   # pragma: no cover - under NUMBA_ENABLE_CUDASIM
        caching = None
    if caching is not None:
        cache_outside_the_package(caching)
    warnings.filterwarnings("ignore", message="Grid size .* will likely result in GPU under-utilization")


def memory_budget(resident_bytes: float, what: str) -> float:
    """Bytes left on the GPU for chunks once ``resident_bytes`` are placed (infinite under the simulator).

    Raises :class:`DeviceMemoryError` when the resident part alone does not fit; callers then
    run on the CPU (:func:`fall_back`).
    """
    from numba import cuda

    left = _MEMORY_SHARE * float(cuda.current_context().get_memory_info()[0]) - resident_bytes
    if left <= 0:
        raise DeviceMemoryError(f"{what} needs {resident_bytes / 2**30:.1f} GiB on the GPU, more than its free memory")
    return left


def blocks_for(shape: tuple[int, ...], block: tuple[int, ...]) -> tuple[int, ...]:
    """CUDA blocks of ``block`` threads covering ``shape`` (both fastest axis first)."""
    return tuple((n + b - 1) // b for n, b in zip(shape, block))


def chunk_views(per_view_bytes: float, budget_bytes: float, n_views: int, most: int | None = None) -> int:
    """Views per chunk that fit in ``budget_bytes`` (at least one, at most ``most`` and ``n_views``)."""
    n = n_views if most is None else min(n_views, most)
    if budget_bytes == float("inf"):
        return max(1, n)
    return int(max(1, min(n, budget_bytes // max(per_view_bytes, 1.0))))
