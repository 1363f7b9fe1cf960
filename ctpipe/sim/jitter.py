"""Nominal turntable angles and the angle errors of a real stage, with the truth kept.

A scan is commanded at nominal angles; the stage actually stops at ``true = nominal +
offsets``. The offsets are the sum of the components of a :class:`Jitter`, each a model of
one mechanical error, drawn from an explicit ``numpy.random.Generator``::

    jitter:                                   # a YAML list; [] or null means no jitter
      - gaussian: {sigma_deg: 0.2}            # i.i.d. per view
      - random_walk: {sigma_deg: 0.02}        # drift: offsets[k] = sum of k steps of sigma_deg
      - periodic: {amplitude_deg: 0.1, phase_deg: 0, harmonic: 1}   # encoder eccentricity
      - jumps: {count: 3, size_deg: 1.0}      # backlash: persistent steps at random views
      - jumps: {rate_per_view: 0.01, size_deg: 0.5, size_sigma_deg: 0.1, sign: positive}

``jumps`` takes exactly one of ``count`` (that many jumps, at distinct views 1..V-1) or
``rate_per_view`` (each of the V-1 steps jumps with this probability). A jump before view
``k`` offsets views ``k, k+1, ...``: a persistent step. Its size is
``size_deg + size_sigma_deg * N(0, 1)`` with a random sign (``sign: random``, the default)
or always ``positive``/``negative``.

Components draw from the generator in list order, so the same list and seed give the same
offsets. The first view of a random walk has offset 0; ``periodic`` uses no randomness.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np

from ctpipe.config import check_keys
from ctpipe.errors import ConfigError, InputError
from ctpipe.stages import ParamSpec, check_value

__all__ = ["nominal_angles_deg", "JitterModel", "GaussianJitter", "RandomWalkJitter", "PeriodicJitter",
           "JumpJitter", "Jitter", "parse_jitter", "JITTER_KINDS"]


def nominal_angles_deg(n_views: int, range_deg: float = 360.0, start_deg: float = 0.0,
                       closing_view: bool = False) -> np.ndarray:
    """Uniformly spaced commanded angles, shape (n_views,), float64, degrees.

    A full scan (``range_deg`` a multiple of 360) excludes the endpoint, which would repeat the
    first view: step ``range_deg / n_views``. A short scan includes it, so that the last view
    is at ``start_deg + range_deg``: step ``range_deg / (n_views - 1)``; so does a full scan with
    ``closing_view``, whose last view is the first again a turn on (a scanner's closing image).
    """
    if not (isinstance(n_views, (int, np.integer)) and not isinstance(n_views, bool) and n_views >= 1):
        raise InputError(f"n_views: must be an integer >= 1, got {n_views!r}")
    if not (math.isfinite(range_deg) and range_deg > 0):
        raise InputError(f"range_deg: must be a finite number > 0, got {range_deg!r}")
    full = math.isclose(range_deg / 360.0, round(range_deg / 360.0), abs_tol=1e-12) and range_deg >= 360.0 \
        and not closing_view
    if n_views == 1:
        return np.array([float(start_deg)])
    step = range_deg / n_views if full else range_deg / (n_views - 1)
    return start_deg + step * np.arange(n_views, dtype=np.float64)


class JitterModel:
    """One component of the angle error; a frozen dataclass with a ``sample`` method."""

    kind: ClassVar[str] = ""

    def sample(self, nominal_deg: np.ndarray, rng: np.random.Generator) -> np.ndarray:  # pragma: no cover
        """Offsets (degrees) of shape ``nominal_deg.shape`` to add to the nominal angles."""
        raise NotImplementedError

    def to_dict(self) -> dict:
        """The one-key YAML mapping that parses back to this model."""
        return {self.kind: {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}}


def _views(nominal_deg) -> np.ndarray:
    nominal = np.asarray(nominal_deg, dtype=np.float64)
    if nominal.ndim != 1:
        raise InputError(f"nominal_deg: must be a 1-D array of angles, got shape {nominal.shape}")
    return nominal


@dataclass(frozen=True)
class GaussianJitter(JitterModel):
    """Independent normal errors of standard deviation ``sigma_deg`` at every view."""

    sigma_deg: float
    kind: ClassVar[str] = "gaussian"

    def sample(self, nominal_deg, rng):
        nominal = _views(nominal_deg)
        return rng.normal(0.0, self.sigma_deg, nominal.shape)


@dataclass(frozen=True)
class RandomWalkJitter(JitterModel):
    """Drift: independent normal steps of ``sigma_deg`` between views, starting at 0."""

    sigma_deg: float
    kind: ClassVar[str] = "random_walk"

    def sample(self, nominal_deg, rng):
        nominal = _views(nominal_deg)
        steps = rng.normal(0.0, self.sigma_deg, max(len(nominal) - 1, 0))
        return np.concatenate([[0.0], np.cumsum(steps)])[: len(nominal)]


@dataclass(frozen=True)
class PeriodicJitter(JitterModel):
    """Encoder eccentricity: ``amplitude_deg * sin(harmonic * nominal + phase_deg)``."""

    amplitude_deg: float
    phase_deg: float = 0.0
    harmonic: int = 1
    kind: ClassVar[str] = "periodic"

    def sample(self, nominal_deg, rng):
        nominal = _views(nominal_deg)
        return self.amplitude_deg * np.sin(np.deg2rad(self.harmonic * nominal + self.phase_deg))


@dataclass(frozen=True)
class JumpJitter(JitterModel):
    """Backlash: occasional persistent steps (see the module docstring)."""

    size_deg: float
    count: int | None = None
    rate_per_view: float | None = None
    size_sigma_deg: float = 0.0
    sign: Literal["random", "positive", "negative"] = "random"
    kind: ClassVar[str] = "jumps"

    def sample(self, nominal_deg, rng):
        nominal = _views(nominal_deg)
        n_steps = max(len(nominal) - 1, 0)
        if self.count is not None:
            if self.count > n_steps:
                raise InputError(f"jumps.count: {self.count} jumps need at least {self.count + 1} views, "
                                 f"got {len(nominal)}")
            where = np.sort(rng.choice(n_steps, size=self.count, replace=False)) + 1 if self.count else np.zeros(0, int)
        else:
            where = np.flatnonzero(rng.random(n_steps) < self.rate_per_view) + 1
        sizes = self.size_deg + self.size_sigma_deg * rng.normal(size=len(where))
        if self.sign == "random":
            sizes = sizes * rng.choice([-1.0, 1.0], size=len(where))
        elif self.sign == "negative":
            sizes = -sizes
        steps = np.zeros(len(nominal))
        np.add.at(steps, where, sizes)
        return np.cumsum(steps)

    def to_dict(self) -> dict:
        params = {"size_deg": self.size_deg, "size_sigma_deg": self.size_sigma_deg, "sign": self.sign}
        params.update({"count": self.count} if self.count is not None else {"rate_per_view": self.rate_per_view})
        return {self.kind: params}


@dataclass(frozen=True)
class Jitter:
    """The sum of jitter components; empty means the stage stops exactly at the nominal angles."""

    components: tuple[JitterModel, ...] = ()

    def sample(self, nominal_deg, rng: np.random.Generator) -> np.ndarray:
        """Offsets (degrees), shape (V,): the sum of every component's draw, in list order."""
        nominal = _views(nominal_deg)
        total = np.zeros(nominal.shape)
        for component in self.components:
            total = total + component.sample(nominal, rng)
        return total

    def to_dict(self) -> list:
        """The YAML list that parses back to this jitter."""
        return [component.to_dict() for component in self.components]

    def __bool__(self) -> bool:
        return bool(self.components)


_PARAMS: dict[str, dict[str, ParamSpec]] = {
    "gaussian": {"sigma_deg": ParamSpec("sigma_deg", float, None, "", ge=0, le=360)},
    "random_walk": {"sigma_deg": ParamSpec("sigma_deg", float, None, "", ge=0, le=360)},
    "periodic": {"amplitude_deg": ParamSpec("amplitude_deg", float, None, "", ge=-360, le=360),
                 "phase_deg": ParamSpec("phase_deg", float, 0.0, "", ge=-36_000, le=36_000),
                 "harmonic": ParamSpec("harmonic", int, 1, "", ge=1, le=100_000)},
    "jumps": {"count": ParamSpec("count", int, None, "", ge=0, le=100_000),
              "rate_per_view": ParamSpec("rate_per_view", float, None, "", ge=0, le=1),
              "size_deg": ParamSpec("size_deg", float, None, "", ge=0, le=360),
              "size_sigma_deg": ParamSpec("size_sigma_deg", float, 0.0, "", ge=0, le=360),
              "sign": ParamSpec("sign", Literal["random", "positive", "negative"], "random", "")},
}
_REQUIRED = {"gaussian": ("sigma_deg",), "random_walk": ("sigma_deg",), "periodic": ("amplitude_deg",),
             "jumps": ("size_deg",)}
_CLASSES = {"gaussian": GaussianJitter, "random_walk": RandomWalkJitter, "periodic": PeriodicJitter,
            "jumps": JumpJitter}

#: Jitter component names a YAML list accepts.
JITTER_KINDS = tuple(_CLASSES)


def _parse_component(kind: str, params: Any, path: str) -> JitterModel:
    table = _PARAMS[kind]
    check_keys(params, path, allowed=tuple(table), required=_REQUIRED[kind])
    values = {key: check_value(table[key], value, f"{path}.{key}") for key, value in params.items()}
    if kind == "jumps" and ("count" in values) == ("rate_per_view" in values):
        raise ConfigError(f"{path}: give exactly one of count (a number of jumps) or rate_per_view (a probability)")
    return _CLASSES[kind](**values)


def parse_jitter(value: Any, path: str = "jitter") -> Jitter:
    """Validate a YAML jitter list (see the module docstring); None or [] is no jitter."""
    if value is None:
        return Jitter()
    if not isinstance(value, list):
        raise ConfigError(f"{path}: must be a list of one-key mappings {{kind: parameters}} with kind one of "
                          f"{', '.join(JITTER_KINDS)}, got {value!r}")
    components = []
    for i, item in enumerate(value):
        where = f"{path}[{i}]"
        if not isinstance(item, Mapping) or len(item) != 1:
            raise ConfigError(f"{where}: must be a one-key mapping {{kind: parameters}} with kind one of "
                              f"{', '.join(JITTER_KINDS)}, got {item!r}")
        ((kind, params),) = item.items()
        if kind not in _CLASSES:
            raise ConfigError(f"{where}.{kind}: unknown jitter kind; allowed: {', '.join(JITTER_KINDS)}")
        components.append(_parse_component(kind, params, f"{where}.{kind}"))
    return Jitter(tuple(components))
