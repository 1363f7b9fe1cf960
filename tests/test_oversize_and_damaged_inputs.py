"""Hostile inputs: sizes that cannot fit, damaged files, calibration frames that cannot correct.

Each case must end in one line naming what is wrong (an InputError subclass through the API;
``ctpipe: error: ...`` and exit status 2 on the command line), quickly, with no traceback and
no output left behind. Nothing here allocates a large array: the checks refuse first.
"""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest
import tifffile
import yaml

from ctpipe._shared.resources import check_fits, format_bytes
from ctpipe.errors import ConfigError, InputError, ResourceError
from ctpipe.geometry import Geometry
from ctpipe.io.arrays import read_image, read_projections
from ctpipe.io.scan_folder import read_scan, write_scan
from ctpipe.sim.scan_spec import parse_scan_spec

GEOMETRY = Geometry(source_to_object_mm=190.0, source_to_detector_mm=390.0, detector_cols=12, detector_rows=10,
                    pixel_pitch_u_mm=0.8, pixel_pitch_v_mm=0.8)
SMALL = {"source_to_object_mm": 150.0, "source_to_detector_mm": 390.0, "detector_cols": 64, "detector_rows": 64,
         "pixel_pitch_u_mm": 6.4, "pixel_pitch_v_mm": 6.4}


def big(rows: int, cols: int) -> dict:
    return {**SMALL, "detector_rows": rows, "detector_cols": cols,
            "pixel_pitch_u_mm": 6.4 * 64 / cols, "pixel_pitch_v_mm": 6.4 * 64 / rows}


@pytest.fixture
def one_gigabyte(monkeypatch):
    """Make the machine look small, so the API tests do not depend on its memory."""
    monkeypatch.setattr("ctpipe._shared.resources.available_bytes", lambda: 10**9)


def run_cli(*args, cwd, timeout=60):
    return subprocess.run([sys.executable, "-m", "ctpipe.cli", *map(str, args)], cwd=cwd, capture_output=True,
                          text=True, timeout=timeout)


def assert_one_line_error(result, *fragments):
    lines = result.stderr.splitlines()
    assert result.returncode == 2, result.stderr
    assert len(lines) == 1 and lines[0].startswith("ctpipe: error:"), result.stderr
    assert "Traceback" not in result.stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


# ---------------------------------------------------------------------------------------------
# Sizes that cannot fit


def test_check_fits_names_the_size_and_what_is_available(one_gigabyte):
    with pytest.raises(ResourceError, match=r"^simulating 100000 views of 512 x 512 needs 209.7 GB of float32; "
                                            r"1.0 GB is available$"):
        check_fits("simulating 100000 views of 512 x 512", 2 * 100_000 * 512 * 512 * 4)
    check_fits("a small request", 10**6)
    assert format_bytes(999) == "999 B" and format_bytes(1.5e12) == "1.5 TB"


@pytest.mark.parametrize("scan, fragment", [
    ({"geometry": SMALL, "angles": {"n_views": 100_000}}, "simulating 100000 views of 64 x 64"),
    ({"geometry": big(20_000, 20_000), "angles": {"n_views": 2}}, "simulating 2 views of 20000 x 20000"),
    ({"geometry": big(2048, 2048), "angles": {"n_views": 1},
      "noise": {"photons_per_pixel": 1000, "flat_frames": 10_000}}, "10000 flat and 4 dark frames"),
])
def test_simulate_refuses_what_cannot_fit_before_allocating(one_gigabyte, scan, fragment):
    from ctpipe.sim.phantoms import load_phantom
    from ctpipe.sim.simulator import simulate

    with pytest.raises(ResourceError, match="is available") as info:
        simulate(load_phantom("granular"), parse_scan_spec(scan), rng=np.random.default_rng(0))
    assert fragment in str(info.value) and "\n" not in str(info.value)


def test_validate_refuses_a_grid_that_cannot_fit_before_simulating(one_gigabyte, monkeypatch):
    from ctpipe.evaluate.validate import parse_validate
    from ctpipe.plugins import get_registry

    monkeypatch.setattr("ctpipe.sim.simulator.project_phantom", lambda *a, **k: pytest.fail("simulated anyway"))
    experiment = {"phantom": "granular", "scan": {"geometry": SMALL, "angles": {"n_views": 36}},
                  "reconstruction": {"grid_size": 1024}}
    with pytest.raises(ResourceError, match=r"on a 1024\^3 grid needs .* is available; lower .*grid_size"):
        parse_validate(experiment, get_registry())


def test_fdk_and_projectors_refuse_volumes_that_cannot_fit(one_gigabyte):
    from ctpipe.recon.feldkamp import fdk
    from ctpipe.recon.volume import VolumeGrid
    from ctpipe.sim.projectors import VoxelProjector

    grid = VolumeGrid.cube(1024, 0.1)
    with pytest.raises(ResourceError, match="reconstructing a 1024 x 1024 x 1024 volume"):
        fdk(np.zeros((4, 10, 12), np.float32), GEOMETRY, np.arange(4.0) * 90, grid)
    with pytest.raises(ResourceError, match="back-projecting onto a 1024 x 1024 x 1024 volume"):
        VoxelProjector(GEOMETRY, grid).back(np.zeros((4, 10, 12), np.float32), np.arange(4.0))


def test_a_huge_count_in_scan_yaml_is_refused_without_building_names(tmp_path):
    write_scan(tmp_path / "s", np.zeros((5, 10, 12), np.float32), GEOMETRY, np.arange(5.0))
    document = tmp_path / "s" / "scan.yaml"
    document.write_text(document.read_text().replace("count: 5", "count: 1000000000000"))
    with pytest.raises(InputError, match=r"proj_00005.tif: no such file; .*projections.count says 1000000000000 "
                                         r"files, of which only the first 5 exist"):
        read_scan(tmp_path / "s")


# ---------------------------------------------------------------------------------------------
# Damaged input files


def _damaged_files(folder):
    """name -> (file, what the message must say)."""
    folder.mkdir(exist_ok=True)
    (folder / "empty.npy").write_bytes(b"")
    (folder / "text.npy").write_text("views,rows,cols\n1,2,3\n")
    (folder / "text.png").write_text("not a picture\n")
    np.save(folder / "objects.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    np.save(folder / "good.npy", np.zeros((3, 10, 12), np.float32))
    (folder / "truncated.npy").write_bytes((folder / "good.npy").read_bytes()[:200])
    tifffile.imwrite(folder / "good.tif", np.random.default_rng(0).random((3, 40, 48)).astype(np.float32),
                     photometric="minisblack")
    tiff = (folder / "good.tif").read_bytes()
    (folder / "truncated.tif").write_bytes(tiff[: len(tiff) // 3])
    (folder / "garbage.tif").write_bytes(b"II*\x00" + bytes(range(256)) * 4)
    with tifffile.TiffWriter(folder / "odd.tif") as writer:
        for shape in ((10, 12), (10, 12), (8, 12)):
            writer.write(np.zeros(shape, np.float32))
    return {
        "empty.npy": "is empty (0 bytes), not a npy file",
        "text.npy": "is not a npy file (it does not start with the npy signature; it looks like text)",
        "text.png": "is not a PNG file (it does not start with the PNG signature; it looks like text)",
        "objects.npy": "holds Python objects",
        "truncated.npy": "truncated npy file",
        "truncated.tif": "damaged or truncated TIFF file",
        "garbage.tif": "TIFF file",
        "odd.tif": "page 2 of 3 is float32 of shape (8, 12) but page 0 is float32 of shape (10, 12)",
    }


def test_damaged_files_give_one_line_naming_the_damage(tmp_path, capfd):
    cases = _damaged_files(tmp_path)
    for name, fragment in cases.items():
        reader = read_image if name.endswith(".png") else read_projections
        with pytest.raises(InputError) as info:
            reader(tmp_path / name)
        assert fragment in str(info.value) and str(info.value).startswith(str(tmp_path / name)), str(info.value)
        assert "\n" not in str(info.value)
    captured = capfd.readouterr()
    assert captured.out == "" and captured.err == "", "a library logged or warned"
    assert read_projections(tmp_path / "good.tif").shape == (3, 40, 48)


def test_cli_estimate_and_detect_on_damaged_files(tmp_path):
    cases = _damaged_files(tmp_path)
    (tmp_path / "g.yaml").write_text(yaml.safe_dump(GEOMETRY.to_dict()))
    for name, fragment in cases.items():
        if name.endswith(".png"):
            result = run_cli("detect", name, "--detector", "orb", "--out", "out/kp.npz", cwd=tmp_path)
        else:
            result = run_cli("estimate", name, "--geometry", "g.yaml", "--out", "out", cwd=tmp_path)
        assert_one_line_error(result, name, fragment)
        assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------------------------
# Calibration frames that cannot correct


def test_darks_brighter_than_flats_are_refused_where_the_correction_happens(tmp_path):
    from ctpipe.io.flatfield import log_transform

    intensities = np.full((5, 10, 12), 500, np.uint16)
    flats, darks = np.full((2, 10, 12), 100, np.uint16), np.full((2, 10, 12), 1000, np.uint16)
    flats[:, :2, :] = 2000  # a few live rows: still far more dead pixels than allowed
    write_scan(tmp_path / "s", intensities, GEOMETRY, np.arange(5.0), flats=flats, darks=darks, values="intensities")
    with pytest.raises(InputError, match=r"flats must be brighter than darks: 80 % of pixels have dark >= flat"):
        read_scan(tmp_path / "s")
    with pytest.raises(InputError, match="the flat/dark correction is impossible"):
        log_transform(intensities, flats, darks)
    # A few dead pixels stay what they were: line integral 0.
    flats[:] = 2000
    flats[:, 0, 0] = 100
    assert log_transform(intensities, flats, darks)[:, 0, 0].tolist() == [0.0] * 5
    result = run_cli("estimate", "s", "--out", "out", cwd=tmp_path)
    assert_one_line_error(result, "flats must be brighter than darks")
    assert not (tmp_path / "out").exists()


def test_cli_scan_folder_with_a_huge_count_fails_at_once(tmp_path):
    write_scan(tmp_path / "s", np.zeros((5, 10, 12), np.float32), GEOMETRY, np.arange(5.0))
    document = tmp_path / "s" / "scan.yaml"
    document.write_text(document.read_text().replace("count: 5", "count: 1000000000000"))
    result = run_cli("estimate", "s", "--out", "out", cwd=tmp_path, timeout=30)
    assert_one_line_error(result, "count says 1000000000000 files, of which only the first 5 exist")
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------------------------
# Sizes on the command line: beyond any machine, so no patching is needed


def test_cli_simulate_and_validate_refuse_sizes_beyond_memory(tmp_path):
    scans = {
        "views.yaml": {"geometry": big(4096, 4096), "angles": {"n_views": 100_000}},
        "flats.yaml": {"geometry": big(4096, 4096), "angles": {"n_views": 1},
                       "noise": {"photons_per_pixel": 1000, "flat_frames": 10_000}},
    }
    for name, scan in scans.items():
        (tmp_path / name).write_text(yaml.safe_dump(scan))
        result = run_cli("simulate", "granular", "--scan", name, "--out", "out", cwd=tmp_path)
        assert_one_line_error(result, "simulating", "needs", "B of float32", "is available")
        assert not (tmp_path / "out").exists()
    experiment = {"phantom": "granular", "scan": {"geometry": big(4096, 4096), "angles": {"n_views": 100_000}},
                  "reconstruction": {"grid_size": 1024}}
    (tmp_path / "exp.yaml").write_text(yaml.safe_dump(experiment))
    result = run_cli("validate", "exp.yaml", "--out", "out", cwd=tmp_path)
    assert_one_line_error(result, "exp.yaml: simulating 2 scans of 100000 views", "1024^3 grid", "is available")
    assert not (tmp_path / "out").exists()


def test_cli_simulate_refuses_projections_that_would_run_for_hours(tmp_path):
    # 20,000 grains filling the cone, 2,000 views of 1,024^2 at supersample 3: 4e11 intersections,
    # 350 times the default scan's work, refused before anything is projected or written.
    phantom = {"objects": [{"grains": {"container": {"radius_mm": 60, "height_mm": 120, "density_per_mm": 0.01},
                                       "count": 20_000, "size_mm": [2, 4], "density_per_mm": [0.02, 0.04],
                                       "min_gap_mm": 0.0, "seed": 1}}]}
    scan = {"geometry": {**SMALL, "detector_rows": 1024, "detector_cols": 1024, "pixel_pitch_u_mm": 0.4,
                         "pixel_pitch_v_mm": 0.4}, "angles": {"n_views": 2000}, "projector": {"supersample": 3}}
    (tmp_path / "grains.yaml").write_text(yaml.safe_dump(phantom))
    (tmp_path / "scan.yaml").write_text(yaml.safe_dump(scan))
    result = run_cli("simulate", "grains.yaml", "--scan", "scan.yaml", "--out", "out", cwd=tmp_path)
    assert_one_line_error(result, "simulating 2000 views of 1024 x 1024 at supersample 3 needs about",
                          "ray-primitive intersections, more than the 2e+11", "fewer primitives in the cone of rays")
    assert not (tmp_path / "out").exists()


def _never(*args, **kwargs):
    pytest.fail("projected anyway")


@pytest.fixture
def plenty_of_memory(monkeypatch):
    """Make the machine look large, so that only the work, not the memory, can refuse a simulation."""
    monkeypatch.setattr("ctpipe._shared.resources.available_bytes", lambda: 10**14)


def test_simulate_refuses_a_voxel_phantom_that_would_run_for_hours(tmp_path, monkeypatch, plenty_of_memory):
    # A 64 x 512 x 64 rod along the beam: every ray that meets it samples up to 512 planes, and
    # 2,000 views of 1,024^2 make about 1e12 samples (over an hour), so nothing is projected.
    from ctpipe.sim.phantoms import parse_phantom
    from ctpipe.sim.scan_spec import parse_scan_spec
    from ctpipe.sim.simulator import check_simulation_work, simulate

    np.save(tmp_path / "rod.npy", np.ones((64, 512, 64), np.uint8))
    phantom = parse_phantom({"voxels": {"file": "rod.npy", "voxel_size_mm": 0.1}}, base_dir=tmp_path)
    scan = {"geometry": {**big(1024, 1024), "pixel_pitch_u_mm": 0.02, "pixel_pitch_v_mm": 0.02},
            "angles": {"n_views": 2000}}
    monkeypatch.setattr("ctpipe.sim.projectors.VoxelProjector.forward", _never)
    with pytest.raises(ResourceError, match=r"simulating 2000 views of 1024 x 1024 at supersample 1 needs about "
                                            r"\S+ voxel samples, more than the 6e\+11 .*a voxel phantom of fewer voxels"):
        simulate(phantom, parse_scan_spec(scan), rng=np.random.default_rng(0))
    check_simulation_work(phantom, parse_scan_spec({**scan, "angles": {"n_views": 200}}))   # a tenth is taken on


def test_simulate_counts_every_energy_bin_of_a_polychromatic_beam(monkeypatch, plenty_of_memory):
    # A sphere is little projection work, but each of 256 energy bins is an exponential in every
    # pixel of every view: 2,000 views of 1,024^2 make 5e11 of them.
    pytest.importorskip("spekpy")
    from ctpipe.sim.phantoms import parse_phantom
    from ctpipe.sim.scan_spec import parse_scan_spec
    from ctpipe.sim.simulator import simulate, simulation_work

    phantom = parse_phantom({"objects": [{"sphere": {"radius_mm": 20, "material": "aluminium",
                                                     "centre_mm": [10, 0, 0]}}]})
    spec = {"geometry": big(1024, 1024), "angles": {"n_views": 2000}, "beam": {"kvp": 100, "energy_bins": 256}}
    monkeypatch.setattr("ctpipe.sim.beam.polychromatic_line_integrals", _never)
    work = simulation_work(phantom, parse_scan_spec(spec))
    assert work["energy-bin terms"] == 2000 * 1024 * 1024 * 256 and work["ray-primitive intersections"] < 1e9
    with pytest.raises(ResourceError, match=r"at supersample 1 needs about 5\.4e\+11 energy-bin terms, more than the "
                                            r"1e\+11 .*; use fewer views, a smaller detector or supersample or fewer "
                                            r"beam.energy_bins$"):
        simulate(phantom, parse_scan_spec(spec), rng=np.random.default_rng(0))
    # 40 bins are 84 % of the limit, supersample 16 a quarter of the projectors': together too much.
    spec = {**spec, "beam": {"kvp": 100, "energy_bins": 40}, "projector": {"supersample": 16}}
    with pytest.raises(ResourceError, match=r"needs about \S+ ray-primitive intersections \(of 2e\+11\) and about "
                                            r"8\.4e\+10 energy-bin terms \(of 1e\+11\), 1\.\d times the work .*"
                                            r"fewer primitives in the cone of rays or fewer beam.energy_bins$"):
        simulate(phantom, parse_scan_spec(spec), rng=np.random.default_rng(0))


def test_validate_refuses_two_simulations_that_would_run_for_hours_before_the_first(tmp_path):
    # Each scan alone needs about 1.2e11 intersections; validate simulates two.
    phantom = {"objects": [{"grains": {"container": {"radius_mm": 60, "height_mm": 120, "density_per_mm": 0.01},
                                       "count": 20_000, "size_mm": [2, 4], "density_per_mm": [0.02, 0.04],
                                       "min_gap_mm": 0.0, "seed": 1}}]}
    (tmp_path / "grains.yaml").write_text(yaml.safe_dump(phantom))
    experiment = {"phantom": "grains.yaml", "scan": {
        "geometry": {**SMALL, "detector_rows": 1024, "detector_cols": 1024, "pixel_pitch_u_mm": 0.4,
                     "pixel_pitch_v_mm": 0.4}, "angles": {"n_views": 600}, "projector": {"supersample": 3}},
        "reconstruction": {"grid_size": 64}}
    (tmp_path / "exp.yaml").write_text(yaml.safe_dump(experiment))
    result = run_cli("validate", "exp.yaml", "--out", "out", cwd=tmp_path)
    assert_one_line_error(result, "exp.yaml: simulating 2 scans of 600 views of 1024 x 1024 at supersample 3 needs about",
                          "more than the 2e+11")
    assert not (tmp_path / "out").exists()


def test_objects_that_cannot_be_packed_are_refused_at_once(tmp_path):
    # 200,000 beads of 0.2 mm radius would fill 107 % of this container: random placement gave up after
    # 45 s (placing 54,000 of them); it is refused before the first is placed.
    from ctpipe.sim.phantoms import parse_phantom

    beads = {"container": {"radius_mm": 10, "height_mm": 20, "density_per_mm": 0.01}, "count": 200_000,
             "radius_mm": [0.2, 0.2], "density_per_mm": [0.02, 0.08], "min_gap_mm": 0.0, "seed": 1}
    start = time.perf_counter()
    with pytest.raises(ConfigError, match=r"phantom.objects\[0\].beads: the 200000 beads .* would fill 107% of the "
                                          r"container, more than the 45% random placement reaches"):
        parse_phantom({"objects": [{"beads": beads}]})
    assert time.perf_counter() - start < 5.0   # refused, not tried (45 s of placement before)
    parse_phantom({"objects": [{"beads": {**beads, "count": 5_000}}]})   # 3 %: placed


def test_validate_short_scan_message_names_the_experiment_setting():
    from ctpipe.evaluate.validate import parse_validate
    from ctpipe.plugins import get_registry

    experiment = {"phantom": "granular", "scan": {"geometry": SMALL, "angles": {"n_views": 30, "range_deg": 120.0}},
                  "reconstruction": {"grid_size": 16}}
    with pytest.raises(ConfigError) as info:
        parse_validate(experiment, get_registry())
    assert "experiment.scan.angles.range_deg" in str(info.value) and "short_scan" not in str(info.value)
