"""Analytic phantom primitives as flat arrays (what the projector and voxeliser consume).

Every primitive is a unit shape in its own local frame, scaled by ``half_size_mm``, turned by
``rotation`` and moved to ``centre_mm``::

    X_object = centre_mm + rotation @ (half_size_mm * u),   u in the unit shape

Unit shapes (local coordinates ``u = (u_x, u_y, u_z)``):

``ellipsoid`` (kind 0)  ``u_x^2 + u_y^2 + u_z^2 <= 1``; ``half_size_mm`` holds the semi-axes.
``cylinder``  (kind 1)  ``u_x^2 + u_z^2 <= 1`` and ``|u_y| <= 1``: the axis is the local ``y``,
                        so an unrotated cylinder stands along the rotation axis;
                        ``half_size_mm = (radius_x, half_height, radius_z)``.
``box``       (kind 2)  ``|u_x|, |u_y|, |u_z| <= 1``; ``half_size_mm`` holds the half edges.

Densities are linear attenuation coefficients in 1/mm and add where primitives overlap (a void
in a container is a primitive of negative density). Positions are in the object frame of
:mod:`ctpipe.volume`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ctpipe.errors import InputError

__all__ = ["Primitives", "KINDS"]

#: Primitive kinds, indexed by the ``kind`` code.
KINDS = ("ellipsoid", "cylinder", "box")


@dataclass(frozen=True, eq=False)
class Primitives:
    """N analytic primitives in the object frame.

    Attributes
    ----------
    kind : ndarray of shape (N,), int32
        Index into :data:`KINDS`.
    centre_mm : ndarray of shape (N, 3), float64
        Centre ``(x, y, z)``.
    half_size_mm : ndarray of shape (N, 3), float64
        Half extents along the local axes (see the module docstring), all > 0.
    rotation : ndarray of shape (N, 3, 3), float64
        Orthonormal, columns are the local axes in the object frame.
    density_per_mm : ndarray of shape (N,), float64
        Attenuation added inside the primitive, 1/mm (may be negative).
    """

    kind: np.ndarray
    centre_mm: np.ndarray
    half_size_mm: np.ndarray
    rotation: np.ndarray
    density_per_mm: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.kind)
        arrays = {"kind": (np.int32, (n,)), "centre_mm": (np.float64, (n, 3)), "half_size_mm": (np.float64, (n, 3)),
                  "rotation": (np.float64, (n, 3, 3)), "density_per_mm": (np.float64, (n,))}
        for name, (dtype, shape) in arrays.items():
            value = np.ascontiguousarray(np.asarray(getattr(self, name), dtype=dtype))
            if value.shape != shape:
                raise InputError(f"Primitives.{name} must have shape {shape}, got {value.shape}")
            if not np.all(np.isfinite(value)):
                raise InputError(f"Primitives.{name} has NaN or infinite values")
            value.flags.writeable = False
            object.__setattr__(self, name, value)
        if n and (self.kind.min() < 0 or self.kind.max() >= len(KINDS)):
            raise InputError(f"Primitives.kind must index {KINDS}, got codes {sorted(set(self.kind.tolist()))}")
        if n and self.half_size_mm.min() <= 0:
            raise InputError("Primitives.half_size_mm must be > 0 everywhere")
        if n and not np.allclose(np.einsum("nji,njk->nik", self.rotation, self.rotation), np.eye(3), atol=1e-9):
            raise InputError("Primitives.rotation must hold orthonormal 3x3 matrices")

    def __len__(self) -> int:
        return len(self.kind)

    @classmethod
    def concatenate(cls, parts: "list[Primitives]") -> "Primitives":
        """All primitives of ``parts`` in one set, in order."""
        if not parts:
            return cls(np.zeros(0, np.int32), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0))
        return cls(*(np.concatenate([getattr(p, name) for p in parts]) for name in
                     ("kind", "centre_mm", "half_size_mm", "rotation", "density_per_mm")))

    def bounding_boxes_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned object-frame boxes ``(low, high)``, each of shape (N, 3), that contain each primitive."""
        # |R diag(h)| summed over local axes bounds the unit cube's image, which contains all three shapes.
        reach = np.abs(self.rotation) @ self.half_size_mm[:, :, None]
        reach = reach[:, :, 0]
        return self.centre_mm - reach, self.centre_mm + reach
