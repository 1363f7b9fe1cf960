"""Sample holders: what sits in the beam besides the sample, turning with it or not.

A scan spec's optional ``holder`` key (off by default)::

    holder:
      origin: sample_bottom        # or axis (default): where y = 0 of the objects below is
      turning:                     # turns with the sample: a pin or tube it is glued to
        - cylinder: {centre_mm: [0, 15, 0], radius_mm: 3, height_mm: 30, material: aluminium}
      static:                      # does not turn: a table edge, a clamp, the stage's top plate
        - box: {centre_mm: [60, 34, 0], size_mm: [100, 8, 200], material: aluminium}

``turning`` and ``static`` are object lists of the phantom schema (:mod:`ctpipe.sim.phantoms`:
primitives with densities or materials, and the generators), in the object frame. With
``origin: sample_bottom`` they are moved down the rotation axis by the phantom's half height
(``y`` points down the detector rows), so ``y = 0`` is the sample's lowest point and one holder
fits every phantom; with ``origin: axis`` positions are absolute.

The holder lives in the scan spec, not in the phantom, because it belongs to the scanner set-up:
the same pin and table hold every sample, so a sweep draws holder and phantom independently,
and a phantom file stays the sample alone (what reconstructions are compared against). The
simulator adds the turning objects to the phantom's and projects the static ones at turntable
angle 0 in every view (:func:`ctpipe.sim.simulator.simulate`), so they stay put on the detector
while everything else turns (on a misaligned scanner they follow the detector's drift).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ctpipe.config import check_keys
from ctpipe.errors import ConfigError
from ctpipe.sim.primitives import Primitives

__all__ = ["Holder", "parse_holder", "HOLDER_ORIGINS"]

#: Values of ``holder.origin``.
HOLDER_ORIGINS = ("axis", "sample_bottom")


@dataclass(frozen=True, eq=False)
class Holder:
    """A validated holder (see the module docstring).

    Attributes
    ----------
    turning, static : Primitives
        Objects that turn with the sample, and objects that do not (either may be empty), with
        ``origin`` not yet applied.
    origin : str
        One of :data:`HOLDER_ORIGINS`.
    mapping : dict
        The mapping it was parsed from (``to_dict`` gives it back).
    """

    turning: Primitives
    static: Primitives
    origin: str = "axis"
    mapping: dict | None = None

    def placed(self, phantom) -> tuple[Primitives, Primitives]:
        """``(turning, static)`` in the object frame of ``phantom`` (``origin`` applied)."""
        if self.origin == "axis":
            return self.turning, self.static
        shift = np.array([0.0, float(phantom.half_height_mm), 0.0])
        return tuple(replace(p, centre_mm=p.centre_mm + shift) for p in (self.turning, self.static))

    def to_dict(self) -> dict:
        return copy.deepcopy(self.mapping or {})


def parse_holder(value: Any, path: str = "holder") -> Holder | None:
    """Validate a scan spec's ``holder`` (None or a mapping; see the module docstring)."""
    if value is None:
        return None
    from ctpipe.sim.phantoms import parse_objects

    check_keys(value, path, allowed=("origin", "turning", "static"))
    origin = value.get("origin", "axis")
    if origin not in HOLDER_ORIGINS:
        raise ConfigError(f"{path}.origin: must be one of {', '.join(HOLDER_ORIGINS)}, got {origin!r}")
    if "turning" not in value and "static" not in value:
        raise ConfigError(f"{path}: give turning or static objects (or both), or leave holder out")
    empty = Primitives.concatenate([])
    turning = parse_objects(value["turning"], f"{path}.turning") if "turning" in value else empty
    static = parse_objects(value["static"], f"{path}.static") if "static" in value else empty
    return Holder(turning, static, origin, copy.deepcopy(dict(value)))
