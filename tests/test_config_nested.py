"""Nested stage specs: a stage that uses another stage names it in YAML and gets it through the registry."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from ctpipe.builtin.bundle import BundleAdjustmentRefiner
from ctpipe.builtin.estimators import Ransac1ptEstimator
from ctpipe.builtin.projection_matching import ProjectionMatchingRefiner
from ctpipe.builtin.refiners import LeastSquaresRefiner
from ctpipe.config import build_stage, load_yaml, parse_pipeline
from ctpipe.errors import ConfigError
from ctpipe.plugins import get_registry
from ctpipe.solve.simulated import synthetic_scan
from ctpipe.stages import StageSpec

REGISTRY = get_registry()


def parse(text: str, registry=REGISTRY):
    return parse_pipeline(load_yaml("p.yaml", text=text), registry)


def refiner(text: str, registry=REGISTRY):
    return build_stage(parse(text, registry).refiner, registry)


def test_a_bare_name_means_the_named_stage_with_its_defaults():
    config = parse("refiner: {name: projection-matching, start: bundle-adjustment}\n")
    assert config.refiner.params["start"] == StageSpec("refiner", "bundle-adjustment", {})
    stage = build_stage(config.refiner, REGISTRY)
    assert stage.start == BundleAdjustmentRefiner()


def test_a_mapping_gives_the_nested_stage_its_parameters():
    config = parse("refiner: {name: projection-matching, start: {name: bundle-adjustment, loss_scale_px: 0.7}}\n")
    assert config.to_dict()["refiner"] == {"name": "projection-matching",
                                           "start": {"name": "bundle-adjustment", "loss_scale_px": 0.7}}
    stage = build_stage(config.refiner, REGISTRY)
    assert stage.start == BundleAdjustmentRefiner(loss_scale_px=0.7)
    assert pickle.loads(pickle.dumps(stage)) == stage   # stages travel to Dask workers


def test_the_words_keep_their_meaning_and_the_default_is_the_view_graph():
    assert refiner("refiner: {name: projection-matching, start: nominal}\n").start == "nominal"
    assert refiner("refiner: projection-matching\n").start == "view-graph"
    assert ProjectionMatchingRefiner().start == "view-graph"


@pytest.mark.parametrize("text, message", [
    ("refiner: {name: projection-matching, start: nope}",
     "pipeline.refiner.start.name: unknown refiner 'nope'; registered refiners: ball-calibration, bundle-adjustment, "
     "least-squares, projection-matching"),
    ("refiner: {name: projection-matching, start: {name: bundle-adjustment, loss_scale_px: -1}}",
     "pipeline.refiner.start.loss_scale_px: must be a number > 0 and <= 1000, got -1"),
    ("refiner: {name: projection-matching, start: {name: bundle-adjustment, scale: 1}}",
     "pipeline.refiner.start.scale: unknown parameter of refiner 'bundle-adjustment'; allowed: loss, loss_scale_px"),
    ("refiner: {name: projection-matching, start: {loss_scale_px: 1}}",
     "pipeline.refiner.start.name: missing; registered refiners: ball-calibration, bundle-adjustment, least-squares"),
    ("refiner: {name: projection-matching, start: 3}",
     "pipeline.refiner.start: must be a refiner (its name, or a mapping with 'name' and its parameters) or one of "
     "'view-graph', 'nominal', got 3"),
])
def test_a_bad_nested_stage_is_named_by_its_yaml_path(text, message):
    with pytest.raises(ConfigError) as caught:
        parse(text + "\n")
    assert str(caught.value).startswith(message)
    assert "\n" not in str(caught.value)


def test_a_blocked_plugins_stage_cannot_be_the_start():
    registry = get_registry(blocked=("ctpipe.builtin.bundle",))
    with pytest.raises(ConfigError, match=r"^pipeline.refiner.start.name: unknown refiner 'bundle-adjustment'; "
                                          r"registered refiners: ball-calibration, least-squares, projection-matching$"):
        parse("refiner: {name: projection-matching, start: bundle-adjustment}\n", registry)
    # and a Python stage naming it is refused when it is built through that registry
    with pytest.raises(ConfigError, match="^ProjectionMatchingRefiner.start.name: unknown refiner 'bundle-adjustment'"):
        build_stage(ProjectionMatchingRefiner(start="bundle-adjustment"), registry)


def test_python_takes_a_stage_or_a_name():
    given = BundleAdjustmentRefiner(loss_scale_px=0.7)
    assert ProjectionMatchingRefiner(start=given).start is given
    named = ProjectionMatchingRefiner(start={"name": "bundle-adjustment", "loss_scale_px": 0.7})
    assert named.start == StageSpec("refiner", "bundle-adjustment", {"loss_scale_px": 0.7})
    assert build_stage(named, REGISTRY).start == given
    with pytest.raises(ConfigError, match="^ProjectionMatchingRefiner.start.loss_scale_px: must be a number > 0"):
        build_stage(ProjectionMatchingRefiner(start={"name": "bundle-adjustment", "loss_scale_px": 0}), REGISTRY)
    with pytest.raises(ConfigError, match="^ProjectionMatchingRefiner.start: must be a refiner"):
        ProjectionMatchingRefiner(start=Ransac1ptEstimator())
    with pytest.raises(ConfigError, match="only named, not built"):
        ProjectionMatchingRefiner(start="least-squares").refine(None, rng=np.random.default_rng(0))


def test_the_start_is_the_nested_refiners_angles():
    """Without projections matching is skipped and the start comes back: the nested stage's angles."""
    observations = synthetic_scan(24, 60, rng=3).observations
    rng = np.random.default_rng(0)
    default = ProjectionMatchingRefiner().refine(observations, rng=rng)
    view_graph = LeastSquaresRefiner(weighting="inliers").refine(observations, rng=rng)
    assert default.info["start"] == "view-graph" and "no projections" in default.info["matching"]
    np.testing.assert_allclose(default.angles_rad, view_graph.angles_rad - view_graph.angles_rad[0], rtol=0, atol=1e-12)
    bundle = refiner("refiner: {name: projection-matching, start: {name: bundle-adjustment, loss_scale_px: 0.7}}\n")
    solution = bundle.refine(observations, rng=rng)
    expected = BundleAdjustmentRefiner(loss_scale_px=0.7).refine(observations, rng=rng).angles_rad
    assert solution.info["start"] == "BundleAdjustmentRefiner"
    np.testing.assert_allclose(solution.angles_rad, expected - expected[0], rtol=0, atol=1e-12)


def test_ransac_1pt_named_bare_is_the_default_estimator():
    bare = build_stage(parse("estimator: ransac-1pt\n").estimator, REGISTRY)
    default = build_stage(parse("{}\n").estimator, REGISTRY)
    assert bare == default == Ransac1ptEstimator()
    assert default.sampson_threshold == 8e-4


def test_a_pipeline_built_in_python_builds_a_nested_stage_given_by_name():
    from ctpipe.builtin import (BruteForceMatcher, BundleAdjustmentRefiner, ProjectionMatchingRefiner,
                                Ransac1ptEstimator, SiftDetector)
    from ctpipe.pipeline import Pipeline

    pipeline = Pipeline(SiftDetector(), BruteForceMatcher(), Ransac1ptEstimator(),
                        ProjectionMatchingRefiner(start={"name": "bundle-adjustment", "loss_scale_px": 0.7}))
    assert pipeline.refiner.start == BundleAdjustmentRefiner(loss_scale_px=0.7)
    assert Pipeline(SiftDetector(), BruteForceMatcher(), Ransac1ptEstimator(),
                    ProjectionMatchingRefiner()).refiner.start == "view-graph"
