"""Tests of the ctpipe-skimage plugin: discovery, detector contract, pipeline use from YAML."""

from __future__ import annotations

import numpy as np
import pytest
from skimage.data import camera
from skimage.transform import resize

from ctpipe.config import load_yaml, parse_pipeline
from ctpipe.data import Features
from ctpipe.errors import ConfigError, InputError
from ctpipe.geometry import Geometry
from ctpipe.pipeline import Pipeline
from ctpipe.plugins import get_registry
from ctpipe_skimage import SkimageCensureDetector, SkimageOrbDetector, SkimageSiftDetector

NAMES = ("skimage-sift", "skimage-orb", "skimage-censure")
CLASSES = {"skimage-sift": SkimageSiftDetector, "skimage-orb": SkimageOrbDetector,
           "skimage-censure": SkimageCensureDetector}
WIDTH = {"skimage-sift": 128, "skimage-orb": 32, "skimage-censure": 32}


@pytest.fixture(scope="module")
def image() -> np.ndarray:
    """The camera man at 256 x 256, float32 in [0, 1] (small, for speed)."""
    return resize(camera(), (256, 256), anti_aliasing=True).astype(np.float32)


@pytest.fixture(scope="module")
def registry():
    return get_registry()


def test_entry_point_registers_the_three_detectors(registry):
    for name in NAMES:
        info = registry.get("detector", name)
        assert info.plugin == "skimage"
        assert info.cls is CLASSES[name]
        assert info.description.endswith("(scikit-image).")


def test_blocking_the_plugin_removes_its_detectors():
    names = get_registry(blocked=("skimage",)).names("detector")
    assert not set(NAMES) & set(names)
    assert "sift" in names


@pytest.mark.parametrize("name", NAMES)
def test_detector_on_camera(name, image):
    detector = CLASSES[name]()
    before = image.copy()
    features = detector.detect(image)
    assert np.array_equal(image, before), "detect() modified its input"
    assert isinstance(features, Features)
    n = len(features)
    assert n > 0
    assert features.xy.shape == (n, 2) and features.xy.dtype == np.float32
    for field in ("size", "angle_deg", "response"):
        assert getattr(features, field).shape == (n,) and getattr(features, field).dtype == np.float32
    assert features.octave.dtype == np.int32 and features.class_id.dtype == np.int32
    assert features.descriptors.shape == (n, WIDTH[name])
    rows, cols = image.shape
    assert np.all((features.xy >= -0.5) & (features.xy <= [cols - 0.5, rows - 0.5]))
    assert np.all(features.size > 0) and np.all(np.isfinite(features.response))
    assert np.all(np.diff(features.response) <= 0), "strongest first"
    if features.norm == "L2":
        assert features.descriptors.dtype == np.float32
    else:
        assert features.norm == "HAMMING" and features.descriptors.dtype == np.uint8
    if name == "skimage-censure":
        assert np.all(np.isnan(features.angle_deg))
    else:
        assert np.all((features.angle_deg >= 0) & (features.angle_deg < 360))
    again = detector.detect(image)
    for field in ("xy", "size", "angle_deg", "response", "octave", "descriptors"):
        assert np.array_equal(getattr(features, field), getattr(again, field), equal_nan=field == "angle_deg")


@pytest.mark.parametrize("name", NAMES)
def test_image_dtype_and_units_do_not_matter(name, image):
    """The min-max map to [0, 1] makes uint8 and rescaled float images equivalent."""
    as_uint8 = np.rint(image * 200 + 20).astype(np.uint8)
    rescaled = as_uint8.astype(np.float64) * 3.0 - 7.0
    a, b = CLASSES[name]().detect(as_uint8), CLASSES[name]().detect(rescaled)
    assert len(a) > 0
    np.testing.assert_allclose(a.xy, b.xy, atol=1e-4)
    assert np.array_equal(a.descriptors, b.descriptors)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("blank", [np.zeros((64, 64), np.float32), np.full((80, 60), 7, np.uint8),
                                   np.linspace(0, 1, 64 * 64).reshape(64, 64), np.zeros((1, 50)) + np.arange(50),
                                   np.random.default_rng(0).random((5, 5))],
                         ids=["zeros", "constant-uint8", "ramp", "one-row", "tiny"])
def test_image_without_keypoints_gives_empty_features(name, blank):
    features = CLASSES[name]().detect(blank)
    assert len(features) == 0
    assert features.descriptors.shape == (0, WIDTH[name])
    assert features.xy.shape == (0, 2)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("bad", [np.zeros((16, 16, 3)), np.full((32, 32), np.nan), np.zeros((0, 0)),
                                 np.zeros((8, 8), dtype=bool)], ids=["3-D", "NaN", "empty", "bool"])
def test_unusable_image_raises_input_error(name, bad):
    with pytest.raises(InputError, match="image"):
        CLASSES[name]().detect(bad)


@pytest.mark.parametrize("name", NAMES)
def test_ctpipe_conformance(name):
    testing = pytest.importorskip("ctpipe.testing")
    testing.check_detector(CLASSES[name]())


@pytest.mark.parametrize("name", ["skimage-sift", "skimage-orb"])
def test_quarter_turn_maps_positions_and_angles_exactly(name, image):
    """Turning the image 90 deg clockwise on screen (+x -> +y) moves every keypoint of the
    finest level to its turned position and adds 90 deg to its angle: checks the pixel-centre
    corrections and the angle convention (skimage's own SIFT output is off by 0.5 px and
    10 deg here). Coarser levels are decimated on a grid that does not turn with the image."""
    detector = CLASSES[name]()
    a = detector.detect(image)
    b = detector.detect(np.rot90(image, k=-1))
    finest = a.octave == a.octave.min()
    turned = np.stack([image.shape[0] - 1 - a.xy[finest, 1], a.xy[finest, 0]], axis=1)
    found = 0
    for xy, angle in zip(turned, a.angle_deg[finest]):
        near = np.linalg.norm(b.xy - xy, axis=1) < 1e-3
        if near.any():
            found += 1
            diff = (b.angle_deg[near] - angle - 90 + 180) % 360 - 180
            assert np.min(np.abs(diff)) < 0.01
    assert found > 0.9 * np.count_nonzero(finest) > 0


def test_censure_polarity():
    rows, cols = np.mgrid[0:96, 0:96]
    bright = (((rows - 48) ** 2 + (cols - 48) ** 2) < 9).astype(np.float32)
    assert len(SkimageCensureDetector(polarity="dark", patch_size=21).detect(bright)) == 0
    for polarity in ("bright", "both"):
        features = SkimageCensureDetector(polarity=polarity, patch_size=21).detect(bright)
        assert features.xy.tolist() == [[48.0, 48.0]]
    dark = SkimageCensureDetector(polarity="both", patch_size=21).detect(1 - bright)
    assert dark.xy.tolist() == [[48.0, 48.0]]


def test_censure_descriptor_size_and_seed(image):
    wide = SkimageCensureDetector(descriptor_size=512).detect(image)
    assert wide.descriptors.shape[1] == 64
    other_seed = SkimageCensureDetector(seed=2).detect(image)
    same_seed = SkimageCensureDetector(seed=1).detect(image)
    default = SkimageCensureDetector().detect(image)
    assert np.array_equal(same_seed.descriptors, default.descriptors)
    assert not np.array_equal(other_seed.descriptors, default.descriptors)


@pytest.mark.parametrize("make, message", [
    (lambda: SkimageSiftDetector(upsampling=4), r"^SkimageSiftDetector\.sigma_min: must be >= sigma_in \* upsampling"),
    (lambda: SkimageSiftDetector(upsampling=3), r"^SkimageSiftDetector\.upsampling: must be one of 1, 2, 4"),
    (lambda: SkimageCensureDetector(min_scale=3, max_scale=4), r"^SkimageCensureDetector\.max_scale: must be >= "),
    (lambda: SkimageCensureDetector(mode="Octagon", max_scale=12), r"^SkimageCensureDetector\.max_scale: must be <= 11"),
    (lambda: SkimageCensureDetector(descriptor_size=100), r"^SkimageCensureDetector\.descriptor_size"),
    (lambda: SkimageOrbDetector(downscale=1.0), r"^SkimageOrbDetector\.downscale: must be a number > 1"),
])
def test_invalid_parameters_raise_config_error(make, message):
    with pytest.raises(ConfigError, match=message):
        make()


def test_sift_with_four_times_upsampling_works(image):
    features = SkimageSiftDetector(upsampling=4, sigma_min=3.2, n_octaves=3).detect(image[:96, :96])
    assert len(features) > 0 and features.octave.min() == -2


def _shifted_views(image: np.ndarray, shift: int) -> np.ndarray:
    """Two views of the same scene, the second moved ``shift`` px to the left (a crop, no wrap)."""
    width = image.shape[1] - shift
    return np.stack([image[:, :width], image[:, shift:shift + width]])


def test_usable_from_yaml_like_a_builtin(image, registry):
    text = "detector: {name: skimage-orb, n_keypoints: 800}\nmatcher: {name: brute-force, ratio: 0.8}\n"
    config = parse_pipeline(load_yaml("test.yaml", text=text), registry)
    assert config.detector.params == {"n_keypoints": 800}
    pipeline = Pipeline.from_config(config, registry=registry)
    assert isinstance(pipeline.detector, SkimageOrbDetector) and pipeline.detector.n_keypoints == 800
    views = _shifted_views(image, 4)
    rows, cols = views.shape[1:]
    geometry = Geometry(source_to_object_mm=500, source_to_detector_mm=1000, detector_cols=cols, detector_rows=rows,
                        pixel_pitch_u_mm=0.4, pixel_pitch_v_mm=0.4)
    result = pipeline.run(views, geometry)
    ok = [k for k, status in enumerate(result.pair_status) if status == "ok"]
    assert ok, result.pair_status
    assert result.n_matches[ok[0]] > 10
    # A pure horizontal shift is (almost) no turn of the object.
    assert abs(result.pair_angles_deg[ok[0]]) < 1.0


def test_bad_parameter_in_yaml_names_its_path(registry):
    text = "detector: {name: skimage-orb, n_keypoints: -5}\n"
    with pytest.raises(ConfigError) as info:
        parse_pipeline(load_yaml("test.yaml", text=text), registry)
    assert str(info.value).startswith("pipeline.detector.n_keypoints")
    assert "got -5" in str(info.value)


def test_unknown_parameter_in_yaml_lists_the_allowed_ones(registry):
    text = "detector: {name: skimage-censure, rng: 3}\n"
    with pytest.raises(ConfigError, match=r"^pipeline\.detector\.rng: unknown parameter .*seed"):
        parse_pipeline(load_yaml("test.yaml", text=text), registry)
