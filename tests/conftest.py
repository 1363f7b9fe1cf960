"""Shared fixtures: a small bead scan rendered analytically with known angles."""

from __future__ import annotations

import numpy as np
import pytest

from bead_rendering import render_beads
from ctpipe.geometry import Geometry


@pytest.fixture(scope="session")
def bead_scan():
    """(projections, geometry, true angles in degrees) of 200 beads, 5 views with uneven steps.

    A wide cone (half-angle ~12 deg): the angle one correspondence fixes has an error of about
    2 da / b, so narrow cones need many more keypoints than a test image of 256^2 has.
    """
    geometry = Geometry(source_to_object_mm=250.0, source_to_detector_mm=500.0, detector_cols=256,
                        detector_rows=256, pixel_pitch_u_mm=0.8, pixel_pitch_v_mm=0.8)
    rng = np.random.default_rng(3)
    n = 200
    r = 40.0 * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    centres = np.stack([r * np.cos(phi), rng.uniform(-40, 40, n), r * np.sin(phi)], axis=1)
    radii = rng.uniform(0.8, 2.0, n)
    angles = np.array([0.0, 2.0, 3.5, 6.5, 8.0])
    return render_beads(geometry, angles, centres, radii), geometry, angles


#: A small scan folder's acquisition: beads in a cylinder, 48 views over a turn, 0.4 deg jitter, counts.
SMALL_SCAN = {
    "geometry": {"source_to_object_mm": 130.0, "source_to_detector_mm": 300.0, "detector_cols": 128,
                 "detector_rows": 96, "pixel_pitch_u_mm": 1.6, "pixel_pitch_v_mm": 1.6},
    "angles": {"n_views": 48, "range_deg": 360.0, "start_deg": 0.0},
    "jitter": [{"gaussian": {"sigma_deg": 0.4}}],
    "noise": {"photons_per_pixel": 20000, "flat_frames": 2, "dark_frames": 1, "dark_counts": 100},
    "projector": {"kind": "analytic", "supersample": 1, "blur_px": 0.5},
    "seed": 5,
}


@pytest.fixture(scope="session")
def small_scan_folder(tmp_path_factory):
    """A ctpipe scan folder (scan.yaml, uint16 projections, flats, darks) of :data:`SMALL_SCAN`; read-only."""
    from ctpipe.io.scan_folder import write_scan
    from ctpipe.sim import load_phantom, parse_scan_spec, simulate

    spec = parse_scan_spec(SMALL_SCAN)
    scan = simulate(load_phantom("bead-cylinder"), spec, rng=np.random.default_rng(5))
    counts = lambda a: np.round(a).astype(np.uint16)  # noqa: E731 (Poisson counts are integers already)
    return write_scan(tmp_path_factory.mktemp("scan") / "small", counts(scan.intensities), spec.geometry,
                      scan.nominal_angles_deg, scan.true_angles_deg, flats=counts(scan.flats),
                      darks=counts(scan.darks), values="intensities")


@pytest.fixture(scope="session")
def dask_client():
    """A distributed.Client of a LocalCluster of 2 worker processes, 1 thread each, for the session."""
    distributed = pytest.importorskip("distributed")
    from ctpipe.execution import distributed_quiet

    with distributed_quiet():
        cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0")
    client = distributed.Client(cluster)
    yield client
    client.close()
    cluster.close()
