"""Procedural phantom families (trabecular bone, an electronic part, a foam) and sample holders."""

import hashlib
import math

import numpy as np
import pytest

from ctpipe.config import load_yaml
from ctpipe.errors import ConfigError
from ctpipe.recon.volume import VolumeGrid
from ctpipe.sim.materials import MATERIALS
from ctpipe.sim.phantoms import ELECTRONIC_MATERIALS, list_phantoms, load_phantom, parse_phantom
from ctpipe.sim.primitives import KINDS, voxelise
from ctpipe.sim.projectors import project_analytic
from ctpipe.sim.scan_spec import parse_scan_spec
from ctpipe.sim.simulator import simulate

MU_BONE = MATERIALS["bone"].mu_rho_reference_cm2_g * 1.92 * 0.1  # 1/mm at 60 keV
MU_WATER = MATERIALS["water"].mu_rho_reference_cm2_g * 0.1

TRABECULAR = """
objects:
  - trabecular: {radius_mm: 8, height_mm: 12, cortical_mm: 1, spacing_mm: 1.3, thickness_mm: [0.25, 0.5],
                 plate_fraction: 0.3, bone_volume_fraction: 0.12, seed: SEED}
"""
ELECTRONIC = """
objects:
  - electronic: {board_mm: [20, 24, 1.6], traces: 12, chips: 3, chip_size_mm: [4, 7], pads_per_side: 3, seed: SEED}
"""
FOAM = """
objects:
  - foam: {radius_mm: 6, height_mm: 8, material: pmma, porosity: 0.25, cell_radius_mm: [0.4, 1.0], wall_mm: 0.1,
           seed: SEED}
"""


def parse(text: str, seed: int = 1):
    return parse_phantom(load_yaml("p.yaml", text=text.replace("SEED", str(seed))), path="p")


def arrays(p):
    return [p.kind, p.centre_mm, p.half_size_mm, p.rotation, p.density_per_mm, p.material, p.mass_density_g_cm3]


@pytest.mark.parametrize("text", [TRABECULAR, ELECTRONIC, FOAM], ids=["trabecular", "electronic", "foam"])
def test_same_seed_same_primitives_and_another_seed_others(text):
    a, b, c = parse(text, 1).primitives, parse(text, 1).primitives, parse(text, 2).primitives
    for x, y in zip(arrays(a), arrays(b)):
        np.testing.assert_array_equal(x, y)
    assert a.materials == b.materials
    assert len(a) != len(c) or not np.array_equal(a.centre_mm, c.centre_mm)


def test_trabecular_bone_volume_fraction_and_materials_measured_by_voxelising():
    phantom = parse(TRABECULAR)
    p = phantom.primitives
    assert set(p.materials) == {"bone", "water"}
    assert 200 < len(p) < 6000
    struts = p.subset((p.material == p.materials.index("bone")) & (p.density_per_mm > 0) & (p.half_size_mm[:, 1] < 2))
    assert {KINDS[k] for k in struts.kind} == {"cylinder", "box"}  # rods and plates
    # Struts replace marrow: bone minus water inside them; every strut has its water twin.
    assert np.isclose(p.density_per_mm[p.material == p.materials.index("water")], -MU_WATER).sum() == len(struts)
    grid = VolumeGrid(120, 90, 120, 0.15)  # 18 x 13.5 x 18 mm
    volume = voxelise(p, grid, supersample=2)
    x, z = np.meshgrid(grid.axis_mm("x"), grid.axis_mm("z"))  # volume[iy, iz, ix]
    r = np.hypot(x, z)
    rows = np.abs(grid.axis_mm("y")) < 6.0 - 0.15
    core = volume[rows][:, r < 7.0 - 0.3]
    bvf = (core.mean() - MU_WATER) / (MU_BONE - MU_WATER)
    assert bvf == pytest.approx(0.12, rel=0.2), bvf  # measured 0.134 (the rim, left out, is sparser)
    # Not a uniform haze: voxels are mostly marrow or mostly bone.
    assert np.mean(np.abs(core - MU_WATER) < 0.1 * (MU_BONE - MU_WATER)) > 0.6  # measured 0.83
    shell = volume[:, (r > 7.2) & (r < 7.8)]
    assert np.median(shell) == pytest.approx(MU_BONE, rel=1e-3)
    assert phantom.radius_mm == pytest.approx(8.0, rel=1e-3) and phantom.half_height_mm == pytest.approx(6.0)


def test_trabecular_dry_bone_has_no_water():
    p = parse(TRABECULAR.replace("seed: SEED", "marrow: air, seed: 3")).primitives
    assert p.materials == ("bone",)


def test_foam_porosity_measured_by_voxelising():
    p = parse(FOAM).primitives
    mu = MATERIALS["pmma"].mu_rho_reference_cm2_g * 1.18 * 0.1
    assert p.materials == ("pmma",) and np.allclose(np.abs(p.density_per_mm), mu)
    cells = p.subset(p.density_per_mm < 0)
    assert len(cells) > 50 and cells.half_size_mm.min() >= 0.4 and cells.half_size_mm.max() <= 1.0
    # Cells are whole and apart: no voxel is emptier than a void.
    grid = VolumeGrid(90, 60, 90, 0.15)  # 13.5 x 9 x 13.5 mm
    volume = voxelise(p, grid, supersample=2)
    assert volume.min() > -1e-6
    x, z = np.meshgrid(grid.axis_mm("x"), grid.axis_mm("z"))
    solid = volume[np.abs(grid.axis_mm("y")) < 4.0 - 0.15][:, np.hypot(x, z) < 6.0 - 0.2]
    porosity = 1.0 - solid.mean() / mu
    assert porosity == pytest.approx(0.25, rel=0.2), porosity  # measured 0.275 (the rim, left out, is sparser)


def test_electronic_part_materials_counts_and_metal_is_densest():
    phantom = parse(ELECTRONIC)
    p = phantom.primitives
    assert set(p.materials) == {name for name, _ in ELECTRONIC_MATERIALS.values()}
    for part, (name, rho) in ELECTRONIC_MATERIALS.items():  # monochromatic values are the materials' at 60 keV
        mask = p.material == p.materials.index(name)
        np.testing.assert_allclose(p.mass_density_g_cm3[mask], rho)
    expected = {n: MATERIALS[n].mu_rho_reference_cm2_g * r * 0.1 for n, r in ELECTRONIC_MATERIALS.values()}
    np.testing.assert_allclose(p.density_per_mm, [expected[p.materials[m]] for m in p.material])
    chips = p.subset(p.material == p.materials.index("aluminium"))
    assert len(chips) == 3
    traces = p.subset((p.material == p.materials.index("copper")) & (p.kind == KINDS.index("box")))
    assert len(traces) == 12
    balls = p.subset(p.kind == KINDS.index("ellipsoid"))
    assert len(balls) >= 3 * 4 and set(balls.materials[m] for m in balls.material) == {"copper"}
    pads = p.subset(p.material == p.materials.index("tungsten"))
    assert len(pads) == 3 * 4 * 3
    # Chips lie on the board and apart.
    lo, hi = chips.bounding_boxes_mm()
    assert np.all(lo[:, :2] >= [-10, -12]) and np.all(hi[:, :2] <= [10, 12])
    for i in range(3):
        for j in range(i):
            assert np.any((lo[i, :2] > hi[j, :2]) | (lo[j, :2] > hi[i, :2]))
    metal = np.isin(p.material, [p.materials.index(n) for n in ("copper", "tungsten")])
    assert p.density_per_mm[metal].min() > 2 * p.density_per_mm[~metal].max()
    # Voxelised, the most attenuating voxels are metal ones.
    grid = VolumeGrid(220, 260, 60, 0.1, (0.0, 0.0, 1.5))
    volume = voxelise(p, grid)
    metal_only = voxelise(p.subset(metal), grid)
    top = volume >= np.quantile(volume[volume > 0], 0.99)
    assert np.all(metal_only[top] > 0)


def test_built_in_families_load_and_project_like_a_lab_sample():
    from ctpipe.geometry import Geometry

    assert {"trabecular", "electronic", "foam"} <= set(list_phantoms())
    geometry = Geometry(150.0, 390.0, 64, 64, 3.2, 3.2)
    for name, most in (("trabecular", 6000), ("electronic", 1000), ("foam", 2000)):
        phantom = load_phantom(name)
        assert len(phantom.primitives) <= most
        views = project_analytic(phantom.primitives, geometry, [0.0, 90.0])
        assert views.max() > 0.5 and np.isfinite(views).all()


# Digests of the built-in phantoms' primitives before the families existed (numpy 1.26/2.x,
# scipy's Rotation.random): adding generators must not move a single primitive of the old ones.
_OLD_DIGESTS = {"ball-bar": "21c8850a36dbc748", "ball-bar-5": "20fa312e5a29f0f9", "bead-cloud-10": "cd8f9f88e8be87f4",
                "bead-cloud-30": "f70cfee2719d1534", "bead-cylinder": "f5c2846334000a80",
                "granular": "d86e57f98fd62d54", "metal-insert": "c5ad8c5bfca1efdc",
                "shepp-logan-3d": "662ba697f2e91efc"}


@pytest.mark.parametrize("name", sorted(_OLD_DIGESTS))
def test_the_older_built_in_phantoms_are_unchanged(name):
    p = load_phantom(name).primitives
    h = hashlib.sha256()
    for x in arrays(p):
        h.update(np.ascontiguousarray(x).tobytes())
    h.update(repr(p.materials).encode())
    assert h.hexdigest()[:16] == _OLD_DIGESTS[name]


@pytest.mark.parametrize("text, message", [
    ("trabecular: {radius_mm: 8, height_mm: 12, bone_volume_fraction: 0.2, marrow: blood, seed: 1}",
     "p.objects[0].trabecular.marrow: must be one of water, air, got 'blood'"),
    ("trabecular: {radius_mm: 8, height_mm: 12, bone_volume_fraction: 0.7, seed: 1}",
     "p.objects[0].trabecular.bone_volume_fraction: must be"),
    ("trabecular: {radius_mm: 8, height_mm: 12, spacing_mm: 1.5, thickness_mm: [0.1, 0.2], bone_volume_fraction: 0.5, "
     "seed: 1}", "p.objects[0].trabecular.bone_volume_fraction: 0.5 is more than this lattice holds"),
    ("trabecular: {radius_mm: 8, height_mm: 12, spacing_mm: 1.0, thickness_mm: 0.6, bone_volume_fraction: 0.1, "
     "seed: 1}", "p.objects[0].trabecular.thickness_mm: must stay below half of spacing_mm"),
    ("trabecular: {radius_mm: 2, height_mm: 12, bone_volume_fraction: 0.1, seed: 1}",
     "p.objects[0].trabecular: radius_mm - cortical_mm"),
    ("trabecular: {radius_mm: 8, height_mm: 12, bone_volume_fraction: 0.1}",
     "p.objects[0].trabecular.seed: missing; it is required"),
    ("foam: {radius_mm: 6, height_mm: 8, porosity: 0.6, seed: 1}",
     "p.objects[0].foam.porosity: must be a number > 0 and <= 0.4, got 0.6"),
    ("foam: {radius_mm: 6, height_mm: 8, porosity: 0.3, cell_radius_mm: [1, 5], seed: 1}",
     "p.objects[0].foam.cell_radius_mm: cells up to 5 mm"),
    ("foam: {radius_mm: 6, height_mm: 8, porosity: 0.4, cell_radius_mm: 1.5, wall_mm: 0.5, seed: 1}",
     "p.objects[0].foam.porosity: random packing does not place"),
    ("foam: {radius_mm: 6, height_mm: 8, porosity: 0.3, material: Ca5(PO4)3OH, seed: 1}",
     "p.objects[0].foam.material: must be a built-in material"),
    ("electronic: {board_mm: [20, 24, 1.6], chips: 40, seed: 1}",
     "p.objects[0].electronic.chips: placed only"),
    ("electronic: {board_mm: [20, 24, 1.6], chip_size_mm: [4, 30], seed: 1}",
     "p.objects[0].electronic.chip_size_mm: chips up to 30 mm do not fit"),
    ("electronic: {board_mm: [20, 24], seed: 1}", "p.objects[0].electronic.board_mm: must be a list of 3 numbers > 0"),
    ("electronic: {board_mm: [20, 24, 1.6], solder: lead, seed: 1}",
     "p.objects[0].electronic.solder: unknown key; allowed:"),
])
def test_bad_family_parameters_are_one_line_config_errors(text, message):
    with pytest.raises(ConfigError) as info:
        parse(f"objects:\n  - {text}")
    assert str(info.value).startswith(message) and "\n" not in str(info.value)


# ---------------------------------------------------------------------------------------------
# Holders

SCAN = {"geometry": {"source_to_object_mm": 150.0, "source_to_detector_mm": 390.0, "detector_cols": 64,
                     "detector_rows": 64, "pixel_pitch_u_mm": 2.4, "pixel_pitch_v_mm": 2.4},
        "angles": {"n_views": 8}}
PIN = {"box": {"centre_mm": [4, 10, 0], "size_mm": [3, 20, 6], "material": "aluminium"}}  # off-axis: shows turning
TABLE = {"box": {"centre_mm": [30, 24, 0], "size_mm": [40, 8, 100], "material": "aluminium"}}


def _holder_part(holder: dict, **extra):
    """Line integrals of the holder alone: the scan with it less the scan without."""
    phantom = parse_phantom({"objects": [{"sphere": {"radius_mm": 5, "density_per_mm": 0.02}}]})
    bare = simulate(phantom, parse_scan_spec({**SCAN, **extra}), rng=np.random.default_rng(0)).projections
    spec = parse_scan_spec({**SCAN, **extra, "holder": holder})
    return simulate(phantom, spec, rng=np.random.default_rng(0)).projections - bare, phantom


def test_a_static_holder_is_the_same_in_every_view_and_a_turning_one_is_not():
    static, _ = _holder_part({"static": [TABLE]})
    assert static.max() > 1.0  # 40 mm of aluminium edge-on: about 3
    assert np.abs(static - static[0]).max() < 1e-5  # measured 0.0 (max 4.3)
    turning, _ = _holder_part({"turning": [PIN]})
    change = np.abs(turning - turning[0]).max(axis=(1, 2))
    assert change[1:].min() > 0.1  # measured 0.32-0.46
    # The static part is the table projected at turntable angle 0.
    from ctpipe.geometry import Geometry

    alone = project_analytic(parse_phantom({"objects": [TABLE]}).primitives, Geometry(**SCAN["geometry"]), [0.0])
    np.testing.assert_allclose(static[3], alone[0], atol=1e-5)


def test_sample_bottom_origin_puts_the_holder_below_the_sample():
    spec = parse_scan_spec({**SCAN, "holder": {"origin": "sample_bottom", "turning": [PIN], "static": [TABLE]}})
    phantom = load_phantom("bead-cloud-10")
    turning, static = spec.holder.placed(phantom)
    assert turning.centre_mm[0, 1] == pytest.approx(10 + phantom.half_height_mm)
    assert static.centre_mm[0, 1] == pytest.approx(24 + phantom.half_height_mm)
    assert parse_scan_spec(spec.to_dict()).holder.to_dict() == spec.holder.to_dict()
    assert "holder" not in parse_scan_spec(SCAN).to_dict()  # off by default


def test_a_static_holder_follows_a_misaligned_detector():
    # A centre-of-rotation offset of 2 px moves every projection, the static table's too, by 2 columns.
    static, _ = _holder_part({"static": [TABLE]}, misalignment={"cor_offset_px": 2.0})
    aligned, _ = _holder_part({"static": [TABLE]})
    np.testing.assert_allclose(static[:, :, 2:], aligned[:, :, :-2], atol=1e-4)
    assert np.abs(static - static[0]).max() < 1e-5


@pytest.mark.parametrize("holder, message", [
    ({"origin": "top", "static": [TABLE]}, "scan.holder.origin: must be one of axis, sample_bottom, got 'top'"),
    ({}, "scan.holder: give turning or static objects"),
    ({"static": [{"box": {"size_mm": [1, 1]}}]}, "scan.holder.static[0].box.size_mm: must be a list of 3"),
    ({"turning": [PIN], "clamp": []}, "scan.holder.clamp: unknown key; allowed: origin, turning, static"),
])
def test_bad_holders_are_one_line_config_errors(holder, message):
    with pytest.raises(ConfigError) as info:
        parse_scan_spec({**SCAN, "holder": holder})
    assert str(info.value).startswith(message) and "\n" not in str(info.value)


def test_a_static_holder_under_a_beam_is_refused_in_one_line():
    with pytest.raises(ConfigError, match=r"^scan\.holder\.static: a static holder is not simulated under a "):
        parse_scan_spec({**SCAN, "beam": {"energy_kev": 60}, "holder": {"static": [TABLE]}})
    spec = parse_scan_spec({**SCAN, "beam": {"energy_kev": 60}, "holder": {"turning": [PIN]}})
    assert len(spec.holder.turning) == 1 and math.isfinite(spec.holder.turning.density_per_mm[0])


def test_a_voxel_phantoms_turning_holder_is_added_exactly(tmp_path):
    np.save(tmp_path / "v.npy", np.full((4, 4, 4), 0.01, np.float32))
    (tmp_path / "v.yaml").write_text("voxels: {file: v.npy, voxel_size_mm: 2.0}\n")
    voxel = load_phantom(tmp_path / "v.yaml")
    spec = parse_scan_spec({**SCAN, "holder": {"turning": [PIN]}})
    bare = simulate(voxel, parse_scan_spec(SCAN), rng=np.random.default_rng(0)).projections
    held = simulate(voxel, spec, rng=np.random.default_rng(0)).projections
    pin, _ = _holder_part({"turning": [PIN]})
    np.testing.assert_allclose(held - bare, pin, atol=1e-5)


def test_a_turning_holder_at_one_energy_is_the_monochromatic_one():
    pytest.importorskip("xraydb")
    pin, phantom = _holder_part({"turning": [PIN]})
    spec = parse_scan_spec({**SCAN, "beam": {"energy_kev": 60}, "holder": {"turning": [PIN]}})
    bare = simulate(phantom, parse_scan_spec({**SCAN, "beam": {"energy_kev": 60}}), rng=np.random.default_rng(0))
    held = simulate(phantom, spec, rng=np.random.default_rng(0))
    np.testing.assert_allclose(held.projections - bare.projections, pin, atol=2e-4)
