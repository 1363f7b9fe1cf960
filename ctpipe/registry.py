"""The typed registry that plugins add their stages to."""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Iterator
from dataclasses import dataclass

from ctpipe.errors import ConfigError, PluginError
from ctpipe.stages import STAGE_KINDS, Stage

__all__ = ["StageInfo", "StageRegistry", "StageRegistrar"]

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
