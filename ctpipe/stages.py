"""The four stage kinds and how a stage declares its parameters.

A stage is a frozen dataclass: its fields are its parameters, declared with :func:`param`
(default, one-line doc, bounds). Parameters are validated when the stage is constructed,
from Python or from YAML, with the same messages. Stages keep no state after ``__init__``;
they return new results and never modify their inputs. A solver's settings can be declared the
same way (a :class:`Parameters` dataclass) and a stage can then *be* those settings by
subclassing them, so every setting is declared once.

A stage that uses another stage (projection matching starts from a refiner's angles) declares
it with ``param(..., stage="refiner")``: the value is a stage of that kind, written in YAML as
a top-level stage is (a bare name, or ``{name: ..., <param>: ...}``) and built through the
same registry (:func:`ctpipe.config.build_stage`), so its parameters are validated with their
YAML path and a blocked plugin's stage cannot be used.

Detector -> Matcher -> Estimator -> Refiner::

    Detector.detect(image) -> Features
    Matcher.match(features_a, features_b) -> Matches
    Estimator.estimate(q_a, q_b, *, rng) -> PairEstimate | FailedEstimation
    Refiner.refine(observations, *, rng) -> ScanSolution
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np

from ctpipe._shared.checks import as_integer, short_repr
from ctpipe.errors import ConfigError

__all__ = ["param", "ParamSpec", "Parameters", "Stage", "StageSpec", "Detector", "Matcher", "Estimator", "Refiner",
           "STAGE_KINDS", "check_value"]


def param(default: Any, *, doc: str, ge=None, gt=None, le=None, lt=None, stage: str | None = None) -> Any:
    """Declare a parameter: a dataclass field with a doc line and bounds.

    ``stage`` (a kind, e.g. ``"refiner"``) declares a nested stage: the value is a stage of that
    kind, or its spec (a registered name, or a mapping ``{name: ..., <param>: ...}``) that
    :func:`ctpipe.config.build_stage` builds through the registry; the words of a ``Literal`` in
    the annotation (e.g. ``"nominal"``) are accepted beside it.
    """
    return dataclasses.field(default=default, metadata={"doc": doc, "ge": ge, "gt": gt, "le": le, "lt": lt,
                                                        "stage": stage})


@dataclass(frozen=True)
class StageSpec:
    """A stage chosen by name with explicit parameters, not built yet.

    :func:`ctpipe.config.parse_stage` makes validated ones from YAML; a nested stage given by
    name from Python is held as one (its parameters unchecked) until
    :func:`ctpipe.config.build_stage` validates and builds it through a registry.
    """

    kind: str
    name: str
    params: Mapping[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict:
        """``{"name": ..., **params}``, nested specs as mappings too (YAML/JSON friendly)."""
        return {"name": self.name, **{key: value.to_dict() if isinstance(value, StageSpec) else value
                                      for key, value in self.params.items()}}


@dataclass(frozen=True)
class ParamSpec:
    """What a parameter accepts: its type, default, doc line and bounds."""

    name: str
    annotation: Any
    default: Any
    doc: str
    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    #: Kind of a nested stage (``"refiner"``), or None for a plain value.
    stage: str | None = None

    @property
    def allowed(self) -> str:
        """Human description of the accepted values, e.g. ``a number > 0``."""
        if self.stage is not None:
            text = f"a {self.stage} (its name, or a mapping with 'name' and its parameters)"
            return text + (" or one of " + ", ".join(repr(v) for v in self.words) if self.words else "")
        return _describe(self.annotation, self)

    def is_word(self, value: Any) -> bool:
        """Whether ``value`` is one of :attr:`words` (as written: ``1`` is not ``True``)."""
        return any(value == word and type(value) is type(word) for word in self.words)

    @property
    def words(self) -> tuple:
        """The ``Literal`` values of the annotation (a nested stage's special words, e.g. ``"nominal"``)."""
        return tuple(v for option in _options(self.annotation) if typing.get_origin(option) is Literal
                     for v in typing.get_args(option))


_TYPE_WORDS = {bool: "true or false", int: "an integer", float: "a number", str: "a string", type(None): "null"}


def _options(annotation) -> tuple:
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        return typing.get_args(annotation)
    return (annotation,)


def _describe(annotation, spec: ParamSpec | None = None) -> str:
    parts = []
    for option in _options(annotation):
        if typing.get_origin(option) is Literal:
            parts.append("one of " + ", ".join(repr(v) for v in typing.get_args(option)))
        elif typing.get_origin(option) is tuple:
            inner = typing.get_args(option)[0]
            single = _describe(inner, spec)
            plural = {int: "integers", float: "numbers", str: "strings"}.get(inner)
            parts.append("a non-empty list of " + (single.replace(_TYPE_WORDS[inner], plural, 1) if plural else single))
        else:
            word = _TYPE_WORDS.get(option, getattr(option, "__name__", str(option)))
            if option in (int, float) and spec is not None:
                bounds = [f"{op} {_number(v)}" for op, v in ((">=", spec.ge), (">", spec.gt), ("<=", spec.le), ("<", spec.lt)) if v is not None]
                word += (" " + " and ".join(bounds)) if bounds else ""
            parts.append(word)
    return " or ".join(parts)


def _number(v: float) -> str:
    """A bound as people write it: 1000000 and 1e12 rather than 1e+06 and 1000000000000, 0.5 rather than 0.500000."""
    if float(v).is_integer() and abs(v) < 1e7:
        return str(int(v))
    return f"{v:g}".replace("e+", "e")


def _matches_type(option, value) -> bool:
    if typing.get_origin(option) is Literal:
        return any(value == v and type(value) is type(v) for v in typing.get_args(option))
    if typing.get_origin(option) is tuple:
        inner = typing.get_args(option)[0]
        return isinstance(value, (list, tuple)) and len(value) > 0 and all(_matches_type(inner, v) for v in value)
    if option is float:
        return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
    if option is int:
        return isinstance(value, (int, np.integer)) and not isinstance(value, bool)
    if option is type(None):
        return value is None
    return isinstance(value, option)


def _in_bounds(spec: ParamSpec, value) -> bool:
    values = value if isinstance(value, (list, tuple)) else (value,)
    for v in values:
        if not isinstance(v, (int, float, np.integer, np.floating)) or isinstance(v, bool):
            continue
        if isinstance(v, (float, np.floating)) and not math.isfinite(v):
            return False
        if spec.ge is not None and not v >= spec.ge or spec.gt is not None and not v > spec.gt:
            return False
        if spec.le is not None and not v <= spec.le or spec.lt is not None and not v < spec.lt:
            return False
    return True


def check_value(spec: ParamSpec, value: Any, path: str) -> Any:
    """Return ``value`` (floats as float, lists as tuples) or raise :class:`ConfigError`.

    The message names ``path``, the value received and what is allowed. A nested stage
    (``spec.stage``) is kept as given if it is a stage of that kind, a :class:`StageSpec` of it or
    one of the annotation's words; a name or a mapping with a ``name`` becomes a :class:`StageSpec`
    (its parameters are checked when it is built, :func:`ctpipe.config.build_stage`).
    """
    if spec.stage is not None:
        return _check_stage(spec, value, path)
    if not any(_matches_type(option, value) for option in _options(spec.annotation)) or not _in_bounds(spec, value):
        raise ConfigError(f"{path}: must be {spec.allowed}, got {short_repr(value)}")
    return _plain(spec.annotation, value)


def _check_stage(spec: ParamSpec, value: Any, path: str) -> Any:
    kind = spec.stage
    if isinstance(value, STAGE_KINDS[kind]) or isinstance(value, StageSpec) and value.kind == kind:
        return value
    if spec.is_word(value):
        return value
    if isinstance(value, str):
        return StageSpec(kind, value, {})
    if isinstance(value, Mapping) and isinstance(value.get("name"), str):
        return StageSpec(kind, value["name"], {key: v for key, v in value.items() if key != "name"})
    raise ConfigError(f"{path}: must be {spec.allowed}, got {short_repr(value)}")


def _plain(annotation, value):
    """``value`` with numpy scalars as Python numbers, floats as float where allowed, lists as tuples."""
    options = _options(annotation)
    if isinstance(value, (list, tuple)):
        inner = next((typing.get_args(o)[0] for o in options if typing.get_origin(o) is tuple), None)
        return tuple(_plain(inner, v) for v in value)
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if float in options and isinstance(value, (int, float, np.integer, np.floating)):
        return float(value)
    if isinstance(value, np.integer):
        return as_integer(value)
    return value


class Parameters:
    """Base of frozen dataclasses whose fields are declared with :func:`param` and checked on construction.

    Stages are such dataclasses; so are settings a solver takes (``BundleSettings``), which a
    stage may subclass to take them over as its own parameters.
    """

    def __post_init__(self) -> None:
        for spec in self.parameters():
            value = check_value(spec, getattr(self, spec.name), f"{type(self).__name__}.{spec.name}")
            object.__setattr__(self, spec.name, value)

    @classmethod
    def parameters(cls) -> tuple[ParamSpec, ...]:
        """The parameters in declaration order."""
        hints = typing.get_type_hints(cls)
        specs = []
        for f in dataclasses.fields(cls):
            meta = f.metadata
            specs.append(
                ParamSpec(f.name, hints[f.name], f.default, meta.get("doc", ""),
                          meta.get("ge"), meta.get("gt"), meta.get("le"), meta.get("lt"), meta.get("stage"))
            )
        return tuple(specs)

    def params(self) -> dict[str, Any]:
        """Current parameter values, as plain Python values."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


class Stage(Parameters):
    """Base of the four stage kinds. Subclasses are frozen dataclasses."""

    kind: ClassVar[str] = ""

    @classmethod
    def summary(cls) -> str:
        """First line of the class docstring: the stage's one-line description."""
        doc = (cls.__doc__ or "").strip()
        return doc.splitlines()[0].strip() if doc else ""


class Detector(Stage):
    """Finds keypoints and computes descriptors on one 2-D image."""

    kind = "detector"
    #: Whether keypoints found on a binned copy of a view stand for the view's own (multi-scale
    #: keypoint detectors: yes; a ball finder fitting sub-pixel discs: no). A pipeline with
    #: ``preprocess.detect_max_px`` detects on such a copy when the detector is larger.
    working_resolution: ClassVar[bool] = False
    #: Whether :meth:`detect` spends most of its time holding the GIL (Python and numpy's small
    #: calls), so that threads do not run it in parallel. A pipeline on threads then detects views
    #: of a megapixel or more on worker processes, one per core (:class:`ctpipe.execution.ProcessPool`);
    #: the detector and its results must pickle, and its class be importable by name.
    holds_gil: ClassVar[bool] = False

    def detect(self, image: np.ndarray):  # pragma: no cover - interface
        """Return the :class:`~ctpipe.data.Features` of ``image`` (2-D, uint8 or float)."""
        raise NotImplementedError


class Matcher(Stage):
    """Pairs keypoints of two views by descriptor similarity."""

    kind = "matcher"

    def match(self, features_a, features_b):  # pragma: no cover - interface
        """Return :class:`~ctpipe.data.Matches` between two :class:`~ctpipe.data.Features`."""
        raise NotImplementedError


class Estimator(Stage):
    """Estimates the turntable angle of one view pair from its correspondences."""

    kind = "estimator"

    def estimate(self, q_a: np.ndarray, q_b: np.ndarray, *, rng: np.random.Generator):  # pragma: no cover
        """Return a :class:`~ctpipe.data.PairEstimate` or a falsy ``FailedEstimation``.

        ``q_a``, ``q_b``: normalised coordinates of shape (M, 2) in the first and second view.
        """
        raise NotImplementedError


class Refiner(Stage):
    """Turns all pair estimates of a scan into per-view angles."""

    kind = "refiner"
    #: Whether :meth:`refine` reads the features' descriptors. A pipeline whose refiner does not
    #: drops them once the pairs are matched (:meth:`~ctpipe.data.Features.without_descriptors`):
    #: SIFT's are 286 MB at 2,000 views of 2,048^2 (measured) that nothing reads again. True by
    #: default, so that a refiner from a plugin keeps them unless it says otherwise.
    reads_descriptors: ClassVar[bool] = True

    def refine(self, observations, *, rng: np.random.Generator):  # pragma: no cover - interface
        """Return a :class:`~ctpipe.data.ScanSolution` for :class:`~ctpipe.data.ScanObservations`."""
        raise NotImplementedError


STAGE_KINDS: dict[str, type[Stage]] = {
    "detector": Detector,
    "matcher": Matcher,
    "estimator": Estimator,
    "refiner": Refiner,
}
