"""Hook specifications of ctpipe: the contract between ctpipe and its plugins.

A plugin is a module (or object) with functions decorated by :data:`hookimpl`. Built-in
stages are plugins too (``ctpipe.plugins.BUILTIN_PLUGINS``); third-party distributions expose
theirs through the ``ctpipe`` entry-point group::

    [project.entry-points.ctpipe]
    myplugin = "my_package.ctpipe_plugin"
"""

from __future__ import annotations

import pluggy

from ctpipe.registry import StageRegistrar

__all__ = ["hookspec", "hookimpl", "ctpipe_register_stages"]

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
