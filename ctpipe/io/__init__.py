"""Reading scans and images: files in, in ctpipe's conventions; results out, never half-written.

:func:`open_scan` opens a scan in any registered format (ctpipe's own scan folder, Nikon,
Zeiss, Bruker SkyScan, GE/Waygate, NSI, a TIFF stack with a YAML, or a third-party plugin's):
a :class:`ScanFiles` with the geometry and angles in ctpipe's conventions and the projections
as a :class:`ViewStack`, read and corrected one view at a time. The ``open_<vendor>`` readers
open one format directly, and ``read_xtekct`` / ``read_skyscan_log`` / ``read_nsipro`` read a
vendor's settings file alone. :func:`read_scan` and :func:`write_scan` are ctpipe's own scan
folder (``scan.yaml`` beside one TIFF per frame); :func:`read_projections`, :func:`read_image`
and :func:`read_array` read ``.npy``, TIFF and PNG; :func:`cone_vectors` and
:func:`scanner_frame_deg` hand corrected angles and per-view geometry to another reconstructor.

A new scan format is a plugin (``ctpipe_register_formats``, see :mod:`ctpipe.hookspecs`) built
from :class:`ScanFiles`, :class:`ViewStack`, :class:`ViewFiles` and :func:`check_angles`.
Writing vendors' files, which only tests and benchmarks need, is in :mod:`ctpipe.testing`.

The readers are imported on first use, so that a blocked format plugin is never imported.
"""

from __future__ import annotations

from ctpipe._shared.lazy import lazy_exports

#: Public name -> the module that defines it.
_EXPORTS = {
    "open_scan": "scans", "ScanFiles": "scans", "ViewStack": "scans", "ViewFiles": "scans",
    "StackReference": "scans", "check_angles": "scans", "find_bad_views": "scans",
    "Scan": "scan_folder", "read_scan": "scan_folder", "write_scan": "scan_folder", "open_scan_folder": "scan_folder",
    "open_tiff_stack": "tiff_stack",
    "open_nikon": "nikon", "read_xtekct": "nikon",
    "open_zeiss": "zeiss",
    "open_bruker": "bruker", "read_skyscan_log": "bruker",
    "open_waygate": "waygate",
    "open_nsi": "nsi", "read_nsipro": "nsi",
    "read_projections": "arrays", "read_image": "arrays", "read_array": "arrays",
    "log_transform": "flatfield",
    "cone_vectors": "corrected", "scanner_frame_deg": "corrected", "CONE_VECTOR_COLUMNS": "corrected",
    "TO_ASTRA": "corrected",
}

__all__ = list(_EXPORTS)


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
