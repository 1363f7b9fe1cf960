"""Reconstruction grids: where every voxel of a volume array sits in the object frame.

Frames
------
The object frame is the camera frame of :mod:`ctpipe.geometry` at turntable angle 0, moved so
that its origin lies on the rotation axis at the height of the central ray: ``x`` along the
detector rows (increasing column), ``y`` along the rotation axis (increasing detector row, i.e.
downwards on the displayed projection), ``z`` from the source towards the detector. A point
``X`` of the object is seen in the view at turntable angle ``theta`` at::

    X_cam = R(theta) X + c,   c = (0, 0, source_to_object_mm)

with ``R`` of :func:`ctpipe.model.rotation_matrix`, so that the pair (i, j) is turned by
``theta_j - theta_i`` in the sign convention of :mod:`ctpipe.model`.

Volume arrays
-------------
A volume is a float32 array indexed ``volume[iy, iz, ix]``, shape ``(n_y, n_z, n_x)``: the
first index runs along the rotation axis, so ``volume[k]`` is an axial slice (rows along
``z``, columns along ``x``). Voxel ``(iy, iz, ix)`` is centred at::

    x = centre_mm[0] + (ix - (n_x - 1) / 2) * voxel_size_mm
    y = centre_mm[1] + (iy - (n_y - 1) / 2) * voxel_size_mm
    z = centre_mm[2] + (iz - (n_z - 1) / 2) * voxel_size_mm
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ctpipe._shared.checks import as_integer, as_real, short_repr
from ctpipe.errors import InputError

__all__ = ["VolumeGrid"]


@dataclass(frozen=True)
class VolumeGrid:
    """A regular grid of cubic voxels in the object frame.

    Parameters
    ----------
    n_x, n_y, n_z : int
        Voxels along x (lateral), y (rotation axis) and z (depth at angle 0).
    voxel_size_mm : float
        Edge length of a voxel.
    centre_mm : tuple of 3 floats
        Object-frame position ``(x, y, z)`` of the grid centre; default the origin.
    """

    n_x: int
    n_y: int
    n_z: int
    voxel_size_mm: float
    centre_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        # numpy scalars are accepted and stored as Python ints and floats.
        for name in ("n_x", "n_y", "n_z"):
            value = as_integer(getattr(self, name))
            if value is None or value <= 0:
                raise InputError(f"grid.{name}: must be an integer > 0, got {short_repr(getattr(self, name))}")
            object.__setattr__(self, name, value)
        size = as_real(self.voxel_size_mm)
        if size is None or not (math.isfinite(size) and size > 0):
            raise InputError(f"grid.voxel_size_mm: must be a finite number > 0, got {short_repr(self.voxel_size_mm)}")
        object.__setattr__(self, "voxel_size_mm", size)
        try:
            centre = tuple(float(c) for c in np.asarray(self.centre_mm, dtype=np.float64).reshape(-1))
        except (TypeError, ValueError):
            centre = ()
        if len(centre) != 3 or not all(math.isfinite(c) for c in centre):
            raise InputError(f"grid.centre_mm: must be 3 finite numbers (x, y, z), got {short_repr(self.centre_mm)}")
        object.__setattr__(self, "centre_mm", centre)

    @classmethod
    def cube(cls, n: int, voxel_size_mm: float, centre_mm=(0.0, 0.0, 0.0)) -> "VolumeGrid":
        """An ``n x n x n`` grid."""
        return cls(n, n, n, voxel_size_mm, centre_mm)

    @property
    def shape(self) -> tuple[int, int, int]:
        """Array shape ``(n_y, n_z, n_x)`` of a volume on this grid."""
        return (self.n_y, self.n_z, self.n_x)

    def axis_mm(self, axis: str) -> np.ndarray:
        """Voxel-centre coordinates along ``"x"``, ``"y"`` or ``"z"``, float64."""
        n = {"x": self.n_x, "y": self.n_y, "z": self.n_z}[axis]
        c = self.centre_mm["xyz".index(axis)]
        return c + (np.arange(n) - (n - 1) / 2.0) * self.voxel_size_mm

    @property
    def origin_mm(self) -> np.ndarray:
        """Object-frame position ``(x, y, z)`` of the centre of voxel ``(0, 0, 0)``."""
        half = (np.array([self.n_x, self.n_y, self.n_z]) - 1) / 2.0
        return np.asarray(self.centre_mm) - half * self.voxel_size_mm

    @property
    def extent_mm(self) -> np.ndarray:
        """Edge lengths ``(x, y, z)`` of the grid."""
        return np.array([self.n_x, self.n_y, self.n_z]) * self.voxel_size_mm

    def to_dict(self) -> dict:
        return {"n_x": self.n_x, "n_y": self.n_y, "n_z": self.n_z, "voxel_size_mm": self.voxel_size_mm,
                "centre_mm": list(self.centre_mm)}
