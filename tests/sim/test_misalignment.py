"""The misaligned scanner: detector drift, centre-of-rotation offset and tilt (ctpipe.sim.drift)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ctpipe.errors import ConfigError
from ctpipe.io.scan_folder import read_scan
from ctpipe.sim.drift import DetectorDrift, Misalignment, parse_misalignment, resample_to_detector
from ctpipe.sim.jitter import Jitter
from ctpipe.sim.phantoms import parse_phantom
from ctpipe.sim.projectors import project_analytic
from ctpipe.sim.scan_spec import parse_scan_spec
from ctpipe.sim.simulator import project_phantom, simulate, write_simulated_scan

GEOMETRY = {"source_to_object_mm": 100.0, "source_to_detector_mm": 250.0, "detector_cols": 64, "detector_rows": 56,
            "pixel_pitch_u_mm": 0.5, "pixel_pitch_v_mm": 0.5, "u0_px": 31.7, "v0_px": 27.2}


def _phantom(*objects):
    return parse_phantom({"name": "test", "objects": list(objects)})


def _spec(n_views=24, supersample=3, **extra):
    return parse_scan_spec({"geometry": GEOMETRY, "angles": {"n_views": n_views},
                            "jitter": [{"gaussian": {"sigma_deg": 0.3}}],
                            "projector": {"supersample": supersample}, **extra})


def _centroids(projections):
    """Intensity-weighted (col, row) of every view, shape (V, 2)."""
    rows, cols = np.mgrid[: projections.shape[1], : projections.shape[2]]
    weight = projections.astype(np.float64)
    total = weight.sum(axis=(1, 2))
    return np.stack([(weight * cols).sum(axis=(1, 2)) / total, (weight * rows).sum(axis=(1, 2)) / total], axis=1)


# A small bead off the axis (7.5 px across on the detector), inside the field of view in every view.
BEAD = _phantom({"sphere": {"centre_mm": [4.0, -3.0, 2.5], "radius_mm": 1.5, "density_per_mm": 0.05}})


def test_a_bead_moves_by_exactly_the_drift_in_every_view():
    section = {"drift": {"walk_px": 0.08, "jumps": 3, "jump_px": 0.4, "axis": "both"}}
    # 8 x 8 sub-rays per pixel: the sampled centroid of the bead's disc is good to 1e-3 px.
    drifted = simulate(BEAD, _spec(supersample=8, misalignment=section), rng=np.random.default_rng(5))
    nominal = simulate(BEAD, _spec(supersample=8), rng=np.random.default_rng(5))

    offsets = drifted.true_detector_offsets_px
    assert offsets.shape == (24, 2)
    np.testing.assert_array_equal(offsets[0], [0.0, 0.0])  # the walk and the jumps start at view 0
    steps = np.abs(np.diff(offsets, axis=0))
    assert 0.25 < steps.max() and np.ptp(offsets) < 3.0  # the jumps are there; the drift stays small
    assert np.ptp(offsets[:, 0]) > 0.1 and np.ptp(offsets[:, 1]) > 0.1  # both axes drift
    # The jitter's draws come first and are unchanged; the geometry is the nominal one.
    np.testing.assert_array_equal(drifted.true_angles_deg, nominal.true_angles_deg)
    assert drifted.geometry == nominal.geometry
    shift = _centroids(drifted.projections) - _centroids(nominal.projections)
    np.testing.assert_allclose(shift, offsets, atol=2e-3)


def test_drift_along_one_axis_leaves_the_other_alone():
    offsets = DetectorDrift(walk_px=0.1, jumps=2, jump_px=0.5, axis="v").sample(50, np.random.default_rng(0))
    np.testing.assert_array_equal(offsets[:, 0], 0.0)
    assert np.count_nonzero(np.isclose(np.abs(np.diff(offsets[:, 1])), 0.5, atol=0.35)) >= 2


def test_jumps_are_persistent_steps_of_the_given_size():
    offsets = DetectorDrift(jumps=4, jump_px=0.3, axis="u").sample(40, np.random.default_rng(2))[:, 0]
    steps = np.diff(offsets)
    assert np.count_nonzero(steps) == 4
    np.testing.assert_allclose(np.abs(steps[steps != 0]), 0.3)


def test_a_centre_of_rotation_offset_moves_the_sinogram_centre_of_mass_by_the_offset():
    # A sphere on the axis images symmetrically about the axis' column: the centre of mass of
    # every view is u0 + cor_offset_px in closed form.
    sphere = _phantom({"sphere": {"centre_mm": [0.0, 0.0, 0.0], "radius_mm": 5.0, "density_per_mm": 0.02}})
    scan = simulate(sphere, _spec(n_views=8, misalignment={"cor_offset_px": 1.5}), rng=np.random.default_rng(0))
    centroids = _centroids(scan.projections)
    np.testing.assert_allclose(centroids[:, 0], GEOMETRY["u0_px"] + 1.5, atol=1e-3)
    np.testing.assert_allclose(centroids[:, 1], GEOMETRY["v0_px"], atol=1e-3)
    np.testing.assert_array_equal(scan.true_detector_offsets_px, [[1.5, 0.0]] * 8)
    # An off-axis bead over a turn: the sinogram's centre of mass moves by the offset.
    shifted = simulate(BEAD, _spec(misalignment={"cor_offset_px": -0.7}), rng=np.random.default_rng(1))
    nominal = simulate(BEAD, _spec(), rng=np.random.default_rng(1))
    shift = _centroids(shifted.projections).mean(axis=0) - _centroids(nominal.projections).mean(axis=0)
    np.testing.assert_allclose(shift, [-0.7, 0.0], atol=1e-3)


# A rod along the rotation axis: its image is the column u0 in every row, whatever the perspective.
ROD = _phantom({"cylinder": {"centre_mm": [0.0, 0.0, 0.0], "radius_mm": 1.5, "height_mm": 30.0,
                             "density_per_mm": 0.05}})


@pytest.mark.parametrize("tilt_deg", [2.0, -0.5])
def test_a_tilt_turns_the_image_of_a_vertical_line_by_the_tilt(tilt_deg):
    scan = simulate(ROD, _spec(n_views=2, supersample=6, misalignment={"tilt_deg": tilt_deg}),
                    rng=np.random.default_rng(0))
    view = scan.projections[0].astype(np.float64)
    rows = np.arange(8, 48)  # inside the rod's image, away from its ends
    cols = np.arange(view.shape[1])
    centres = (view[rows] * cols).sum(axis=1) / view[rows].sum(axis=1)
    slope, intercept = np.polyfit(rows, centres, 1)
    # col - u0 = tan(tilt) (row - v0) for square pixels: the axis turns by the tilt about the principal point.
    assert slope == pytest.approx(math.tan(math.radians(tilt_deg)), abs=2e-4)
    assert intercept + slope * GEOMETRY["v0_px"] == pytest.approx(GEOMETRY["u0_px"], abs=5e-3)
    assert scan.true_detector_tilt_deg == tilt_deg


def test_tilt_with_unequal_pitches_follows_the_detector_in_mm():
    geometry = dict(GEOMETRY, pixel_pitch_v_mm=0.25, detector_rows=112, v0_px=55.1)
    spec = parse_scan_spec({"geometry": geometry, "angles": {"n_views": 1}, "projector": {"supersample": 6},
                            "misalignment": {"tilt_deg": 3.0}})
    view = simulate(ROD, spec, rng=np.random.default_rng(0)).projections[0].astype(np.float64)
    rows = np.arange(16, 96)
    centres = (view[rows] * np.arange(view.shape[1])).sum(axis=1) / view[rows].sum(axis=1)
    slope = np.polyfit(rows, centres, 1)[0]
    assert slope == pytest.approx(math.tan(math.radians(3.0)) * 0.25 / 0.5, abs=2e-4)


def test_no_section_is_bit_identical_to_the_plain_chain():
    """Without ``misalignment`` the scan is the chain of before: jitter, projection, noise, same draws."""
    from ctpipe.io.flatfield import log_transform
    from ctpipe.sim.acquisition import acquire

    extra = {"noise": {"photons_per_pixel": 10_000, "flat_frames": 2, "dark_frames": 1}}
    spec = _spec(n_views=6, **extra)
    assert spec.misalignment is None and "misalignment" not in spec.to_dict()
    scan = simulate(BEAD, spec, rng=np.random.default_rng(9))
    assert scan.true_detector_offsets_px is None and scan.true_detector_tilt_deg == 0.0

    rng = np.random.default_rng(9)
    nominal = spec.nominal_angles_deg()
    truth = nominal + spec.jitter.sample(nominal, rng)
    lines = project_analytic(BEAD.primitives, spec.geometry, truth, supersample=3)
    intensities, flats, darks = acquire(lines, spec.noise, rng)
    np.testing.assert_array_equal(scan.true_angles_deg, truth)
    np.testing.assert_array_equal(scan.intensities, intensities)
    np.testing.assert_array_equal(scan.projections, log_transform(intensities, flats, darks))
    # A zero misalignment draws nothing and places the detector exactly where the nominal one is.
    zero = simulate(BEAD, _spec(n_views=6, misalignment={"cor_offset_px": 0.0}, **extra), rng=np.random.default_rng(9))
    np.testing.assert_array_equal(zero.projections, scan.projections)
    np.testing.assert_array_equal(zero.true_detector_offsets_px, np.zeros((6, 2)))


def test_the_jitter_free_reference_keeps_the_static_misalignment_and_drops_the_drift():
    spec = _spec(n_views=6, misalignment={"cor_offset_px": 0.5, "tilt_deg": 0.2, "drift": {"walk_px": 0.1}})
    reference = simulate(BEAD, spec, rng=np.random.default_rng(0), jitter=False)
    np.testing.assert_array_equal(reference.true_detector_offsets_px, [[0.5, 0.0]] * 6)
    assert reference.true_detector_tilt_deg == 0.2


def test_voxel_resampling_matches_the_exact_detector():
    geometry = _spec().geometry
    angles = np.array([0.0, 40.0, 130.0])
    offsets = np.array([[0.3, -0.2], [-0.45, 0.1], [0.7, 0.35]])
    blob = _phantom({"ellipsoid": {"centre_mm": [1.0, 0.5, -1.0], "semi_axes_mm": [4.0, 5.0, 3.0],
                                   "density_per_mm": 0.02}})
    exact = project_analytic(blob.primitives, geometry, angles, supersample=2, detector_offsets_px=offsets,
                             detector_tilt_deg=1.5)
    plain = project_analytic(blob.primitives, geometry, angles, supersample=2)
    resampled = resample_to_detector(plain, geometry, offsets, 1.5)
    # Linear interpolation: errors at the object's steep edges (measured: 6 % of the peak at
    # most, 0.5 % RMS), against 25 % and 2.9 % for the nominal projections left as they are.
    error = np.abs(resampled - exact) / exact.max()
    assert error.max() < 0.1 and np.sqrt(np.mean(error ** 2)) < 0.008
    assert np.sqrt(np.mean(((plain - exact) / exact.max()) ** 2)) > 0.02
    # project_phantom reaches the exact projector for primitives.
    np.testing.assert_array_equal(project_phantom(blob, geometry, angles, supersample=2, detector_offsets_px=offsets,
                                                  detector_tilt_deg=1.5), exact)


def test_the_spec_round_trips_and_the_scan_folder_keeps_the_truth(tmp_path):
    section = {"cor_offset_px": -1.25, "tilt_deg": 0.3, "drift": {"walk_px": 0.05, "jumps": 1, "jump_px": 0.5,
                                                                   "axis": "u"}}
    spec = _spec(n_views=4, misalignment=section)
    assert spec.misalignment == Misalignment(-1.25, 0.3, DetectorDrift(0.05, 1, 0.5, "u"))
    assert parse_scan_spec(spec.to_dict()) == spec
    scan = simulate(BEAD, spec, rng=np.random.default_rng(0))
    folder = write_simulated_scan(tmp_path / "scan", scan, phantom=BEAD, spec=spec, seed=0)
    read = read_scan(folder)
    assert read.geometry == spec.geometry  # the nominal geometry, as the scanner's file says
    np.testing.assert_array_equal(read.provenance["true_detector_offsets_px"], scan.true_detector_offsets_px)
    assert read.provenance["true_detector_tilt_deg"] == 0.3
    assert read.provenance["scan_spec"]["misalignment"] == spec.misalignment.to_dict()


@pytest.mark.parametrize("section, where", [
    ({"tilt_deg": 60}, "scan.misalignment.tilt_deg"),
    ({"tilt_deg": "a bit"}, "scan.misalignment.tilt_deg"),
    ({"cor_offset_px": float("nan")}, "scan.misalignment.cor_offset_px"),
    ({"cor_px": 1.0}, "scan.misalignment.cor_px"),
    ({"drift": {"walk_px": -0.1}}, "scan.misalignment.drift.walk_px"),
    ({"drift": {"axis": "w"}}, "scan.misalignment.drift.axis"),
    ({"drift": {"jumps": 1.5, "jump_px": 1}}, "scan.misalignment.drift.jumps"),
    ({"drift": {"jumps": 2}}, "scan.misalignment.drift.jump_px"),
    ({"drift": {"jumps": 30, "jump_px": 0.5}}, "scan.misalignment.drift.jumps"),
    ({"drift": [0.1]}, "scan.misalignment.drift"),
    ([1.5], "scan.misalignment"),
])
def test_bad_values_are_one_line_naming_the_path(section, where):
    with pytest.raises(ConfigError) as info:
        _spec(n_views=24, misalignment=section)
    message = str(info.value)
    assert message.startswith(f"{where}:") and "\n" not in message


def test_null_section_and_defaults():
    assert parse_misalignment(None) is None
    assert parse_misalignment({}) == Misalignment()
    assert Misalignment(cor_offset_px=2.0).sample_offsets_px(3, np.random.default_rng(0)).tolist() == [[2.0, 0.0]] * 3
    assert Jitter().sample(np.zeros(3), np.random.default_rng(0)).tolist() == [0.0] * 3


def test_a_voxel_phantom_is_resampled_onto_the_true_detector(tmp_path):
    from ctpipe.sim.projectors import VoxelProjector

    volume = np.zeros((20, 20, 20), dtype=np.float32)
    volume[6:14, 8:12, 5:15] = 0.03
    np.save(tmp_path / "cube.npy", volume)
    phantom = parse_phantom({"name": "cube", "voxels": {"file": "cube.npy", "voxel_size_mm": 0.5}}, base_dir=tmp_path)
    geometry = _spec().geometry
    angles = np.array([0.0, 33.0])
    offsets = np.array([[0.4, -0.3], [-0.2, 0.6]])
    projections = project_phantom(phantom, geometry, angles, detector_offsets_px=offsets, detector_tilt_deg=0.8)
    plain = VoxelProjector(geometry, phantom.grid).forward(phantom.volume, angles)
    np.testing.assert_array_equal(projections, resample_to_detector(plain, geometry, offsets, 0.8))
    assert not np.array_equal(projections, plain)


def test_an_axis_off_the_sources_perpendicular_images_where_the_ball_calibration_models_it():
    """``axis_offset_mm``: the axis moved sideways, the principal point kept. A sphere on the axis images at ``u0 +
    a SDD / (SOD pitch)`` in every view (to the few thousandths of a pixel its centroid is off, off the principal
    ray), and an off-axis bead's disc moves as the ball calibration's model of the same scanner says
    (:func:`ctpipe.solve.balls.ellipse_centres`), to its centroid's own sampling (up to 0.006 px near the detector's
    edge), by 2.87-3.07 px: not one shift, the cone's perspective being off the axis."""
    from ctpipe.geometry import Geometry
    from ctpipe.solve.balls import ellipse_centres

    sphere = _phantom({"sphere": {"centre_mm": [0.0, 0.0, 0.0], "radius_mm": 3.0, "density_per_mm": 0.02}})
    offset_mm = 0.6
    spec = _spec(n_views=6, supersample=6, misalignment={"axis_offset_mm": offset_mm})
    scan = simulate(sphere, spec, rng=np.random.default_rng(0))
    assert scan.true_axis_offset_mm == offset_mm
    column = GEOMETRY["u0_px"] + offset_mm * GEOMETRY["source_to_detector_mm"] / (
        GEOMETRY["source_to_object_mm"] * GEOMETRY["pixel_pitch_u_mm"])
    np.testing.assert_allclose(_centroids(scan.projections)[:, 0], column, atol=0.01)
    geometry = Geometry(**GEOMETRY)
    moved = simulate(BEAD, spec, rng=np.random.default_rng(3))
    plain = simulate(BEAD, _spec(n_views=6, supersample=6), rng=np.random.default_rng(3))
    np.testing.assert_array_equal(moved.true_angles_deg, plain.true_angles_deg)
    theta = np.deg2rad(moved.true_angles_deg)
    centre, radius = np.tile(BEAD.primitives.centre_mm, (6, 1)), np.full(6, 1.5)
    model = (ellipse_centres(centre, radius, theta, geometry, column, geometry.v0_px, 0.0, offset_mm)
             - ellipse_centres(centre, radius, theta, geometry, geometry.u0_px, geometry.v0_px, 0.0))
    np.testing.assert_allclose(_centroids(moved.projections) - _centroids(plain.projections), model, atol=0.01)
    assert np.ptp(model[:, 0]) > 0.1     # not a plain shift: the cone's perspective is off the axis


def test_an_axis_off_the_perpendicular_round_trips_and_is_refused_for_a_voxel_phantom(tmp_path):
    spec = _spec(n_views=4, misalignment={"axis_offset_mm": -0.8})
    assert spec.misalignment == Misalignment(axis_offset_mm=-0.8)
    assert parse_scan_spec(spec.to_dict()) == spec
    with pytest.raises(ConfigError, match=r"^scan\.misalignment\.axis_offset_mm:"):
        _spec(misalignment={"axis_offset_mm": 500.0})
    from ctpipe.errors import InputError

    np.save(tmp_path / "cube.npy", np.ones((8, 8, 8), dtype=np.float32))
    volume = parse_phantom({"name": "cube", "voxels": {"file": "cube.npy", "voxel_size_mm": 0.5}}, base_dir=tmp_path)
    with pytest.raises(InputError, match="primitive phantoms only"):
        project_phantom(volume, spec.geometry, [0.0], axis_offset_mm=1.0)
    from ctpipe.sim.beam import parse_beam, polychromatic_line_integrals

    with pytest.raises(InputError, match="primitive phantoms only"):
        polychromatic_line_integrals(volume, parse_beam({"energy_kev": 60}), spec.geometry, [0.0], axis_offset_mm=1.0)


def test_a_source_spot_that_moves_shifts_a_bead_by_its_parallax_and_the_axis_by_the_drift(tmp_path):
    """``drift.at: source``: the spot moves, the detector stays. The drift is the axis's image's move; a bead at
    distance ``z`` from the spot moves by ``(SDD / z - 1) / (SDD / SOD - 1)`` times it (0.92-1.08 across this bead's
    depths), where a detector's drift moves every bead by the drift itself. The same draws: the jitter and the drift
    are those of ``at: detector``."""
    section = {"drift": {"walk_px": 0.3, "jumps": 1, "jump_px": 1.0, "at": "source"}}
    spec = _spec(n_views=6, supersample=8, misalignment=section)
    assert spec.misalignment.drift.at == "source" and parse_scan_spec(spec.to_dict()) == spec
    moved = simulate(BEAD, spec, rng=np.random.default_rng(5))
    still = simulate(BEAD, _spec(n_views=6, supersample=8), rng=np.random.default_rng(5))
    detector = simulate(BEAD, _spec(n_views=6, supersample=8, misalignment={"drift": {**section["drift"],
                                                                                    "at": "detector"}}),
                        rng=np.random.default_rng(5))
    np.testing.assert_array_equal(moved.true_angles_deg, still.true_angles_deg)
    np.testing.assert_array_equal(moved.true_spot_offsets_px, detector.true_detector_offsets_px)
    np.testing.assert_array_equal(moved.true_detector_offsets_px, 0.0)   # the detector keeps its place
    theta = np.deg2rad(moved.true_angles_deg)
    x, _, z = BEAD.primitives.centre_mm[0]
    depth = np.sin(theta) * x + np.cos(theta) * z + GEOMETRY["source_to_object_mm"]
    sdd, sod = GEOMETRY["source_to_detector_mm"], GEOMETRY["source_to_object_mm"]
    parallax = (sdd / depth - 1.0) / (sdd / sod - 1.0)
    shift = _centroids(moved.projections) - _centroids(still.projections)
    np.testing.assert_allclose(shift, parallax[:, None] * moved.true_spot_offsets_px, atol=0.005)
    assert np.ptp(parallax) > 0.05   # not the detector's drift, which moves the bead by the drift itself
    np.testing.assert_allclose(_centroids(detector.projections) - _centroids(still.projections),
                               detector.true_detector_offsets_px, atol=0.005)
    np.save(tmp_path / "cube.npy", np.ones((8, 8, 8), dtype=np.float32))
    volume = parse_phantom({"name": "cube", "voxels": {"file": "cube.npy", "voxel_size_mm": 0.5}}, base_dir=tmp_path)
    from ctpipe.errors import InputError

    with pytest.raises(InputError, match=r"^misalignment\.drift\.at: source is simulated for primitive phantoms only"):
        project_phantom(volume, spec.geometry, [0.0], spot_offsets_px=[[1.0, 0.0]])
