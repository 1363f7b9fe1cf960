"""Cone-beam acquisition geometry and the pixel <-> normalised coordinate maps.

Frames
------
The source (the "camera" centre) is the origin. ``z`` runs along the central ray towards
the detector, ``x`` along the detector rows (increasing column), ``y`` along the detector
columns (increasing row, i.e. downwards on the displayed image). The rotation axis is
parallel to ``y`` and crosses the central ray at ``z = source_to_object_mm``.

A pixel position is given as OpenCV gives it, ``(x=col, y=row)``. Its normalised
coordinates are the tangent of the ray angle::

    x_n = (x - u0_px) * pixel_pitch_u_mm / source_to_detector_mm
    y_n = (y - v0_px) * pixel_pitch_v_mm / source_to_detector_mm

with ``(u0_px, v0_px)`` the pixel hit by the central ray (the principal point).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ctpipe._shared.checks import as_integer, as_real, short_repr
from ctpipe.errors import InputError

__all__ = ["Geometry", "FIELDS", "MAX_DETECTOR_PX", "check_geometry"]

#: Largest detector side accepted, pixels (flat panels have at most a few thousand).
MAX_DETECTOR_PX = 65_536

#: Type and bounds of every :class:`Geometry` field, declared once: :class:`Geometry` checks
#: them, and the YAML reader (:func:`ctpipe.config.parse_geometry`) reports them with their path.
FIELDS: dict[str, tuple[Any, dict[str, float]]] = {
    "source_to_object_mm": (float, {"gt": 0}),
    "source_to_detector_mm": (float, {"gt": 0}),
    "detector_cols": (int, {"ge": 1, "le": MAX_DETECTOR_PX}),
    "detector_rows": (int, {"ge": 1, "le": MAX_DETECTOR_PX}),
    "pixel_pitch_u_mm": (float, {"gt": 0}),
    "pixel_pitch_v_mm": (float, {"gt": 0}),
    "u0_px": (float | None, {}),
    "v0_px": (float | None, {}),
}


@dataclass(frozen=True)
class Geometry:
    """Circular cone-beam geometry with a flat detector.

    Parameters
    ----------
    source_to_object_mm : float
        Distance from the source to the rotation axis (SOD).
    source_to_detector_mm : float
        Distance from the source to the detector plane (SDD); must exceed SOD.
    detector_cols, detector_rows : int
        Detector size in pixels (x=col, y=row).
    pixel_pitch_u_mm, pixel_pitch_v_mm : float
        Pixel size along x (columns) and y (rows).
    u0_px, v0_px : float or None
        Principal point in pixels; ``None`` means the detector centre,
        ``(cols - 1) / 2`` and ``(rows - 1) / 2``.
    """

    source_to_object_mm: float
    source_to_detector_mm: float
    detector_cols: int
    detector_rows: int
    pixel_pitch_u_mm: float
    pixel_pitch_v_mm: float
    u0_px: float | None = None
    v0_px: float | None = None

    def __post_init__(self) -> None:
        # numpy scalars (np.float32(150), a value read from an array) are numbers too; they are
        # stored as Python floats and ints so that every consumer sees plain values.
        for name, (annotation, bounds) in FIELDS.items():
            if annotation is float:
                value = as_real(getattr(self, name))
                if value is None or not (math.isfinite(value) and value > bounds["gt"]):
                    raise InputError(f"geometry.{name}: must be a finite number > {bounds['gt']}, "
                                     f"got {short_repr(getattr(self, name))}")
                object.__setattr__(self, name, value)
            elif annotation is int:
                value = as_integer(getattr(self, name))
                if value is None or not bounds["ge"] <= value <= bounds["le"]:
                    raise InputError(f"geometry.{name}: must be an integer >= {bounds['ge']} and <= {bounds['le']}, "
                                     f"got {short_repr(getattr(self, name))}")
                object.__setattr__(self, name, value)
        if self.source_to_detector_mm <= self.source_to_object_mm:
            raise InputError(
                "geometry: source_to_detector_mm must exceed source_to_object_mm "
                f"(the axis must lie between source and detector), got SDD={self.source_to_detector_mm!r}, "
                f"SOD={self.source_to_object_mm!r}"
            )
        # Fill the principal point in once so that every consumer sees the same value.
        if self.u0_px is None:
            object.__setattr__(self, "u0_px", (self.detector_cols - 1) / 2.0)
        if self.v0_px is None:
            object.__setattr__(self, "v0_px", (self.detector_rows - 1) / 2.0)
        for name in ("u0_px", "v0_px"):
            value = as_real(getattr(self, name))
            if value is None or not math.isfinite(value):
                raise InputError(f"geometry.{name}: must be a finite number or null, got {short_repr(getattr(self, name))}")
            object.__setattr__(self, name, value)

    @property
    def magnification(self) -> float:
        """SDD / SOD: how much larger an object at the axis appears on the detector."""
        return self.source_to_detector_mm / self.source_to_object_mm

    @property
    def shape(self) -> tuple[int, int]:
        """Detector image shape ``(rows, cols)`` as numpy stores a projection."""
        return (self.detector_rows, self.detector_cols)

    def pixels_to_normalised(self, xy: np.ndarray) -> np.ndarray:
        """Map pixel positions ``(x=col, y=row)`` to normalised coordinates.

        Parameters
        ----------
        xy : ndarray of shape (N, 2)

        Returns
        -------
        ndarray of shape (N, 2), float64
        """
        xy = np.asarray(xy, dtype=np.float64)
        scale = np.array([self.pixel_pitch_u_mm, self.pixel_pitch_v_mm]) / self.source_to_detector_mm
        return (xy - np.array([self.u0_px, self.v0_px])) * scale

    def normalised_to_pixels(self, q: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`pixels_to_normalised`; ``q`` has shape (N, 2)."""
        q = np.asarray(q, dtype=np.float64)
        scale = self.source_to_detector_mm / np.array([self.pixel_pitch_u_mm, self.pixel_pitch_v_mm])
        return q * scale + np.array([self.u0_px, self.v0_px])

    def to_dict(self) -> dict:
        """Plain mapping with the field names as keys (YAML/JSON friendly)."""
        return {name: getattr(self, name) for name in self.__dataclass_fields__}


def check_geometry(geometry) -> Geometry:
    """``geometry`` itself if it is a :class:`Geometry`, else an InputError naming what it is."""
    if not isinstance(geometry, Geometry):
        raise InputError(f"geometry: must be a ctpipe.geometry.Geometry, got {type(geometry).__name__}")
    return geometry
