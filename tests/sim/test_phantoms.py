from pathlib import Path

import numpy as np
import pytest

from ctpipe.config import load_yaml
from ctpipe.errors import ConfigError, InputError
from ctpipe.sim.phantoms import list_phantoms, load_phantom, parse_phantom, rotation_from_deg
from ctpipe.sim.primitives import KINDS
from ctpipe.sim.scan_spec import parse_scan_spec
from ctpipe.testing import overlapping_spheres, phantom_spheres


def parse(text: str, **kwargs):
    return parse_phantom(load_yaml("p.yaml", text=text), **kwargs)


def test_primitive_objects_compile_to_primitives():
    phantom = parse("""
name: four
objects:
  - ellipsoid: {centre_mm: [1, 2, 3], semi_axes_mm: [4, 5, 6], rotation_deg: [0, 90, 0], density_per_mm: 0.02}
  - sphere: {radius_mm: 2, density_per_mm: -0.01}
  - cylinder: {centre_mm: [0, 10, 0], radii_mm: [3, 4], height_mm: 8, density_per_mm: 0.5}
  - box: {size_mm: [2, 4, 6], density_per_mm: 0.1}
""")
    p = phantom.primitives
    assert phantom.name == "four" and phantom.volume is None and phantom.grid is None
    assert [KINDS[k] for k in p.kind] == ["ellipsoid", "ellipsoid", "cylinder", "box"]
    np.testing.assert_allclose(p.centre_mm[0], [1, 2, 3])
    np.testing.assert_allclose(p.half_size_mm, [[4, 5, 6], [2, 2, 2], [3, 4, 4], [1, 2, 3]])
    np.testing.assert_allclose(p.density_per_mm, [0.02, -0.01, 0.5, 0.1])
    # rotation_deg is scipy's extrinsic "xyz": 90 deg about y sends local x to -z.
    np.testing.assert_allclose(p.rotation[0] @ [1, 0, 0], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(rotation_from_deg([0, 90, 0]), p.rotation[0])
    # The cylinder reaches y = 10 + 4; the turned ellipsoid (x-z semi-axes 6 and 4) is the widest:
    # its centre's distance plus its major semi-axis bounds its distance from the axis.
    assert phantom.half_height_mm == pytest.approx(14.0)
    assert phantom.radius_mm == pytest.approx(np.sqrt(10.0) + 6.0)


def test_extent_of_centred_shapes_is_exact():
    phantom = parse("objects:\n  - box: {centre_mm: [3, -2, 4], size_mm: [2, 2, 2], density_per_mm: 1}")
    assert phantom.radius_mm == pytest.approx(np.hypot(4, 5))
    assert phantom.half_height_mm == pytest.approx(3.0)
    tilted = parse("objects:\n  - ellipsoid: {semi_axes_mm: [1, 2, 3], rotation_deg: [90, 0, 0], density_per_mm: 1}")
    # 90 deg about x: local y -> z, local z -> -y.
    assert tilted.half_height_mm == pytest.approx(3.0)
    assert tilted.radius_mm == pytest.approx(2.0)


@pytest.mark.parametrize("text, message", [
    ("objects:\n  - sphere: {radius_mm: -1, density_per_mm: 0.1}",
     "p.objects[0].sphere.radius_mm: must be a number > 0, got -1"),
    ("objects:\n  - sphere: {radius_mm: 1, density_per_mm: 0.1, colour: red}",
     "p.objects[0].sphere.colour: unknown key; allowed: centre_mm, radius_mm, density_per_mm"),
    ("objects:\n  - sphere: {radius_mm: one, density_per_mm: 0.1}",
     "p.objects[0].sphere.radius_mm: must be a number > 0, got 'one'"),
    ("objects:\n  - sphere: {radius_mm: 1}", "p.objects[0].sphere.density_per_mm: missing; it is required"),
    ("objects:\n  - ellipsoid: {semi_axes_mm: [1, 2], density_per_mm: 0.1}",
     "p.objects[0].ellipsoid.semi_axes_mm: must be a list of 3 numbers > 0, got [1, 2]"),
    ("objects:\n  - torus: {radius_mm: 1}",
     "p.objects[0].torus: unknown object kind; allowed: ellipsoid, sphere, cylinder, box, beads, grains"),
    ("objects:\n  - cylinder: {radius_mm: 1, radii_mm: [1, 2], height_mm: 2, density_per_mm: 1}",
     "p.objects[0].cylinder: give exactly one of radius_mm"),
    ("objects: []", "p.objects: must be a non-empty list"),
    ("units: cm\nobjects:\n  - sphere: {radius_mm: 1, density_per_mm: 1}", "p.units: must be 'mm', got 'cm'"),
    ("colour: red", "p.colour: unknown key; allowed: name, description, units, objects, voxels"),
    ("name: x", "p: give exactly one of objects (analytic primitives) or voxels"),
    ("objects:\n  - beads: {container: {radius_mm: 10, height_mm: 10}, count: 5, radius_mm: [2, 1], "
     "density_per_mm: 1, seed: 0}", "p.objects[0].beads.radius_mm: must be a number or a list [min, max] of numbers > 0"),
    ("objects:\n  - beads: {container: {radius_mm: 10, height_mm: 10}, count: 5, radius_mm: 1, density_per_mm: 1}",
     "p.objects[0].beads.seed: missing; it is required"),
    ("objects:\n  - grains: {container: {radius_mm: 10, height_mm: 10}, count: 5, size_mm: 1, aspect: [0.5, 2], "
     "density_per_mm: 1, seed: 0}", "p.objects[0].grains.aspect: must be fractions in (0, 1]"),
    ("objects:\n  - grains: {container: {radius_mm: 5, height_mm: 5}, count: 1000, size_mm: 2, density_per_mm: 1, "
     "seed: 0}", "p.objects[0].grains: the 1000 grains (as spheres 0 mm apart) would fill 1067% of the container"),
    ("objects:\n  - beads: {container: {radius_mm: 10, height_mm: 20}, count: 600, radius_mm: 1, density_per_mm: 1, "
     "seed: 0}", "p.objects[0].beads: placed only"),   # 40 %: tried, and jammed
])
def test_bad_phantoms_name_the_path_the_value_and_what_is_allowed(text, message):
    with pytest.raises(ConfigError) as info:
        parse(text, path="p")
    assert message in str(info.value)
    assert "\n" not in str(info.value)


GRAINS = """
objects:
  - grains:
      container: {{radius_mm: 20, height_mm: 30, centre_mm: [1, 2, 3], density_per_mm: 0.01,
                  wall_mm: 1, wall_density_per_mm: 0.05}}
      count: 300
      size_mm: [1.0, 3.0]
      aspect: [0.5, 1.0]
      density_per_mm: [0.02, 0.05]
      void_fraction: 0.3
      min_gap_mm: 0.1
      seed: {seed}
"""


def test_grains_are_deterministic_per_seed_counted_and_inside_the_container():
    a, b, c = (parse(GRAINS.format(seed=s)).primitives for s in (5, 5, 6))
    for name in ("kind", "centre_mm", "half_size_mm", "rotation", "density_per_mm"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.centre_mm, c.centre_mm)
    # Tube = outer cylinder + inner correction, then the grains.
    assert len(a) == 2 + 300
    grains = slice(2, None)
    np.testing.assert_allclose(a.density_per_mm[:2], [0.05, 0.01 - 0.05])
    material = a.density_per_mm[grains] + 0.01
    voids = np.isclose(material, 0.0)
    assert 0.2 < voids.mean() < 0.4
    assert np.all((material[~voids] >= 0.02) & (material[~voids] <= 0.05))
    semi = a.half_size_mm[grains]
    assert semi.max() <= 1.5 + 1e-12 and semi.max(axis=1).min() >= 0.5 - 1e-12
    assert np.all(semi.min(axis=1) >= 0.5 * semi.max(axis=1) - 1e-12)
    # Bounding spheres inside the cavity and apart by the gap.
    rel = a.centre_mm[grains] - [1, 2, 3]
    r = semi.max(axis=1)
    assert np.all(np.hypot(rel[:, 0], rel[:, 2]) + r <= 20 + 1e-9)
    assert np.all(np.abs(rel[:, 1]) + r <= 15 + 1e-9)
    d = np.linalg.norm(rel[:, None] - rel[None], axis=2) - r[:, None] - r[None]
    np.fill_diagonal(d, np.inf)
    assert d.min() >= 0.1 - 1e-9


def test_beads_are_spheres_of_the_material_in_the_matrix():
    phantom = parse("""
objects:
  - beads: {container: {radius_mm: 15, height_mm: 20, density_per_mm: 0.01}, count: 40, radius_mm: [1, 2],
            density_per_mm: [0.03, 0.05], min_gap_mm: 0.5, seed: 2}
""")
    p = phantom.primitives
    assert len(p) == 41 and KINDS[p.kind[0]] == "cylinder"
    assert np.all(p.half_size_mm[1:, 0] == p.half_size_mm[1:, 1])
    assert np.all((p.density_per_mm[1:] + 0.01 >= 0.03 - 1e-12) & (p.density_per_mm[1:] + 0.01 <= 0.05 + 1e-12))
    assert phantom.half_height_mm == pytest.approx(10.0)


def test_every_shipped_phantom_loads():
    names = list_phantoms()
    assert {"shepp-logan-3d", "bead-cylinder", "granular", "metal-insert", "ball-bar", "bead-cloud-10",
            "bead-cloud-30"} <= set(names)
    for name in names:
        phantom = load_phantom(name)
        assert phantom.name == name
        assert phantom.description
        assert phantom.radius_mm > 0 and phantom.half_height_mm > 0
    granular = load_phantom("granular")
    assert 2000 <= len(granular.primitives) <= 4000
    assert 60 <= granular.radius_mm <= 70 and 120 <= 2 * granular.half_height_mm <= 140


CALIBRATION_EXPERIMENT = Path(__file__).parents[2] / "configs" / "experiments" / "calibration-16-views.yaml"


def _cylinder(phantom):
    """Centre (3,), axis direction (3,), half sizes (3,) and density of the phantom's one cylinder."""
    p = phantom.primitives
    (rod,) = np.flatnonzero(p.kind == KINDS.index("cylinder"))
    return p.centre_mm[rod], p.rotation[rod][:, 1], p.half_size_mm[rod], p.density_per_mm[rod]


def test_ball_bar_is_seven_identical_steel_balls_threaded_on_a_slanted_off_axis_rod():
    phantom = load_phantom("ball-bar")
    centres, radii = phantom_spheres(phantom)
    assert len(radii) == 7 and len(phantom.primitives) == 8
    np.testing.assert_array_equal(radii, 1.25)
    balls = phantom.primitives.density_per_mm[phantom.primitives.kind == KINDS.index("ellipsoid")]
    np.testing.assert_array_equal(balls, 0.5)
    centre, axis, half, density = _cylinder(phantom)
    assert density == pytest.approx(0.005) and half[0] == half[2] == pytest.approx(0.5)
    # On the rod's axis, 6 mm apart, the rod reaching past both end balls.
    along = (centres - centre) @ axis
    np.testing.assert_allclose(np.linalg.norm(centres - centre - along[:, None] * axis, axis=1), 0.0, atol=2e-3)
    np.testing.assert_allclose(np.diff(np.sort(along)), 6.0, atol=2e-3)
    assert np.abs(along).max() + 1.25 < half[1]
    # Slanted (18 deg from the horizontal) and off the rotation axis: the balls differ in height and
    # in distance from the axis, all within 20 mm of it.
    assert np.degrees(np.arcsin(abs(axis[1]))) == pytest.approx(18.0)
    heights, distances = centres[:, 1], np.hypot(centres[:, 0], centres[:, 2])
    assert np.ptp(heights) > 10.0 and np.diff(np.sort(heights)).min() > 1.0
    assert np.diff(np.sort(distances)).min() > 0.5 and distances.min() > 4.0 and distances.max() + 1.25 < 20.0


@pytest.mark.parametrize("name, count", [("bead-cloud-30", 30), ("bead-cloud-10", 10)])
def test_bead_clouds_are_identical_balls_inside_their_foam_and_apart(name, count):
    phantom = load_phantom(name)
    centres, radii = phantom_spheres(phantom)
    assert len(radii) == count and len(phantom.primitives) == count + 1
    np.testing.assert_array_equal(radii, 1.0)
    centre, axis, half, foam = _cylinder(phantom)
    assert foam == pytest.approx(0.002) and half[0] == half[2] == pytest.approx(24.0) and half[1] == pytest.approx(20.0)
    np.testing.assert_array_equal(axis, [0, 1, 0])
    # Ruby replacing foam: 0.1/mm inside every ball.
    ellipsoids = phantom.primitives.kind == KINDS.index("ellipsoid")
    np.testing.assert_allclose(phantom.primitives.density_per_mm[ellipsoids] + foam, 0.1)
    assert np.all(np.hypot(centres[:, 0], centres[:, 2]) + 1.0 < 24.0) and np.all(np.abs(centres[:, 1]) + 1.0 < 20.0)
    gaps = np.linalg.norm(centres[:, None] - centres[None], axis=2) - 2.0
    np.fill_diagonal(gaps, np.inf)
    assert gaps.min() > 1.0
    # Three rows of balls at equal height: 4, 3 and 2 balls.
    _, per_height = np.unique(centres[:9, 1], return_counts=True)
    assert sorted(per_height) == [2, 3, 4]


def test_bead_cloud_10_is_the_first_ten_balls_of_bead_cloud_30():
    ten, thirty = (phantom_spheres(load_phantom(name))[0] for name in ("bead-cloud-10", "bead-cloud-30"))
    np.testing.assert_array_equal(ten, thirty[:10])


@pytest.mark.parametrize("name, at_least, at_most", [("ball-bar", 2, 8), ("bead-cloud-30", 2, 16),
                                                     ("bead-cloud-10", 2, 8)])
def test_ball_phantoms_have_overlapping_balls_in_some_views_of_a_16_view_turn(name, at_least, at_most):
    geometry = parse_scan_spec(load_yaml(CALIBRATION_EXPERIMENT)["scan"]).geometry
    centres, radii = phantom_spheres(load_phantom(name))
    # Whatever angle the turn starts at: the bar and the rows overlap over more than one 22.5 deg step.
    for start_deg in (0.0, 5.0, 11.25, 17.5):
        pairs = overlapping_spheres(centres, radii, geometry, start_deg + np.arange(16) * 22.5)
        views = sum(len(p) > 0 for p in pairs)
        assert at_least <= views <= at_most, f"{name} from {start_deg} deg: {views} of 16 views overlap"


def test_unknown_phantom_name_lists_the_built_in_ones():
    with pytest.raises(ConfigError, match="phantom 'granula': not a built-in phantom or a file; built-in: .*granular"):
        load_phantom("granula")


def test_phantom_file_name_defaults_and_missing_file(tmp_path):
    (tmp_path / "mine.yaml").write_text("objects:\n  - sphere: {radius_mm: 1, density_per_mm: 1}\n")
    assert load_phantom(tmp_path / "mine.yaml").name == "mine"
    with pytest.raises(ConfigError, match="no such file"):
        load_phantom(str(tmp_path / "other.yaml"))


def test_voxel_phantom_loads_relative_to_its_file(tmp_path):
    volume = np.zeros((4, 5, 6), np.float32)
    volume[1:3, 2, 1:5] = 0.5
    np.save(tmp_path / "tiny.npy", volume)
    (tmp_path / "tiny.yaml").write_text("voxels: {file: tiny.npy, voxel_size_mm: 2.0, scale: 0.1}\n")
    phantom = load_phantom(str(tmp_path / "tiny.yaml"))
    assert phantom.primitives is None and phantom.grid.shape == (4, 5, 6)
    np.testing.assert_allclose(phantom.volume, volume * 0.1)
    # Non-zero voxel centres: x in {-3, -1, 1, 3}, z = 0, y in {-1, 1}; plus half a voxel (diagonal).
    assert phantom.half_height_mm == pytest.approx(2.0)
    assert phantom.radius_mm == pytest.approx(3.0 + np.sqrt(2.0))
    (tmp_path / "bad.yaml").write_text("voxels: {file: missing.npy, voxel_size_mm: 2.0}\n")
    with pytest.raises(InputError, match="voxels.file: .*missing.npy: no such file"):
        load_phantom(str(tmp_path / "bad.yaml"))
    np.save(tmp_path / "flat.npy", np.zeros((3, 3)))
    (tmp_path / "flat.yaml").write_text("voxels: {file: flat.npy, voxel_size_mm: 2.0}\n")
    with pytest.raises(InputError, match="must hold a real 3-D array"):
        load_phantom(str(tmp_path / "flat.yaml"))
