"""Names of a package imported on first use (PEP 562), so that importing the package stays cheap.

``ctpipe`` itself, :mod:`ctpipe.io`, :mod:`ctpipe.builtin`, :mod:`ctpipe.features` and
:mod:`ctpipe.testing` export names this way: a blocked plugin module is then never imported, and
``import ctpipe`` does not load numba, OpenCV or the readers. scikit-image does the same with
``lazy_loader.attach``.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["lazy_exports"]


def lazy_exports(package: str, exports: Mapping[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module ``__getattr__`` and ``__dir__`` of ``package``, whose ``exports`` map a name to its module.

    The module is given relative to ``package`` (``"nikon"`` in ``ctpipe.io``, ``"io.scans"`` in
    ``ctpipe``). A name is imported from it on first use and kept in the package's namespace, so
    it is looked up once; an unknown name raises AttributeError as for any module.
    """
    namespace = vars(sys.modules[package])

    def __getattr__(name: str) -> Any:
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{module}"), name)
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(exports))

    return __getattr__, __dir__
