"""The typed registries that plugins add their stages and scan formats to."""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ctpipe.errors import ConfigError, PluginError
from ctpipe.stages import STAGE_KINDS, Stage

__all__ = ["StageInfo", "StageRegistry", "StageRegistrar", "FormatInfo", "FormatRegistry", "FormatRegistrar"]

_NAME = re.compile(r"^[a-z0-9][a-z0-9_-]*$")


@dataclass(frozen=True)
class StageInfo:
    """One registered stage: its kind, name, class and the plugin that provided it."""

    kind: str
    name: str
    cls: type[Stage]
    plugin: str

    @property
    def description(self) -> str:
        return self.cls.summary()

    def to_dict(self) -> dict:
        return {"kind": self.kind, "name": self.name, "plugin": self.plugin, "description": self.description}


class StageRegistry:
    """All stages known to one run, by kind and name."""

    def __init__(self) -> None:
        self._stages: dict[str, dict[str, StageInfo]] = {kind: {} for kind in STAGE_KINDS}

    def registrar(self, plugin: str) -> "StageRegistrar":
        """The object handed to ``plugin``'s ``ctpipe_register_stages`` hook."""
        return StageRegistrar(self, plugin)

    def _add(self, kind: str, name: str, cls: type, plugin: str) -> None:
        base = STAGE_KINDS[kind]
        if not isinstance(name, str) or not _NAME.match(name):
            raise PluginError(f"plugin {plugin!r}: {kind} name {name!r} must match {_NAME.pattern}")
        if not (isinstance(cls, type) and issubclass(cls, base) and dataclasses.is_dataclass(cls)):
            raise PluginError(f"plugin {plugin!r}: {kind} {name!r} must be a dataclass subclassing ctpipe.stages.{base.__name__}")
        if not cls.summary():
            raise PluginError(f"plugin {plugin!r}: {kind} {name!r} needs a docstring (its first line describes it)")
        existing = self._stages[kind].get(name)
        if existing is not None:
            raise PluginError(
                f"{kind} {name!r} is registered twice: by plugin {existing.plugin!r} and by plugin {plugin!r}; "
                "block one of them"
            )
        self._stages[kind][name] = StageInfo(kind, name, cls, plugin)

    def get(self, kind: str, name: str, *, path: str | None = None) -> StageInfo:
        """Look a stage up; an unknown name raises :class:`ConfigError` listing the known ones."""
        try:
            return self._stages[kind][name]
        except KeyError:
            where = f"{path}: " if path else ""
            known = ", ".join(self.names(kind)) or "(none registered)"
            raise ConfigError(f"{where}unknown {kind} {name!r}; registered {kind}s: {known}") from None

    def names(self, kind: str) -> list[str]:
        return sorted(self._stages[kind])

    def __iter__(self) -> Iterator[StageInfo]:
        for kind in STAGE_KINDS:
            yield from (self._stages[kind][name] for name in self.names(kind))

    def __len__(self) -> int:
        return sum(len(v) for v in self._stages.values())


class StageRegistrar:
    """A plugin's view of the registry: every stage it adds is recorded as its own."""

    def __init__(self, registry: StageRegistry, plugin: str) -> None:
        self._registry = registry
        self.plugin = plugin

    def add_detector(self, name: str, cls: type) -> None:
        """Register a :class:`~ctpipe.stages.Detector` subclass under ``name``."""
        self._registry._add("detector", name, cls, self.plugin)

    def add_matcher(self, name: str, cls: type) -> None:
        """Register a :class:`~ctpipe.stages.Matcher` subclass under ``name``."""
        self._registry._add("matcher", name, cls, self.plugin)

    def add_estimator(self, name: str, cls: type) -> None:
        """Register an :class:`~ctpipe.stages.Estimator` subclass under ``name``."""
        self._registry._add("estimator", name, cls, self.plugin)

    def add_refiner(self, name: str, cls: type) -> None:
        """Register a :class:`~ctpipe.stages.Refiner` subclass under ``name``."""
        self._registry._add("refiner", name, cls, self.plugin)


@dataclass(frozen=True)
class FormatInfo:
    """One registered scan format: how :func:`ctpipe.io.open_scan` recognises and opens it.

    Attributes
    ----------
    name : str
        The format's name (``nikon``, ``bruker``, ...), as ``ScanFiles.format`` and a
        :class:`~ctpipe.io.StackReference` carry it.
    detect : callable
        ``detect(path) -> bool``: whether ``path`` (a folder or a file) is a scan in this format.
        Cheap and silent: it looks at names and magic bytes, never raises on a foreign scan.
    open : callable
        ``open(path) -> ScanFiles``.
    description : str
        What the format looks like on disk, for the message listing the formats.
    plugin : str
        The plugin that registered it.
    corrected_angle_log : callable or None
        ``corrected_angle_log(scan, angles_deg) -> (file name, bytes)``: the scanner's own
        per-view angle file for corrected angles, for formats whose software reads one.
    """

    name: str
    detect: Callable[[Path], bool]
    open: Callable[[Path], Any]
    description: str
    plugin: str
    corrected_angle_log: Callable[[Any, Any], tuple[str, bytes]] | None = None

    def to_dict(self) -> dict:
        return {"kind": "format", "name": self.name, "plugin": self.plugin, "description": self.description}


class FormatRegistry:
    """All scan formats known to one run, in the order :func:`ctpipe.io.open_scan` tries them."""

    def __init__(self) -> None:
        self._formats: dict[str, FormatInfo] = {}

    def registrar(self, plugin: str) -> "FormatRegistrar":
        """The object handed to ``plugin``'s ``ctpipe_register_formats`` hook."""
        return FormatRegistrar(self, plugin)

    def _add(self, info: FormatInfo) -> None:
        if not isinstance(info.name, str) or not _NAME.match(info.name):
            raise PluginError(f"plugin {info.plugin!r}: format name {info.name!r} must match {_NAME.pattern}")
        for what in ("detect", "open"):
            if not callable(getattr(info, what)):
                raise PluginError(f"plugin {info.plugin!r}: format {info.name!r}: {what} must be callable")
        if info.corrected_angle_log is not None and not callable(info.corrected_angle_log):
            raise PluginError(f"plugin {info.plugin!r}: format {info.name!r}: corrected_angle_log must be callable")
        if not isinstance(info.description, str) or not info.description.strip():
            raise PluginError(f"plugin {info.plugin!r}: format {info.name!r} needs a description")
        existing = self._formats.get(info.name)
        if existing is not None:
            raise PluginError(f"format {info.name!r} is registered twice: by plugin {existing.plugin!r} and by plugin "
                              f"{info.plugin!r}; block one of them")
        self._formats[info.name] = info

    def get(self, name: str) -> FormatInfo | None:
        """The format called ``name``, or None."""
        return self._formats.get(name)

    def __getitem__(self, name: str) -> FormatInfo:
        return self._formats[name]

    def __contains__(self, name: object) -> bool:
        return name in self._formats

    def names(self) -> list[str]:
        """Names in the order they are tried."""
        return list(self._formats)

    def __iter__(self) -> Iterator[FormatInfo]:
        return iter(list(self._formats.values()))

    def __len__(self) -> int:
        return len(self._formats)


class FormatRegistrar:
    """A plugin's view of the format registry: every format it adds is recorded as its own."""

    def __init__(self, registry: FormatRegistry, plugin: str) -> None:
        self._registry = registry
        self.plugin = plugin

    def add_format(self, name: str, detect: Callable[[Path], bool], open: Callable[[Path], Any], description: str, *,
                   corrected_angle_log: Callable[[Any, Any], tuple[str, bytes]] | None = None) -> None:
        """Register a scan format; see :class:`FormatInfo` for what each argument must do."""
        self._registry._add(FormatInfo(name, detect, open, description, self.plugin, corrected_angle_log))
