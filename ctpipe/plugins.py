"""Loading plugins: built-in ones and third-party ones, through the same path.

Every run builds a fresh plugin manager with :func:`get_plugin_manager` (no module-level
global), then :func:`collect_stages` asks each plugin to register its stages.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterable

import pluggy

from ctpipe import hookspecs
from ctpipe.errors import PluginError
from ctpipe.registry import StageRegistry

__all__ = ["BUILTIN_PLUGINS", "ENTRY_POINT_GROUP", "get_plugin_manager", "collect_stages", "get_registry"]

#: Modules holding ctpipe's own stages, registered by name like any other plugin.
BUILTIN_PLUGINS: tuple[str, ...] = (
    "ctpipe.builtin.opencv_detectors",
    "ctpipe.builtin.surf",
    "ctpipe.builtin.beads",
    "ctpipe.builtin.matchers",
    "ctpipe.builtin.estimators",
    "ctpipe.builtin.refiners",
    "ctpipe.builtin.projection_matching",
    "ctpipe.builtin.bundle",
)

#: Entry-point group third-party distributions advertise their plugins in.
ENTRY_POINT_GROUP = "ctpipe"


def get_plugin_manager(*, blocked: Iterable[str] = (), entry_points: bool = True) -> pluggy.PluginManager:
    """A new plugin manager with the built-in and (optionally) entry-point plugins loaded.

    Parameters
    ----------
    blocked : iterable of str
        Plugin names not to load: a built-in module name from :data:`BUILTIN_PLUGINS` or a
        third-party entry-point name.
    entry_points : bool
        Load third-party plugins from the ``ctpipe`` entry-point group.
    """
    pm = pluggy.PluginManager("ctpipe")
    pm.add_hookspecs(hookspecs)
    for name in blocked:
        pm.set_blocked(name)
    for module_name in BUILTIN_PLUGINS:
        if not pm.is_blocked(module_name):
            pm.register(importlib.import_module(module_name), name=module_name)
    if entry_points:
        _load_entry_points(pm)
    pm.check_pending()
    return pm


def _load_entry_points(pm: pluggy.PluginManager) -> None:
    """pluggy's ``load_setuptools_entrypoints``, with a plugin that fails to import named in one line.

    A plugin missing from one environment (a cluster worker, an old virtualenv) otherwise ends
    the run with a traceback from deep in importlib.
    """
    from importlib.metadata import entry_points

    for entry in entry_points(group=ENTRY_POINT_GROUP):
        if pm.is_blocked(entry.name) or pm.has_plugin(entry.name):
            continue
        try:
            plugin = entry.load()
        except Exception as exc:
            dist = getattr(entry, "dist", None)
            source = f" of {dist.name} {dist.version}" if dist is not None else ""
            raise PluginError(f"plugin {entry.name!r} ({entry.value}{source}) failed to load: {type(exc).__name__}: "
                              f"{exc}; reinstall it, or run without it with --block-plugin {entry.name}") from None
        pm.register(plugin, name=entry.name)


def collect_stages(pm: pluggy.PluginManager) -> StageRegistry:
    """Ask every registered plugin for its stages.

    Each implementation is called with a registrar bound to its plugin's name, so the registry
    knows who provided every stage and can name both plugins on a clash.
    """
    registry = StageRegistry()
    for impl in pm.hook.ctpipe_register_stages.get_hookimpls():
        impl.function(registry=registry.registrar(impl.plugin_name))
    return registry


def get_registry(*, blocked: Iterable[str] = ()) -> StageRegistry:
    """Shortcut: a fresh plugin manager's registry."""
    return collect_stages(get_plugin_manager(blocked=blocked))
