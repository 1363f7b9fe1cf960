"""Hook specifications of ctpipe: the contract between ctpipe and its plugins.

A plugin is a module (or object) with functions decorated by :data:`hookimpl`, one hook per
extension point: :func:`ctpipe_register_stages` for detectors, matchers, estimators and
refiners, :func:`ctpipe_register_formats` for scan formats. Built-in stages and formats are
plugins too (``ctpipe.plugins.BUILTIN_PLUGINS``); third-party distributions expose theirs
through the ``ctpipe`` entry-point group::

    [project.entry-points.ctpipe]
    myplugin = "my_package.ctpipe_plugin"
"""

from __future__ import annotations

import pluggy

from ctpipe.registry import FormatRegistrar, StageRegistrar

__all__ = ["hookspec", "hookimpl", "ctpipe_register_stages", "ctpipe_register_formats"]

hookspec = pluggy.HookspecMarker("ctpipe")
hookimpl = pluggy.HookimplMarker("ctpipe")


@hookspec
def ctpipe_register_stages(registry: StageRegistrar) -> None:
    """Register the stages this plugin provides.

    Parameters
    ----------
    registry : StageRegistrar
        Call ``registry.add_detector(name, cls)``, ``add_matcher``, ``add_estimator`` or
        ``add_refiner`` once per stage. ``cls`` is a frozen dataclass subclassing the matching
        base in :mod:`ctpipe.stages`; its docstring's first line is the description that
        ``ctpipe plugins`` shows. A name already taken by another plugin is an error naming
        both plugins.
    """


@hookspec
def ctpipe_register_formats(registry: FormatRegistrar) -> None:
    """Register the scan formats this plugin reads.

    Parameters
    ----------
    registry : FormatRegistrar
        Call ``registry.add_format(name, detect, open, description, corrected_angle_log=None)``
        once per format: ``detect(path) -> bool`` recognises a scan (a folder or a file) without
        raising, ``open(path) -> ctpipe.io.ScanFiles`` opens it. :func:`ctpipe.io.open_scan`
        tries the built-in formats first, then third-party ones in the order they load. A
        name already taken by another plugin is an error naming both plugins.
    """
