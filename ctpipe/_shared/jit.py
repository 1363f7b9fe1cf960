"""The fast-math flags every numba kernel of ctpipe compiles with, and where their cache goes.

``fastmath=True`` is LLVM's ``fast``, which includes ``nsz`` (signed zeros may be ignored).
With ``reassoc`` and ``nsz`` together, the code numba compiles in a process and the code it
loads from its on-disk cache (``cache=True``) are not the same: FDK volumes of one input differed
in their last bits, and the default pipeline's angles on a 48-view scan came out 6e-7 deg apart
between a Dask worker that loaded the kernels and a client that compiled them. Each flag alone,
and every flag but ``nsz``, gives bit-identical results either way, at the same speed (FDK
backprojection within 1 % of ``fastmath=True``). Hence ``fastmath=FASTMATH`` everywhere.
"""

from __future__ import annotations

import os

import numba

__all__ = ["FASTMATH", "NOGIL", "cache_outside_the_package", "njit"]

#: LLVM's ``fast`` without ``nsz``: fused multiply-add, reassociation, reciprocals, approximate
#: functions, no NaN or infinity operands. A set, as numba requires (a frozenset is refused).
FASTMATH = {"contract", "reassoc", "arcp", "afn", "nnan", "ninf"}


def _threadsafe_layer() -> bool:
    """Whether numba's parallel kernels may be launched from several threads at once here.

    numba picks its threading layer at the first parallel call: TBB, else OpenMP, else its own
    workqueue. The first two take launches from any number of threads; the workqueue aborts the
    process on a second concurrent launch (numba's "Threading layers" documentation). A layer
    chosen with ``NUMBA_THREADING_LAYER`` is taken at its word.
    """
    import importlib

    layer = str(numba.config.THREADING_LAYER).lower()
    if layer in ("tbb", "omp", "safe", "threadsafe"):
        return True
    if layer != "default":
        return False
    for module in ("numba.np.ufunc.tbbpool", "numba.np.ufunc.omppool"):
        try:
            importlib.import_module(module)   # fails when the library (libtbb, libgomp) is missing
        except ImportError:
            continue
        return True
    return False


#: Whether kernels release the GIL while they run (see :func:`njit`).
NOGIL = _threadsafe_layer()


def njit(*args, **options):
    """``numba.njit`` whose kernels release the GIL (``nogil``): serial ones always, parallel ones where the layer allows it.

    A kernel that holds the GIL holds up every other thread for as long as it runs: detection in
    the other worker threads, and the main thread that handles Ctrl-C and SIGTERM while the
    ``ctpipe`` command runs in a thread of its own (:func:`ctpipe.cli.entry`). Only a parallel
    kernel needs the threading layer: without a thread-safe one (workqueue only) the GIL keeps
    parallel kernels from being launched from two threads at once. A serial kernel needs no
    layer, so it releases the GIL everywhere.
    """
    options.setdefault("nogil", NOGIL or not options.get("parallel", False))
    return numba.njit(*args, **options)


def _cache_outside_the_package() -> None:
    """Keep numba's on-disk cache of ctpipe's kernels (``cache=True``) out of the installed package.

    numba writes it next to the source, into ``ctpipe/*/__pycache__``, wherever that is
    writable: in an environment's ``site-packages`` too. ``pip uninstall`` removes only the
    files it installed, so those folders stayed behind, and after ``pip install .`` then ``pip
    install -e .`` (the README's two commands, run in one environment) Python found
    ``site-packages/ctpipe`` first as a namespace package without ``__init__``: ``import
    ctpipe`` gave a package without ``Pipeline``. ctpipe's kernels are cached in numba's
    user-wide cache folder instead (``~/.cache/numba`` on Linux; one subfolder per source
    folder, so two installs do not mix), as numba does for a read-only package.
    ``NUMBA_CACHE_DIR`` set by the user still wins. Uses numba's cache locators
    (``numba.core.caching``); with a numba that has them elsewhere, numba's default stands.
    """
    try:
        from numba.core import caching
    except ImportError:   # pragma: no cover - numba moved its caching module
        return
    cache_outside_the_package(caching)


def cache_outside_the_package(caching) -> None:
    """Put ctpipe's kernels cached through the caching module ``caching`` in its user-wide folder.

    ``numba.core.caching`` for the CPU kernels (at import); numba-cuda keeps its own copy of
    the machinery (``numba.cuda.core.caching``, with ``_UserWideCacheLocator``), which the GPU
    kernels' modules pass here when they are imported.
    """
    user_wide = getattr(caching, "UserWideCacheLocator", None) or getattr(caching, "_UserWideCacheLocator", None)
    classes = getattr(getattr(caching, "CacheImpl", None), "_locator_classes", None)
    if user_wide is None or not isinstance(classes, list):   # pragma: no cover - numba's internals changed
        return
    package = os.path.dirname(os.path.dirname(os.path.abspath(__file__))) + os.sep

    class CtpipeCacheLocator(user_wide):
        """numba's user-wide cache folder for ctpipe's own source files (see above)."""

        @classmethod
        def from_function(cls, py_func, py_file):
            if numba.config.CACHE_DIR or not os.path.abspath(py_file).startswith(package):
                return None
            return super().from_function(py_func, py_file)

    if any(getattr(c, "__name__", "") == CtpipeCacheLocator.__name__ for c in classes):
        return
    # After a cache folder the user named (UserProvidedCacheLocator), before numba's in-tree one.
    named = [k for k, c in enumerate(classes)
             if getattr(c, "__name__", "") in ("UserProvidedCacheLocator", "_UserProvidedCacheLocator")]
    classes.insert(named[0] + 1 if named else 0, CtpipeCacheLocator)


_cache_outside_the_package()
