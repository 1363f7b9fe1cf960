"""Simulated scans: a phantom, a scan spec, known angle jitter -> projections as a detector sees them.

The chain is the one of a real scan: nominal angles -> true angles (nominal + jitter) ->
line integrals at the true angles (analytic projector for primitive phantoms, the voxel
projector for voxel phantoms) -> Beer-Lambert intensities with Poisson noise, flat and dark
fields -> the ``-log`` transform a reconstruction starts from.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ctpipe._shared.resources import FLOAT32, check_fits, memory_guard
from ctpipe.geometry import Geometry
from ctpipe.recon.volume import VolumeGrid

__all__ = ["SimulatedScan", "project_phantom", "simulate", "simulation_bytes", "check_simulation_fits",
           "simulation_work", "check_simulation_work", "voxelise_phantom", "write_simulated_scan"]


@dataclass(frozen=True, eq=False)
class SimulatedScan:
    """A simulated acquisition with its truth.

    Attributes
    ----------
    projections : ndarray of shape (V, rows, cols), float32
        Line integrals as a reconstruction sees them (``-log`` of the flat/dark-corrected
        intensities when the scan has noise, the exact line integrals otherwise).
    nominal_angles_deg, true_angles_deg : ndarray of shape (V,)
    geometry : Geometry
    intensities : ndarray of shape (V, rows, cols), float32, or None
        Detector counts before the ``-log`` (None for a noise-free scan).
    flats, darks : ndarray of shape (F, rows, cols), float32, or None
    true_detector_offsets_px : ndarray of shape (V, 2), float64, or None
        True minus nominal principal point ``(du, dv)`` pixels in every view: the centre-of-rotation
        offset plus the drift of a misaligned scan (:mod:`ctpipe.sim.drift`); None when the
        scan has no ``misalignment``. ``geometry`` stays the nominal one.
    true_detector_tilt_deg : float
        The detector's true in-plane tilt (degrees; 0 unless the scan is misaligned).
    true_axis_offset_mm : float
        How far the true axis lies off the source's perpendicular to the detector (mm; 0 unless the scan's
        misalignment says so: :class:`ctpipe.sim.drift.Misalignment`).
    true_spot_offsets_px : ndarray of shape (V, 2), float64, or None
        Where the drift is the source spot's (``drift.at: source``), how far it moved the rotation axis's image in
        every view ``(du, dv)`` px; ``true_detector_offsets_px`` then holds the centre-of-rotation offset alone.
        None otherwise.
    """

    projections: np.ndarray
    nominal_angles_deg: np.ndarray
    true_angles_deg: np.ndarray
    geometry: Geometry
    intensities: np.ndarray | None = None
    flats: np.ndarray | None = None
    darks: np.ndarray | None = None
    true_detector_offsets_px: np.ndarray | None = None
    true_detector_tilt_deg: float = 0.0
    true_axis_offset_mm: float = 0.0
    true_spot_offsets_px: np.ndarray | None = None


def project_phantom(phantom, geometry: Geometry, angles_deg, *, supersample: int = 1, blur_px: float = 0.0,
                    progress: Callable[[int], object] | None = None, detector_offsets_px=None,
                    detector_tilt_deg: float = 0.0, axis_offset_mm: float = 0.0, spot_offsets_px=None) -> np.ndarray:
    """Line integrals (V, rows, cols), float32, of a primitive or voxel phantom.

    ``detector_offsets_px`` (V, 2) and ``detector_tilt_deg`` place the true detector of a misaligned
    scan (:func:`ctpipe.sim.projectors.project_analytic`); a voxel phantom's projections on the
    nominal detector are resampled onto it (:func:`ctpipe.sim.drift.resample_to_detector`).
    ``axis_offset_mm`` puts the axis off the source's perpendicular and ``spot_offsets_px`` moves the source spot
    (primitive phantoms only).
    """
    from ctpipe.sim.drift import _refuse_axis_offset
    from ctpipe.sim.projectors import VoxelProjector, project_analytic

    if phantom.primitives is not None:
        return project_analytic(phantom.primitives, geometry, angles_deg, supersample=supersample, blur_px=blur_px,
                                progress=progress, detector_offsets_px=detector_offsets_px,
                                detector_tilt_deg=detector_tilt_deg, axis_offset_mm=axis_offset_mm,
                                spot_offsets_px=spot_offsets_px)
    _refuse_axis_offset(axis_offset_mm, spot_offsets_px)
    projections = VoxelProjector(geometry, phantom.grid).forward(phantom.volume, angles_deg)
    if detector_offsets_px is not None or detector_tilt_deg != 0:
        from ctpipe.sim.drift import resample_to_detector

        projections = resample_to_detector(projections, geometry, detector_offsets_px, detector_tilt_deg)
    if blur_px > 0:
        from scipy.ndimage import gaussian_filter

        projections = gaussian_filter(projections, sigma=(0.0, blur_px, blur_px)).astype(np.float32)
    if progress is not None:
        progress(len(projections))
    return projections


def simulation_bytes(spec, *, scans: int = 1) -> int:
    """Peak memory (bytes) of :func:`simulate` for ``spec``, ``scans`` results held at once.

    A noise-free scan holds one float32 stack (V, rows, cols), two while the detector blur
    runs; a noisy one holds the line integrals, the intensities and their ``-log`` at once, plus
    the flat and dark frames. Every scan but the last keeps what it returns (projections, and
    intensities, flats and darks when noisy). Python ints: no overflow for any size.
    """
    rows, cols = spec.geometry.detector_rows, spec.geometry.detector_cols
    frame = int(rows) * int(cols) * FLOAT32
    stack = int(spec.n_views) * frame
    if spec.noise is None:
        kept, peak = stack, stack * (2 if spec.projector.blur_px > 0 else 1)
    else:
        frames = (int(spec.noise.flat_frames) + int(spec.noise.dark_frames)) * frame
        kept, peak = 2 * stack + frames, 3 * stack + frames
    return (scans - 1) * kept + peak


def check_simulation_fits(spec, *, scans: int = 1, hint: str | None = None) -> None:
    """Raise :class:`ctpipe._shared.resources.ResourceError` when :func:`simulate` of ``spec`` cannot fit in memory."""
    geometry = spec.geometry
    frames = "" if spec.noise is None else \
        f" with {spec.noise.flat_frames} flat and {spec.noise.dark_frames} dark frames"
    times = "" if scans == 1 else f" {scans} times"
    check_fits(f"simulating {spec.n_views} views of {geometry.detector_rows} x {geometry.detector_cols}{frames}{times}",
               simulation_bytes(spec, scans=scans), hint=hint)


def simulation_work(phantom, spec) -> dict[str, float]:
    """The work of :func:`simulate` of ``phantom`` in ``spec``, by kind, each an upper bound.

    ``"ray-primitive intersections"`` of the analytic projector (the phantom's primitives and the
    holder's, :func:`ctpipe.sim.projectors.analytic_work`), ``"voxel samples"`` of the voxel
    projector (a voxel phantom, :func:`ctpipe.sim.projectors.voxel_work`) and ``"energy-bin terms"``
    of a polychromatic beam (one exponential per pixel, view and energy bin). Counted at the nominal
    angles on the nominal detector: the jitter and a misalignment move the shapes by far less than
    a bound's slack.
    """
    from ctpipe.sim.projectors import analytic_work, voxel_work

    g, angles = spec.geometry, spec.nominal_angles_deg()
    supersample = spec.projector.supersample
    work = {"ray-primitive intersections": 0.0, "voxel samples": 0.0, "energy-bin terms": 0.0}
    if phantom.primitives is not None:
        work["ray-primitive intersections"] += analytic_work(phantom.primitives, g, angles, supersample=supersample)
    else:
        work["voxel samples"] += voxel_work(g, phantom.grid, angles)
    holder = getattr(spec, "holder", None)
    for objects in holder.placed(phantom) if holder is not None else ():
        if len(objects):   # a static holder turns with nothing, but may be projected in every view: counted so
            work["ray-primitive intersections"] += analytic_work(objects, g, angles, supersample=supersample)
    beam = getattr(spec, "beam", None)
    if beam is not None:
        bins = 1 if beam.energy_kev is not None else beam.energy_bins
        work["energy-bin terms"] += float(spec.n_views) * g.detector_rows * g.detector_cols * bins
    return work


def check_simulation_work(phantom, spec, *, scans: int = 1) -> None:
    """Raise :class:`ctpipe.errors.ResourceError` when ``scans`` simulations of ``spec`` would run too long.

    Each kind of :func:`simulation_work` has a limit worth about 10-20 minutes on two cores
    (:data:`~ctpipe.sim.projectors.MAX_SUB_RAYS`, :data:`~ctpipe.sim.projectors.MAX_VOXEL_STEPS`,
    :data:`~ctpipe.sim.beam.MAX_ENERGY_TERMS`); a simulation that needs more than that in all,
    the shares of the limits added up, is refused before anything is projected, naming the work,
    its limit and what to lower.
    """
    from ctpipe.errors import ResourceError
    from ctpipe.sim.beam import MAX_ENERGY_TERMS
    from ctpipe.sim.projectors import MAX_SUB_RAYS, MAX_VOXEL_STEPS

    limits = {"ray-primitive intersections": MAX_SUB_RAYS, "voxel samples": MAX_VOXEL_STEPS,
              "energy-bin terms": MAX_ENERGY_TERMS}
    lower = {"ray-primitive intersections": "fewer primitives in the cone of rays",
             "voxel samples": "a voxel phantom of fewer voxels", "energy-bin terms": "fewer beam.energy_bins"}
    work = {kind: scans * amount for kind, amount in simulation_work(phantom, spec).items() if amount > 0}
    load = sum(amount / limits[kind] for kind, amount in work.items())
    if load <= 1.0:
        return
    # The message names the kinds that make up the load (a twentieth of it or more).
    work = {kind: amount for kind, amount in work.items() if amount / limits[kind] >= load / 20}
    g = spec.geometry
    what = (f"simulating {'' if scans == 1 else f'{scans} scans of '}{spec.n_views} views of {g.detector_rows} x "
            f"{g.detector_cols} at supersample {spec.projector.supersample}")
    if len(work) == 1:
        (kind, amount), = work.items()
        needs = f"about {amount:.1e} {kind}, more than the {limits[kind]:.0e}"
    else:
        needs = (" and ".join(f"about {amount:.1e} {kind} (of {limits[kind]:.0e})" for kind, amount in work.items())
                 + f", {load:.1f} times the work")
    hints = ["fewer views", "a smaller detector or supersample", *(lower[kind] for kind in work)]
    raise ResourceError(f"{what} needs {needs} (10-20 minutes on two cores) ctpipe takes on in one simulation; use "
                        f"{', '.join(hints[:-1])} or {hints[-1]}")


def simulate(phantom, spec, *, rng: np.random.Generator, jitter: bool = True,
             progress: Callable[[int], object] | None = None) -> SimulatedScan:
    """Simulate the scan ``spec`` of ``phantom``.

    Parameters
    ----------
    phantom : ctpipe.sim.phantoms.Phantom
    spec : ctpipe.sim.scan_spec.ScanSpec
        Geometry, nominal angles, jitter, noise and projector settings.
    rng : numpy.random.Generator
        Draws the jitter, then the detector noise.
    jitter : bool
        False scans at the nominal angles (the jitter-free reference of ``ctpipe validate``).

    Raises
    ------
    ctpipe._shared.resources.ResourceError
        The scan cannot fit in the memory available, or would take too long
        (:func:`check_simulation_work`): checked before anything is allocated.
    """
    check_simulation_fits(spec, hint="use fewer views, a smaller detector or fewer flat/dark frames")
    check_simulation_work(phantom, spec)
    with memory_guard(f"simulating {spec.n_views} views of {spec.geometry.detector_rows} x "
                      f"{spec.geometry.detector_cols}", simulation_bytes(spec)):
        return _simulate(phantom, spec, rng, jitter, progress)


def _simulate(phantom, spec, rng, jitter, progress) -> SimulatedScan:
    from ctpipe.io.flatfield import log_transform
    from ctpipe.sim.acquisition import acquire

    nominal = spec.nominal_angles_deg()
    truth = nominal + spec.jitter.sample(nominal, rng) if jitter else nominal.copy()
    # After the jitter, before the noise; a scan without misalignment draws nothing here.
    misaligned = _true_detector(spec, rng, jitter)
    true_detector = {f"true_{key}": value for key, value in misaligned.items()}
    holder = getattr(spec, "holder", None)
    turning, static = holder.placed(phantom) if holder is not None else (None, None)
    if turning is not None and len(turning) and phantom.primitives is not None:
        from dataclasses import replace

        from ctpipe.sim.primitives import Primitives

        phantom = replace(phantom, primitives=Primitives.concatenate([phantom.primitives, turning]))
        turning = None
    if getattr(spec, "beam", None) is not None:  # polychromatic: -log of the flat-normalised transmission
        from ctpipe.sim.beam import polychromatic_line_integrals

        if (turning is not None and len(turning)) or (static is not None and len(static)):
            from ctpipe.errors import InputError

            raise InputError("holder: under a polychromatic beam only a turning holder of a primitive phantom is "
                             "simulated; leave out the beam, the static objects or the voxel phantom")
        line_integrals = polychromatic_line_integrals(phantom, spec.beam, spec.geometry, truth,
                                                      supersample=spec.projector.supersample,
                                                      blur_px=spec.projector.blur_px, progress=progress,
                                                      **misaligned)
    else:
        line_integrals = project_phantom(phantom, spec.geometry, truth, supersample=spec.projector.supersample,
                                         blur_px=spec.projector.blur_px, progress=progress, **misaligned)
        if turning is not None and len(turning):  # a voxel phantom's turning holder: its own exact projection
            _add_holder(line_integrals, turning, spec, truth, misaligned)
        if static is not None and len(static):  # does not turn: turntable angle 0 in every view
            _add_holder(line_integrals, static, spec, np.zeros(len(truth)), misaligned)
    detector = spec.detector
    if spec.noise is None:
        if detector is not None:  # artefacts act on intensities: exp(-p) with I0 = 1, flat-corrected back
            from ctpipe.sim.detector import detected_line_integrals

            detected_line_integrals(line_integrals, detector, rng, out=line_integrals)
        return SimulatedScan(line_integrals, nominal, truth, spec.geometry, **true_detector)
    if detector is not None:
        from ctpipe.sim.detector import record

        intensities, flats, darks = record(line_integrals, spec.noise, detector, rng)
    else:
        intensities, flats, darks = acquire(line_integrals, spec.noise, rng)
    return SimulatedScan(log_transform(intensities, flats, darks), nominal, truth, spec.geometry, intensities, flats,
                         darks, **true_detector)


def _add_holder(out: np.ndarray, primitives, spec, angles_deg: np.ndarray, misaligned: dict) -> None:
    """Add to ``out`` (V, rows, cols) the line integrals of holder ``primitives`` at ``angles_deg``.

    On the scan's (true) detector. Projections are linear, so adding them to the sample's is
    projecting both together (the detector blur included). A static holder without per-view
    detector offsets is projected once (all its angles are 0) and broadcast; otherwise views go
    in chunks, so the holder never holds a second stack in memory.
    """
    from ctpipe.sim.projectors import project_analytic

    settings = {"supersample": spec.projector.supersample, "blur_px": spec.projector.blur_px,
                "detector_tilt_deg": misaligned.get("detector_tilt_deg", 0.0),
                "axis_offset_mm": misaligned.get("axis_offset_mm", 0.0)}
    offsets, spot = misaligned.get("detector_offsets_px"), misaligned.get("spot_offsets_px")
    if offsets is None and spot is None and np.all(angles_deg == angles_deg[0]) and not settings["axis_offset_mm"]:
        out += project_analytic(primitives, spec.geometry, angles_deg[:1], **settings)
        return
    chunk = 32
    for start in range(0, len(angles_deg), chunk):
        stop = min(start + chunk, len(angles_deg))
        out[start:stop] += project_analytic(primitives, spec.geometry, angles_deg[start:stop],
                                            detector_offsets_px=None if offsets is None else offsets[start:stop],
                                            spot_offsets_px=None if spot is None else spot[start:stop], **settings)


def _true_detector(spec, rng, jitter: bool) -> dict:
    """The projector's ``detector_offsets_px`` and ``detector_tilt_deg`` of a misaligned scan, or {}.

    ``jitter=False`` (the reference at the nominal angles) leaves out the per-view drift too,
    keeping the static centre-of-rotation offset and tilt of the scanner.
    """
    misalignment = getattr(spec, "misalignment", None)
    if misalignment is None:
        return {}
    offsets = misalignment.sample_offsets_px(spec.n_views, rng, drift=jitter)
    spot = {}
    if jitter and misalignment.drift is not None and misalignment.drift.at == "source":
        # The drift is the source spot's: the detector keeps the centre-of-rotation offset alone.
        still = np.array([misalignment.cor_offset_px, 0.0])
        offsets, spot = np.tile(still, (len(offsets), 1)), {"spot_offsets_px": offsets - still}
    return {"detector_offsets_px": offsets, "detector_tilt_deg": misalignment.tilt_deg,
            **({"axis_offset_mm": misalignment.axis_offset_mm} if misalignment.axis_offset_mm else {}), **spot}


def voxelise_phantom(phantom, grid: VolumeGrid, *, supersample: int = 2) -> np.ndarray:
    """The phantom's density (1/mm) on ``grid``, float32 of ``grid.shape``.

    Primitive phantoms average ``supersample^3`` points per voxel; voxel phantoms are
    resampled trilinearly (zero outside their own grid).
    """
    if phantom.primitives is not None:
        from ctpipe.sim.primitives import voxelise

        return voxelise(phantom.primitives, grid, supersample=supersample)
    from scipy.ndimage import map_coordinates

    source = phantom.grid
    coords = [(grid.axis_mm(axis) - source.origin_mm["xyz".index(axis)]) / source.voxel_size_mm for axis in "yzx"]
    iy, iz, ix = np.meshgrid(*coords, indexing="ij")
    return map_coordinates(phantom.volume, [iy, iz, ix], order=1, mode="constant", cval=0.0).astype(np.float32)


def write_simulated_scan(out: str | Path, scan: SimulatedScan, *, phantom, spec, seed: int,
                         overwrite: bool = False) -> Path:
    """Write ``scan`` as a scan folder (raw intensities + flats/darks when it has noise)."""
    import datetime

    from ctpipe._version import __version__
    from ctpipe.io.scan_folder import write_scan

    provenance = {"generator": f"ctpipe {__version__} simulate", "phantom": phantom.name,
                  "scan_spec": spec.to_dict(), "seed": seed,
                  "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
    if scan.true_detector_offsets_px is not None:  # the scan folder's truth of a misaligned scanner
        provenance["true_detector_offsets_px"] = np.asarray(scan.true_detector_offsets_px).tolist()
        provenance["true_detector_tilt_deg"] = float(scan.true_detector_tilt_deg)
        if scan.true_axis_offset_mm:
            provenance["true_axis_offset_mm"] = float(scan.true_axis_offset_mm)
        if scan.true_spot_offsets_px is not None:
            provenance["true_spot_offsets_px"] = np.asarray(scan.true_spot_offsets_px).tolist()
    if scan.intensities is None:
        return write_scan(out, scan.projections, scan.geometry, scan.nominal_angles_deg, scan.true_angles_deg,
                          values="line_integrals", provenance=provenance, overwrite=overwrite)
    return write_scan(out, scan.intensities, scan.geometry, scan.nominal_angles_deg, scan.true_angles_deg,
                      flats=scan.flats, darks=scan.darks, values="intensities", provenance=provenance,
                      overwrite=overwrite)
