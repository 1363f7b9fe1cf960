import pytest

from ctpipe.config import load_yaml, parse_geometry, parse_pipeline
from ctpipe.errors import ConfigError
from ctpipe.plugins import get_registry

REGISTRY = get_registry()


def parse(text: str):
    return parse_pipeline(load_yaml("p.yaml", text=text), REGISTRY)


def test_defaults_and_bare_names():
    config = parse("refiner: least-squares\n")
    assert (config.detector.name, config.matcher.name, config.estimator.name) == ("sift", "brute-force", "ransac-1pt")
    assert config.baselines == (1,) and config.seed == 0


def test_a_bare_on_or_off_is_the_word_not_yaml_1_1s_boolean():
    config = parse("gate: off\npreprocess: {static_background: on}\n")
    assert (config.gate, config.static_background) == ("off", "on")
    assert parse("gate: on\npreprocess: {static_background: off}\n").static_background == "off"


@pytest.mark.parametrize("text, message", [
    ("estimator: {name: ransac-1pt, sampson_threshold: -1}",
     "pipeline.estimator.sampson_threshold: must be a number > 0 and <= 1, got -1"),
    ("estimator: {name: ransac-1pt, probability: yes}",
     "pipeline.estimator.probability: must be a number > 0 and < 1, got True"),
    ("estimator: {name: ransac-1pt, hypotheses: some}",
     "pipeline.estimator.hypotheses: must be one of 'random', 'all', got 'some'"),
    ("detector: {name: sift, n_features: 2.5}", "pipeline.detector.n_features: must be an integer >= 0 and <= 1000000, got 2.5"),
    ("detector: {name: sift, nfeatures: 10}", "pipeline.detector.nfeatures: unknown parameter of detector 'sift'; allowed: n_features"),
    ("detector: {name: surff}", "pipeline.detector.name: unknown detector 'surff'; registered detectors: akaze, beads, brisk"),
    ("detector: {n_features: 3}", "pipeline.detector.name: missing; registered detectors: akaze"),
    ("matcher: [1, 2]", "pipeline.matcher: must be a matcher name or a mapping"),
    ("colour: red", "pipeline.colour: unknown key; allowed: detector, matcher, estimator, refiner, pairs, preprocess, gate, seed"),
    ("pairs: {baselines: [0]}", "pipeline.pairs.baselines: must be a non-empty list of integers >= 1, got [0]"),
    ("seed: -3", "pipeline.seed: must be an integer >= 0 or null, got -3"),
    ("gate: maybe", "pipeline.gate: must be one of 'auto', 'off', got 'maybe'"),
    ("[1, 2", "p.yaml: not valid YAML at line 1"),
    ("seed: 1\nseed: 2\n", "p.yaml: duplicate key 'seed' at line 2"),
])
def test_bad_configs_name_the_path_the_value_and_what_is_allowed(text, message):
    with pytest.raises(ConfigError) as info:
        parse(text)
    assert str(info.value).startswith(message), str(info.value)
    assert "\n" not in str(info.value)


def test_geometry_is_validated_with_units_in_its_keys():
    good = {"source_to_object_mm": 500, "source_to_detector_mm": 1000, "detector_cols": 512, "detector_rows": 256,
            "pixel_pitch_u_mm": 0.4, "pixel_pitch_v_mm": 0.4}
    geometry = parse_geometry(good)
    assert (geometry.u0_px, geometry.v0_px) == (255.5, 127.5)
    with pytest.raises(ConfigError, match="geometry.pixel_pitch_mm: unknown key"):
        parse_geometry({**good, "pixel_pitch_mm": 0.4})
    with pytest.raises(ConfigError, match="geometry.source_to_object_mm: missing"):
        parse_geometry({k: v for k, v in good.items() if k != "source_to_object_mm"})
    with pytest.raises(ConfigError, match="geometry: source_to_detector_mm must exceed source_to_object_mm"):
        parse_geometry({**good, "source_to_object_mm": 2000})
    with pytest.raises(ConfigError, match="geometry.detector_cols: must be an integer >= 1 and <= 65536, got 0"):
        parse_geometry({**good, "detector_cols": 0})


def test_example_configs_are_valid():
    from pathlib import Path

    configs = sorted((Path(__file__).parents[1] / "configs").glob("*.yaml"))
    assert configs
    for path in configs:
        parse_pipeline(load_yaml(path), REGISTRY)


def test_paper_real_data_config_has_the_papers_settings():
    from pathlib import Path

    config = parse_pipeline(load_yaml(Path(__file__).parents[1] / "configs" / "paper-real-data.yaml"), REGISTRY)
    assert config.estimator.params == {"probability": 0.999, "outlier_fraction": 0.05, "sampson_threshold": 8e-4,
                                       "min_consensus": 0.6, "noise_scale_factor": None}


def test_detect_max_px_is_read_checked_and_written_back():
    from ctpipe.config import parse_pipeline
    from ctpipe.errors import ConfigError
    from ctpipe.plugins import get_registry

    registry = get_registry()
    assert parse_pipeline({}, registry).detect_max_px == 1024
    config = parse_pipeline({"preprocess": {"detect_max_px": None}}, registry)
    assert config.detect_max_px is None and config.to_dict()["preprocess"]["detect_max_px"] is None
    assert parse_pipeline({"preprocess": {"detect_max_px": 2048}}, registry).detect_max_px == 2048
    for bad in (10, "big", 1.5, True):
        with pytest.raises(ConfigError, match=r"pipeline\.preprocess\.detect_max_px"):
            parse_pipeline({"preprocess": {"detect_max_px": bad}}, registry)
