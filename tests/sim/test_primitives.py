"""Voxelisation of analytic primitives: mass, partial volumes and input checks."""

from __future__ import annotations

import numpy as np
import pytest

from ctpipe.errors import InputError
from ctpipe.model import rotation_matrix
from ctpipe.recon.volume import VolumeGrid
from ctpipe.sim.primitives import Primitives, unit_interval, voxelise

GRID = VolumeGrid.cube(64, 0.5, centre_mm=(0.5, -0.3, 0.2))


def _tilt(a: float, b: float) -> np.ndarray:
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(b), -np.sin(b)], [0.0, np.sin(b), np.cos(b)]])
    return rotation_matrix(a) @ tilt


@pytest.mark.parametrize("kind, volume_of", [
    (0, lambda h: 4.0 / 3.0 * np.pi * h.prod()),
    (1, lambda h: np.pi * h[0] * h[2] * 2.0 * h[1]),
    (2, lambda h: 8.0 * h.prod()),
])
def test_total_mass_is_density_times_volume(kind, volume_of):
    half = np.array([9.0, 6.0, 4.5])
    prim = Primitives(np.array([kind]), np.array([[1.0, -2.0, 0.7]]), half[None], _tilt(0.5, 0.3)[None],
                      np.array([0.03]))
    volume = voxelise(prim, GRID, supersample=2)
    assert volume.shape == GRID.shape and volume.dtype == np.float32
    mass = volume.sum(dtype=np.float64) * GRID.voxel_size_mm ** 3
    assert mass == pytest.approx(0.03 * volume_of(half), rel=0.01)


def test_overlapping_densities_add_and_values_are_means():
    prims = Primitives(np.array([2, 2]), np.zeros((2, 3)), np.array([[5.0, 5.0, 5.0], [2.0, 2.0, 2.0]]),
                       np.stack([np.eye(3)] * 2), np.array([0.01, -0.004]))
    volume = voxelise(prims, VolumeGrid.cube(32, 0.5), supersample=2)
    assert volume.max() == pytest.approx(0.01)
    assert volume.min() == pytest.approx(0.0)
    assert volume[16, 16, 16] == pytest.approx(0.006)
    assert np.all(volume <= 0.01 + 1e-7)


def test_unit_intervals_of_an_axis_ray():
    # u(t) = (-2 + 4 t, 0.5, 0): enters every unit shape where u_x = -1 ... the exit depends on the shape.
    t_in, t_out = unit_interval(0, -2.0, 0.5, 0.0, 4.0, 0.0, 0.0)
    assert (t_out - t_in) * 4.0 == pytest.approx(2.0 * np.sqrt(0.75), rel=1e-12)
    t_in, t_out = unit_interval(1, -2.0, 0.5, 0.0, 4.0, 0.0, 0.0)
    assert (t_out - t_in) * 4.0 == pytest.approx(2.0, rel=1e-12)
    t_in, t_out = unit_interval(2, -2.0, 1.5, 0.0, 4.0, 0.0, 0.0)
    assert t_out <= t_in


def test_bad_inputs_raise_input_error():
    prim = Primitives(np.array([0]), np.zeros((1, 3)), np.ones((1, 3)), np.eye(3)[None], np.array([1.0]))
    with pytest.raises(InputError, match="supersample"):
        voxelise(prim, GRID, supersample=0)
    with pytest.raises(InputError, match="grid"):
        voxelise(prim, (64, 64, 64))
    with pytest.raises(InputError, match="primitives"):
        voxelise([prim], GRID)
