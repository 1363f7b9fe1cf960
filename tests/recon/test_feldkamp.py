"""FDK against closed-form line integrals through ellipsoids.

The projections are exact line integrals through a phantom of a few ellipsoids (solve the
quadratic of the ray in each ellipsoid's unit frame), computed with numpy by :mod:`ctpipe.testing`
so that the test depends on nothing but the geometry convention. Errors are measured in the
interior: voxels at least ``MARGIN_MM`` from every ellipsoid surface, where a band-limited
reconstruction can match the piecewise-constant phantom.
"""

from __future__ import annotations

import numpy as np
import pytest

from ctpipe.errors import InputError
from ctpipe.geometry import Geometry
from ctpipe.recon.feldkamp import FILTERS, fdk, parker_weights, view_weights
from ctpipe.recon.volume import VolumeGrid
from ctpipe.testing import phantom_volume, project_ellipsoids, relative_rmse

# SOD 200, SDD 400, 160^2 pixels of 0.5 mm: half fan angle 5.7 deg, a field of view of radius
# 19.9 mm at the axis; the phantom reaches 14 mm in x and z, 13 mm along the axis.
GEOMETRY = Geometry(source_to_object_mm=200.0, source_to_detector_mm=400.0, detector_cols=160,
                    detector_rows=160, pixel_pitch_u_mm=0.5, pixel_pitch_v_mm=0.5)
GRID = VolumeGrid.cube(128, 0.25)


@pytest.fixture(scope="module")
def truth():
    return phantom_volume(GRID)


@pytest.fixture(scope="module")
def full_scan():
    angles = np.arange(240) * 1.5
    return project_ellipsoids(GEOMETRY, angles), angles


def test_full_scan_reconstructs_the_phantom_interior(full_scan, truth):
    projections, angles = full_scan
    volume = fdk(projections, GEOMETRY, angles, GRID)
    assert volume.shape == GRID.shape and volume.dtype == np.float32
    assert relative_rmse(volume, *truth) <= 0.05


@pytest.mark.parametrize("filter", ["ram-lak", "shepp-logan"])
def test_every_window_keeps_the_density_scale(full_scan, truth, filter):
    projections, angles = full_scan
    volume = fdk(projections, GEOMETRY, angles, GRID, filter=filter)
    assert relative_rmse(volume, *truth) <= 0.05


def test_negated_angles_reconstruct_clearly_worse(full_scan, truth):
    """The sign convention: negated angles reconstruct the mirror image (z -> -z)."""
    projections, angles = full_scan
    right = relative_rmse(fdk(projections, GEOMETRY, angles, GRID), *truth)
    wrong = relative_rmse(fdk(projections, GEOMETRY, -angles, GRID), *truth)
    assert wrong > 10.0 * right and wrong > 0.1


def test_jittered_unsorted_angles_reconstruct_as_well_as_uniform(full_scan, truth):
    rng = np.random.default_rng(7)
    uniform = relative_rmse(fdk(*full_scan[:1], GEOMETRY, full_scan[1], GRID), *truth)
    angles = full_scan[1] + rng.uniform(-0.6, 0.6, full_scan[1].size) * 1.5
    angles = angles[rng.permutation(angles.size)]
    jittered = relative_rmse(fdk(project_ellipsoids(GEOMETRY, angles), GEOMETRY, angles, GRID), *truth)
    assert jittered <= uniform + 0.005


def test_full_turn_that_lost_two_degrees_to_backlash_is_still_a_full_scan(truth):
    """A full turn whose stage lost 2 deg spans 358 deg but leaves no wedge out.

    Judged by its span it would be Parker-weighted as a short scan, which throws away half the
    data and reconstructs clearly worse than the same scan weighted as the full turn it is.
    """
    nominal = np.arange(240) * 1.5
    angles = nominal - np.linspace(0.0, 2.0, nominal.size)
    projections = project_ellipsoids(GEOMETRY, angles)
    as_is = relative_rmse(fdk(projections, GEOMETRY, angles, GRID), *truth)
    full = relative_rmse(fdk(projections, GEOMETRY, angles, GRID, short_scan=False), *truth)
    assert as_is == pytest.approx(full, rel=1e-6)
    assert as_is <= 0.05


def test_unevenly_sampled_angles_are_weighted_by_their_intervals(truth):
    """1 deg steps over two opposite quadrants, 2 deg over the others: equal weights give ~4 % error."""
    angles = np.concatenate([np.arange(0, 90, 1.0), np.arange(90, 180, 2.0),
                             np.arange(180, 270, 1.0), np.arange(270, 360, 2.0)])
    volume = fdk(project_ellipsoids(GEOMETRY, angles), GEOMETRY, angles, GRID)
    assert relative_rmse(volume, *truth) <= 0.01


def test_short_scan_with_parker_weights(truth):
    fan_deg = 2.0 * np.degrees(np.arctan(79.5 * 0.5 / 400.0))
    angles = 10.0 + np.linspace(0.0, 180.0 + fan_deg + 3.0, 200)
    volume = fdk(project_ellipsoids(GEOMETRY, angles), GEOMETRY, angles, GRID)
    assert relative_rmse(volume, *truth) <= 0.02


def test_principal_point_offset_gives_the_same_reconstruction(full_scan, truth):
    projections, angles = full_scan
    centred = fdk(projections, GEOMETRY, angles, GRID)
    shifted = Geometry(**{**GEOMETRY.to_dict(), "u0_px": 79.5 + 9.3, "v0_px": 79.5 - 6.7})
    offset = fdk(project_ellipsoids(shifted, angles), shifted, angles, GRID)
    assert relative_rmse(offset, *truth) <= 0.05
    assert relative_rmse(offset, centred, truth[1]) <= 0.01
    # Ignoring the offset is clearly visible, so the test above has teeth.
    assert relative_rmse(fdk(project_ellipsoids(shifted, angles), GEOMETRY, angles, GRID), *truth) > 0.1


def test_view_weights_cover_the_circle_once():
    rng = np.random.default_rng(3)
    angles = rng.permutation(np.sort(rng.uniform(0.0, 2.0 * np.pi, 50)))
    weights = view_weights(angles, full_scan=True)
    assert weights.sum() == pytest.approx(2.0 * np.pi)
    assert np.all(weights > 0)
    short = view_weights(np.array([0.0, 0.1, 0.3, 0.6]), full_scan=False)
    np.testing.assert_allclose(short, [0.05, 0.15, 0.25, 0.15])


def test_parker_weights_of_the_two_measurements_of_a_ray_add_up_to_one():
    delta = np.deg2rad(8.0)
    gamma = np.deg2rad(np.linspace(-7.0, 7.0, 15))
    beta = np.linspace(0.0, np.pi + 2.0 * delta, 301)
    w = parker_weights(beta, gamma, delta)
    # The ray (beta, gamma) is measured again at (beta + pi + 2 gamma, -gamma).
    for j, g in enumerate(gamma):
        conjugate = beta + np.pi + 2.0 * g
        inside = conjugate <= np.pi + 2.0 * delta
        w_conj = parker_weights(conjugate[inside], -gamma[j:j + 1], delta)[:, 0]
        np.testing.assert_allclose(w[inside, j] + w_conj, 1.0, atol=1e-12)


def test_progress_counts_every_view():
    angles = np.arange(40) * 9.0
    projections = project_ellipsoids(GEOMETRY, angles)
    seen = []
    fdk(projections, GEOMETRY, angles, VolumeGrid.cube(8, 2.0), progress=seen.append)
    assert sum(seen) == angles.size


def _bad(**changes):
    angles = np.arange(8) * 45.0
    args = {"projections": np.zeros((8, 160, 160), np.float32), "geometry": GEOMETRY, "angles_deg": angles,
            "grid": VolumeGrid.cube(4, 1.0)}
    args.update(changes)
    return args


@pytest.mark.parametrize("changes, message", [
    ({"projections": np.zeros((8, 160), np.float32)}, "3-D float"),
    ({"projections": np.zeros((8, 160, 160), np.int16)}, "3-D float"),
    ({"projections": np.zeros((7, 160, 160), np.float32)}, "shape"),
    ({"projections": np.zeros((8, 160, 150), np.float32)}, "shape"),
    ({"projections": np.full((8, 160, 160), np.nan, np.float32)}, "NaN"),
    ({"angles_deg": np.zeros((8, 1))}, "1-D"),
    ({"angles_deg": np.r_[np.arange(7) * 45.0, np.inf]}, "finite"),
    ({"filter": "butterworth"}, "ram-lak"),
    ({"angles_deg": np.linspace(0.0, 150.0, 8)}, r"at least 191\.35 deg \(180 \+ fan angle 11\.35 deg\)"),
    ({"angles_deg": np.arange(8) * 60.0, "short_scan": True}, "< 360 deg"),
    ({"short_scan": "yes"}, "short_scan"),
    ({"grid": (4, 4, 4)}, "VolumeGrid"),
])
def test_bad_inputs_raise_one_line_input_errors(changes, message):
    with pytest.raises(InputError, match=message) as info:
        fdk(**_bad(**changes))
    assert "\n" not in str(info.value)


def test_limited_angle_scan_when_asked():
    angles = np.linspace(0.0, 150.0, 76)
    volume = fdk(project_ellipsoids(GEOMETRY, angles), GEOMETRY, angles, VolumeGrid.cube(16, 2.0), short_scan=False)
    assert np.all(np.isfinite(volume))


def test_filters_are_listed():
    assert FILTERS == ("ram-lak", "shepp-logan", "cosine", "hamming", "hann")


def test_a_dense_turn_with_jitter_as_large_as_its_step_is_a_full_scan():
    """1,440 views 0.25 deg apart with 0.2 deg jitter: sorted, most gaps are tiny and a few near a
    degree. Judged against the median gap, such a gap looked like a missing wedge, and FDK refused
    the angles as a short scan spanning 360 deg (projection matching stopped on it)."""
    from ctpipe.recon.feldkamp import covers_full_circle

    for seed in (18, 26, 35):    # the old rule called these short scans
        angles = np.arange(1440) * 0.25 + np.random.default_rng(seed).normal(0.0, 0.2, 1440)
        assert covers_full_circle(angles), seed
    rng = np.random.default_rng(0)
    assert not covers_full_circle(np.linspace(0.0, 245.0, 1440) + rng.normal(0.0, 0.2, 1440))


_FDK_DIGEST = """
import hashlib, numpy as np
from ctpipe.geometry import Geometry
from ctpipe.recon.feldkamp import fdk
from ctpipe.recon.volume import VolumeGrid
geometry = Geometry(source_to_object_mm=400.0, source_to_detector_mm=800.0, detector_cols=32, detector_rows=24,
                    pixel_pitch_u_mm=0.4, pixel_pitch_v_mm=0.4)
views = np.random.default_rng(3).random((40, 24, 32), dtype=np.float32)
volume = fdk(views, geometry, np.linspace(0.0, 360.0, 40, endpoint=False), VolumeGrid.cube(24, 0.25))
print(hashlib.sha256(volume.tobytes()).hexdigest())
"""


def test_fdk_compiled_here_and_loaded_from_numba_cache_agree_bit_for_bit(tmp_path):
    """A Dask worker loads the kernels from numba's cache while the client compiled them: the
    two must compute the same bits (``fastmath=True``'s ``nsz`` broke this; see ctpipe._shared.jit)."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")}
    compiled, loaded = (subprocess.run([sys.executable, "-c", _FDK_DIGEST], env=env, capture_output=True, text=True,
                                       check=True).stdout.split()[-1] for _ in range(2))
    assert any((tmp_path / "numba-cache").rglob("*.nbi")), "the first run wrote no cache"
    assert compiled == loaded


def test_a_region_of_interest_scan_is_extended_and_reconstructs_inside_its_field_of_view(truth):
    # 64 columns: a field of view of radius 8 mm at the axis, the phantom 14 mm wide.
    from ctpipe.recon.feldkamp import is_truncated

    narrow = Geometry(source_to_object_mm=200.0, source_to_detector_mm=400.0, detector_cols=64, detector_rows=160,
                      pixel_pitch_u_mm=0.5, pixel_pitch_v_mm=0.5)
    angles = np.arange(240) * 1.5
    projections = project_ellipsoids(narrow, angles)
    assert is_truncated(projections)
    volume, mask = truth
    x, z = GRID.axis_mm("x"), GRID.axis_mm("z")
    inside = mask & (np.hypot(x[None, None, :], z[None, :, None]) < 0.8 * 16.0 * 200.0 / 400.0)
    zero = relative_rmse(fdk(projections, narrow, angles, GRID, truncation="zero"), volume, inside)
    extended = fdk(projections, narrow, angles, GRID, truncation="extend")
    assert relative_rmse(extended, volume, inside) <= 0.12 < 0.25 <= zero   # measured 0.093 and 0.296
    np.testing.assert_array_equal(fdk(projections, narrow, angles, GRID), extended)


def test_a_scan_that_fits_its_field_of_view_is_not_extended(full_scan):
    from ctpipe.recon.feldkamp import is_truncated

    projections, angles = full_scan
    assert not is_truncated(projections)
    np.testing.assert_array_equal(fdk(projections, GEOMETRY, angles, GRID),
                                  fdk(projections, GEOMETRY, angles, GRID, truncation="zero"))
    with pytest.raises(InputError, match="truncation: must be one of auto, zero, extend, got 'mirror'"):
        fdk(projections, GEOMETRY, angles, GRID, truncation="mirror")
