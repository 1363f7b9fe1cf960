"""Evaluation: scoring estimated angles and reconstructions against a known truth.

:mod:`~ctpipe.evaluate.validate` is ``ctpipe validate``, the end-to-end check: simulate a scan
with known jitter, estimate its angles with a pipeline, reconstruct with nominal, estimated and
true angles and score each; :mod:`~ctpipe.evaluate.experiments` runs the synthetic studies of
``ctpipe synthetic`` on correspondences drawn from the model (:mod:`~ctpipe.evaluate.synthetic`);
:mod:`~ctpipe.evaluate.scoring` holds the metrics (angle errors after the common offset, PSNR,
SSIM, recovery) and :mod:`~ctpipe.evaluate.report` the figures and tables;
:mod:`~ctpipe.evaluate.preview` the truth-free before/after slices ``ctpipe estimate`` writes;
:mod:`~ctpipe.evaluate.sweep` is ``ctpipe experiment sweep``, validate on many scenarios drawn
from distributions over any key of an experiment, one row each;
:mod:`~ctpipe.evaluate.compare` is ``ctpipe experiment compare``, several pipelines on the same
simulated scenarios with paired tests. Their built-in defaults are
``validate.yaml``, ``synthetic.yaml`` and ``sweep.yaml`` in this folder.
"""

from ctpipe.evaluate.compare import (ALPHA, BUILTIN_COMPARISONS, ComparedPipeline, CompareReport, CompareSettings,
                                     builtin_pipelines, file_scenarios, load_pipelines, paired_comparison, run_compare,
                                     run_compare_scenario, sweep_scenarios, write_compare_outputs)
from ctpipe.evaluate.preview import BeforeAfter, before_after, before_after_png
from ctpipe.evaluate.experiments import (STUDIES, SyntheticReport, SyntheticSettings, load_synthetic_settings,
                                         run_synthetic)
from ctpipe.evaluate.report import (angle_errors_png, estimate_angles_png, keypoints_png, slices_png, synthetic_table,
                                    write_synthetic_outputs)
from ctpipe.evaluate.scoring import (align_offset, error_table, keypoint_agreement, pair_errors_deg, recovery,
                                     score_against_truth, se_coverage, support_mask, view_errors_deg, volume_metrics)
from ctpipe.evaluate.sweep import (DISTRIBUTIONS, SweepReport, SweepSettings, draw_scenario, load_sweep_settings,
                                   parse_sweep, report_row, failure_reason, run_scenario, run_sweep, worse_than_nominal,
                                   write_sweep_outputs)
from ctpipe.evaluate.synthetic import Cylinder, cylinder_points, make_correspondences
from ctpipe.evaluate.validate import (SimulatedExperiment, ValidateReport, ValidateSettings, check_experiment,
                                      estimate_problems, load_validate_settings, pair_chained_deg, parse_validate,
                                      run_validate, score_pipeline, simulate_experiment, write_validate_outputs)

__all__ = ["run_validate", "load_validate_settings", "parse_validate", "check_experiment", "ValidateSettings",
           "ValidateReport", "write_validate_outputs", "estimate_problems", "pair_chained_deg", "run_synthetic",
           "load_synthetic_settings", "SyntheticSettings", "SyntheticReport", "STUDIES", "error_table",
           "view_errors_deg", "pair_errors_deg", "score_against_truth", "align_offset", "support_mask", "volume_metrics",
           "recovery", "keypoint_agreement", "synthetic_table", "write_synthetic_outputs", "slices_png",
           "angle_errors_png", "estimate_angles_png", "keypoints_png", "Cylinder", "cylinder_points",
           "make_correspondences", "run_sweep", "load_sweep_settings", "parse_sweep", "draw_scenario", "run_scenario",
           "write_sweep_outputs", "worse_than_nominal", "SweepSettings", "SweepReport", "DISTRIBUTIONS", "BeforeAfter", "before_after",
           "before_after_png", "se_coverage", "report_row", "failure_reason", "SimulatedExperiment", "simulate_experiment",
           "score_pipeline", "ALPHA", "BUILTIN_COMPARISONS", "ComparedPipeline", "CompareReport", "CompareSettings",
           "builtin_pipelines", "file_scenarios", "load_pipelines", "paired_comparison", "run_compare",
           "run_compare_scenario", "sweep_scenarios", "write_compare_outputs"]
