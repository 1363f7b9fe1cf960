"""ctpipe: rotation angles of every view of a cone-beam CT scan, estimated from its projections.

The names here are the ones a user needs first::

    import ctpipe

    scan = ctpipe.open_scan("my_scan")    # any format: Nikon, Zeiss, Bruker, Waygate, NSI, ctpipe's
    result = ctpipe.Pipeline.from_config("configs/default.yaml").run(
        scan.projections, scan.geometry, nominal_angles_deg=scan.nominal_angles_deg)
    volume = ctpipe.fdk(scan.projections, scan.geometry, result.angles_deg, ctpipe.VolumeGrid.cube(256, 0.1))

The framework (stages, registry, plugins, configuration, the pipeline) is in the modules at
this level; each area has its folder: :mod:`ctpipe.builtin` (the built-in stages),
:mod:`ctpipe.solve` (whole-scan solving), :mod:`ctpipe.sim` (the simulator), :mod:`ctpipe.recon`
(volume grids and FDK), :mod:`ctpipe.io` (scan folders and files) and :mod:`ctpipe.evaluate`
(``ctpipe validate`` and the scores). ``docs/architecture.md`` has the map.

``open_scan`` opens a scan in any format ctpipe reads (reading views on demand);
``read_scan`` reads ctpipe's own scan folder whole, and ``simulate`` makes one.

The names are imported on first use, so ``import ctpipe`` (and the ``ctpipe`` command's start)
stays fast.
"""

from __future__ import annotations

from ctpipe._shared.lazy import lazy_exports

from ctpipe._version import __version__

#: Public name -> the module (under ctpipe) that defines it.
_EXPORTS = {
    "Pipeline": "pipeline",
    "ScanResult": "pipeline",
    "Geometry": "geometry",
    "Features": "data",
    "Matches": "data",
    "PairEstimate": "data",
    "ScanObservations": "data",
    "ScanSolution": "data",
    "get_registry": "plugins",
    "CtpipeError": "errors",
    "ConfigError": "errors",
    "InputError": "errors",
    "EstimationError": "errors",
    "PluginError": "errors",
    "open_scan": "io.scans",
    "ScanFiles": "io.scans",
    "Scan": "io.scan_folder",
    "read_scan": "io.scan_folder",
    "write_scan": "io.scan_folder",
    "simulate": "sim.simulator",
    "load_phantom": "sim.phantoms",
    "load_scan_spec": "sim.scan_spec",
    "VolumeGrid": "recon.volume",
    "fdk": "recon.feldkamp",
    "run_validate": "evaluate.validate",
}

__all__ = ["__version__", *_EXPORTS]


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
