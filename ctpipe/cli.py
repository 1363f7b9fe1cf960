"""Command line: ``ctpipe plugins | estimate | detect | simulate | validate | experiment synthetic``.

Errors caused by the user's input print one line ``ctpipe: error: ...`` on stderr and exit
with status 2; nothing half-written is left behind: every output path is checked before the
work starts, and a result of several files is written all-or-nothing. SIGTERM (what
``timeout`` and batch schedulers send) is handled like Ctrl-C, so temporary files are removed.
See docs/errors.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import signal
import sys
import time
from pathlib import Path

import numpy as np

from ctpipe.errors import ConfigError, CtpipeError, InputError

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
    from ctpipe.config import load_geometry, load_yaml, parse_pipeline
    from ctpipe.io.arrays import read_projections
    from ctpipe.io.outputs import check_output_dir, csv_bytes, json_bytes, to_jsonable, write_files
    from ctpipe.pipeline import Pipeline

    if args.out is not None:
        check_output_dir(args.out)
    registry = _registry(args)
    config = parse_pipeline(load_yaml(args.pipeline) if args.pipeline else None, registry)
    source = Path(args.projections)
    truth = nominal = None
    if not source.exists():
        raise InputError(f"{source}: no such file or scan folder")
    if source.is_dir() or source.suffix.lower() in (".txrm", ".txm"):
        from ctpipe.io.scans import open_scan

        scan = open_scan(source)
        projections, geometry, truth = scan.projections, scan.geometry, scan.true_angles_deg
        nominal = scan.nominal_angles_deg
        if args.geometry:
            raise InputError(f"{source} is a {scan.format} scan with its own geometry; drop --geometry")
    else:
        if not args.geometry:
            raise InputError(f"{source}: a projection file needs --geometry GEOMETRY.yaml (or give a scan folder)")
        geometry = load_geometry(args.geometry)
        projections = read_projections(source)
    pipeline = Pipeline.from_config(config, registry=registry)
    with _progress(len(projections), "views", quiet=args.json) as advance:
        result = pipeline.run(projections, geometry, nominal_angles_deg=nominal, progress=advance)
    report = {"pipeline": config.to_dict(), "geometry": geometry.to_dict(), **result.to_dict()}
    header, columns = ["view", "angle_deg", "n_keypoints"], [result.angles_deg, result.n_keypoints]
    if truth is not None:
        from ctpipe.evaluate.scoring import error_table, pair_errors_deg, view_errors_deg

        errors = view_errors_deg(result.angles_deg, truth)
        report["angle_errors"] = {
            "views": error_table(errors),
            "pairs": error_table(pair_errors_deg(result.pairs, result.pair_angles_deg, truth)),
        }
        header, columns = header + ["true_deg", "error_deg"], columns + [truth - truth[0], errors]
    if args.out is not None:
        out = Path(args.out)
        angles_csv = csv_bytes(header, [[v, *row] for v, row in enumerate(zip(*columns))])
        result_json = json_bytes(report)
        write_files({out / "angles.csv": lambda h: h.write(angles_csv), out / "result.json": lambda h: h.write(result_json)})
    if args.json:
        print(json.dumps(to_jsonable(report), indent=2))
    else:
        failed = [s for s in result.pair_status if s != "ok"]
        print(f"{len(result.pairs) - len(failed)}/{len(result.pairs)} pairs estimated, "
              f"median {np.median(result.n_inliers):.0f} inliers of {np.median(result.n_matches):.0f} matches")
        for view, angle in enumerate(result.angles_deg):
            print(f"view {view:5d}  {angle:12.5f} deg")
        if truth is not None:
            table = report["angle_errors"]["views"]
            print(f"against the true angles in scan.yaml: RMS {table['rms_deg']:.4f} deg, MAE {table['mae_deg']:.4f} deg, "
                  f"max {table['max_deg']:.4f} deg ({table['estimated']}/{table['total']} views)")
        if failed:
            print(f"warning: {len(failed)} pairs failed, e.g. {failed[0]}", file=sys.stderr)
    return 0


def _cmd_detect(args) -> int:
    from ctpipe.config import build_stage, parse_stage
    from ctpipe.io.arrays import read_image
    from ctpipe.io.outputs import check_output_file, keypoints_writer, to_jsonable, write_files

    # Checked before the detector runs: a typo in a suffix should cost nothing, and writing
    # keypoints to "kp.png" or a picture to "kp.npz" would only surprise later.
    out = check_output_file(args.out, "--out", ".npz")
    overlay = check_output_file(args.overlay, "--overlay", ".png") if args.overlay is not None else None
    if overlay is not None and overlay.absolute() == out.absolute():
        raise InputError(f"--overlay {overlay}: is the --out file too; give two different files")
    registry = _registry(args)
    params = {}
    for key, value in args.set:
        if key == "name":
            raise ConfigError("detector.name: choose the detector with --detector, not --set name=...")
        if key in params:
            raise ConfigError(f"detector.{key}: given twice with --set ({params[key]!r} and {value!r}); give it once")
        params[key] = value
    # The path pipeline YAML takes, so an unknown key or a bad value reads as it would in a config.
    spec = parse_stage({"name": args.detector, **params}, "detector", registry, "detector")
    detector = build_stage(spec, registry)
    image = read_image(args.image)
    start = time.perf_counter()
    features = detector.detect(image)
    seconds = time.perf_counter() - start
    effective = detector.params()
    # Render before writing anything, so a failure leaves neither file behind.
    picture = None
    if overlay is not None:
        from ctpipe.evaluate.report import keypoints_png

        picture = keypoints_png(image, features, f"{args.detector}: {len(features)} keypoints")
    files = {out: keypoints_writer(features, detector=args.detector, params=effective)}
    if picture is not None:
        files[overlay] = lambda handle: handle.write(picture)
    write_files(files)
    outputs = {"out": str(out), "overlay": str(overlay) if overlay is not None else None}
    if args.json:
        report = {"detector": args.detector, "params": effective, "n_keypoints": len(features),
                  "norm": features.norm, "image": {"path": str(args.image), "shape": list(image.shape),
                                                   "dtype": str(image.dtype)},
                  "seconds": seconds, "outputs": outputs}
        print(json.dumps(to_jsonable(report), indent=2))
    else:
        written = ", ".join(str(p) for p in (out, overlay) if p is not None)
        print(f"{args.detector}: {len(features)} keypoints on {image.shape[0]} x {image.shape[1]} ({image.dtype}) "
              f"in {seconds:.3f} s -> {written}")
    return 0


def _cmd_simulate(args) -> int:
    from ctpipe.io.scan_folder import check_scan_folder_free
    from ctpipe.sim.phantoms import load_phantom
    from ctpipe.sim.scan_spec import load_scan_spec
    from ctpipe.sim.simulator import simulate, write_simulated_scan

    out = Path(args.out) if args.out.strip() else args.out
    check_scan_folder_free(out, overwrite=args.overwrite)
    phantom = load_phantom(args.phantom)
    spec = load_scan_spec(args.scan)
    seed = spec.seed if args.seed is None else args.seed
    with _progress(spec.n_views, "views", quiet=False) as advance:
        scan = simulate(phantom, spec, rng=np.random.default_rng(seed), progress=advance)
    write_simulated_scan(out, scan, phantom=phantom, spec=spec, seed=seed, overwrite=args.overwrite)
    offsets = scan.true_angles_deg - scan.nominal_angles_deg
    print(f"{spec.n_views} views of {spec.geometry.detector_rows} x {spec.geometry.detector_cols} written to {out}; "
          f"jitter: RMS {np.sqrt(np.mean(offsets**2)):.4f} deg, max |{np.max(np.abs(offsets)):.4f}| deg")
    return 0


def _cmd_validate(args) -> int:
    from ctpipe.evaluate.validate import load_validate_settings, run_validate, write_validate_outputs
    from ctpipe.io.outputs import check_output_dir, staged_folder, to_jsonable

    check_output_dir(args.out)
    registry = _registry(args)
    settings = load_validate_settings(args.experiment, registry)
    if args.seed is not None:
        settings = dataclasses.replace(settings, seed=args.seed)

    def progress(step: str, total: int):
        return _progress(total, "views", quiet=args.json, description=step)

    report = run_validate(settings, registry, progress=progress)
    with staged_folder(args.out) as tmp:
        written = [Path(args.out) / p.relative_to(tmp) for p in write_validate_outputs(report, tmp)]
    if args.json:
        print(json.dumps(to_jsonable(report.to_dict()), indent=2))
        return 0
    for line in report.summary_lines():
        print(line)
    print("timings: " + ", ".join(f"{k} {v:.1f} s" for k, v in report.timings_s.items()))
    if written:
        print(f"results in {args.out}: " + ", ".join(p.name for p in written))
    return 0


def _cmd_experiment_synthetic(args) -> int:
    from ctpipe.evaluate.experiments import load_synthetic_settings, run_synthetic
    from ctpipe.evaluate.report import synthetic_table, write_synthetic_outputs
    from ctpipe.io.outputs import check_output_dir, staged_folder, to_jsonable

    if args.out is not None:
        check_output_dir(args.out)
    registry = _registry(args)
    settings = load_synthetic_settings(args.config, registry=registry)
    reps = args.reps or settings.reps
    total = reps * (len(settings.angles_deg) * len(settings.outlier_models) + len(settings.noise_sigmas))
    with _progress(total, "trials", quiet=args.json) as advance:
        report = run_synthetic(settings, reps=args.reps, seed=args.seed, jobs=args.jobs,
                               blocked=tuple(args.block_plugin), progress=advance)
    if args.out is not None:
        with staged_folder(args.out) as tmp:
            write_synthetic_outputs(report, tmp)
    if args.json:
        print(json.dumps(to_jsonable(report.summary()), indent=2))
    else:
        for study in report.studies:
            print(f"\n## {study}\n")
            print(synthetic_table(report, study))
        print(f"{report.wall_s:.1f} s" + (f"; results in {args.out}" if args.out else ""))
    return 0


class _progress:
    """A tqdm bar on stderr when it is a terminal; otherwise one line naming the step (if any)."""

    def __init__(self, total: int, unit: str, quiet: bool = False, description: str | None = None) -> None:
        self.total, self.unit, self.quiet, self.description, self.bar = total, unit, quiet, description, None

    def __enter__(self):
        if self.quiet:
            return None
        if sys.stderr.isatty():
            from tqdm import tqdm

            self.bar = tqdm(total=self.total, unit=self.unit, file=sys.stderr, leave=False, desc=self.description)
        elif self.description:
            print(f"ctpipe: {self.description}", file=sys.stderr, flush=True)
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


def _key_value(text: str) -> tuple[str, object]:
    """argparse type of ``--set``: ``key=value`` with the value parsed as YAML (``1e-3`` a float)."""
    from ctpipe.config import load_yaml

    key, sep, raw = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"must be key=value (e.g. n_features=500), got {text!r}")
    try:
        return key, load_yaml(f"--set {key}", text=raw)
    except ConfigError:
        raise argparse.ArgumentTypeError(f"{key}: value {raw[:40]!r} is not a YAML scalar or list") from None


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="ctpipe", description="Estimate the rotation angle of every view of a cone-beam CT scan.")
    parser.add_argument("--block-plugin", action="append", default=[], metavar="NAME",
                        help="do not load this plugin (entry-point name or built-in module); repeatable")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    p = sub.add_parser("plugins", help="list the registered stages")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(run=_cmd_plugins)

    p = sub.add_parser("estimate", help="estimate per-view angles of a scan folder or a projection stack")
    p.add_argument("projections", help="a scan folder (scan.yaml + TIFFs, as 'ctpipe simulate' writes) or a "
                                       "projection stack (views, rows, cols): .npy or multi-page .tif")
    p.add_argument("--geometry", help="geometry YAML (keys: source_to_object_mm, ...); only for a projection stack")
    p.add_argument("--pipeline", help="pipeline YAML (default: sift, brute-force, ransac-1pt, least-squares)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--out", help="directory for result.json and angles.csv")
    p.set_defaults(run=_cmd_estimate)

    p = sub.add_parser("detect", help="run one detector on one image: keypoints to .npz, optionally a picture",
                       description="Run one registered detector on one 2-D image and write what it finds.")
    p.add_argument("image", help="a 2-D grey-level image (rows, cols): .npy, .tif/.tiff or .png")
    p.add_argument("--detector", required=True, metavar="NAME",
                   help="a registered detector (see 'ctpipe plugins'), e.g. sift or orb")
    p.add_argument("--set", action="append", default=[], type=_key_value, metavar="KEY=VALUE",
                   help="a detector parameter, value read as YAML (n_features=500, upright=true); repeatable")
    p.add_argument("--out", required=True, metavar="FILE.npz",
                   help="keypoints and descriptors with OpenCV reference keys (pt, size, angle, response, "
                        "octave, class_id, descriptors) plus norm, detector and params")
    p.add_argument("--overlay", metavar="FILE.png",
                   help="the image in grey with each keypoint as a circle of its size and a tick at its angle")
    p.add_argument("--json", action="store_true", help="print a JSON summary instead of one line")
    p.set_defaults(run=_cmd_detect)

    p = sub.add_parser("simulate", help="write a simulated scan folder of a phantom with known angle jitter")
    p.add_argument("phantom", help="phantom YAML, or a built-in name such as granular or shepp-logan-3d")
    p.add_argument("--scan", required=True, help="scan spec YAML: geometry, angles, jitter, noise, projector, seed")
    p.add_argument("--out", required=True, help="scan folder to write (scan.yaml + projections/*.tif)")
    p.add_argument("--seed", type=_int_at_least(0), help="random seed (default: the scan spec's)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing non-empty --out folder")
    p.set_defaults(run=_cmd_simulate)

    p = sub.add_parser("validate", help="simulate a jittered scan, estimate its angles, score the reconstructions")
    p.add_argument("experiment", nargs="?", help="experiment YAML (default: the built-in ctpipe/evaluate/validate.yaml)")
    p.add_argument("--out", default="results/validate",
                   help="directory for report.json, angles.csv and PNGs (default: results/validate)")
    p.add_argument("--seed", type=_int_at_least(0), help="random seed (default: the experiment's)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(run=_cmd_validate)

    p = sub.add_parser("experiment", help="run an experiment")
    experiments = p.add_subparsers(dest="experiment", required=True, parser_class=_Parser)
    p = experiments.add_parser("synthetic", help="the paper's synthetic experiments, every estimator")
    p.add_argument("--config", help="experiment YAML (default: the built-in ctpipe/evaluate/synthetic.yaml)")
    p.add_argument("--reps", type=_int_at_least(1), help="repetitions per swept value (default 300)")
    p.add_argument("--seed", type=_int_at_least(0), help="random seed (default 0)")
    p.add_argument("--jobs", type=_int_at_least(1), help="worker processes (default: number of CPUs)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--out", help="directory for synthetic.csv, summary.json, tables.md and PNG plots")
    p.set_defaults(run=_cmd_experiment_synthetic)
    return parser


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the program is, so every ``finally`` removes its temporary files."""


def _on_sigterm(signum, frame) -> None:
    if os.getpid() != _MAIN_PID[0]:
        # A forked worker (experiment synthetic): its parent cleans up; die as SIGTERM means.
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGTERM)
        return
    # A second SIGTERM (schedulers repeat it) must not cut the clean-up of the first short.
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raise _Terminated()


_MAIN_PID = [0]


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    previous = None
    try:
        _MAIN_PID[0] = os.getpid()
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    except ValueError:  # not the main thread (main() called from a thread): leave signals alone
        pass
    try:
        return args.run(args)
    except CtpipeError as exc:
        print(f"ctpipe: error: {exc}", file=sys.stderr)
        return 2
    except _Terminated:
        print("ctpipe: terminated", file=sys.stderr)
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        print("ctpipe: interrupted", file=sys.stderr)
        return 130
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
