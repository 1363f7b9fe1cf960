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

import importlib

from ctpipe._version import __version__

#: Public name -> the module that defines it.
_EXPORTS = {
    "Pipeline": "ctpipe.pipeline",
    "ScanResult": "ctpipe.pipeline",
    "Geometry": "ctpipe.geometry",
    "Features": "ctpipe.data",
    "Matches": "ctpipe.data",
    "PairEstimate": "ctpipe.data",
    "ScanObservations": "ctpipe.data",
    "ScanSolution": "ctpipe.data",
    "get_registry": "ctpipe.plugins",
    "CtpipeError": "ctpipe.errors",
    "ConfigError": "ctpipe.errors",
    "InputError": "ctpipe.errors",
    "EstimationError": "ctpipe.errors",
    "PluginError": "ctpipe.errors",
    "open_scan": "ctpipe.io.scans",
    "ScanFiles": "ctpipe.io.scans",
    "Scan": "ctpipe.io.scan_folder",
    "read_scan": "ctpipe.io.scan_folder",
    "write_scan": "ctpipe.io.scan_folder",
    "simulate": "ctpipe.sim.simulator",
    "load_phantom": "ctpipe.sim.phantoms",
    "load_scan_spec": "ctpipe.sim.scan_spec",
    "VolumeGrid": "ctpipe.recon.volume",
    "fdk": "ctpipe.recon.feldkamp",
    "run_validate": "ctpipe.evaluate.validate",
}

__all__ = ["__version__", *_EXPORTS]


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'ctpipe' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
