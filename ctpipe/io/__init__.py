"""Reading scans and images, writing results: files in, files out, never half-written.

:func:`open_scan` opens a scan in any format ctpipe reads (:mod:`~ctpipe.io.scans`): the
geometry and angles in ctpipe's conventions, the projections as a :class:`ViewStack` read and
corrected one view at a time. :mod:`~ctpipe.io.scan_folder` reads and writes ctpipe's scan folder (a ``scan.yaml`` beside
one TIFF per frame), the format of simulated scans and of real ones given a ``scan.yaml``;
:mod:`~ctpipe.io.arrays` reads projection stacks and images from ``.npy``, TIFF and PNG with a
one-line error for anything else; :mod:`~ctpipe.io.flatfield` turns raw counts, flats and darks
into line integrals; :mod:`~ctpipe.io.corrected` hands corrected angles and per-view vector
geometry back to the user's reconstructor; :mod:`~ctpipe.io.outputs` writes files and folders atomically (staged,
then renamed into place) and checks output paths before any work starts.
"""

from ctpipe.io.arrays import read_array, read_image, read_projections
from ctpipe.io.bruker import open_bruker, read_skyscan_log, write_bruker
from ctpipe.io.corrected import CONE_VECTOR_COLUMNS, TO_ASTRA, cone_vectors, scanner_frame_deg
from ctpipe.io.flatfield import MAX_DEAD_FRACTION, log_transform, mean_frame
from ctpipe.io.nikon import open_nikon, read_xtekct, write_nikon, write_nikon_angles
from ctpipe.io.nsi import open_nsi, read_nsipro
from ctpipe.io.outputs import (atomic_write, check_output_dir, check_output_file, csv_bytes, json_bytes,
                               keypoints_writer, staged_folder, to_jsonable, write_csv, write_files, write_json,
                               write_keypoints)
from ctpipe.io.scan_folder import (SCAN_FORMAT, VALUE_KINDS, Scan, check_scan_folder_free, open_scan_folder, read_scan,
                                   write_scan)
from ctpipe.io.scans import FORMATS, ScanFiles, StackReference, ViewFiles, ViewStack, check_angles, open_scan, register_format
from ctpipe.io.tiff_stack import open_tiff_stack
from ctpipe.io.waygate import open_waygate, write_waygate, write_waygate_angles
from ctpipe.io.zeiss import open_zeiss, write_zeiss

__all__ = ["cone_vectors", "scanner_frame_deg", "CONE_VECTOR_COLUMNS", "TO_ASTRA", "open_scan", "ScanFiles", "ViewStack", "ViewFiles", "StackReference", "FORMATS", "register_format", "check_angles", "open_scan_folder",
           "open_tiff_stack",
           "open_nikon", "write_nikon", "write_nikon_angles", "read_xtekct", "open_waygate",
           "write_waygate", "write_waygate_angles", "open_zeiss", "write_zeiss", "open_bruker", "write_bruker",
           "read_skyscan_log", "open_nsi", "read_nsipro",
           "Scan", "read_scan", "write_scan", "check_scan_folder_free", "SCAN_FORMAT", "VALUE_KINDS",
           "read_projections", "read_image", "read_array", "log_transform", "mean_frame", "MAX_DEAD_FRACTION", "atomic_write",
           "write_files", "staged_folder", "write_json", "write_csv", "json_bytes", "csv_bytes", "to_jsonable",
           "check_output_dir", "check_output_file", "write_keypoints", "keypoints_writer"]
