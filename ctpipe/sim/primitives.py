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
:mod:`ctpipe.recon.volume`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import prange

from ctpipe._shared.jit import FASTMATH, njit
from ctpipe.errors import InputError
from ctpipe.recon.volume import VolumeGrid

__all__ = ["Primitives", "KINDS", "voxelise", "unit_interval", "local_maps"]

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
    material : ndarray of shape (N,), int32, or None
        Index into ``materials`` of what a polychromatic beam (:mod:`ctpipe.sim.beam`) sees,
        -1 for none (water-equivalent to ``density_per_mm``); None means -1 everywhere.
    mass_density_g_cm3 : ndarray of shape (N,), float64, or None
        Mass density added inside the primitive for its ``material`` (g/cm^3, may be negative);
        None means 0 everywhere.
    materials : tuple of str
        Material names (see :func:`ctpipe.sim.materials.resolve_material`) ``material`` indexes.
    """

    kind: np.ndarray
    centre_mm: np.ndarray
    half_size_mm: np.ndarray
    rotation: np.ndarray
    density_per_mm: np.ndarray
    material: np.ndarray | None = None
    mass_density_g_cm3: np.ndarray | None = None
    materials: tuple = ()

    def __post_init__(self) -> None:
        n = len(self.kind)
        arrays = {"kind": (np.int32, (n,)), "centre_mm": (np.float64, (n, 3)), "half_size_mm": (np.float64, (n, 3)),
                  "rotation": (np.float64, (n, 3, 3)), "density_per_mm": (np.float64, (n,)),
                  "material": (np.int32, (n,)), "mass_density_g_cm3": (np.float64, (n,))}
        if self.material is None:
            object.__setattr__(self, "material", np.full(n, -1, np.int32))
        if self.mass_density_g_cm3 is None:
            object.__setattr__(self, "mass_density_g_cm3", np.zeros(n))
        object.__setattr__(self, "materials", tuple(self.materials))
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
        if n and (self.material.min() < -1 or self.material.max() >= len(self.materials)):
            raise InputError(f"Primitives.material must be -1 or index materials {self.materials}")
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
        materials = tuple(dict.fromkeys(name for p in parts for name in p.materials))
        # Each part's material indices, renumbered into the merged table (-1 stays -1).
        material = np.concatenate([np.array([-1, *(materials.index(m) for m in p.materials)], np.int32)[p.material + 1]
                                   for p in parts])
        return cls(*(np.concatenate([getattr(p, name) for p in parts]) for name in
                     ("kind", "centre_mm", "half_size_mm", "rotation", "density_per_mm")), material,
                   np.concatenate([p.mass_density_g_cm3 for p in parts]), materials)

    def subset(self, mask) -> "Primitives":
        """The primitives where ``mask`` (bool of shape (N,)) is true, with the same ``materials``."""
        mask = np.asarray(mask, dtype=bool)
        return Primitives(self.kind[mask], self.centre_mm[mask], self.half_size_mm[mask], self.rotation[mask],
                          self.density_per_mm[mask], self.material[mask], self.mass_density_g_cm3[mask],
                          self.materials)

    def bounding_boxes_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned object-frame boxes ``(low, high)``, each of shape (N, 3), that contain each primitive."""
        # |R diag(h)| summed over local axes bounds the unit cube's image, which contains all three shapes.
        reach = np.abs(self.rotation) @ self.half_size_mm[:, :, None]
        reach = reach[:, :, 0]
        return self.centre_mm - reach, self.centre_mm + reach


def local_maps(primitives: Primitives) -> np.ndarray:
    """Object frame -> unit frame linear maps ``diag(1 / half_size_mm) @ rotation.T``, shape (N, 3, 3).

    ``u = local_maps[i] @ (X - centre_mm[i])`` is the local unit-shape coordinate of the object
    point ``X`` (mm). The map is affine, so a ray ``X(t) = S + t d`` keeps its parameter ``t``
    in the unit frame, and a chord is ``(t_out - t_in) * |d|``.
    """
    return np.ascontiguousarray(np.transpose(primitives.rotation, (0, 2, 1)) / primitives.half_size_mm[:, :, None])


@njit(cache=True, fastmath=False)
def _ellipsoid_interval(a0, a1, a2, b0, b1, b2):
    """``t`` interval of ``a + t b`` inside the unit ball; empty when ``t_in >= t_out``."""
    bb = b0 * b0 + b1 * b1 + b2 * b2
    if bb <= 0.0:
        return (-math.inf, math.inf) if a0 * a0 + a1 * a1 + a2 * a2 <= 1.0 else (0.0, 0.0)
    t_mid = -(a0 * b0 + a1 * b1 + a2 * b2) / bb
    # Distance from the centre to the line, from the nearest point itself rather than from
    # B^2 - AC: no cancellation between two large terms for rays far from the origin.
    m0 = a0 + t_mid * b0
    m1 = a1 + t_mid * b1
    m2 = a2 + t_mid * b2
    gap = 1.0 - (m0 * m0 + m1 * m1 + m2 * m2)
    if gap <= 0.0:
        return (0.0, 0.0)
    half = math.sqrt(gap / bb)
    return (t_mid - half, t_mid + half)


@njit(cache=True, fastmath=False)
def _slab_interval(a, b, t_in, t_out):
    """Intersect ``[t_in, t_out]`` with ``|a + t b| <= 1``."""
    if b == 0.0:
        if abs(a) > 1.0:
            return (0.0, 0.0)
        return (t_in, t_out)
    t_lo = (-1.0 - a) / b
    t_hi = (1.0 - a) / b
    if t_lo > t_hi:
        t_lo, t_hi = t_hi, t_lo
    return (max(t_in, t_lo), min(t_out, t_hi))


@njit(cache=True, fastmath=False)
def _cylinder_interval(a0, a1, a2, b0, b1, b2):
    """``t`` interval inside ``u_x^2 + u_z^2 <= 1, |u_y| <= 1`` (axis along local ``y``)."""
    bb = b0 * b0 + b2 * b2
    if bb <= 0.0:
        if a0 * a0 + a2 * a2 > 1.0:
            return (0.0, 0.0)
        t_in, t_out = -math.inf, math.inf
    else:
        t_mid = -(a0 * b0 + a2 * b2) / bb
        m0 = a0 + t_mid * b0
        m2 = a2 + t_mid * b2
        gap = 1.0 - (m0 * m0 + m2 * m2)
        if gap <= 0.0:
            return (0.0, 0.0)
        half = math.sqrt(gap / bb)
        t_in, t_out = t_mid - half, t_mid + half
    return _slab_interval(a1, b1, t_in, t_out)


@njit(cache=True, fastmath=False)
def _box_interval(a0, a1, a2, b0, b1, b2):
    """``t`` interval inside the unit cube ``|u_x|, |u_y|, |u_z| <= 1``."""
    t_in, t_out = _slab_interval(a0, b0, -math.inf, math.inf)
    t_in, t_out = _slab_interval(a1, b1, t_in, t_out)
    return _slab_interval(a2, b2, t_in, t_out)


@njit(cache=True, fastmath=False)
def unit_interval(kind, a0, a1, a2, b0, b1, b2):
    """Ray parameter interval ``(t_in, t_out)`` of ``u(t) = a + t b`` inside a unit shape.

    Parameters
    ----------
    kind : int
        Code of :data:`KINDS` (0 ellipsoid, 1 cylinder, 2 box).
    a0, a1, a2, b0, b1, b2 : float
        Ray origin ``a`` and direction ``b`` in the primitive's unit frame (see :func:`local_maps`).

    Returns
    -------
    (float, float)
        ``t_in < t_out`` when the line crosses the shape, else an empty interval
        (``t_in >= t_out``). Unbounded ends are infinite.
    """
    if kind == 0:
        return _ellipsoid_interval(a0, a1, a2, b0, b1, b2)
    if kind == 1:
        return _cylinder_interval(a0, a1, a2, b0, b1, b2)
    return _box_interval(a0, a1, a2, b0, b1, b2)


@njit(cache=True, fastmath=FASTMATH)
def _inside(kind, u0, u1, u2):
    if kind == 0:
        return u0 * u0 + u1 * u1 + u2 * u2 <= 1.0
    if kind == 1:
        return u0 * u0 + u2 * u2 <= 1.0 and abs(u1) <= 1.0
    return abs(u0) <= 1.0 and abs(u1) <= 1.0 and abs(u2) <= 1.0


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def _voxelise(volume, kind, centre, maps, density, lo_idx, hi_idx, origin, voxel, ss):
    """Add each primitive's mean density to the voxels of its index box.

    Parallel over axial slices ``iy``: every thread owns the slices it writes, and loops over
    the primitives whose box reaches that slice, so the work is the voxels inside the boxes.
    lo_idx, hi_idx : (N, 3) inclusive voxel index ranges in (x, y, z) order.
    """
    n_y = volume.shape[0]
    n_prim = kind.shape[0]
    inv = 1.0 / (ss * ss * ss)
    for iy in prange(n_y):
        for n in range(n_prim):
            if iy < lo_idx[n, 1] or iy > hi_idx[n, 1]:
                continue
            m = maps[n]
            k = kind[n]
            for iz in range(lo_idx[n, 2], hi_idx[n, 2] + 1):
                for ix in range(lo_idx[n, 0], hi_idx[n, 0] + 1):
                    count = 0
                    for jy in range(ss):
                        y = origin[1] + (iy + (jy + 0.5) / ss - 0.5) * voxel - centre[n, 1]
                        for jz in range(ss):
                            z = origin[2] + (iz + (jz + 0.5) / ss - 0.5) * voxel - centre[n, 2]
                            for jx in range(ss):
                                x = origin[0] + (ix + (jx + 0.5) / ss - 0.5) * voxel - centre[n, 0]
                                u0 = m[0, 0] * x + m[0, 1] * y + m[0, 2] * z
                                u1 = m[1, 0] * x + m[1, 1] * y + m[1, 2] * z
                                u2 = m[2, 0] * x + m[2, 1] * y + m[2, 2] * z
                                if _inside(k, u0, u1, u2):
                                    count += 1
                    if count:
                        volume[iy, iz, ix] += np.float32(density[n] * count * inv)


def voxelise(primitives: Primitives, grid: VolumeGrid, *, supersample: int = 2) -> np.ndarray:
    """Mean density of the primitives in every voxel of ``grid``.

    Each voxel averages ``supersample^3`` regularly spaced sub-samples (cell-centred), so edges
    are partial volumes. The cost is the number of voxels inside each primitive's bounding box
    times ``supersample^3``.

    Parameters
    ----------
    primitives : Primitives
    grid : VolumeGrid
    supersample : int
        Sub-samples per voxel edge, >= 1.

    Returns
    -------
    ndarray of shape grid.shape = (n_y, n_z, n_x), float32
        Density in 1/mm, indexed ``volume[iy, iz, ix]``.
    """
    if not isinstance(primitives, Primitives):
        raise InputError(f"primitives: must be a ctpipe.sim.primitives.Primitives, got {type(primitives).__name__}")
    if not isinstance(grid, VolumeGrid):
        raise InputError(f"grid: must be a ctpipe.recon.volume.VolumeGrid, got {type(grid).__name__}")
    if not (isinstance(supersample, (int, np.integer)) and not isinstance(supersample, bool) and supersample >= 1):
        raise InputError(f"supersample: must be an integer >= 1, got {supersample!r}")
    volume = np.zeros(grid.shape, dtype=np.float32)
    if len(primitives) == 0:
        return volume
    origin = grid.origin_mm
    size = np.array([grid.n_x, grid.n_y, grid.n_z])
    low, high = primitives.bounding_boxes_mm()
    # Voxels whose cell (centre +- half a voxel) meets the box.
    lo_idx = np.clip(np.floor((low - origin) / grid.voxel_size_mm - 0.5), 0, size)
    hi_idx = np.clip(np.ceil((high - origin) / grid.voxel_size_mm + 0.5), -1, size - 1)
    _voxelise(volume, primitives.kind, primitives.centre_mm, local_maps(primitives), primitives.density_per_mm,
              lo_idx.astype(np.int64), hi_idx.astype(np.int64), origin, float(grid.voxel_size_mm), int(supersample))
    return volume
