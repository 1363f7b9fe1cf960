"""Loading plugins: built-in ones and third-party ones, through the same path.

Every run builds a fresh plugin manager with :func:`get_plugin_manager` (no module-level
global), then :func:`collect_stages` asks each plugin to register its stages and
:func:`collect_formats` its scan formats. Modules are imported when a manager loads them, not
before: a blocked plugin is never imported, and a manager that only needs formats
(:func:`get_formats`, what :func:`ctpipe.io.open_scan` uses) imports no stage module (so
neither OpenCV nor numba).
"""

from __future__ import annotations

import importlib
from collections.abc import Iterable

import pluggy

from ctpipe import hookspecs
from ctpipe.errors import PluginError
from ctpipe.registry import FormatRegistry, StageRegistry

__all__ = ["BUILTIN_PLUGINS", "BUILTIN_STAGE_PLUGINS", "BUILTIN_FORMAT_PLUGINS", "ENTRY_POINT_GROUP",
           "get_plugin_manager", "collect_stages", "collect_formats", "get_registry", "get_formats"]

#: Modules holding ctpipe's own scan formats, in the order :func:`ctpipe.io.open_scan` tries
#: them (most specific first: a scan.yaml beside a vendor's files makes it ctpipe's folder).
BUILTIN_FORMAT_PLUGINS: tuple[str, ...] = (
    "ctpipe.io.scan_folder",
    "ctpipe.io.nikon",
    "ctpipe.io.zeiss",
    "ctpipe.io.bruker",
    "ctpipe.io.waygate",
    "ctpipe.io.nsi",
    "ctpipe.io.tiff_stack",
)

#: Modules holding ctpipe's own stages.
BUILTIN_STAGE_PLUGINS: tuple[str, ...] = (
    "ctpipe.builtin.opencv_detectors",
    "ctpipe.builtin.surf",
    "ctpipe.builtin.beads",
    "ctpipe.builtin.matchers",
    "ctpipe.builtin.estimators",
    "ctpipe.builtin.refiners",
    "ctpipe.builtin.projection_matching",
    "ctpipe.builtin.bundle",
    "ctpipe.builtin.ball_calibration",
)

#: Every built-in plugin module, registered by name like any third-party plugin.
BUILTIN_PLUGINS: tuple[str, ...] = BUILTIN_STAGE_PLUGINS + BUILTIN_FORMAT_PLUGINS

#: Entry-point group third-party distributions advertise their plugins in.
ENTRY_POINT_GROUP = "ctpipe"


def get_plugin_manager(*, blocked: Iterable[str] = (), entry_points: bool = True,
                       builtins: Iterable[str] = BUILTIN_PLUGINS) -> pluggy.PluginManager:
    """A new plugin manager with the built-in and (optionally) entry-point plugins loaded.

    Parameters
    ----------
    blocked : iterable of str
        Plugin names not to load (nor import): a built-in module name from
        :data:`BUILTIN_PLUGINS` or a third-party entry-point name.
    entry_points : bool
        Load third-party plugins from the ``ctpipe`` entry-point group.
    builtins : iterable of str
        The built-in modules to load: all by default, :data:`BUILTIN_FORMAT_PLUGINS` when only
        formats are wanted.
    """
    pm = pluggy.PluginManager("ctpipe")
    pm.add_hookspecs(hookspecs)
    for name in blocked:
        pm.set_blocked(name)
    for module_name in builtins:
        if not pm.is_blocked(module_name):
            try:
                module = importlib.import_module(module_name)
            except ImportError as exc:
                # A dependency broken in this environment (an OpenCV wheel that fails to load):
                # one line, and the way to run without the plugin that needs it.
                raise PluginError(f"plugin {module_name!r} failed to load: {type(exc).__name__}: {exc}; repair the "
                                  f"installation, or run without it with --block-plugin {module_name}") from None
            pm.register(module, name=module_name)
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


def collect_formats(pm: pluggy.PluginManager) -> FormatRegistry:
    """Ask every registered plugin for its scan formats, in the order the plugins were loaded."""
    registry = FormatRegistry()
    for impl in pm.hook.ctpipe_register_formats.get_hookimpls():
        impl.function(registry=registry.registrar(impl.plugin_name))
    return registry


def get_registry(*, blocked: Iterable[str] = ()) -> StageRegistry:
    """Shortcut: a fresh plugin manager's stage registry."""
    return collect_stages(get_plugin_manager(blocked=blocked))


def get_formats(*, blocked: Iterable[str] = ()) -> FormatRegistry:
    """Shortcut: the scan formats of the built-in format plugins and the entry-point plugins."""
    return collect_formats(get_plugin_manager(blocked=blocked, builtins=BUILTIN_FORMAT_PLUGINS))
