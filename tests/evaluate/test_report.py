"""The plots of a run: per-view angle errors stay readable whatever one curve does."""

from __future__ import annotations

import io

import numpy as np

from ctpipe.evaluate.report import angle_errors_png


def _height(png: bytes) -> int:
    from PIL import Image

    return Image.open(io.BytesIO(png)).size[1]


def test_a_curve_far_past_the_others_gets_a_panel_of_its_own_and_does_not_flatten_them():
    rng = np.random.default_rng(0)
    curves = {"nominal angles": rng.normal(0, 0.5, 100), "estimated angles": rng.normal(0, 0.02, 100),
              "pair-chained": np.cumsum(rng.normal(0, 3.0, 100))}
    scaled = angle_errors_png(curves, "t", scale_to=("nominal angles", "estimated angles"))
    plain = angle_errors_png(curves, "t")
    within = angle_errors_png({k: v for k, v in curves.items() if k != "pair-chained"}, "t",
                              scale_to=("nominal angles", "estimated angles"))
    # Off the scale: a second, full-scale panel below; every curve on the scale: one panel as before.
    assert _height(scaled) > _height(plain) == _height(within)
