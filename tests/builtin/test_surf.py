"""ctpipe's SURF against OpenCV's own output (``../shared/surf-reference``) and on its own terms."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from ctpipe.builtin.surf import SurfDetector, surf
from ctpipe.config import build_stage, parse_stage
from ctpipe.errors import InputError
from ctpipe.evaluate.scoring import keypoint_agreement
from ctpipe.features import integral_image
from ctpipe.geometry import Geometry
from ctpipe.images import to_uint8
from ctpipe.model import rotation_matrix
from ctpipe.pipeline import Pipeline
from ctpipe.plugins import get_registry

ROOT = Path(__file__).resolve().parents[2]
REFERENCE = Path(os.environ.get("CTPIPE_SURF_REFERENCE", ROOT.parent / "shared" / "surf-reference"))
needs_reference = pytest.mark.skipif(not (REFERENCE / "surf").is_dir(),
                                     reason=f"OpenCV SURF reference outputs not found at {REFERENCE} "
                                            "(set CTPIPE_SURF_REFERENCE to the surf-reference folder)")
IMAGES = ("camera", "astronaut1024", "xray_a", "xray_b", "xray_rot0", "xray_rot1")
SETTINGS = [(extended, upright) for extended in (0, 1) for upright in (0, 1)]


def load_image(name: str) -> np.ndarray:
    return np.load(REFERENCE / "images" / f"{name}.npy")


def load_reference(name: str, extended: int, upright: int):
    return np.load(REFERENCE / "surf" / f"{name}_ext{extended}_up{upright}.npz")


@needs_reference
@pytest.mark.parametrize("name", IMAGES)
def test_keypoints_and_descriptors_agree_with_opencv(name):
    """The issue's targets are recall/precision >= 0.95, angle <= 1 deg, cosine >= 0.98; ctpipe
    reproduces OpenCV to float rounding, so these bounds are tighter and guard regressions."""
    image = load_image(name)
    for extended, upright in SETTINGS:
        reference = load_reference(name, extended, upright)
        features = surf(image, extended=bool(extended), upright=bool(upright))
        score = keypoint_agreement(reference, features)
        setting = f"{name} extended={extended} upright={upright}: {score}"
        assert score["recall"] >= 0.98 and score["precision"] >= 0.98, setting
        assert score["median_angle_diff_deg"] <= 0.1, setting
        assert score["median_descriptor_cosine"] >= 0.995, setting
        assert features.descriptors.shape == (len(features), 128 if extended else 64)


@needs_reference
def test_every_keypoint_field_matches_opencv_on_xray_a():
    """Positions, sizes, octaves, class ids and responses, keypoint by keypoint."""
    reference = load_reference("xray_a", 0, 0)
    features = surf(load_image("xray_a"))
    order = np.lexsort((reference["pt"][:, 0], reference["pt"][:, 1], -reference["response"]))
    assert len(features) == len(order)
    np.testing.assert_allclose(features.xy, reference["pt"][order], atol=1e-3)
    np.testing.assert_array_equal(features.size, reference["size"][order])
    np.testing.assert_array_equal(features.octave, reference["octave"][order])
    np.testing.assert_array_equal(features.class_id, reference["class_id"][order])
    np.testing.assert_allclose(features.response, reference["response"][order], rtol=1e-4)
    assert np.all(features.response >= 100.0)


@needs_reference
def test_rotation_pair_recovers_the_one_degree_turn():
    """SURF + ratio matching + ransac-1pt (configs/paper-surf.yaml) on xray_rot0 -> xray_rot1.

    The reference turns its cloud by what is -1 deg in ctpipe's convention (its rotation matrix
    is the transpose of :func:`ctpipe.model.rotation_matrix`); the sign is read from the sphere
    centres, not assumed.
    """
    before = np.load(REFERENCE / "images" / "xray_rot0_geometry.npz")
    after = np.load(REFERENCE / "images" / "xray_rot1_geometry.npz")
    turn = float(after["rot_deg"])
    signs = [s for s in (1.0, -1.0)
             if np.allclose(before["centres"] @ rotation_matrix(np.deg2rad(s * turn)).T, after["centres"], atol=1e-9)]
    assert len(signs) == 1
    truth_deg = signs[0] * turn
    geometry = Geometry(float(before["SOD"]), float(before["SDD"]), 512, 512, float(before["PIX"]), float(before["PIX"]))
    projections = np.stack([load_image("xray_rot0"), load_image("xray_rot1")])
    result = Pipeline.from_config(ROOT / "configs" / "paper-surf.yaml").run(projections, geometry)
    assert result.pair_status == ("ok",)
    assert abs(result.pair_angles_deg[0] - truth_deg) < 0.25


def blobs(size: int = 160, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:size, 0:size]
    image = np.zeros((size, size))
    for _ in range(40):
        x, y = rng.uniform(10, size - 10, 2)
        image += rng.uniform(0.3, 1.0) * np.exp(-((cols - x) ** 2 + (rows - y) ** 2) / (2 * rng.uniform(1.5, 5) ** 2))
    return image


def test_float_images_are_mapped_to_uint8_by_their_range():
    image = blobs()
    as_float = surf(image.astype(np.float32) * 3.5 - 1.0)
    as_uint8 = surf(to_uint8(image))
    assert len(as_float) > 10
    np.testing.assert_array_equal(as_float.xy, as_uint8.xy)
    np.testing.assert_array_equal(as_float.descriptors, as_uint8.descriptors)


def test_outputs_follow_the_features_contract():
    features = surf(to_uint8(blobs()), extended=True)
    n = len(features)
    assert n > 10 and features.norm == "L2"
    np.testing.assert_allclose(np.linalg.norm(features.descriptors, axis=1), 1.0, rtol=1e-5)
    assert np.all(np.diff(features.response) <= 0)
    assert set(np.unique(features.class_id)) <= {-1, 1}
    assert np.all((features.angle_deg >= 0) & (features.angle_deg < 360))
    upright = surf(to_uint8(blobs()), upright=True)
    assert np.all(upright.angle_deg == 270.0)


def test_turning_the_image_by_90_degrees_turns_the_keypoints():
    """The box filters are symmetric under quarter turns, so a turned image shows the same blobs
    at the turned positions (up to the half-pixel offsets of even-sized boxes)."""
    image = to_uint8(blobs(161))
    a = surf(image)
    b = surf(np.ascontiguousarray(np.rot90(image)))
    # rot90 maps (x, y) -> (y, W - 1 - x).
    turned = np.stack([a.xy[:, 1], 160 - a.xy[:, 0]], axis=1)
    near = np.linalg.norm(turned[:, None, :] - b.xy[None, :, :], axis=2).min(axis=1) < 1.5
    assert near.mean() > 0.8


def test_integral_image_sums_boxes():
    image = np.arange(12, dtype=np.uint8).reshape(3, 4)
    sums = integral_image(image)
    assert sums.shape == (4, 5) and sums[0].sum() == 0 and sums[:, 0].sum() == 0
    assert sums[3, 4] == image.sum() and sums[2, 3] == image[:2, :3].sum()


def test_blank_and_tiny_images_give_no_keypoints():
    for image in (np.zeros((64, 64), np.uint8), np.full((8, 8), 200, np.uint8)):
        features = surf(image)
        assert len(features) == 0 and features.descriptors.shape == (0, 64)


@pytest.mark.parametrize("image, message", [
    (np.zeros((4, 4, 3), np.uint8), "must be a 2-dimensional array"),
    (np.zeros((0, 5), np.uint8), "is empty"),
    (np.array([[0.0, np.nan], [1.0, 2.0]]), "NaN or infinite"),
])
def test_bad_images_raise_one_line_input_errors(image, message):
    with pytest.raises(InputError, match=message):
        surf(image)


def test_surf_is_a_registered_detector_with_opencv_parameters():
    registry = get_registry()
    spec = parse_stage({"name": "surf", "hessian_threshold": 400.0, "extended": True}, "detector", registry, "detector")
    stage = build_stage(spec, registry)
    assert isinstance(stage, SurfDetector) and stage.extended
    defaults = SurfDetector()
    assert (defaults.hessian_threshold, defaults.n_octaves, defaults.n_octave_layers, defaults.extended,
            defaults.upright) == (100.0, 4, 3, False, False)
    image = to_uint8(blobs())
    assert len(stage.detect(image)) < len(defaults.detect(image))


def test_paper_surf_config_runs_end_to_end():
    """configs/paper-surf.yaml as shipped, on beads rendered in the paper's geometry (SOD 500 mm,
    SDD 1 m, 0.4 mm pixels, where its Sampson threshold 8e-4 is 2 px). A 1 deg turn moves these
    beads at most ~0.3 px vertically, which bounds how well any pair can be estimated."""
    from bead_rendering import render_beads

    geometry = Geometry(500.0, 1000.0, 512, 512, 0.4, 0.4)
    rng = np.random.default_rng(5)
    centres, radii = rng.uniform(-40, 40, (300, 3)), rng.uniform(1.0, 4.0, 300)
    truth = np.array([0.0, 1.0, 2.5])
    projections = render_beads(geometry, truth, centres, radii)
    result = Pipeline.from_config(ROOT / "configs" / "paper-surf.yaml").run(projections, geometry)
    assert result.pair_status == ("ok", "ok")
    assert np.all(result.n_inliers > 100)
    np.testing.assert_allclose(result.angles_deg, truth, atol=0.35)
