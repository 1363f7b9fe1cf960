"""Command line: ``ctpipe plugins | estimate | detect | simulate | validate | experiment synthetic | sweep | compare``.

Errors caused by the user's input print one line ``ctpipe: error: ...`` on stderr and exit
with status 2; nothing half-written is left behind: every output path is checked before the
work starts, and a result of several files is written all-or-nothing; in a batch of scans
(``ctpipe estimate SCAN SCAN ...``) each failed scan gets its line and the others are finished,
with status 2 at the end if any failed. SIGTERM (what
``timeout`` and batch schedulers send) is handled like Ctrl-C, so temporary files are removed.
See docs/errors.md.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import re
import signal
import sys
import time
from pathlib import Path

import numpy as np

from ctpipe import gpu
from ctpipe.errors import ClusterError, ConfigError, CtpipeError, InputError, OutputError

__all__ = ["main"]


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error on one line (and points at --help)."""

    def error(self, message: str):  # noqa: D401 - argparse API
        self.exit(2, f"ctpipe: error: {message} (see '{self.prog} --help')\n")


def _registry(args):
    from ctpipe.plugins import get_registry

    return get_registry(blocked=tuple(args.block_plugin))


def _cmd_plugins(args) -> int:
    from ctpipe.plugins import get_formats

    registry = _registry(args)
    stages = [info.to_dict() for info in registry]
    formats = [info.to_dict() for info in get_formats(blocked=tuple(args.block_plugin))]
    if args.json:
        print(json.dumps({"stages": stages, "formats": formats}, indent=2))
        return 0
    rows = stages + formats
    width = max(len(s["name"]) for s in rows)
    plugin_width = max(len(s["plugin"]) for s in rows)
    for s in rows:
        print(f"{s['kind']:<9}  {s['name']:<{width}}  {s['plugin']:<{plugin_width}}  {s['description']}")
    return 0


def _cmd_estimate(args) -> int:
    from ctpipe.config import load_yaml, parse_pipeline
    from ctpipe.io.outputs import check_output_dir
    from ctpipe.pipeline import Pipeline

    sources = _scan_paths(args.projections, args.dask)
    batch = len(sources) > 1
    if batch and args.geometry:
        raise InputError("--geometry goes with one projection stack; a batch takes scans that carry their own geometry")
    outs = _batch_outputs(sources, args.out) if batch else {sources[0]: args.out}
    for out in outs.values():
        if out is not None:
            check_output_dir(out)
    registry = _registry(args)
    config = parse_pipeline(load_yaml(args.pipeline) if args.pipeline else None, registry)
    pipeline = Pipeline.from_config(config, registry=registry)
    address = args.dask if args.dask is not None and _is_address(args.dask) else None
    with _dask_executor(args.dask, address) as executor:
        if not batch:
            report, summary, warning = _estimate_scan(args, config, pipeline, sources[0], outs[sources[0]], executor,
                                                      progress=True)
            print(json.dumps(_jsonable(report), indent=2) if args.json else summary)
            if warning:
                print(warning, file=sys.stderr)
            return 0
        return _estimate_batch(args, config, pipeline, sources, outs, executor)


@contextlib.contextmanager
def _dask_executor(option: str | None, address: str | None):
    """The Dask executor ``--dask`` asks for (None without the option), said on stderr, closed after the block.

    ``address`` is the scheduler to connect to; None starts a LocalCluster.
    """
    if option is None:
        yield None
        return
    from ctpipe.execution import DaskExecutor

    executor = DaskExecutor.connect(address)
    print(f"ctpipe: {executor.describe()}", file=sys.stderr, flush=True)
    try:
        yield executor
    finally:
        executor.close()


def _estimate_scan(args, config, pipeline, source: Path, out: Path | None, executor, *, progress: bool):
    """Estimate one scan (or projection stack) and write its outputs: (report, summary, warning or None)."""
    from ctpipe.config import load_geometry
    from ctpipe.io.arrays import read_projections
    from ctpipe.io.outputs import write_files

    scan = None
    if not source.exists():
        raise InputError(f"{source}: no such file or scan folder")
    if source.is_dir() or source.suffix.lower() not in (".npy", ".tif", ".tiff"):
        from ctpipe.io.scans import open_scan

        scan = open_scan(source, blocked=tuple(args.block_plugin))
        if args.geometry:
            raise InputError(f"{source} is a {scan.format} scan with its own geometry; drop --geometry")
        if args.skip_bad_views:
            from ctpipe.io.scans import find_bad_views

            scan = scan.without_views(find_bad_views(scan.projections))
        if progress and not args.json:
            print("\n".join(scan.describe()), flush=True)
        inputs, n_views = (scan,), scan.n_views
    else:
        if not args.geometry:
            raise InputError(f"{source}: a projection file needs --geometry GEOMETRY.yaml (or give a scan folder)")
        geometry = load_geometry(args.geometry)
        projections = read_projections(source)
        inputs, n_views = (projections, geometry), len(projections)
    if args.pipeline is None:
        pipeline = _ball_phantom_pipeline(args, inputs[0] if scan is None else scan.projections, pipeline)
    with _progress(n_views, "views", quiet=args.json or not progress) as advance:
        result = pipeline.run(*inputs, progress=advance, executor=executor)
    if scan is not None and scan.true_angles_deg is not None:
        from ctpipe.evaluate.scoring import score_against_truth

        result = score_against_truth(result)
    if out is not None and not args.no_slices:
        result = _with_before_after(result, scan.projections if scan is not None else inputs[0])
    report = result.report()
    files = _estimate_files(Path(out), report, result) if out is not None else {}
    if files:
        write_files(files)
    summary = result.summary(source=source, written=sorted(path.name for path in files),
                             described=scan is not None and progress and not args.json)
    if scan is not None and scan.skipped_views:
        summary += (f"\nskipped: {len(scan.skipped_views)} views that could not be read "
                    f"({', '.join(map(str, sorted(scan.skipped_views)[:12]))}{', ...' if len(scan.skipped_views) > 12 else ''}"
                    f"); result.json lists why")
    return report, summary, result.failed_pairs_warning()


def _with_before_after(result, projections):
    """The result with its before/after slices and measure, when it has nominal angles and every view an angle."""
    from ctpipe.evaluate.preview import before_after

    estimated = result.estimated_deg
    if result.nominal_angles_deg is None or not np.all(np.isfinite(estimated)):
        return result
    comparison = before_after(projections, result.geometry, result.nominal_angles_deg, estimated)
    return dataclasses.replace(result, before_after=comparison)


def _ball_phantom_pipeline(args, projections, pipeline):
    """The ball calibration where the views show a ball phantom (and no pipeline was asked for), else ``pipeline``."""
    from ctpipe.config import BALL_PHANTOM_PIPELINE, parse_pipeline
    from ctpipe.features.ball_phantom import looks_like_ball_phantom
    from ctpipe.pipeline import Pipeline

    yes, why = looks_like_ball_phantom(projections)
    if not yes:
        return pipeline
    registry = _registry(args)
    try:
        balls = Pipeline.from_config(parse_pipeline(BALL_PHANTOM_PIPELINE, registry), registry=registry)
    except ConfigError:
        return pipeline     # a blocked plugin holds one of its stages
    if not args.json:
        print(f"ctpipe: a ball phantom ({why}): running the ball calibration, as configs/calibration-beads.yaml "
              "does; --pipeline configs/default.yaml runs the default pipeline instead", file=sys.stderr, flush=True)
    return balls


def _estimate_batch(args, config, pipeline, sources: list[Path], outs: dict, executor) -> int:
    """Several scans in one call: each to its own folder; a failed scan is reported, the others finish.

    On a cluster a few scans are in flight at once, so that one scan's central solve overlaps
    the next one's detection; in this process they run one after the other, each on every core.
    """
    from concurrent.futures import ThreadPoolExecutor, as_completed

    def one(source: Path):
        try:
            return "ok", _estimate_scan(args, config, pipeline, source, outs[source], executor, progress=False)
        except CtpipeError as exc:
            return "failed", str(exc)
        except Exception as exc:  # a bug, not the scan: say so, and go on with the others
            return "failed", (f"unexpected {type(exc).__name__}: {exc} (run 'ctpipe estimate {source}' alone to see "
                              f"the traceback, and please report it)")

    in_flight = 1 if executor is None else min(len(sources), 2 + executor.workers // 16)
    outcomes = {}
    pool = ThreadPoolExecutor(max_workers=in_flight, thread_name_prefix="ctpipe-scan")
    with _progress(len(sources), "scans", quiet=args.json) as advance:
        futures = {pool.submit(one, source): source for source in sources}
        try:
            for future in as_completed(futures):
                source = futures[future]
                outcomes[source] = status, detail = future.result()
                if not args.json:
                    print(f"ctpipe: {source}: " + ("done" if status == "ok" else f"FAILED: {detail}"),
                          file=sys.stderr, flush=True)
                if advance is not None:
                    advance(1)
        except BaseException:
            # Ctrl-C or SIGTERM: start no further scan and do not wait for those running; the
            # program ends without them, removing what they had not committed (entry()).
            pool.shutdown(wait=False, cancel_futures=True)
            raise
    pool.shutdown()
    failed = [source for source in sources if outcomes[source][0] != "ok"]
    if args.json:
        entries = []
        for source in sources:
            status, detail = outcomes[source]
            entry = {"scan": str(source), "status": status, "out": None if outs[source] is None else str(outs[source])}
            entry.update({"report": detail[0]} if status == "ok" else {"error": detail})
            entries.append(entry)
        print(json.dumps(_jsonable({"scans": entries, "failed": len(failed)}), indent=2))
    else:
        for source in sources:
            status, detail = outcomes[source]
            if status == "ok":
                print(f"== {source}" + (f" -> {outs[source]}" if outs[source] is not None else ""))
                print(detail[1])
                if detail[2]:
                    print(detail[2], file=sys.stderr)
                print()
        print(f"batch: {len(sources) - len(failed)} of {len(sources)} scans estimated"
              + (f", {len(failed)} failed:" if failed else ""))
        for source in failed:
            print(f"  {source}: {outcomes[source][1]}")
    return 2 if failed else 0


def _jsonable(report):
    from ctpipe.io.outputs import to_jsonable

    return to_jsonable(report)


def _is_address(text: str) -> bool:
    """Whether ``--dask``'s value is a scheduler (tcp://host:port, host:port, a scheduler file), not a scan."""
    return "://" in text or text.endswith(".json") or re.fullmatch(r"[\w.\-]+:\d+", text) is not None


def _scan_paths(arguments: list[str], dask: str | None) -> list[Path]:
    """The scans named on the command line, globs expanded (quoted ones too), in order and once each.

    ``--dask`` takes an optional address, so ``--dask SCAN`` gives it the first scan: that is
    put back among the scans when it is not an address.
    """
    import glob

    if dask and not _is_address(dask):
        arguments = [dask, *arguments]
    paths = []
    for argument in arguments:
        if not Path(argument).exists() and glob.has_magic(argument):
            matches = sorted(glob.glob(argument))
            if not matches:
                raise InputError(f"{argument}: the pattern matches no scan")
            paths.extend(Path(m) for m in matches)
        else:
            paths.append(Path(argument))
    return list(dict.fromkeys(paths))


def _batch_outputs(sources: list[Path], out: str | None) -> dict[Path, Path | None]:
    """Each scan's own output folder under ``out``: its name, with its parent's where two names clash."""
    if out is None:
        return dict.fromkeys(sources)
    names = {source: (source.name if source.is_dir() else source.stem) or "scan" for source in sources}
    clashing = {name for name in names.values() if list(names.values()).count(name) > 1}
    names = {source: f"{source.resolve().parent.name}-{name}" if name in clashing else name
             for source, name in names.items()}
    seen = {}
    for source, name in names.items():
        if name in seen:
            raise InputError(f"{seen[name]} and {source} would both write to {Path(out) / name}; give scans whose "
                             f"folder names (or parents' names) differ")
        seen[name] = source
    return {source: Path(out) / name for source, name in names.items()}


def _estimate_files(out: Path, report: dict, result) -> dict:
    """What ``ctpipe estimate --out`` writes, as {path: writer} for one atomic write_files call."""
    from ctpipe.evaluate.report import estimate_angles_png
    from ctpipe.io.corrected import CONE_VECTOR_COLUMNS
    from ctpipe.io.outputs import csv_bytes, json_bytes

    columns = result.angle_columns()
    scan = result.scan
    # Each view by its number in the scan (with views skipped, the rows are the others only).
    numbers = scan.view_numbers if scan is not None else range(len(result.estimated_deg))
    blobs = {
        "angles.csv": csv_bytes(["view", *columns], [[v, *row] for v, row in zip(numbers, zip(*columns.values()))]),
        "result.json": json_bytes(report),
        "geometry_vectors.csv": csv_bytes(["view", *CONE_VECTOR_COLUMNS],
                                          [[v, *row] for v, row in zip(numbers, result.cone_vectors())]),
    }
    picture = estimate_angles_png(result)
    if picture is not None:
        blobs["angles.png"] = picture
    if result.before_after is not None:
        from ctpipe.evaluate.preview import before_after_png

        blobs["before_after.png"] = before_after_png(result.before_after,
                                                     f"{scan.format} scan {scan.path.name}" if scan is not None else "")
    writer = None if scan is None else _angle_log_writer(scan.format)
    if writer is not None:
        name, blob = writer(*_every_view(scan, result.estimated_deg))
        blobs[name] = blob
    return {out / name: (lambda blob: lambda handle: handle.write(blob))(blob) for name, blob in blobs.items()}


def _every_view(scan, estimated_deg):
    """The scan with every view, and an angle for each: (scan, angles) for a corrected angle log.

    The scanner's log has a line per view it took. A view left out (``--skip-bad-views``) gets
    its nominal angle moved by the correction (estimated minus nominal) interpolated from the
    views on either side of it; the result's notes say which views these are.
    """
    if not scan.skipped_views:
        return scan, estimated_deg
    whole = scan.whole
    numbers = np.asarray(scan.view_numbers)
    correction = np.asarray(estimated_deg) - np.asarray(scan.nominal_angles_deg)
    filled = np.interp(np.arange(whole.n_views), numbers, correction)
    return whole, np.asarray(whole.nominal_angles_deg) + filled


def _angle_log_writer(format_name: str):
    from ctpipe.plugins import get_formats

    fmt = get_formats().get(format_name)
    return None if fmt is None else fmt.corrected_angle_log


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


def _cmd_experiment_sweep(args) -> int:
    from ctpipe.evaluate.sweep import load_sweep_settings, run_sweep, write_sweep_outputs
    from ctpipe.io.outputs import check_output_dir, staged_folder, to_jsonable

    check_output_dir(args.out)
    registry = _registry(args)
    settings = load_sweep_settings(args.sweep, registry)
    if args.seed is not None:
        settings = dataclasses.replace(settings, seed=args.seed)
    count = args.n or settings.n
    with _dask_executor(args.dask, args.dask or None) as executor, \
            _progress(count, "scenarios", quiet=args.json, description="sweep") as advance:
        report = run_sweep(settings, n=count, executor=executor, blocked=tuple(args.block_plugin), progress=advance)
    with staged_folder(args.out) as tmp:
        write_sweep_outputs(report, tmp)
    if args.json:
        print(json.dumps(to_jsonable({"summary": report.summary(), "rows": report.rows}), indent=2))
        return 0
    for row in report.rows:
        if row["status"] == "ok":
            print(f"scenario {row['scenario']:3d}: RMS {row['nominal_rms_deg']:.4f} -> {row['estimated_rms_deg']:.4f} deg, "
                  f"recovery {row['recovery_reference']:+.3f}, kept {row['refiner_kept'] or '-'}, gate {row['gate'] or '-'}, "
                  f"{row['seconds']:.0f} s")
        else:
            print(f"scenario {row['scenario']:3d}: failed: {row['reason']}")
    print(report.summary_line())
    print(f"results in {args.out}: sweep.csv, sweep.json, sweep.png, scenarios/NNN.yaml "
          f"(re-run one: ctpipe validate {Path(args.out) / 'scenarios' / '000.yaml'})")
    return 0


def _cmd_experiment_compare(args) -> int:
    from ctpipe.evaluate.compare import (CompareSettings, builtin_pipelines, file_scenarios, load_pipelines,
                                         run_compare, sweep_scenarios, write_compare_outputs)
    from ctpipe.io.outputs import check_output_dir, staged_folder, to_jsonable

    check_output_dir(args.out)
    registry = _registry(args)
    if args.builtin is not None:
        pipelines = builtin_pipelines(args.builtin, registry)
        # Files given beside a built-in comparison join it: e.g. a variant scored against the built-ins.
        pipelines = pipelines + load_pipelines(args.pipelines, registry, minimum=0)
    else:
        pipelines = load_pipelines(args.pipelines, registry)
    names = [p.name for p in pipelines]
    if len(set(names)) != len(names):
        raise ConfigError(f"pipelines: two are named alike ({', '.join(names)}); rename a file")
    if args.scenario:
        for option, value in (("--n", args.n), ("--seed", args.seed), ("--sweep", args.sweep)):
            if value is not None:
                raise ConfigError(f"{option}: only with scenarios drawn from a sweep, not with --scenario files")
        scenarios, source = file_scenarios(args.scenario, registry), "experiment files"
    else:
        scenarios, source = sweep_scenarios(args.sweep, registry, n=args.n or 6, seed=args.seed)
    settings = CompareSettings(pipelines=pipelines, scenarios=scenarios, source=source)
    with _dask_executor(args.dask, args.dask or None) as executor, \
            _progress(len(scenarios), "scenarios", quiet=args.json,
                      description=f"compare ({len(pipelines)} pipelines)") as advance:
        report = run_compare(settings, executor=executor, blocked=tuple(args.block_plugin), progress=advance)
    with staged_folder(args.out) as tmp:
        write_compare_outputs(report, tmp)
    if args.json:
        print(json.dumps(to_jsonable({"summary": report.summary_lines(), "pairs": report.pairs(),
                                      "rows": report.rows}), indent=2))
        return 0
    for row in report.rows:
        if row["status"] == "ok":
            print(f"scenario {row['scenario']} ({row['class']}), {row['pipeline']}: RMS {row['nominal_rms_deg']:.4f} -> "
                  f"{row['estimated_rms_deg']:.4f} deg, recovery {row['recovery_reference']:+.3f}, "
                  f"gate {row['gate'] or '-'}, {row['seconds']:.0f} s")
        else:
            print(f"scenario {row['scenario']} ({row['class']}), {row['pipeline']}: failed: {row['reason']}")
    for line in report.summary_lines():
        print(line)
    print(f"results in {args.out}: compare.csv, compare.json, compare.png, summary.txt, scenarios/")
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
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default=None,
                        help="where the projectors and FDK run: a CUDA GPU when numba-cuda sees one (auto, the "
                             "default), or as named; cuda falls back to the CPU with the reason when it cannot be used")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    p = sub.add_parser("plugins", help="list the registered stages and scan formats")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(run=_cmd_plugins)

    p = sub.add_parser("estimate", help="estimate per-view angles of scans (any format ctpipe reads) or a "
                                        "projection stack")
    p.add_argument("projections", nargs="+", metavar="SCAN",
                   help="a scan (folder or file in a format ctpipe reads: ctpipe, Nikon, Zeiss, Bruker, Waygate, "
                        "TIFFs + YAML) or a projection stack (views, rows, cols): .npy or multi-page .tif. Several "
                        "scans, or a glob, make a batch: each is estimated on its own and a failed one is reported")
    p.add_argument("--geometry", help="geometry YAML (keys: source_to_object_mm, ...); only for a projection stack")
    p.add_argument("--pipeline", help="pipeline YAML (default: sift, brute-force, ransac-1pt, projection-matching)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--out", help="folder for result.json, angles.csv, angles.png, before_after.png, ...; in a batch, "
                                 "one subfolder per scan")
    p.add_argument("--no-slices", action="store_true",
                   help="do not make before_after.png (slices reconstructed with the nominal and the returned angles: "
                        "one more pass over the views)")
    p.add_argument("--dask", nargs="?", const="", default=None, metavar="ADDRESS",
                   help="run on Dask: a LocalCluster on this machine, or the scheduler at ADDRESS "
                        "(tcp://host:8786 or a scheduler file). Needs: pip install 'ctpipe[dask]'")
    p.add_argument("--skip-bad-views", action="store_true",
                   help="read every view of a scan first and leave out those that cannot be read (damaged or "
                        "truncated files, NaN pixels); result.json lists them and why. Default: stop at the first")
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
    p = experiments.add_parser("sweep", help="validate on many scenarios drawn from distributions; one table and plot")
    p.add_argument("sweep", nargs="?", help="sweep YAML (default: the built-in ctpipe/evaluate/sweep.yaml)")
    p.add_argument("--n", type=_int_at_least(1), help="scenarios to draw (default: the sweep's n)")
    p.add_argument("--seed", type=_int_at_least(0), help="random seed of the draws (default: the sweep's)")
    p.add_argument("--out", default="results/sweep",
                   help="directory for sweep.csv, sweep.json, sweep.png and scenarios/ (default: results/sweep)")
    p.add_argument("--dask", nargs="?", const="", default=None, metavar="ADDRESS",
                   help="run the scenarios on a Dask cluster (a scheduler address or file; none: a LocalCluster)")
    p.add_argument("--json", action="store_true", help="print the summary and rows as JSON")
    p.set_defaults(run=_cmd_experiment_sweep)
    p = experiments.add_parser("compare", help="score pipelines against each other on the same simulated scans")
    p.add_argument("pipelines", nargs="*", metavar="PIPELINE.yaml", help="pipeline YAML files (at least two, or "
                   "--builtin); the first is the one the others are drawn against")
    p.add_argument("--builtin", choices=("detectors", "refiners"),
                   help="a built-in comparison: the paper's three detectors end to end, or the whole-scan refiners")
    p.add_argument("--sweep", help="draw the scenarios from this sweep YAML (default: the built-in sweep)")
    p.add_argument("--scenario", nargs="+", metavar="EXPERIMENT.yaml",
                   help="validate experiment files to run instead of drawn scenarios (their pipeline is replaced)")
    p.add_argument("--n", type=_int_at_least(1), help="scenarios to draw from the sweep (default 6)")
    p.add_argument("--seed", type=_int_at_least(0), help="random seed of the draws (default: the sweep's)")
    p.add_argument("--out", default="results/compare",
                   help="directory for compare.csv, compare.json, compare.png, summary.txt and scenarios/ "
                        "(default: results/compare)")
    p.add_argument("--dask", nargs="?", const="", default=None, metavar="ADDRESS",
                   help="run the scenarios on a Dask cluster (a scheduler address or file; none: a LocalCluster)")
    p.add_argument("--json", action="store_true", help="print the summary, the paired tests and the rows as JSON")
    p.set_defaults(run=_cmd_experiment_compare)
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


def _end_now(code: int) -> None:
    """End the process with ``code`` at once: an interrupted run of the ``ctpipe`` command.

    Python would otherwise wait for the threads still running: a detection, a reconstruction or
    a simulation in flight can take minutes, and a run that is stopped must stop. What they were
    writing and had not committed is removed first (:func:`ctpipe.io.outputs.discard_pending`),
    so every output is as it was before the run, or wholly the new one; child processes (the
    worker pools of ``experiment synthetic``, a LocalCluster's workers, the ball finder's
    processes) are ended with it.
    """
    import multiprocessing

    from ctpipe.execution import end_worker_processes
    from ctpipe.io.outputs import discard_pending

    discard_pending()
    for child in multiprocessing.active_children():
        child.kill()   # SIGTERM would wait, as here, for a long compiled call to return
    end_worker_processes()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def entry() -> None:
    """The ``ctpipe`` command: :func:`main`, ending within moments on Ctrl-C and SIGTERM (exit 130 and 143).

    The command runs in a worker thread while the main thread only waits for it. Python handles
    a signal in the main thread, between two of its calls; a command run there would not see
    Ctrl-C until a long numba or OpenCV call returned (a reconstruction, one chunk of a
    projection: seconds to minutes). Waiting, the main thread sees it at once and ends the
    process (:func:`_end_now`).
    """
    import threading

    args = build_parser().parse_args()   # a usage error exits here, as argparse does
    _MAIN_PID[0] = os.getpid()
    signal.signal(signal.SIGTERM, _on_sigterm)
    outcome: list = []

    def run() -> None:
        try:
            outcome.append(_run(args))
        except BaseException as exc:  # a bug's traceback is printed by the main thread, as before
            outcome.append(exc)

    command = threading.Thread(target=run, name="ctpipe-command")
    try:
        command.start()
        while command.is_alive():
            command.join(0.05)
    except KeyboardInterrupt as stop:   # _Terminated too
        _end_now(_stopped(stop))
    result = outcome[0]
    if isinstance(result, BaseException):
        raise result
    if result != 0 and any(t.is_alive() and not t.daemon for t in threading.enumerate()
                           if t is not threading.main_thread()):
        _end_now(result)   # tasks a failed command left running must not hold its exit for minutes
    sys.exit(result)


def main(argv: list[str] | None = None) -> int:
    """Run the command line ``argv`` (default ``sys.argv[1:]``); the exit status.

    For Python callers: Ctrl-C and SIGTERM (in the main thread) return 130 and 143 once the
    command's own clean-up has run; the ``ctpipe`` command (:func:`entry`) ends at once instead.
    """
    args = build_parser().parse_args(argv)
    previous = None
    try:
        _MAIN_PID[0] = os.getpid()
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    except ValueError:  # not the main thread (main() called from a thread): leave signals alone
        pass
    try:
        return _run(args)
    except KeyboardInterrupt as stop:   # _Terminated too
        return _stopped(stop)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _stopped(stop: KeyboardInterrupt) -> int:
    """Say on stderr how the run was stopped; its exit status (143 for SIGTERM, 130 for Ctrl-C)."""
    if isinstance(stop, _Terminated):
        print("ctpipe: terminated", file=sys.stderr)
        return 128 + signal.SIGTERM
    print("ctpipe: interrupted", file=sys.stderr)
    return 130


def _name_leftovers(args) -> None:
    """Say on stderr what runs killed before their clean-up (SIGKILL, a power cut) left where this one writes.

    One line, with the command that removes it all; nothing is removed without the user.
    """
    import shlex

    from ctpipe.io.outputs import leftovers

    targets = [getattr(args, name, None) for name in ("out", "overlay")]
    found = sorted({path for target in targets if target for path in leftovers(target)})
    if found:
        names = ", ".join(path.name for path in found)
        print(f"ctpipe: note: {names}: left by an earlier run that was killed before it could clean up (SIGKILL, a "
              f"crash, a power cut); nothing reads {'it' if len(found) == 1 else 'them'}; remove with: rm -rf -- "
              f"{' '.join(shlex.quote(str(path)) for path in found)}", file=sys.stderr)


def _run(args) -> int:
    """Run the parsed command; a user's error is one line on stderr and exit status 2.

    A result that could not be written (a full disk) or a Dask cluster that cannot go on is one
    line too, with exit status 1: it is not the input's fault, and the run can be repeated as it
    was once there is room or a cluster.
    """
    try:
        _name_leftovers(args)
        device = getattr(args, "device", None)
        if device is None:
            gpu.requested()   # a bad CTPIPE_DEVICE is bad input: said now, before any work
        with gpu.use(device) if device is not None else contextlib.nullcontext():
            return args.run(args)
    except CtpipeError as exc:
        print(f"ctpipe: error: {exc}", file=sys.stderr)
        return 1 if isinstance(exc, (OutputError, ClusterError)) else 2


if __name__ == "__main__":  # pragma: no cover
    entry()
