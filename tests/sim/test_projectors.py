"""Projectors against exact chords, numerical integration, each other, and their adjoint."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from ctpipe.errors import InputError
from ctpipe.geometry import Geometry
from ctpipe.model import rotation_matrix
from ctpipe.recon.volume import VolumeGrid
from ctpipe.sim.primitives import Primitives, local_maps, voxelise
from ctpipe.sim.projectors import VoxelProjector, project_analytic

# Principal point off the centre by a non-integer amount in both directions.
GEOMETRY = Geometry(source_to_object_mm=200.0, source_to_detector_mm=400.0, detector_cols=96, detector_rows=80,
                    pixel_pitch_u_mm=0.5, pixel_pitch_v_mm=0.45, u0_px=50.3, v0_px=37.6)
ANGLES = np.array([0.0, 17.0, 100.0, 251.5])


def _tilt(a: float, b: float) -> np.ndarray:
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(b), -np.sin(b)], [0.0, np.sin(b), np.cos(b)]])
    return rotation_matrix(a) @ tilt


def _one(kind, centre, half, rotation, density=0.02) -> Primitives:
    return Primitives(np.array([kind]), np.array([centre], float), np.array([half], float), rotation[None],
                      np.array([density]))


def _rays(geometry, angle_deg, cols, rows):
    """Source and detector end points (object frame, mm) of the rays of pixels (cols, rows)."""
    r = rotation_matrix(np.deg2rad(angle_deg))
    c = np.array([0.0, 0.0, geometry.source_to_object_mm])
    d_cam = np.stack([(cols - geometry.u0_px) * geometry.pixel_pitch_u_mm,
                      (rows - geometry.v0_px) * geometry.pixel_pitch_v_mm,
                      np.full(len(cols), geometry.source_to_detector_mm)], axis=1)
    source = r.T @ (-c)
    return source, (d_cam - c) @ r  # row-wise R^T (X_cam - c)


def _numerical(prims: Primitives, source, ends, n=200_000):
    """Midpoint-rule integral of the density along each segment (error <= 2 steps x density)."""
    maps = local_maps(prims)
    t = (np.arange(n) + 0.5) / n
    out = []
    for end in ends:
        points = source + t[:, None] * (end - source)
        total = np.zeros(n)
        for k in range(len(prims)):
            u = (points - prims.centre_mm[k]) @ maps[k].T
            if prims.kind[k] == 0:
                inside = (u ** 2).sum(1) <= 1
            elif prims.kind[k] == 1:
                inside = (u[:, 0] ** 2 + u[:, 2] ** 2 <= 1) & (np.abs(u[:, 1]) <= 1)
            else:
                inside = np.all(np.abs(u) <= 1, axis=1)
            total += prims.density_per_mm[k] * inside
        out.append(total.sum() * np.linalg.norm(end - source) / n)
    return np.array(out), np.linalg.norm(ends[0] - source) / n


@pytest.mark.parametrize("kind", [0, 1, 2])
def test_analytic_matches_numerical_integration(kind):
    prim = _one(kind, (2.0, -1.5, 3.0), (7.0, 5.0, 4.0), _tilt(0.7, 0.4))
    rng = np.random.default_rng(kind)
    for angle in ANGLES[[1, 3]]:
        image = project_analytic(prim, GEOMETRY, [angle])[0]
        hit = np.argwhere(image > 0)
        pick = hit[rng.choice(len(hit), 6, replace=False)]
        # Also rays just beside the shadow, which must be exactly 0 in both.
        rows = np.concatenate([pick[:, 0], [0, 79]]).astype(float)
        cols = np.concatenate([pick[:, 1], [0, 95]]).astype(float)
        source, ends = _rays(GEOMETRY, angle, cols, rows)
        expected, step = _numerical(prim, source, ends)
        got = image[rows.astype(int), cols.astype(int)]
        np.testing.assert_allclose(got, expected, atol=2.5 * step * 0.02, rtol=0)


def test_sphere_chords_match_the_closed_form():
    centre = np.array([3.0, -2.0, 4.0])
    radius = 6.0
    prim = _one(0, centre, (radius,) * 3, _tilt(0.3, 1.1))
    views = project_analytic(prim, GEOMETRY, ANGLES)
    rows, cols = np.mgrid[0:80, 0:96]
    for k, angle in enumerate(ANGLES):
        source, ends = _rays(GEOMETRY, angle, cols.ravel().astype(float), rows.ravel().astype(float))
        d = ends - source
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        w = centre - source
        dist2 = (w ** 2).sum() - (d @ w) ** 2
        expected = 0.02 * 2.0 * np.sqrt(np.clip(radius ** 2 - dist2, 0.0, None))
        got = views[k].ravel()
        inside = expected > 0.02 * 0.5
        np.testing.assert_allclose(got[inside], expected[inside], rtol=1e-6)
        # The rim: tangent rays differ by float32 rounding of sqrt of tiny gaps only.
        np.testing.assert_allclose(got, expected, atol=2e-4)


def _ellipsoid_reference(prims: Primitives, geometry, angle_deg, supersample, tilt_deg):
    """Mean over each pixel's sub-rays of every ellipsoid's exact chord x density, float64, every pixel."""
    ss = supersample
    offsets = (np.arange(ss) + 0.5) / ss - 0.5
    rows, cols = np.mgrid[0:geometry.detector_rows, 0:geometry.detector_cols].astype(float)
    au = ((cols[..., None, None] + offsets[None, None, None, :] - geometry.u0_px) * geometry.pixel_pitch_u_mm)
    bv = ((rows[..., None, None] + offsets[None, None, :, None] - geometry.v0_px) * geometry.pixel_pitch_v_mm)
    ct, st = np.cos(np.deg2rad(tilt_deg)), np.sin(np.deg2rad(tilt_deg))
    d_cam = np.stack(np.broadcast_arrays(ct * au - st * bv, st * au + ct * bv,
                                         np.full(au.shape, geometry.source_to_detector_mm)), axis=-1)
    r = rotation_matrix(np.deg2rad(angle_deg))
    source = r.T @ np.array([0.0, 0.0, -geometry.source_to_object_mm])
    d = d_cam @ r  # row-wise R^T d_cam: source to detector pixel, object frame
    total = np.zeros(rows.shape)
    for k, m in enumerate(local_maps(prims)):
        a = m @ (source - prims.centre_mm[k])
        b = d @ m.T
        bb = (b ** 2).sum(-1)
        ab = b @ a
        gap = ab ** 2 - bb * (a @ a - 1.0)
        chord = 2.0 * np.sqrt(np.clip(gap, 0.0, None)) / bb * np.linalg.norm(d, axis=-1)
        total += prims.density_per_mm[k] * chord.mean(axis=(-2, -1))
    return total


def test_ellipsoid_images_keep_every_grazing_sub_ray():
    # Thin, long, tilted ellipsoids near the edges of the cone, on a tilted detector with 3 x 3
    # sub-rays: the kernel only visits the pixels its ellipse bound allows, the reference all.
    rng = np.random.default_rng(5)
    n = 6
    rotations = np.stack([_tilt(*rng.uniform(0, 2 * np.pi, 2)) for _ in range(n)])
    prims = Primitives(np.zeros(n, np.int32), rng.uniform([-10, -8, -10], [10, 8, 10], (n, 3)),
                       rng.uniform([0.2, 0.5, 1.5], [0.5, 1.5, 6.0], (n, 3)), rotations, np.full(n, 0.02))
    for angle in ANGLES[[0, 2]]:
        got = project_analytic(prims, GEOMETRY, [angle], supersample=3, detector_tilt_deg=7.0)[0]
        expected = _ellipsoid_reference(prims, GEOMETRY, angle, 3, 7.0)
        assert (expected > 0).sum() > 200
        np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)


def test_turntable_invariant_shapes_project_as_in_every_view():
    # A container on the axis (projected once, added to every view) plus an off-axis grain that
    # turns: every view must still be the line integral through both.
    container = _one(1, (0.0, 1.0, 0.0), (9.0, 8.0, 9.0), rotation_matrix(0.4))
    grain = _one(0, (5.0, -2.0, 1.0), (2.0, 3.0, 1.5), _tilt(0.3, 0.8))
    prims = Primitives.concatenate([container, grain])
    views = project_analytic(prims, GEOMETRY, ANGLES[[1, 3]])
    rng = np.random.default_rng(2)
    for k, angle in enumerate(ANGLES[[1, 3]]):
        hit = np.argwhere(views[k] > 0)
        pick = hit[rng.choice(len(hit), 6, replace=False)]
        source, ends = _rays(GEOMETRY, angle, pick[:, 1].astype(float), pick[:, 0].astype(float))
        expected, step = _numerical(prims, source, ends)
        np.testing.assert_allclose(views[k][pick[:, 0], pick[:, 1]], expected, atol=2.5 * step * 0.04, rtol=0)
    # Moved off the axis the container turns too, and the views differ.
    moved = Primitives.concatenate([_one(1, (0.5, 1.0, 0.0), (9.0, 8.0, 9.0), np.eye(3)), grain])
    off_axis = project_analytic(moved, GEOMETRY, ANGLES[[1, 3]])
    assert not np.allclose(off_axis[0], off_axis[1], atol=1e-3)


def test_shapes_behind_the_source_add_nothing_and_cost_nothing():
    from ctpipe.sim.projectors import _kernel_shapes, _sub_rays

    seen = _one(0, (1.0, 0.0, 2.0), (3.0, 3.0, 3.0), np.eye(3))
    # At angle 0 the source is at z = -SOD: this sphere sits wholly behind it, that one across it.
    behind = _one(0, (0.0, 0.0, -GEOMETRY.source_to_object_mm - 20.0), (5.0, 5.0, 5.0), np.eye(3))
    across = _one(0, (0.0, 0.0, -GEOMETRY.source_to_object_mm), (5.0, 5.0, 5.0), np.eye(3))
    alone = project_analytic(seen, GEOMETRY, [0.0])
    np.testing.assert_array_equal(project_analytic(Primitives.concatenate([seen, behind]), GEOMETRY, [0.0]), alone)
    theta, u0, v0 = np.zeros(1), np.full(1, GEOMETRY.u0_px), np.full(1, GEOMETRY.v0_px)
    work = [_sub_rays(_kernel_shapes(p)[3], GEOMETRY, theta, u0, v0, 1.0, 0.0) for p in (seen, behind, across)]
    assert 0 < work[0] < 96 * 80 and work[1] == 0 and work[2] == 96 * 80


def test_primitives_that_miss_the_detector_still_count_as_work():
    # 2,000 small spheres far beside the cone: no pixel to visit, but the kernel still bounds each in
    # every view (about 250 ns a primitive and view): 200,000 of them in 360 views took 18 s.
    from ctpipe.sim.projectors import _PRIMITIVE_VIEW_SUB_RAYS, analytic_work

    n = 2000
    far = Primitives(np.zeros(n, int), np.column_stack([np.full(n, 5000.0), np.zeros(n), np.zeros(n)]),
                     np.full((n, 3), 0.5), np.broadcast_to(np.eye(3), (n, 3, 3)), np.full(n, 0.02))
    angles = np.linspace(0.0, 10.0, 50)   # the far side of the turn, all in front of the source
    placed = n * len(angles) * _PRIMITIVE_VIEW_SUB_RAYS
    assert placed <= analytic_work(far, GEOMETRY, angles, supersample=3) < 2 * placed   # and a few pixels' bound
    assert not project_analytic(far, GEOMETRY, angles[:2]).any()


def test_too_much_work_is_refused_before_projecting(monkeypatch):
    from ctpipe.errors import ResourceError

    prim = _one(0, (0.0, 0.0, 0.0), (8.0, 8.0, 8.0), np.eye(3))
    monkeypatch.setattr("ctpipe.sim.projectors._project_primitives", lambda *a: pytest.fail("projected anyway"))
    monkeypatch.setattr("ctpipe.sim.projectors.MAX_SUB_RAYS", 1e4)
    with pytest.raises(ResourceError, match=r"projecting 1 primitives into 4 views of 80 x 96 at supersample 2 needs "
                                            r"about .* ray-primitive intersections, more than the 1e\+04"):
        project_analytic(prim, GEOMETRY, ANGLES, supersample=2)


def test_supersampling_and_blur_keep_the_sum():
    prim = _one(2, (0.0, 0.0, 0.0), (5.0, 4.0, 3.0), _tilt(0.2, 0.1))
    plain = project_analytic(prim, GEOMETRY, [30.0])
    fine = project_analytic(prim, GEOMETRY, [30.0], supersample=3)
    blurred = project_analytic(prim, GEOMETRY, [30.0], supersample=3, blur_px=1.5)
    assert fine.sum() == pytest.approx(plain.sum(), rel=5e-3)
    assert blurred.sum() == pytest.approx(fine.sum(), rel=1e-4)
    assert blurred.max() < fine.max()


def test_progress_reports_every_chunk():
    prim = _one(0, (0.0, 0.0, 0.0), (3.0, 3.0, 3.0), np.eye(3))
    seen = []
    project_analytic(prim, GEOMETRY, np.arange(40.0), progress=seen.append)
    assert seen[-1] == 40 and seen == sorted(seen)


def test_sign_convention_and_principal_point_shift():
    # A point between the axis and the source (z < 0) moves towards larger columns for a
    # positive angle: R(theta) (0, 0, -r) = (r sin theta, 0, -r cos theta).
    geometry = Geometry(200.0, 400.0, 128, 64, 0.5, 0.5)
    prim = _one(0, (0.0, 0.0, -20.0), (1.0, 1.0, 1.0), np.eye(3))
    views = project_analytic(prim, geometry, [0.0, 10.0], supersample=2)
    cols = np.arange(128)
    centroid = (views.sum(1) * cols).sum(1) / views.sum((1, 2))
    assert centroid[0] == pytest.approx(geometry.u0_px, abs=1e-3)
    a = np.deg2rad(10.0)
    predicted = geometry.u0_px + 20 * np.sin(a) / (200.0 - 20 * np.cos(a)) * 400.0 / 0.5
    assert centroid[1] > geometry.u0_px + 5
    assert centroid[1] == pytest.approx(predicted, abs=0.05)
    # A sphere at x = +r sits at larger columns already at angle 0.
    right = project_analytic(_one(0, (15.0, 0.0, 0.0), (1.0,) * 3, np.eye(3)), geometry, [0.0])[0]
    assert np.unravel_index(right.argmax(), right.shape)[1] == pytest.approx(63.5 + 15 * 2 / 0.5, abs=1)
    # Moving the principal point by whole pixels moves the image by exactly that much.
    shifted = Geometry(200.0, 400.0, 128, 64, 0.5, 0.5, u0_px=geometry.u0_px + 3, v0_px=geometry.v0_px - 2)
    grid = VolumeGrid.cube(32, 0.5)
    vol = voxelise(_one(0, (2.0, 1.0, -3.0), (5.0, 4.0, 3.0), _tilt(0.3, 0.2)), grid)
    prim = _one(0, (2.0, 1.0, -3.0), (5.0, 4.0, 3.0), _tilt(0.3, 0.2))
    for project in (lambda g: project_analytic(prim, g, [25.0]),
                    lambda g: VoxelProjector(g, grid).forward(vol, [25.0])):
        base, moved = project(geometry), project(shifted)
        np.testing.assert_allclose(moved[0, 0:62, 3:], base[0, 2:64, :125], rtol=1e-6, atol=1e-7)


def test_voxel_projector_matches_analytic_on_an_ellipsoid():
    """Relative RMSE over the whole image, normalised by the analytic image's norm."""
    prim = _one(0, (1.0, 0.5, -1.0), (9.0, 7.0, 6.0), _tilt(0.4, 0.3))
    grid = VolumeGrid.cube(64, 0.3)
    volume = voxelise(prim, grid, supersample=4)
    exact = project_analytic(prim, GEOMETRY, ANGLES, supersample=2)
    voxel = VoxelProjector(GEOMETRY, grid).forward(volume, ANGLES)
    assert voxel.shape == exact.shape and voxel.dtype == np.float32
    assert np.linalg.norm(voxel - exact) / np.linalg.norm(exact) <= 0.02


def test_adjoint_identity():
    # A wide cone (rows reach past SDD / sqrt 2) so that rays along all three axes are used.
    geometry = Geometry(100.0, 150.0, 40, 48, 3.0, 5.0, u0_px=21.2, v0_px=22.7)
    grid = VolumeGrid(24, 20, 22, 1.5, centre_mm=(1.0, -2.0, 0.5))
    projector = VoxelProjector(geometry, grid)
    assert projector._with_y
    rng = np.random.default_rng(7)
    angles = rng.uniform(0, 360, 9)
    x = rng.uniform(size=grid.shape).astype(np.float32)
    y = rng.uniform(size=(9, 48, 40)).astype(np.float32)
    lhs = np.dot(projector.forward(x, angles).ravel().astype(np.float64), y.ravel())
    rhs = np.dot(x.ravel().astype(np.float64), projector.back(y, angles).ravel())
    assert lhs > 0 and lhs == pytest.approx(rhs, rel=1e-3)


def test_forward_runs_a_chunk_of_views_per_kernel_call_with_the_numbers_of_one_call(monkeypatch):
    # A long projection returns to Python between chunks (where Ctrl-C is seen), to the bit the same.
    import ctpipe.sim.projectors as projectors

    geometry = Geometry(100.0, 150.0, 40, 48, 3.0, 5.0, u0_px=21.2, v0_px=22.7)
    grid = VolumeGrid(24, 20, 22, 1.5, centre_mm=(1.0, -2.0, 0.5))
    rng = np.random.default_rng(9)
    volume = rng.normal(size=grid.shape).astype(np.float32)
    angles = rng.uniform(0, 360, 11)
    whole = VoxelProjector(geometry, grid).forward(volume, angles)
    calls = []
    kernel = projectors._forward
    monkeypatch.setattr(projectors, "_forward", lambda out, *args: (calls.append(len(out)), kernel(out, *args)))
    monkeypatch.setattr(projectors, "_SAMPLES_PER_CALL", 40 * 48 * 24 * 4.5)   # 4 views a call, at least 2 x threads
    chunked = VoxelProjector(geometry, grid).forward(volume, angles)
    size = max(4, 2 * numba.get_num_threads())
    assert calls == [min(size, 11 - start) for start in range(0, 11, size)]
    np.testing.assert_array_equal(chunked, whole)


def test_forward_pair_is_two_forwards_in_chunks():
    # The wide cone of the adjoint test: rays along all three axes, each layout read in pairs.
    geometry = Geometry(100.0, 150.0, 40, 48, 3.0, 5.0, u0_px=21.2, v0_px=22.7)
    grid = VolumeGrid(24, 20, 22, 1.5, centre_mm=(1.0, -2.0, 0.5))
    projector = VoxelProjector(geometry, grid)
    rng = np.random.default_rng(8)
    first, second = (rng.normal(size=grid.shape).astype(np.float32) for _ in range(2))
    angles = rng.uniform(0, 360, 7)
    chunks = list(projector.forward_pair(first, second, angles, chunk_views=3))
    assert [part for part, _, _ in chunks] == [slice(0, 3), slice(3, 6), slice(6, 7)]
    # The same sums in the same order, but two kernels: LLVM may fuse a multiply-add in one and not
    # the other (fastmath's "contract"), as it did on an Intel Xeon: a float32 ulp apart at most.
    for paired, volume in ((np.concatenate([a for _, a, _ in chunks]), first),
                           (np.concatenate([b for _, _, b in chunks]), second)):
        alone = projector.forward(volume, angles)
        np.testing.assert_allclose(paired, alone, rtol=4 * np.finfo(np.float32).eps,
                                   atol=4 * np.finfo(np.float32).eps * float(np.abs(alone).max()))
    # Checked when called, not when first iterated.
    with pytest.raises(InputError, match="second: must have shape"):
        projector.forward_pair(first, second[:2], angles)


@pytest.mark.parametrize("call, message", [
    (lambda p: p.forward(np.zeros((4, 4, 4), np.float32), [0.0]), "volume: must have shape"),
    (lambda p: p.forward(np.zeros((8, 8, 8), np.int32), [0.0]), "volume: must be a float array"),
    (lambda p: p.forward(np.full((8, 8, 8), np.nan, np.float32), [0.0]), "volume: contains NaN"),
    (lambda p: p.forward(np.zeros((8, 8, 8), np.float32), [[0.0]]), "angles_deg: must be a non-empty 1-D"),
    (lambda p: p.forward(np.zeros((8, 8, 8), np.float32), [np.inf]), "angles_deg: must be finite"),
    (lambda p: p.back(np.zeros((2, 80, 96), np.float32), [0.0]), "projections: must have shape"),
    (lambda p: project_analytic(None, GEOMETRY, [0.0]), "primitives"),
    (lambda p: project_analytic(_one(0, (0, 0, 0), (1, 1, 1), np.eye(3)), GEOMETRY, [0.0], supersample=0),
     "supersample"),
    (lambda p: project_analytic(_one(0, (0, 0, 0), (1, 1, 1), np.eye(3)), GEOMETRY, [0.0], blur_px=-1),
     "blur_px"),
])
def test_bad_inputs_raise_input_error(call, message):
    projector = VoxelProjector(GEOMETRY, VolumeGrid.cube(8, 1.0))
    with pytest.raises(InputError, match=message):
        call(projector)
