"""Hostile configuration: YAML that explodes, is not UTF-8 or nests deeply, YAML 1.2 floats,
folders and FIFOs as files, unbounded stage parameters, and wrong types through the Python API.

Every case must end in one ``ConfigError``/``InputError`` line (exit 2 on the CLI), quickly.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import typing

import numpy as np
import pytest
import yaml

from ctpipe._shared.checks import short_repr
from ctpipe.cli import _key_value
from ctpipe.config import load_geometry, load_yaml, parse_geometry, parse_pipeline
from ctpipe.errors import ConfigError, CtpipeError, InputError
from ctpipe.geometry import Geometry
from ctpipe.pipeline import Pipeline
from ctpipe.plugins import get_registry
from ctpipe.recon.volume import VolumeGrid
from ctpipe.sim.acquisition import parse_noise
from ctpipe.sim.scan_spec import parse_scan_spec
from ctpipe.stages import ParamSpec, check_value

GEOMETRY = {"source_to_object_mm": 100.0, "source_to_detector_mm": 200.0, "detector_cols": 32, "detector_rows": 32,
            "pixel_pitch_u_mm": 0.1, "pixel_pitch_v_mm": 0.1}


def _bomb(levels: int = 9) -> str:
    """'Billion laughs': each level aliases the previous one nine times (9 ** levels values)."""
    lines = ["l0: &l0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
    lines += [f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 9)}]" for i in range(1, levels)]
    return "\n".join(lines) + "\n"


def _ctpipe(*args: str, cwd=None, shell: str | None = None) -> subprocess.CompletedProcess:
    command = ["bash", "-c", shell] if shell else [sys.executable, "-m", "ctpipe.cli", *args]
    return subprocess.run(command, capture_output=True, text=True, timeout=60, cwd=cwd)


def _assert_one_line_exit_2(result: subprocess.CompletedProcess, *expected: str) -> str:
    assert result.returncode == 2, result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("ctpipe: error:"), result.stderr
    assert "Traceback" not in result.stderr
    for text in expected:
        assert text in lines[0], lines[0]
    return lines[0]


# --- YAML that explodes or is not what PyYAML expects -------------------------------------------

@pytest.mark.parametrize("loader", [
    lambda p: load_yaml(p),
    lambda p: parse_pipeline(load_yaml(p), get_registry()),
    lambda p: load_geometry(p),
    lambda p: parse_scan_spec(load_yaml(p)),
])
def test_alias_bomb_is_refused_fast_naming_the_file(tmp_path, loader, monkeypatch):
    path = tmp_path / "bomb.yaml"
    path.write_text(_bomb())
    # "Fast" without a clock: refused before PyYAML constructs any of its billions of values.
    constructed = []
    real = yaml.constructor.BaseConstructor.construct_object
    monkeypatch.setattr(yaml.constructor.BaseConstructor, "construct_object",
                        lambda self, node, deep=False: constructed.append(1) or real(self, node, deep=deep))
    with pytest.raises(ConfigError, match=r"bomb\.yaml: aliases expand to [\d,]+ values") as info:
        loader(path)
    assert not constructed
    assert "\n" not in str(info.value) and len(str(info.value)) < 200


def test_small_aliases_and_merge_keys_still_work():
    text = "base: &b {name: sift, n_features: 10}\ndetector: {<<: *b, n_features: 20}\nsame: *b\n"
    data = load_yaml("a.yaml", text=text)
    assert data["detector"] == {"name": "sift", "n_features": 20} and data["same"]["n_features"] == 10


def test_recursive_alias_is_refused():
    with pytest.raises(ConfigError, match="r.yaml: an alias refers to the node that contains it"):
        load_yaml("r.yaml", text="a: &a [1, *a]\n")


def test_cli_alias_bomb_as_pipeline_is_one_line(tmp_path):
    (tmp_path / "bomb.yaml").write_text(_bomb())
    result = _ctpipe("estimate", "missing.npy", "--pipeline", "bomb.yaml", cwd=tmp_path)
    _assert_one_line_exit_2(result, "bomb.yaml: aliases expand to")


@pytest.mark.parametrize("data", [
    "seed: 1\nname: caf\xe9\n".encode("latin-1"),
    "seed: 1\n".encode("utf-16"),
    bytes(range(256)),
])
def test_non_utf8_file_is_one_config_error(tmp_path, data):
    path = tmp_path / "enc.yaml"
    path.write_bytes(data)
    with pytest.raises(ConfigError, match=r"enc\.yaml: not UTF-8 text \(byte 0x[0-9a-f]{2} at offset \d+\)"):
        load_yaml(path)


def test_cli_binary_pipeline_is_one_line(tmp_path):
    (tmp_path / "p.yaml").write_bytes(b"\x89PNG\r\n\x1a\n\x00\xff\xfe")
    _assert_one_line_exit_2(_ctpipe("estimate", "x.npy", "--pipeline", "p.yaml", cwd=tmp_path), "p.yaml: not UTF-8")


@pytest.mark.parametrize("depth, message", [(150, "nested more than 100 levels"), (5000, "nested too deeply")])
def test_deep_nesting_is_one_config_error(depth, message):
    for text in ("[" * depth + "]" * depth, "{a: " * depth + "1" + "}" * depth):
        with pytest.raises(ConfigError, match=f"deep.yaml: {message}"):
            load_yaml("deep.yaml", text=text)


@pytest.mark.parametrize("text, value", [
    ("1e-3", 1e-3), ("1e5", 1e5), ("+1e5", 1e5), ("-2.5E-3", -2.5e-3), ("1E5", 1e5), (".5e3", 500.0),
    ("1.0e-3", 1e-3), ("12", 12), ("-7", -7), ("1e", "1e"), ("e5", "e5"), ("'1e3'", "1e3"), ("1.5", 1.5),
])
def test_yaml_12_floats_are_numbers_and_ints_stay_ints(text, value):
    loaded = load_yaml("n.yaml", text=f"v: {text}\n")["v"]
    assert loaded == value and type(loaded) is type(value)


def test_exponent_floats_are_accepted_in_pipeline_scan_spec_and_geometry(tmp_path):
    config = parse_pipeline(load_yaml("p.yaml", text="estimator: {name: ransac-1pt, sampson_threshold: 1e-3}\n"),
                            get_registry())
    assert config.estimator.params["sampson_threshold"] == 1e-3
    geometry = parse_geometry(load_yaml("g.yaml", text="source_to_object_mm: 1e2\nsource_to_detector_mm: 2E2\n"
                                        "detector_cols: 32\ndetector_rows: 32\npixel_pitch_u_mm: 1e-1\n"
                                        "pixel_pitch_v_mm: 1e-1\n"))
    assert geometry.source_to_object_mm == 100.0 and geometry.pixel_pitch_u_mm == 0.1
    assert parse_noise(load_yaml("n.yaml", text="photons_per_pixel: 1e5\n")).photons_per_pixel == 1e5


def test_set_values_are_read_as_yaml_12():
    assert _key_value("threshold=1e-3") == ("threshold", 1e-3)
    assert _key_value("n_features=500") == ("n_features", 500)
    assert _key_value("name=1e") == ("name", "1e")


def test_folder_as_pipeline_says_it_is_a_folder(tmp_path):
    (tmp_path / "conf").mkdir()
    with pytest.raises(ConfigError, match="conf: is a folder; a YAML file is expected"):
        load_yaml(tmp_path / "conf")
    _assert_one_line_exit_2(_ctpipe("estimate", "x.npy", "--pipeline", "conf", cwd=tmp_path),
                            "conf: is a folder; a YAML file is expected")


def test_fifo_is_read(tmp_path):
    fifo = tmp_path / "p.fifo"
    os.mkfifo(fifo)
    writer = threading.Thread(target=lambda: fifo.write_text("seed: 7\n"), daemon=True)
    writer.start()
    assert load_yaml(fifo) == {"seed": 7}
    writer.join(5)


def test_cli_process_substitution_as_pipeline_is_read(tmp_path):
    # The pipeline is read from /dev/fd/N: its bad seed is reported, not "no such file".
    result = _ctpipe(shell=f"{sys.executable} -m ctpipe.cli estimate missing.npy --pipeline <(echo 'seed: -1')",
                     cwd=tmp_path)
    _assert_one_line_exit_2(result, "pipeline.seed: must be an integer >= 0")


def test_extra_top_level_key_of_a_geometry_file_is_named(tmp_path):
    path = tmp_path / "g.yaml"
    path.write_text("geometry:\n" + "".join(f"  {k}: {v}\n" for k, v in GEOMETRY.items()) + "extra: 1\n")
    with pytest.raises(ConfigError, match=r"g\.yaml: extra: unknown top-level key"):
        load_geometry(path)
    np.save(tmp_path / "p.npy", np.zeros((2, 32, 32), np.uint8))
    line = _assert_one_line_exit_2(_ctpipe("estimate", "p.npy", "--geometry", "g.yaml", cwd=tmp_path),
                                   "extra: unknown top-level key")
    assert "geometry.geometry" not in line
    path.write_text("geometry:\n" + "".join(f"  {k}: {v}\n" for k, v in GEOMETRY.items()))
    assert load_geometry(path) == Geometry(**GEOMETRY)


def test_error_messages_show_a_short_value():
    huge = list(range(1_000_000))
    with pytest.raises(ConfigError) as info:
        check_value(ParamSpec("x", float, None, ""), huge, "x")
    assert len(str(info.value)) < 140 and "..." in str(info.value)
    assert len(short_repr("a" * 10_000)) == 80
    cyclic: list = []
    cyclic.append(cyclic)
    assert len(short_repr(cyclic)) <= 80


# --- unbounded parameters ------------------------------------------------------------------------

def _numeric(spec: ParamSpec) -> bool:
    options = typing.get_args(spec.annotation) or (spec.annotation,)
    return any(o in (int, float) or (typing.get_origin(o) is tuple and typing.get_args(o)[0] in (int, float))
               for o in options)


def test_every_numeric_stage_parameter_has_an_upper_bound():
    registry = get_registry()
    unbounded = [f"{kind} {name}.{spec.name}" for kind in ("detector", "matcher", "estimator", "refiner")
                 for name in registry.names(kind) for spec in registry.get(kind, name).cls.parameters()
                 if _numeric(spec) and spec.le is None and spec.lt is None]
    assert unbounded == []


@pytest.mark.parametrize("kind, stage, param, value", [
    ("matcher", "flann", "lsh_tables", 100000),
    ("detector", "sift", "n_features", 10 ** 26),
    ("detector", "surf", "n_octaves", 1000),
    ("detector", "kaze", "n_octaves", 16),
    ("detector", "orb", "n_levels", 10 ** 6),
    ("detector", "brisk", "octaves", 1000),
    ("estimator", "ransac-1pt", "max_iterations", 10 ** 12),
    ("estimator", "opencv-5pt", "max_iters", 2 ** 40),
])
def test_unbounded_stage_parameters_are_refused_by_name(kind, stage, param, value):
    registry = get_registry()
    text = f"{kind}: {{name: {stage}, {param}: {value}}}\n"
    with pytest.raises(ConfigError, match=rf"pipeline\.{kind}\.{param}: must be an integer >= \d+ and <= \d+"):
        parse_pipeline(load_yaml("p.yaml", text=text), registry)


def test_cross_parameter_bounds_of_opencv_detectors():
    registry = get_registry()
    with pytest.raises(ConfigError, match="first_level: scale_factor \\*\\* first_level"):
        registry.get("detector", "orb").cls(first_level=31)
    with pytest.raises(ConfigError, match="descriptor_size: must be <= 162"):
        registry.get("detector", "akaze").cls(descriptor_size=486, descriptor_channels=1)


def test_opencv_failure_from_parameters_does_not_blame_the_image():
    image = (np.random.default_rng(0).random((96, 96)) * 255).astype(np.uint8)
    with pytest.raises(ConfigError, match="brisk with .*octaves=8.* fails on this 96 x 96 image although"):
        get_registry().get("detector", "brisk").cls(octaves=8, pattern_scale=16).detect(image)
    with pytest.raises(InputError, match="give it a larger image"):
        get_registry().get("detector", "orb").cls().detect(np.zeros((1, 1), np.uint8))


@pytest.mark.parametrize("section, message", [
    ("projector: {kind: analytic, blur_px: 1e7}", "s.projector.blur_px: must be a number >= 0 and <= 64"),
    ("noise: {photons_per_pixel: 1e30}", "s.noise.photons_per_pixel: must be a number > 0 and <= 1e12"),
    ("noise: {photons_per_pixel: 1e5, dark_counts: 1e30}", "s.noise.dark_counts: must be a number >= 0 and <= 1e12"),
    ("jitter: [{gaussian: {sigma_deg: 1e300}}]", "s.jitter[0].gaussian.sigma_deg: must be a number >= 0 and <= 360"),
    ("angles: {n_views: 8, start_deg: 1e300}", "s.angles.start_deg: must be a number >= -36000 and <= 36000"),
])
def test_scan_spec_numbers_are_bounded(section, message):
    base = {"geometry": GEOMETRY, "angles": {"n_views": 8}}
    spec = {**base, **load_yaml("s.yaml", text=section)}
    with pytest.raises(CtpipeError) as info:
        parse_scan_spec(spec, path="s")
    assert message in str(info.value), str(info.value)


def test_cli_set_out_of_range_is_one_line(tmp_path):
    np.save(tmp_path / "img.npy", np.zeros((32, 32), np.uint8))
    result = _ctpipe("detect", "img.npy", "--detector", "sift", "--set", "n_features=1e26", "--out", "kp.npz",
                     cwd=tmp_path)
    _assert_one_line_exit_2(result, "n_features: must be an integer >= 0 and <= 1000000")
    assert not (tmp_path / "kp.npz").exists()


# --- Python API types ----------------------------------------------------------------------------

def test_pipeline_run_names_the_geometry_type():
    pipeline = Pipeline.from_config(None)
    projections = np.zeros((2, 32, 32), np.uint8)
    with pytest.raises(InputError, match="geometry: must be a ctpipe.geometry.Geometry .*got str"):
        pipeline.run(projections, "geometry.yaml")
    with pytest.raises(ConfigError, match="geometry.extra: unknown key"):
        pipeline.run(projections, {**GEOMETRY, "extra": 1})
    with pytest.raises(InputError, match="detector: must be a ctpipe Detector stage"):
        Pipeline("sift", pipeline.matcher, pipeline.estimator, pipeline.refiner)


def test_numpy_scalars_are_numbers_everywhere():
    geometry = Geometry(**{**GEOMETRY, "source_to_object_mm": np.float32(150), "detector_cols": np.int64(32),
                           "u0_px": np.float64(15.5)})
    assert geometry.source_to_object_mm == 150.0 and type(geometry.source_to_object_mm) is float
    assert type(geometry.detector_cols) is int and type(geometry.u0_px) is float
    grid = VolumeGrid(np.int32(4), 4, 4, np.float32(0.5))
    assert type(grid.n_x) is int and type(grid.voxel_size_mm) is float
    assert type(check_value(ParamSpec("n", int, None, "", ge=0), np.int64(3), "n")) is int
    assert type(check_value(ParamSpec("x", float, None, "", gt=0), np.float32(2), "x")) is float
    stage = get_registry().get("detector", "sift").cls(n_features=np.int64(10), sigma=np.float32(1.6))
    assert type(stage.n_features) is int
    with pytest.raises(InputError, match="source_to_object_mm: must be a finite number > 0, got nan"):
        Geometry(**{**GEOMETRY, "source_to_object_mm": np.float64("nan")})
    with pytest.raises(InputError, match="detector_cols: must be an integer"):
        Geometry(**{**GEOMETRY, "detector_cols": np.bool_(True)})
