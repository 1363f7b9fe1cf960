"""Command line: ``ctpipe plugins | estimate | experiment synthetic``.

Errors caused by the user's input print one line ``ctpipe: error: ...`` on stderr and exit
with status 2; nothing half-written is left behind.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from ctpipe.errors import CtpipeError

__all__ = ["main"]


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error on one line (and points at --help)."""

    def error(self, message: str):  # noqa: D401 - argparse API
        self.exit(2, f"ctpipe: error: {message} (see '{self.prog} --help')\n")


def _registry(args):
    from ctpipe.plugins import get_registry

    return get_registry(blocked=tuple(args.block_plugin))


def _cmd_plugins(args) -> int:
    registry = _registry(args)
    stages = [info.to_dict() for info in registry]
    if args.json:
        print(json.dumps({"stages": stages}, indent=2))
        return 0
    width = max(len(s["name"]) for s in stages)
    plugin_width = max(len(s["plugin"]) for s in stages)
    for s in stages:
        print(f"{s['kind']:<9}  {s['name']:<{width}}  {s['plugin']:<{plugin_width}}  {s['description']}")
    return 0


def _cmd_estimate(args) -> int:
    from ctpipe.config import load_yaml, parse_geometry, parse_pipeline
    from ctpipe.io import read_projections, to_jsonable, write_csv, write_json
    from ctpipe.pipeline import Pipeline

    registry = _registry(args)
    geometry_yaml = load_yaml(args.geometry)
    if isinstance(geometry_yaml, dict) and set(geometry_yaml) == {"geometry"}:
        geometry_yaml = geometry_yaml["geometry"]
    geometry = parse_geometry(geometry_yaml)
    config = parse_pipeline(load_yaml(args.pipeline) if args.pipeline else None, registry)
    projections = read_projections(args.projections)
    pipeline = Pipeline.from_config(config, registry=registry)
    result = pipeline.run(projections, geometry)
    report = {"pipeline": config.to_dict(), "geometry": geometry.to_dict(), **result.to_dict()}
    if args.out:
        out = Path(args.out)
        write_csv(out / "angles.csv", ["view", "angle_deg", "n_keypoints"],
                  [[v, a, n] for v, (a, n) in enumerate(zip(result.angles_deg, result.n_keypoints))])
        write_json(out / "result.json", report)
    if args.json:
        print(json.dumps(to_jsonable(report), indent=2))
    else:
        failed = [s for s in result.pair_status if s != "ok"]
        print(f"{len(result.pairs) - len(failed)}/{len(result.pairs)} pairs estimated, "
              f"median {np.median(result.n_inliers):.0f} inliers of {np.median(result.n_matches):.0f} matches")
        for view, angle in enumerate(result.angles_deg):
            print(f"view {view:5d}  {angle:12.5f} deg")
        if failed:
            print(f"warning: {len(failed)} pairs failed, e.g. {failed[0]}", file=sys.stderr)
    return 0


def _cmd_experiment_synthetic(args) -> int:
    from ctpipe.experiments import load_synthetic_settings, run_synthetic
    from ctpipe.io import to_jsonable
    from ctpipe.report import synthetic_table, write_synthetic_outputs

    registry = _registry(args)
    settings = load_synthetic_settings(args.config, registry=registry)
    reps = args.reps or settings.reps
    total = reps * (len(settings.angles_deg) * len(settings.outlier_models) + len(settings.noise_sigmas))
    with _progress(total, "trials", quiet=args.json) as advance:
        report = run_synthetic(settings, reps=args.reps, seed=args.seed, jobs=args.jobs,
                               blocked=tuple(args.block_plugin), progress=advance)
    if args.out:
        write_synthetic_outputs(report, args.out)
    if args.json:
        print(json.dumps(to_jsonable(report.summary()), indent=2))
    else:
        for study in report.studies:
            print(f"\n## {study}\n")
            print(synthetic_table(report, study))
        print(f"{report.wall_s:.1f} s" + (f"; results in {args.out}" if args.out else ""))
    return 0


class _progress:
    """A tqdm bar on stderr when it is a terminal; silent otherwise."""

    def __init__(self, total: int, unit: str, quiet: bool = False) -> None:
        self.total, self.unit, self.quiet, self.bar = total, unit, quiet, None

    def __enter__(self):
        if not self.quiet and sys.stderr.isatty():
            from tqdm import tqdm

            self.bar = tqdm(total=self.total, unit=self.unit, file=sys.stderr, leave=False)
        return self.bar.update if self.bar is not None else None

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.close()


def _int_at_least(minimum: int):
    """argparse type: an integer >= ``minimum``, with a one-line message otherwise."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < minimum:
            raise argparse.ArgumentTypeError(f"must be an integer >= {minimum}, got {text!r}")
        return value

    return parse


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="ctpipe", description="Estimate the rotation angle of every view of a cone-beam CT scan.")
    parser.add_argument("--block-plugin", action="append", default=[], metavar="NAME",
                        help="do not load this plugin (entry-point name or built-in module); repeatable")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    p = sub.add_parser("plugins", help="list the registered stages")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(run=_cmd_plugins)

    p = sub.add_parser("estimate", help="estimate per-view angles of a projection stack")
    p.add_argument("projections", help="projection stack (views, rows, cols): .npy or multi-page .tif")
    p.add_argument("--geometry", required=True, help="geometry YAML (keys: source_to_object_mm, ...)")
    p.add_argument("--pipeline", help="pipeline YAML (default: sift, brute-force, ransac-1pt, least-squares)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--out", help="directory for result.json and angles.csv")
    p.set_defaults(run=_cmd_estimate)

    p = sub.add_parser("experiment", help="run an experiment")
    experiments = p.add_subparsers(dest="experiment", required=True, parser_class=_Parser)
    p = experiments.add_parser("synthetic", help="the paper's synthetic experiments, every estimator")
    p.add_argument("--config", help="experiment YAML (default: the built-in ctpipe/data/synthetic.yaml)")
    p.add_argument("--reps", type=_int_at_least(1), help="repetitions per swept value (default 300)")
    p.add_argument("--seed", type=_int_at_least(0), help="random seed (default 0)")
    p.add_argument("--jobs", type=_int_at_least(1), help="worker processes (default: number of CPUs)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--out", help="directory for synthetic.csv, summary.json, tables.md and PNG plots")
    p.set_defaults(run=_cmd_experiment_synthetic)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except CtpipeError as exc:
        print(f"ctpipe: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("ctpipe: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
