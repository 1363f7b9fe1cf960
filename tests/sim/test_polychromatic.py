"""The polychromatic beam (ctpipe.sim.beam) and phantom materials (ctpipe.sim.materials)."""

import numpy as np
import pytest

from ctpipe.config import parse_geometry
from ctpipe.errors import ConfigError
from ctpipe.sim.materials import MATERIALS, REFERENCE_KEV, resolve_material
from ctpipe.sim.phantoms import parse_phantom
from ctpipe.sim.primitives import Primitives

xraydb = pytest.importorskip("xraydb")
pytest.importorskip("spekpy")

from ctpipe.sim.beam import beam_spectrum, parse_beam, polychromatic_line_integrals  # noqa: E402
from ctpipe.sim.projectors import project_analytic  # noqa: E402
from ctpipe.sim.scan_spec import parse_scan_spec  # noqa: E402

# An odd detector: its central pixel is on the central ray, which crosses the axis along z at angle 0.
GEOMETRY = {"source_to_object_mm": 200, "source_to_detector_mm": 400, "detector_rows": 9, "detector_cols": 73,
            "pixel_pitch_u_mm": 0.8, "pixel_pitch_v_mm": 0.8}
CENTRE = (4, 36)


def _geometry(**changes):
    return parse_geometry({**GEOMETRY, **changes}, "geometry")


def _mu_per_mm(formula, energy_kev, density):
    return float(xraydb.material_mu(formula, energy_kev * 1e3, density=density)) * 0.1


def _water_and_aluminium():
    return parse_phantom({"objects": [
        {"cylinder": {"radius_mm": 10, "height_mm": 30, "material": "water"}},
        {"sphere": {"radius_mm": 3, "material": "Al", "density_g_cm3": 2.7}},
        {"box": {"size_mm": [2, 2, 2], "centre_mm": [6, 0, 0], "material": "Ca5(PO4)3OH", "density_g_cm3": 3.16}}]})


@pytest.mark.parametrize("energy_kev", [30.0, 60.0, 100.0])
def test_a_single_energy_gives_mu_of_xraydb_times_the_path_length(energy_kev):
    phantom = _water_and_aluminium()
    p = polychromatic_line_integrals(phantom, parse_beam({"energy_kev": energy_kev}), _geometry(), [0.0, 90.0])
    # The central ray crosses 20 mm of water (the cylinder) and 6 mm of aluminium (the sphere, added to it).
    expected = _mu_per_mm("H2O", energy_kev, 1.0) * 20.0 + _mu_per_mm("Al", energy_kev, 2.7) * 6.0
    assert p[0][CENTRE] == pytest.approx(expected, rel=1e-5)
    # Every pixel: the exact projector with each object's mu(E) as its attenuation.
    mono = {"water": _mu_per_mm("H2O", energy_kev, 1.0), "aluminium": _mu_per_mm("Al", energy_kev, 2.7),
            "Ca5(PO4)3OH": _mu_per_mm("Ca5(PO4)3OH", energy_kev, 3.16)}
    prims = phantom.primitives
    mu = np.array([mono[prims.materials[m]] for m in prims.material])
    reference = project_analytic(Primitives(prims.kind, prims.centre_mm, prims.half_size_mm, prims.rotation, mu),
                                 _geometry(), [0.0, 90.0])
    np.testing.assert_allclose(p, reference, rtol=1e-5, atol=1e-6)


def test_one_energy_bin_of_a_tube_spectrum_is_monochromatic_at_its_mean_energy():
    beam = parse_beam({"kvp": 70, "filter_mm": {"Cu": 0.3}, "energy_bins": 1})
    energies, weights = beam_spectrum(beam)
    assert weights.tolist() == [1.0] and 30 < energies[0] < 60
    p = polychromatic_line_integrals(_water_and_aluminium(), beam, _geometry(), [0.0])
    expected = _mu_per_mm("H2O", energies[0], 1.0) * 20.0 + _mu_per_mm("Al", energies[0], 2.7) * 6.0
    assert p[0][CENTRE] == pytest.approx(expected, rel=1e-5)


def test_objects_without_a_material_are_water_equivalent_and_exact_at_the_reference_energy():
    phantom = parse_phantom({"objects": [{"cylinder": {"radius_mm": 9, "height_mm": 30, "density_per_mm": 0.03}},
                                         {"sphere": {"radius_mm": 2, "centre_mm": [3, 0, 0], "density_per_mm": -0.03}},
                                         {"sphere": {"radius_mm": 2, "density_per_mm": 0.2}}]})
    geometry = _geometry()
    mono = project_analytic(phantom.primitives, geometry, [0.0, 45.0])
    poly = polychromatic_line_integrals(phantom, parse_beam({"energy_kev": REFERENCE_KEV}), geometry, [0.0, 45.0])
    np.testing.assert_allclose(poly, mono, rtol=1e-5, atol=1e-6)


def _central_line_integral(beam, thickness_mm, material="aluminium"):
    phantom = parse_phantom({"objects": [{"box": {"size_mm": [20, 20, thickness_mm], "material": material}}]})
    return float(polychromatic_line_integrals(phantom, beam, _geometry(), [0.0])[0][CENTRE])


def test_beam_hardening_makes_the_line_integral_sublinear_in_thickness():
    beam = parse_beam({"kvp": 80, "filter_mm": {"Al": 0.5}})
    thickness = np.array([0.5, 1, 2, 4, 8, 16])
    p = np.array([_central_line_integral(beam, t) for t in thickness])
    mu_eff = p / thickness
    assert np.all(np.diff(p) > 0)
    assert np.all(np.diff(mu_eff) < 0)  # the beam hardens: each further mm attenuates less
    assert p[-1] < 0.7 * 32 * p[0]
    # Between aluminium's mu at the spectrum's highest and lowest energies.
    energies, _ = beam_spectrum(beam)
    assert _mu_per_mm("Al", energies.max(), 2.7) < mu_eff[-1] < mu_eff[0] < _mu_per_mm("Al", energies.min(), 2.7)
    # A photon-counting detector weights the soft photons more than an energy-integrating one does.
    counting = parse_beam({"kvp": 80, "filter_mm": {"Al": 0.5}, "detector_response": "photon-counting"})
    assert _central_line_integral(counting, 4) > p[3] * 1.01


def _cupping(beam: dict, material="aluminium") -> float:
    """(edge - centre) / edge of an FDK slice of a uniform cylinder of radius 10 mm."""
    from ctpipe.recon.feldkamp import fdk
    from ctpipe.recon.volume import VolumeGrid

    geometry = _geometry(detector_rows=8, detector_cols=72)
    angles = np.arange(90) * 4.0
    phantom = parse_phantom({"objects": [{"cylinder": {"radius_mm": 10, "height_mm": 40, "material": material}}]})
    p = polychromatic_line_integrals(phantom, parse_beam(beam), geometry, angles)
    axis = (np.arange(64) - 31.5) * 0.4
    r = np.hypot(*np.meshgrid(axis, axis))
    slice_ = fdk(p, geometry, angles, VolumeGrid(64, 1, 64, 0.4))[0]
    centre, edge = slice_[r < 3].mean(), slice_[(r > 6) & (r < 8)].mean()
    return float((edge - centre) / edge)


def test_fdk_of_a_uniform_cylinder_cups_less_with_filtration_and_more_at_low_kv():
    assert abs(_cupping({"energy_kev": 60})) < 0.003  # one energy: flat
    unfiltered, aluminium, copper = (_cupping({"kvp": 80, "filter_mm": f}) for f in ({}, {"Al": 1}, {"Cu": 0.5}))
    assert unfiltered > aluminium > copper > 0.01
    assert unfiltered > 0.08  # measured 0.106
    # 20 mm of water: 0.032, 0.020, 0.009 measured.
    low, mid, high = (_cupping({"kvp": kv, "filter_mm": {"Al": 1}}, "water") for kv in (40, 80, 150))
    assert low > mid > high > 0.005
    # 20 mm of aluminium from 80 kV up (0.076, 0.060, 0.053); below ~60 kV it absorbs all but a
    # narrow band under the kVp and cups less again (0.073 at 40 kV).
    assert aluminium > _cupping({"kvp": 120, "filter_mm": {"Al": 1}}) > _cupping({"kvp": 150, "filter_mm": {"Al": 1}})


def _spec(**extra):
    return parse_scan_spec({"geometry": GEOMETRY, "angles": {"n_views": 6}, **extra})


def test_without_beam_the_scan_is_the_monochromatic_one_bit_for_bit():
    from ctpipe.sim.acquisition import acquire
    from ctpipe.sim.simulator import project_phantom, simulate

    phantom = _water_and_aluminium()
    spec = _spec(noise={"photons_per_pixel": 1000}, jitter=[{"gaussian": {"sigma_deg": 0.3}}])
    assert spec.beam is None and "beam" not in spec.to_dict()
    scan = simulate(phantom, spec, rng=np.random.default_rng(3))
    rng = np.random.default_rng(3)
    truth = spec.nominal_angles_deg() + spec.jitter.sample(spec.nominal_angles_deg(), rng)
    intensities, _, _ = acquire(project_phantom(phantom, spec.geometry, truth), spec.noise, rng)
    np.testing.assert_array_equal(scan.intensities, intensities)
    # The monochromatic attenuation of a material object is mu/rho at 60 keV times its density.
    assert phantom.primitives.density_per_mm[1] == pytest.approx(_mu_per_mm("Al", REFERENCE_KEV, 2.7), rel=1e-4)


def test_a_beam_scan_round_trips_through_to_dict_and_is_noisy_around_its_mean():
    from ctpipe.sim.simulator import simulate

    spec = _spec(beam={"kvp": 90, "anode": "W", "filter_mm": {"Al": 1.0, "Cu": 0.1}, "energy_bins": 16},
                 noise={"photons_per_pixel": 1e6, "flat_frames": 4})
    assert parse_scan_spec(spec.to_dict()).beam == spec.beam
    phantom = _water_and_aluminium()
    noisy = simulate(phantom, spec, rng=np.random.default_rng(0), jitter=False)
    exact = polychromatic_line_integrals(phantom, spec.beam, spec.geometry, spec.nominal_angles_deg())
    assert noisy.flats.mean() == pytest.approx(1e6, rel=1e-3)  # the flat field is I0 photons
    assert np.abs(noisy.projections - exact).max() < 0.02


def test_built_in_reference_attenuation_matches_xraydb():
    for material in MATERIALS.values():
        if material.formula:
            expected = float(xraydb.material_mu(material.formula, REFERENCE_KEV * 1e3, density=1.0))
        else:
            expected = sum(w * float(xraydb.mu_elam(el, REFERENCE_KEV * 1e3)) for el, w in material.mass_fractions)
        assert material.mu_rho_reference_cm2_g == pytest.approx(expected, rel=2e-4), material.name
    assert resolve_material("Aluminum", "x") is resolve_material("al", "x") is MATERIALS["aluminium"]


def test_primitives_keep_their_materials_when_concatenated():
    a = _water_and_aluminium().primitives
    b = parse_phantom({"objects": [{"sphere": {"radius_mm": 1, "material": "tungsten"}},
                                   {"sphere": {"radius_mm": 1, "density_per_mm": 0.1}},
                                   {"sphere": {"radius_mm": 1, "material": "water"}}]}).primitives
    both = Primitives.concatenate([a, b])
    names = [both.materials[m] if m >= 0 else None for m in both.material]
    assert names == ["water", "aluminium", "Ca5(PO4)3OH", "tungsten", None, "water"]
    assert both.mass_density_g_cm3.tolist() == [1.0, 2.7, 3.16, 19.25, 0.0, 1.0]


@pytest.mark.parametrize("beam, where", [
    ({"kvp": 5}, "scan.beam.kvp"),
    ({"kvp": 600}, "scan.beam.kvp"),
    ({"kvp": "high"}, "scan.beam.kvp"),
    ({"kvp": 80, "anode": "Cu"}, "scan.beam.anode"),
    ({"kvp": 80, "energy_bins": 0}, "scan.beam.energy_bins"),
    ({"kvp": 80, "detector_response": "counting"}, "scan.beam.detector_response"),
    ({"kvp": 80, "filter_mm": {"Al": -1}}, "scan.beam.filter_mm.Al"),
    ({"kvp": 80, "filter_mm": {"Unobtainium": 1}}, "scan.beam.filter_mm.Unobtainium"),
    ({"kvp": 80, "filter_mm": {"SiO2": 1}}, "scan.beam.filter_mm.SiO2"),
    ({"kvp": 80, "filter_mm": [1.0]}, "scan.beam.filter_mm"),
    ({"kvp": 80, "voltage": 3}, "scan.beam.voltage"),
    ({"kvp": 80, "energy_kev": 60}, "scan.beam"),
    ({"anode": "W"}, "scan.beam"),
    ({"energy_kev": 60, "anode": "W"}, "scan.beam"),
    ("120 kV", "scan.beam"),
])
def test_bad_beam_values_are_one_line_config_errors_naming_the_path(beam, where):
    with pytest.raises(ConfigError) as error:
        _spec(beam=beam)
    message = str(error.value)
    assert message.startswith(where + ":") and "\n" not in message, message


@pytest.mark.parametrize("obj, where", [
    ({"sphere": {"radius_mm": 1, "material": "kryptonite"}}, "phantom.objects[0].sphere.material: unknown material"),
    ({"sphere": {"radius_mm": 1, "material": 3}}, "phantom.objects[0].sphere.material"),
    ({"sphere": {"radius_mm": 1, "material": "SiO2"}}, "phantom.objects[0].sphere.density_g_cm3: missing"),
    ({"sphere": {"radius_mm": 1, "density_g_cm3": 2.0}}, "phantom.objects[0].sphere.density_g_cm3"),
    ({"sphere": {"radius_mm": 1}}, "phantom.objects[0].sphere"),
    ({"box": {"size_mm": [1, 1, 1], "material": "iron", "density_g_cm3": "heavy"}},
     "phantom.objects[0].box.density_g_cm3"),
])
def test_bad_materials_are_one_line_config_errors_naming_the_path(obj, where):
    with pytest.raises(ConfigError) as error:
        parse_phantom({"objects": [obj]})
    message = str(error.value)
    assert message.startswith(where) and "\n" not in message, message


def test_a_beam_without_its_libraries_names_the_pip_command(monkeypatch):
    import ctpipe.sim.beam as beam_module

    monkeypatch.setattr(beam_module, "beam_libraries_missing", lambda: ["spekpy"])
    with pytest.raises(ConfigError, match=r"^scan\.beam: .*spekpy.*pip install 'ctpipe\[beam\]'$"):
        _spec(beam={"kvp": 80})


def test_a_polychromatic_beam_draws_a_dark_streak_between_two_metal_rods():
    from ctpipe.recon.feldkamp import fdk
    from ctpipe.recon.volume import VolumeGrid

    geometry = _geometry(detector_rows=8, detector_cols=96)
    angles = np.arange(180) * 2.0
    phantom = parse_phantom({"objects": [
        {"cylinder": {"radius_mm": 16, "height_mm": 40, "material": "pmma"}},
        # Steel replacing PMMA: the rods' mass density adds to the PMMA's, so remove the PMMA there.
        *({"cylinder": {"radius_mm": 1.5, "height_mm": 40, "centre_mm": [x, 0, 0], "material": "steel"}}
          for x in (-8, 8)),
        *({"cylinder": {"radius_mm": 1.5, "height_mm": 40, "centre_mm": [x, 0, 0], "material": "pmma",
                        "density_g_cm3": -1.18}} for x in (-8, 8))]})
    axis = (np.arange(96) - 47.5) * 0.4
    x, z = np.meshgrid(axis, axis)
    between = (np.abs(x) < 5) & (np.abs(z) < 0.8)  # PMMA on the line joining the rods
    aside = (np.abs(x) < 5) & (np.abs(np.abs(z) - 6) < 0.8)  # the same PMMA 6 mm off that line

    def darkening(beam):
        p = polychromatic_line_integrals(phantom, parse_beam(beam), geometry, angles)
        slice_ = fdk(p, geometry, angles, VolumeGrid(96, 1, 96, 0.4))[0]
        return float((slice_[aside].mean() - slice_[between].mean()) / slice_[aside].mean())

    mono, soft, hard = (darkening(b) for b in ({"energy_kev": 60}, {"kvp": 80, "filter_mm": {"Al": 1}},
                                                {"kvp": 150, "filter_mm": {"Cu": 0.5}}))
    assert abs(mono) < 0.02
    assert soft > hard > 0.2  # measured about 1.2 and 0.5 of the PMMA's value


def test_a_voxel_phantom_under_a_beam_is_water_equivalent(tmp_path):
    from ctpipe.sim.simulator import project_phantom

    volume = np.zeros((8, 24, 24), np.float32)
    volume[2:6, 6:18, 6:18] = 0.02
    np.save(tmp_path / "cube.npy", volume)
    phantom = parse_phantom({"voxels": {"file": "cube.npy", "voxel_size_mm": 1.0}}, base_dir=tmp_path)
    geometry = _geometry()
    mono = project_phantom(phantom, geometry, [0.0, 30.0])
    at_reference = polychromatic_line_integrals(phantom, parse_beam({"energy_kev": REFERENCE_KEV}), geometry,
                                                [0.0, 30.0])
    np.testing.assert_allclose(at_reference, mono, rtol=1e-5, atol=1e-6)
    hardened = polychromatic_line_integrals(phantom, parse_beam({"kvp": 60}), geometry, [0.0, 30.0])
    assert hardened.max() > mono.max() * 1.2  # a soft beam attenuates more than 60 keV photons would


@pytest.mark.parametrize("voxels", [False, True])
def test_a_beam_scan_sees_the_misaligned_detector_as_a_monochromatic_one_does(voxels, tmp_path):
    from ctpipe.sim.simulator import simulate

    if voxels:
        volume = np.zeros((8, 24, 24), np.float32)
        volume[2:6, 4:14, 8:20] = 0.03
        np.save(tmp_path / "block.npy", volume)
        phantom = parse_phantom({"voxels": {"file": "block.npy", "voxel_size_mm": 1.0}}, base_dir=tmp_path)
    else:
        phantom = parse_phantom({"objects": [{"box": {"size_mm": [6, 4, 10], "centre_mm": [2, 0, -3],
                                                      "density_per_mm": 0.03}}]})
    misalignment = {"cor_offset_px": 1.5, "tilt_deg": 0.3, "drift": {"walk_px": 0.2, "jumps": 1, "jump_px": 0.5}}
    mono = simulate(phantom, _spec(misalignment=misalignment), rng=np.random.default_rng(5))
    poly = simulate(phantom, _spec(misalignment=misalignment, beam={"energy_kev": REFERENCE_KEV}),
                    rng=np.random.default_rng(5))
    np.testing.assert_array_equal(poly.true_detector_offsets_px, mono.true_detector_offsets_px)
    np.testing.assert_allclose(poly.projections, mono.projections, rtol=1e-5, atol=1e-6)
    assert np.abs(mono.projections).max() > 0.1
