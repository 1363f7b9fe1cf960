import math

import numpy as np
import pytest

from ctpipe.errors import InputError
from ctpipe.evaluate.scoring import (align_offset, error_table, se_coverage, pair_errors_deg, recovery, support_mask,
                                     view_errors_deg, volume_metrics)
from ctpipe.recon.volume import VolumeGrid


def test_error_table_is_the_papers_table_of_absolute_errors():
    table = error_table([0.1, -0.2, np.nan, 0.3, -0.4])
    assert table["estimated"] == 4 and table["total"] == 5
    assert table["mae_deg"] == pytest.approx(0.25)
    assert table["min_deg"] == pytest.approx(0.1) and table["max_deg"] == pytest.approx(0.4)
    assert table["median_deg"] == pytest.approx(0.25)
    assert table["std_deg"] == pytest.approx(np.std([0.1, 0.2, 0.3, 0.4]))
    assert table["bias_deg"] == pytest.approx(-0.05)


def test_error_table_of_nothing_estimated_is_nan_not_an_exception():
    table = error_table([np.nan, np.nan])
    assert table["estimated"] == 0 and math.isnan(table["mae_deg"])


def test_view_errors_ignore_the_unobservable_offset_but_not_relative_errors():
    truth = np.array([0.0, 1.0, 2.0, 3.0, 4.0])
    assert np.allclose(view_errors_deg(truth + 17.0, truth), 0.0)
    estimate = truth + np.array([0.0, 0.0, 0.1, 0.0, 0.0])
    errors = view_errors_deg(estimate, truth)
    assert errors[2] == pytest.approx(0.1) and np.allclose(np.delete(errors, 2), 0.0)
    with pytest.raises(InputError):
        view_errors_deg(truth[:3], truth)


def test_pair_errors_compare_with_true_differences():
    truth = np.array([0.0, 1.2, 2.0])
    errors = pair_errors_deg([[0, 1], [1, 2], [0, 2]], [1.0, 0.8, np.nan], truth)
    assert np.allclose(errors[:2], [-0.2, 0.0]) and np.isnan(errors[2])


def test_align_offset_fills_missing_views_from_the_fallback():
    reference = np.array([10.0, 11.0, 12.0, 13.0])
    aligned, filled = align_offset([0.0, 1.0, np.nan, 3.0], reference, fallback_deg=reference - 10.0)
    assert filled == 1 and np.allclose(aligned, reference)


def test_volume_metrics_are_perfect_for_a_perfect_volume_and_worse_with_noise():
    grid = VolumeGrid.cube(24, 1.0)
    mask = support_mask(grid, 10.0, 10.0)
    rng = np.random.default_rng(0)
    reference = rng.random(grid.shape)
    perfect = volume_metrics(reference, reference, mask)
    assert perfect["rmse"] == 0 and perfect["ssim"] == pytest.approx(1.0)
    noisy = volume_metrics(reference + 0.05 * rng.standard_normal(grid.shape), reference, mask)
    assert 0 < noisy["rmse"] < 0.06 and noisy["ssim"] < 1.0 and 20 < noisy["psnr_db"] < 30


def test_support_mask_is_a_cylinder_about_the_axis():
    grid = VolumeGrid(20, 10, 20, 1.0)
    mask = support_mask(grid, 5.0, 3.0, margin_voxels=0)
    assert mask.shape == grid.shape
    assert mask[:, 10, 10].sum() == 6  # |y| <= 3 at half-integer centres: -2.5 .. 2.5
    with pytest.raises(InputError):
        support_mask(grid, 0.1, 0.1)


def test_recovery_is_signed():
    assert recovery(30.0, 20.0, 40.0) == pytest.approx(0.5)
    assert recovery(15.0, 20.0, 40.0) == pytest.approx(-0.25)
    assert math.isnan(recovery(30.0, 20.0, 20.0))


def test_se_coverage_counts_views_within_two_standard_errors():
    errors = np.array([0.1, -0.3, 0.05, np.nan, 0.2, 0.0])
    se = np.array([0.1, 0.1, 0.01, 0.1, np.inf, 0.0])
    # 0.1 <= 0.2 yes; 0.3 > 0.2 no; 0.05 > 0.02 no; NaN error, infinite and zero SE not counted.
    assert se_coverage(errors, se) == {"views": 3, "within": 1, "fraction": 1 / 3, "median_se_deg": 0.1, "k": 2.0}
    with pytest.raises(InputError, match="one shape"):
        se_coverage(errors, se[:-1])
